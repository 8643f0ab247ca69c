"""matcher_node in-process: persistent track ids against ground truth, resets, bad input."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from msg_adapters import features_to_msg, model_to_camera_info, tracks_from_msg
from semfeat_ros.camera import FisheyeCamera

CAM = FisheyeCamera(640, 512, 186.7, 186.7, 320.0, 256.0, k=(0.02, -0.004, 0.0005, -0.0001),
                    fov_deg=190)
N_POINTS = 600


def world(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points around a corridor (m) and one unit descriptor (D=64) per point."""
    rng = np.random.default_rng(seed)
    pts = np.stack([rng.uniform(-8, 8, N_POINTS), rng.uniform(-3, 1.5, N_POINTS),
                    rng.uniform(2, 40, N_POINTS)], 1)
    desc = rng.normal(size=(N_POINTS, 64))
    return pts, desc / np.linalg.norm(desc, axis=1, keepdims=True)


def observe(pts: np.ndarray, desc: np.ndarray, z: float, rng: np.random.Generator,
            outliers: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints (px), descriptors and ground-truth point ids (-1 = clutter) at camera z (m)."""
    px, valid = CAM.project(pts - [0.0, 0.0, z])
    ok = valid & CAM.in_image(px, border=2)
    ids = np.nonzero(ok)[0]
    kp = px[ok] + rng.normal(0, 0.3, (ok.sum(), 2))
    d = desc[ok] + rng.normal(0, 0.05, (ok.sum(), 64))
    clutter_kp = rng.uniform([0, 0], [639, 511], (outliers, 2))
    clutter_d = rng.normal(size=(outliers, 64))
    kp = np.concatenate([kp, clutter_kp])
    d = np.concatenate([d, clutter_d])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    gt = np.concatenate([ids, -np.ones(outliers, int)])
    keep = CAM.unproject(kp, check=False)
    good = np.isfinite(keep).all(axis=1)
    return kp[good], d[good], gt[good]


class Harness:
    def __init__(self) -> None:
        from semfeat_ros.nodes.matcher_node import MatcherNode

        self.node = MatcherNode()
        self.probe = Node('probe_matcher')
        self.tracks: list[PointCloud2] = []
        self.debug: list[Image] = []
        self.probe.create_subscription(PointCloud2, '/semfeat/tracks', self.tracks.append, 100)
        self.pub = self.probe.create_publisher(PointCloud2, '/semfeat/features', 100)
        self.pub_info = self.probe.create_publisher(CameraInfo, '/camera/front/camera_info', 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def wait(self, cond, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if cond():
                return True
            time.sleep(0.01)
        return cond()

    def send(self, stamp_ns: int, kp: np.ndarray, desc: np.ndarray) -> None:
        n = len(kp)
        self.pub.publish(features_to_msg(kp, np.ones(n), np.zeros(n, np.uint8), desc,
                                         stamp_ns=stamp_ns, frame_id='camera_front_optical',
                                         msg_cls=PointCloud2))

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture
def harness(isolated_ros):
    rclpy.init()
    h = Harness()
    assert h.wait(lambda: h.pub.get_subscription_count() > 0
                  and h.pub_info.get_subscription_count() > 0)
    yield h
    h.close()
    rclpy.try_shutdown()


@pytest.mark.ros_domain(79)
def test_track_ids_persist_and_agree_with_ground_truth(harness: Harness) -> None:
    h = harness
    pts, desc = world()
    rng = np.random.default_rng(1)
    h.pub_info.publish(model_to_camera_info(CAM, stamp_ns=0, frame_id='camera_front_optical',
                                            msg_cls=CameraInfo))
    time.sleep(0.3)
    gt_of: list[dict[int, int]] = []
    for i in range(8):
        kp, d, gt = observe(pts, desc, 0.4 * i, rng)
        h.send(10**9 + i * 10**8, kp, d)
        assert h.wait(lambda n=i: len(h.tracks) > n)
        out = tracks_from_msg(h.tracks[-1])
        # map published keypoints back to ground-truth ids by pixel position
        lookup = {tuple(np.round(p, 3)): g for p, g in zip(kp.astype(np.float32), gt)}
        gt_of.append({int(t): lookup.get(tuple(np.round(p, 3)), -2)
                      for p, t in zip(out.uv, out.track_ids)})
    # A track id always follows the same world point; clutter is (almost) never tracked.
    owners: dict[int, set[int]] = {}
    for frame in gt_of[1:]:
        for tid, g in frame.items():
            owners.setdefault(tid, set()).add(g)
    consistent = sum(len(g) == 1 and -1 not in g and -2 not in g for g in owners.values())
    assert len(owners) > 150
    assert consistent / len(owners) > 0.97
    last = tracks_from_msg(h.tracks[-1])
    assert last.ages.max() == 8  # tracked since the first frame
    np.testing.assert_allclose(np.linalg.norm(last.bearings, axis=1), 1.0, atol=1e-5)
    # Lone outliers (an older stamp, a CameraInfo of another size) are ignored and counted:
    # the tracks go on.
    h.pub_info.publish(model_to_camera_info(CAM.scaled(320, 256), stamp_ns=0,
                                            frame_id='camera_front_optical', msg_cls=CameraInfo))
    h.pub_info.publish(model_to_camera_info(CAM, stamp_ns=0, frame_id='camera_front_optical',
                                            msg_cls=CameraInfo))
    kp, d, _ = observe(pts, desc, 0.4, rng)
    h.send(10**9 + 10**8, kp, d)
    kp, d, _ = observe(pts, desc, 0.4 * 8, rng)
    h.send(10**9 + 8 * 10**8, kp, d)
    assert h.wait(lambda: len(h.tracks) >= 9)
    assert h.wait(lambda: h.node.health.counters.rejected == 2)
    last = tracks_from_msg(h.tracks[-1])
    assert len(h.tracks) == 9 and last.ages.max() == 9 and h.node.resets == 0
    assert h.node._camera.width == 640
    ids_before = set(int(t) for t in last.track_ids)
    # Time going backwards (bag loop) for change_confirm_messages (3) frames: tracks restart
    # with fresh ids, never reused, and the loop's first frames are tracked too.
    for i in range(3):
        kp, d, _ = observe(pts, desc, 0.4 * i, rng)
        h.send(10**9 + i * 10**8, kp, d)
    assert h.wait(lambda: len(h.tracks) >= 12)
    assert h.node.resets == 1 and h.node.health.counters.rejected == 2
    after = tracks_from_msg(h.tracks[-1])
    assert len(after.track_ids) > 100
    assert not ids_before & set(int(t) for t in after.track_ids)
    assert int(after.track_ids.min()) > max(ids_before)


@pytest.mark.ros_domain(90)
def test_bad_input_and_missing_camera_info(harness: Harness) -> None:
    h = harness
    pts, desc = world()
    rng = np.random.default_rng(2)
    kp, d, _ = observe(pts, desc, 0.0, rng)
    h.send(5, kp, d)  # no CameraInfo yet: skipped, not an input error
    assert h.wait(lambda: h.node.health.counters.waiting == 1)
    assert h.node.health.counters.rejected == 0
    assert h.node.health.status().message == 'no output yet: 1 inputs waiting for CameraInfo'
    bad_info = model_to_camera_info(CAM, stamp_ns=0, frame_id='c', msg_cls=CameraInfo)
    bad_info.k[4] = float('nan')
    h.pub_info.publish(bad_info)
    assert h.wait(lambda: h.node.health.counters.rejected == 1)
    h.pub_info.publish(model_to_camera_info(CAM, stamp_ns=0, frame_id='c', msg_cls=CameraInfo))
    time.sleep(0.2)
    wrong = PointCloud2(height=1, width=3, point_step=4, row_step=12, data=bytes(12))
    h.pub.publish(wrong)  # not the features layout
    assert h.wait(lambda: h.node.health.counters.rejected == 2)
    h.send(10, kp, d)
    h.send(10, kp, d)  # repeated stamp
    assert h.wait(lambda: h.node.health.counters.rejected == 3)
    kp2, d2, _ = observe(pts, desc, 0.4, rng)
    h.send(20, kp2, d2)
    assert h.wait(lambda: len(h.tracks) == 2)
    assert len(tracks_from_msg(h.tracks[-1]).track_ids) > 100


@pytest.mark.ros_domain(79)
def test_runtime_parameter_updates(isolated_ros) -> None:
    """Thresholds the matcher reads per frame change at run time; a read-only parameter or an
    out-of-range value is refused with its reason and changes nothing."""
    from rclpy.parameter import Parameter

    from semfeat_ros.nodes.matcher_node import MatcherNode

    rclpy.init()
    node = None
    try:
        node = MatcherNode()
        conf = node.matcher.conf
        (ok,) = node.set_parameters([Parameter('ratio_threshold', value=0.8)])
        assert ok.successful and conf['matching']['ratio_threshold'] == 0.8
        (ok,) = node.set_parameters([Parameter('min_inliers', value=20)])
        assert ok.successful and conf['verification']['min_inliers'] == 20
        (bad,) = node.set_parameters([Parameter('min_inliers', value=2)])
        assert not bad.successful and 'out of range' in bad.reason
        (bad,) = node.set_parameters([Parameter('seed', value=5)])
        assert not bad.successful and 'read-only' in bad.reason
        assert conf['verification']['min_inliers'] == 20 and conf['verification']['seed'] == 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
