"""Recordings: written with rosbags, readable with AnyReader, deterministic; the shipped bag."""
from __future__ import annotations

import hashlib
from pathlib import Path
import shutil

from conftest import REPO
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
import yaml

from msg_adapters import (
    camera_info_to_model,
    compressed_to_numpy,
    image_to_numpy,
    stamp_to_ns,
)
from semfeat_ros.sim import bag as simbag
from semfeat_ros.sim.bag import BagConfig, write_bag
from semfeat_ros.sim.errors import BagWriteError, SimConfigError
from semfeat_ros.sim.scenario import Scenario

SHIPPED = REPO / 'bags' / 'garage_ramp_seed0'
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture(scope='module')
def scenario() -> Scenario:
    return Scenario.create(seed=2, size=(96, 80))


def read_all(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=TYPESTORE) as reader:
        for conn, stamp, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            out.setdefault(conn.topic, []).append((stamp, conn.msgtype, msg))
    return out


def digest(path: Path) -> str:
    h = hashlib.sha256()
    for f in sorted(path.iterdir()):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


@pytest.mark.parametrize('storage,compressed', [('mcap', True), ('sqlite3', False)])
def test_bag_contents(tmp_path: Path, scenario: Scenario, storage: str,
                      compressed: bool) -> None:
    cfg = BagConfig(seed=2, duration=0.6, rate=5.0, size=(96, 80), start=44.0,
                    storage=storage, compressed=compressed, depth_every=2)
    summary = write_bag(tmp_path / 'b', cfg, scenario=scenario, progress=False)
    msgs = read_all(tmp_path / 'b')
    image_topic = simbag.TOPIC_COMPRESSED if compressed else simbag.TOPIC_IMAGE
    assert set(msgs) >= {image_topic, simbag.TOPIC_INFO, simbag.TOPIC_ODOM,
                         simbag.TOPIC_GT_POSE, simbag.TOPIC_GT_SEMANTIC, simbag.TOPIC_GT_DEPTH}
    assert len(msgs[image_topic]) == summary.frames == 3
    assert len(msgs[simbag.TOPIC_GT_DEPTH]) == 2 and len(msgs[simbag.TOPIC_ODOM]) == 30
    for stamp, _, info in msgs[simbag.TOPIC_INFO]:
        assert stamp == stamp_to_ns(info) and info.header.frame_id == simbag.CAMERA_FRAME
        model = camera_info_to_model(info)
        assert model.distortion_model == 'equidistant'
        assert (model.width, model.height) == (96, 80)
        np.testing.assert_allclose(model.K, scenario.camera.K)
    _, _, img = msgs[image_topic][0]
    rgb = compressed_to_numpy(img) if compressed else image_to_numpy(img)
    assert rgb.shape == (80, 96, 3) and rgb.dtype == np.uint8
    _, _, sem = msgs[simbag.TOPIC_GT_SEMANTIC][0]
    lab = image_to_numpy(sem)
    assert sem.encoding == 'mono8' and np.all(lab[~scenario.renderer.valid] == 255)
    assert np.all(lab[scenario.renderer.valid] < 19)
    _, _, dep = msgs[simbag.TOPIC_GT_DEPTH][0]
    depth = image_to_numpy(dep)
    assert dep.encoding == '32FC1' and np.isnan(depth[~scenario.renderer.valid]).all()
    _, _, pose = msgs[simbag.TOPIC_GT_POSE][0]
    T = scenario.base_pose(44.0)
    assert pose.header.frame_id == 'map'
    np.testing.assert_allclose([pose.pose.position.x, pose.pose.position.y,
                                pose.pose.position.z], T[:3, 3], atol=1e-9)
    _, _, odom = msgs[simbag.TOPIC_ODOM][-1]
    assert odom.header.frame_id == 'odom' and odom.child_frame_id == 'base_link'
    assert odom.twist.twist.linear.x > 1.0
    stamps = [s for topic in msgs.values() for s, _, _ in topic]
    assert min(stamps) == simbag.STAMP0_NS + 44 * 10 ** 9
    meta = yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == storage


def test_bag_is_deterministic_and_refuses_overwrite(tmp_path: Path, scenario: Scenario) -> None:
    cfg = BagConfig(seed=2, duration=0.4, rate=5.0, size=(96, 80), start=10.0)
    out = tmp_path / 'same'
    write_bag(out, cfg, scenario=scenario, progress=False)
    first = digest(out)
    with pytest.raises(BagWriteError, match='exists'):
        write_bag(out, cfg, scenario=scenario, progress=False)
    shutil.rmtree(out)
    write_bag(out, cfg, scenario=Scenario.create(seed=2, size=(96, 80)), progress=False)
    assert digest(out) == first
    with pytest.raises(SimConfigError, match='exceeds the drive'):
        write_bag(tmp_path / 'late', BagConfig(seed=2, duration=30.0, start=80.0,
                                               size=(96, 80)), scenario=scenario)


def test_gnss_messages(tmp_path: Path, scenario: Scenario) -> None:
    cfg = BagConfig(seed=2, duration=1.0, rate=2.0, size=(96, 80), start=2.0)
    write_bag(tmp_path / 'g', cfg, scenario=scenario, progress=False)
    fixes = read_all(tmp_path / 'g')[simbag.TOPIC_GNSS]
    assert len(fixes) == 5
    for _, msgtype, fix in fixes:
        assert msgtype == 'sensor_msgs/msg/NavSatFix'
        assert fix.status.status == 2 and fix.position_covariance_type == 2
        assert 1e-5 < fix.position_covariance[0] < 1e-3  # ~1.5 cm RTK on the open deck
        assert abs(fix.latitude - 48.137) < 0.01 and fix.header.frame_id == 'gnss_link'


def test_shipped_bag() -> None:
    """bags/garage_ramp_seed0: regenerate with the command in bags/README.md."""
    assert (REPO / 'bags' / 'README.md').read_text().count('--start ramp') >= 1
    meta = yaml.safe_load((SHIPPED / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9
    msgs = read_all(SHIPPED)
    images = msgs[simbag.TOPIC_COMPRESSED]
    assert len(images) == 200
    duration = (images[-1][0] - images[0][0]) / 1e9
    assert duration == pytest.approx(19.9, abs=1e-6)
    rgb = compressed_to_numpy(images[100][2])
    assert rgb.shape == (512, 640, 3)
    z = np.array([m.pose.position.z for _, _, m in msgs[simbag.TOPIC_GT_POSE]])
    assert z[0] == pytest.approx(3.6) and z[-1] == pytest.approx(0.0)  # deck -> covered
    assert ((z > 0.1) & (z < 3.5)).sum() > 30  # on the ramp for a while
    gnss_t = [s for s, _, _ in msgs[simbag.TOPIC_GNSS]]
    assert gnss_t[0] == images[0][0] and gnss_t[-1] < images[-1][0] - 10 ** 9
