"""semfeat-features: feature_node's front end over a bag, offline, into a new bag.

The network is an untrained one written to tmp_path (plumbing only: its keypoints mean nothing).
"""
from __future__ import annotations

from pathlib import Path

from conftest import REPO
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from msg_adapters import features_from_msg, image_to_numpy, stamp_to_ns
from msg_adapters.layouts import features_dtype
from msg_adapters.point_cloud2 import fields_to_dtype
from semfeat_ros.labels import load_labels
from semfeat_ros.tools import features as tool

BAG = REPO / 'bags' / 'garage_ramp_seed0'
CAMERA = '/camera/front/image_raw/compressed'
INFO = '/camera/front/camera_info'
TS = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture(scope='module')
def untrained_weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import torch

    from semfeat_ros.model.semfeatnet import SemFeatNet
    from semfeat_ros.model.weights_io import save_weights

    torch.manual_seed(0)
    return save_weights(SemFeatNet(), tmp_path_factory.mktemp('w') / 'untrained.safetensors',
                        {'class_names': list(load_labels().names), 'input_size': [640, 512]})


def read_all(path: Path) -> dict[str, list[tuple[int, object, bytes]]]:
    out: dict[str, list[tuple[int, object, bytes]]] = {}
    with AnyReader([path], default_typestore=TS) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype),
                                                   bytes(raw)))
    return out


def copy_topics(dst: Path, topics: set[str], seconds: float = 2.0) -> Path:
    """A bag with the first ``seconds`` of the shipped bag's ``topics``."""
    with AnyReader([BAG], default_typestore=TS) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        end = reader.start_time + int(seconds * 1e9)
        with Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            out = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=TS)
                   for c in conns}
            for c, t, raw in reader.messages(connections=conns):
                if t < end:
                    writer.write(out[c.topic], t, raw)
    return dst


def test_features_bag_topics_layout_and_stamps(tmp_path: Path, untrained_weights: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / 'feat'
    rc = tool.cli([str(BAG), '--out', str(out), '--weights', str(untrained_weights),
                   '--max-frames', '3', '--quiet'])
    assert rc == 0, capsys.readouterr().err
    assert '3 of 3 frames' in capsys.readouterr().out
    got = read_all(out)
    src = read_all(BAG)
    images = src[CAMERA][:3]
    assert set(got) == {'/semfeat/features', '/semfeat/semantic_mask', INFO}
    feats, masks = got['/semfeat/features'], got['/semfeat/semantic_mask']
    assert len(feats) == len(masks) == 3
    want = [(t, stamp_to_ns(m), m.header.frame_id) for t, m, _ in images]
    assert [(t, stamp_to_ns(m), m.header.frame_id) for t, m, _ in feats] == want
    assert [(t, stamp_to_ns(m), m.header.frame_id) for t, m, _ in masks] == want
    names = set(load_labels().names)
    for _, msg, _ in feats:
        assert msg.height == 1 and msg.width > 0
        assert fields_to_dtype(msg.fields, msg.point_step) == features_dtype(64)
        f = features_from_msg(msg)
        np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)
        assert (f.keypoints >= 0).all() and (f.keypoints <= [639, 511]).all()
        assert f.labels.max() < len(names)
        assert not np.isin(f.labels, [16, 17, 18]).any()  # sky and dynamic classes dropped
    for _, msg, _ in masks:
        assert msg.encoding == 'mono8'
        mask = image_to_numpy(msg)
        assert mask.shape == (512, 640)  # class ids, 255 outside the image circle
        assert set(np.unique(mask).tolist()) <= set(range(len(names))) | {255}
    # CameraInfo passed through byte for byte at the recorded times
    src_info = {t: raw for t, _, raw in src[INFO]}
    assert all(src_info[t] == raw for t, _, raw in got[INFO])
    assert len(got[INFO]) >= 3


def one_line_error(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and err.startswith('semfeat-features: error: '), err
    return err


def test_bad_inputs(tmp_path: Path, untrained_weights: Path,
                    capsys: pytest.CaptureFixture) -> None:
    w = ['--weights', str(untrained_weights), '--quiet']
    assert tool.cli([str(tmp_path / 'nope'), '--out', str(tmp_path / 'o1'), *w]) == 1
    assert 'does not exist' in one_line_error(capsys)

    broken = tmp_path / 'broken'
    broken.mkdir()
    (broken / 'metadata.yaml').write_bytes((BAG / 'metadata.yaml').read_bytes())
    (broken / 'garage_ramp_seed0.mcap').write_bytes(
        (BAG / 'garage_ramp_seed0.mcap').read_bytes()[:200_000])
    assert tool.cli([str(broken), '--out', str(tmp_path / 'o2'), *w]) == 1
    assert 'broken or truncated' in one_line_error(capsys)

    no_camera = copy_topics(tmp_path / 'no_camera', {INFO, '/vehicle/odom'})
    assert tool.cli([str(no_camera), '--out', str(tmp_path / 'o3'), *w]) == 1
    assert 'no camera topic' in one_line_error(capsys)
    assert not (tmp_path / 'o3').exists()

    no_info = copy_topics(tmp_path / 'no_info', {CAMERA})
    assert tool.cli([str(no_info), '--out', str(tmp_path / 'o4'), *w]) == 1
    assert "no topic '/camera/front/camera_info'" in one_line_error(capsys)

    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o5'), '--topic', INFO, *w]) == 1
    assert 'expected sensor_msgs/msg/Image or' in one_line_error(capsys)

    (tmp_path / 'exists').mkdir()
    assert tool.cli([str(BAG), '--out', str(tmp_path / 'exists'), *w]) == 1
    assert 'already exists' in one_line_error(capsys)

    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o6'), '--weights',
                     str(tmp_path / 'missing.safetensors'), '--quiet']) == 1
    assert 'missing.safetensors' in one_line_error(capsys)
    assert not (tmp_path / 'o6').exists()
