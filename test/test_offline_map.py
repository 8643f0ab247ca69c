"""semfeat-map: front end -> matcher -> mapper over the shipped bag, offline, and its outputs.

The OpenCV ORB front end labelled by the bag's ground-truth class masks (``--labels
groundtruth``) stands in for the network (no trained weights needed). ORB needs the
car to move before the mapper initialises, so the end-to-end run maps 6 s of the ramp and the
covered level (``--start 12 --max-frames 60``, about 20 m).
"""
from __future__ import annotations

from collections import Counter
import json
from pathlib import Path

from conftest import REPO
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from msg_adapters import tracks_to_msg
from semfeat_ros.mapping import read_ply, read_tum
from semfeat_ros.offline.report import HEADLINE_KEYS
from semfeat_ros.tools import map as tool

BAG = REPO / 'bags' / 'garage_ramp_seed0'
CAMERA = '/camera/front/image_raw/compressed'
TS = get_typestore(Stores.ROS2_JAZZY)
PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
WINDOW = ['--start', '12', '--max-frames', '60']


@pytest.fixture(scope='module')
def orb_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, list]:
    """One ORB run on the ramp window; also records its /semfeat/tracks columns."""
    from semfeat_ros.offline import mapping_run

    out = tmp_path_factory.mktemp('map') / 'orb'
    tracks: list[tuple[int, str, dict]] = []
    real = mapping_run.run_mapping

    def recording(source, conf, progress=True, on_tracks=None):  # noqa: ANN001, ANN202
        return real(source, conf, progress,
                    on_tracks=lambda s, f, c: tracks.append((s, f, dict(c))))

    mapping_run_attr = tool.run_mapping
    tool.run_mapping = recording
    try:
        rc = tool.cli([str(BAG), '--out', str(out), '--frontend', 'orb', '--labels',
                       'groundtruth', '--quiet', *WINDOW])
    finally:
        tool.run_mapping = mapping_run_attr
    assert rc == 0
    return out, json.loads((out / 'metrics.json').read_text()), tracks


def test_orb_end_to_end_outputs(orb_run: tuple[Path, dict, list]) -> None:
    out, m, tracks = orb_run
    for name in ('cloud.ply', 'trajectory.tum', 'trajectory_online.tum', 'metrics.json',
                 'trajectory_top.png', 'altitude.png', 'cloud.png'):
        assert (out / name).is_file(), name
    for name in ('trajectory_top.png', 'altitude.png', 'cloud.png'):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    assert set(HEADLINE_KEYS) <= set(m)
    assert m['has_ground_truth'] and 'evaluation_error' not in m
    assert m['frames_read'] == 60 and m['frames_processed'] == 60
    assert m['run']['labels_source'] == 'ground truth /ground_truth/semantic'
    assert m['run']['odometry_used'] and m['run']['gnss_used']
    cloud = read_ply(out / 'cloud.ply')
    stamps, poses = read_tum(out / 'trajectory.tum')
    assert len(cloud) == m['cloud_points'] > 100
    assert len(stamps) == m['keyframes'] > 10  # with odometry the first frame is keyframe 0
    assert m['dynamic_points'] == 0
    assert not np.isin(cloud.label, [16, 17, 18]).any()
    assert m['keyframe_update_ms']['median'] > 0 and m['frontend_ms']['p95'] > 0
    assert m['matcher_ms']['median'] > 0
    # track length: frames a track id is published in, one value per track
    seen = Counter(i for _, _, c in tracks for i in c['track_id'].tolist())
    lengths = np.array(list(seen.values()), float)
    assert m['run']['track_length_frames']['n'] == len(seen) > 100
    assert m['track_length_frames']['median'] == pytest.approx(np.median(lengths))
    assert np.median(lengths) >= 2


def test_orb_accuracy_on_the_ramp(orb_run: tuple[Path, dict, list]) -> None:
    """Bounds ~3x above what this run measures (Sim(3) ATE ~0.10 m over ~20 m of ramp and
    covered level with odometry + GNSS; ramp altitude RMSE ~0.10 m; 82 % floor accuracy)."""
    _, m, _ = orb_run
    t = m['trajectory']
    assert t['gt_length_m'] > 15.0 and t['n_ramp_poses'] >= 5
    assert m['ate_sim3_rmse_m'] < 0.3
    assert m['ate_se3_rmse_m'] < 0.35  # metric scale from odometry
    assert abs(m['scale_sim3'] - 1.0) < 0.05
    assert m['ramp_altitude_rmse_sim3_m'] < 0.3 and m['ramp_altitude_max_sim3_m'] < 0.6
    assert m['floors']['gt_levels_m'] == pytest.approx([0.0, 3.6], abs=0.05)
    assert m['floor_accuracy'] > 0.6


def test_recorded_tracks_give_the_same_map(orb_run: tuple[Path, dict, list],
                                           tmp_path: Path) -> None:
    """--tracks-topic on the tracks of the same run (as matcher_node would publish them)
    reproduces the trajectory: offline frames and replayed tracks feed the same mapper."""
    out, m, tracks = orb_run
    assert len(tracks) == 60
    bag = tmp_path / 'tracks_bag'
    with AnyReader([BAG], default_typestore=TS) as reader:
        keep = [c for c in reader.connections if c.topic != CAMERA
                and not c.topic.startswith('/ground_truth/') or c.topic == '/ground_truth/pose']
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=TS)
                     for c in keep}
            tconn = writer.add_connection('/semfeat/tracks', 'sensor_msgs/msg/PointCloud2',
                                          typestore=TS)
            rows = [(t, conns[c.topic], raw) for c, t, raw in reader.messages(connections=keep)]
            for stamp, frame, c in tracks:
                msg = tracks_to_msg(np.stack([c['u'], c['v']], 1),
                                    np.stack([c['bx'], c['by'], c['bz']], 1), c['label'],
                                    c['track_id'], c['age'], c['score'], stamp_ns=stamp,
                                    frame_id=frame, msg_cls=TS)
                rows.append((stamp, tconn, TS.serialize_cdr(msg, tconn.msgtype)))
            for t, conn, raw in sorted(rows, key=lambda r: r[0]):
                writer.write(conn, t, raw)
    out2 = tmp_path / 'replay'
    # the tracks are ORB's: the mapper is told their keypoint noise, as semfeat-map --frontend orb
    assert tool.cli([str(bag), '--out', str(out2), '--tracks-topic', '/semfeat/tracks',
                     '--quiet', '--no-figures', '--start', '12',
                     '--set', f'bearing_sigma_px={tool.OPENCV_BEARING_SIGMA_PX}']) == 0
    m2 = json.loads((out2 / 'metrics.json').read_text())
    assert m2['run']['frontend'] == 'tracks' and m2['frames_processed'] == 60
    s1, p1 = read_tum(out / 'trajectory.tum')
    s2, p2 = read_tum(out2 / 'trajectory.tum')
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_allclose(p2, p1, atol=1e-6)
    assert m2['cloud_points'] == m['cloud_points']


def test_without_odometry_and_gnss(tmp_path: Path) -> None:
    out = tmp_path / 'bare'
    assert tool.cli([str(BAG), '--out', str(out), '--frontend', 'orb', '--labels', 'none',
                     '--no-odometry', '--no-gnss', '--max-frames', '12', '--quiet',
                     '--no-figures']) == 0
    m = json.loads((out / 'metrics.json').read_text())
    assert m['config']['use_odometry'] is False and m['config']['use_gnss'] is False
    assert not m['run']['odometry_used'] and not m['run']['gnss_used']
    assert m['run']['counts']['odometry_messages'] == 0 == m['run']['counts']['gnss_fixes']
    assert m['frames_processed'] == 12
    # 12 frames of the deck are too few to initialise: reported, not invented
    assert m['ate_sim3_rmse_m'] is None and 'evaluation_error' in m


def one_line_error(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and err.startswith('semfeat-map: error: '), err
    return err


def test_bad_inputs_and_confinement(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    base = ['--frontend', 'orb', '--labels', 'none', '--quiet', '--no-figures']
    assert tool.cli([str(tmp_path / 'nope'), '--out', str(tmp_path / 'o'), *base]) == 1
    assert 'does not exist' in one_line_error(capsys)

    broken = tmp_path / 'broken.mcap'
    broken.write_bytes((BAG / 'garage_ramp_seed0.mcap').read_bytes()[:100_000])
    assert tool.cli([str(broken), '--out', str(tmp_path / 'o'), *base]) == 1
    assert 'broken or truncated' in one_line_error(capsys)

    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--topic', '/nope', *base]) == 1
    assert "no topic '/nope'" in one_line_error(capsys)

    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--tracks-topic',
                     '/semfeat/tracks', *base]) == 1
    assert "no topic '/semfeat/tracks'" in one_line_error(capsys)

    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--set', 'bogus=1', *base]) == 1
    assert 'bogus' in one_line_error(capsys)
    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--set',
                     'voxel_size_m=-1', *base]) == 1
    assert 'voxel_size_m' in one_line_error(capsys)

    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--frontend', 'semfeat',
                     '--weights', str(tmp_path / 'missing.safetensors'), '--quiet']) == 1
    assert 'missing.safetensors' in one_line_error(capsys)

    # an output name that is a symbolic link leading out of --out is refused before any work
    out = tmp_path / 'confined'
    out.mkdir()
    victim = tmp_path / 'victim.ply'
    victim.write_text('precious')
    (out / 'cloud.ply').symlink_to(victim)
    assert tool.cli([str(BAG), '--out', str(out), '--max-frames', '2', *base]) == 1
    assert 'outside the output directory' in one_line_error(capsys)
    assert victim.read_text() == 'precious'
    assert not (out / 'metrics.json').exists()

    (tmp_path / 'a_file').write_text('x')
    assert tool.cli([str(BAG), '--out', str(tmp_path / 'a_file'), *base]) == 1
    assert 'not a directory' in one_line_error(capsys)


def test_network_frontend_plumbing(tmp_path: Path) -> None:
    """--frontend semfeat runs feature_node's front end (untrained weights: plumbing only)."""
    import torch

    from semfeat_ros.labels import load_labels
    from semfeat_ros.model.semfeatnet import SemFeatNet
    from semfeat_ros.model.weights_io import save_weights

    torch.manual_seed(0)
    weights = save_weights(SemFeatNet(), tmp_path / 'untrained.safetensors',
                           {'class_names': list(load_labels().names), 'input_size': [640, 512]})
    out = tmp_path / 'net'
    assert tool.cli([str(BAG), '--out', str(out), '--weights', str(weights), '--max-frames',
                     '3', '--quiet', '--no-figures']) == 0
    m = json.loads((out / 'metrics.json').read_text())
    assert m['run']['frontend'] == 'semfeat' and m['run']['labels_source'] == 'network'
    assert m['run']['frontend_description'].startswith('SemFeatNet')
    assert m['frames_processed'] == 3 and m['run']['features_per_frame']['median'] > 0
    assert m['frontend_ms']['median'] > 0 and m['matcher_ms']['median'] > 0
