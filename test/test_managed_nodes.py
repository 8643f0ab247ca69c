"""Managed (lifecycle) nodes driven over DDS through their lifecycle_msgs services."""
from __future__ import annotations

from collections.abc import Callable
import signal
import subprocess
import sys
import threading
import time

from conftest import REPO, ros_env
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, PointCloud2

from msg_adapters import features_to_msg, model_to_camera_info
from semfeat_ros.camera import FisheyeCamera

CAM = FisheyeCamera(640, 512, 186.7, 186.7, 320.0, 256.0, k=(0.02, -0.004, 0.0005, -0.0001),
                    fov_deg=190)
UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = 1, 2, 3, 4


def frames(n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Keypoints (px) and unit descriptors of points ahead of a camera moving forward."""
    rng = np.random.default_rng(seed)
    pts = np.stack([rng.uniform(-8, 8, 500), rng.uniform(-3, 1.5, 500),
                    rng.uniform(4, 40, 500)], 1)
    desc = rng.normal(size=(500, 64))
    out = []
    for i in range(n):
        px, valid = CAM.project(pts - [0.0, 0.0, 0.2 * i])
        ok = valid & CAM.in_image(px, border=2)
        d = desc[ok] + rng.normal(0, 0.02, (ok.sum(), 64))
        out.append((px[ok], d / np.linalg.norm(d, axis=1, keepdims=True)))
    return out


class Probe:
    """The test's side: lifecycle service clients, the matcher's inputs, its tracks."""

    def __init__(self, node_name: str) -> None:
        self.node = Node('probe_lifecycle')
        self.change = self.node.create_client(ChangeState, f'/{node_name}/change_state')
        self.get = self.node.create_client(GetState, f'/{node_name}/get_state')
        self.tracks: list[PointCloud2] = []
        self.node.create_subscription(PointCloud2, '/semfeat/tracks', self.tracks.append, 100)
        self.pub = self.node.create_publisher(PointCloud2, '/semfeat/features', 100)
        self.pub_info = self.node.create_publisher(CameraInfo, '/camera/front/camera_info', 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        self.frames = frames(40)
        self.sent = 0

    def call(self, client, request, timeout: float = 120.0):
        assert client.wait_for_service(timeout_sec=60.0), client.srv_name
        future = client.call_async(request)
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert future.done(), f'{client.srv_name}: no answer in {timeout} s'
        return future.result()

    def state(self) -> int:
        return self.call(self.get, GetState.Request()).current_state.id

    def transition(self, transition_id: int) -> bool:
        req = ChangeState.Request()
        req.transition.id = transition_id
        return self.call(self.change, req).success

    def send(self, n: int) -> None:
        """``n`` frames (CameraInfo + features) at 20 Hz, stamps increasing across calls."""
        for _ in range(n):
            kp, desc = self.frames[self.sent % len(self.frames)]
            stamp = 10**9 + self.sent * 50_000_000
            self.pub_info.publish(model_to_camera_info(CAM, frame_id='camera_front_optical',
                                                       stamp_ns=stamp, msg_cls=CameraInfo))
            self.pub.publish(features_to_msg(
                kp, np.ones(len(kp)), np.zeros(len(kp), np.uint8), desc, stamp_ns=stamp,
                frame_id='camera_front_optical', msg_cls=PointCloud2))
            self.sent += 1
            time.sleep(0.05)

    def wait(self, cond: Callable[[], bool], timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not cond():
            time.sleep(0.05)
        return cond()

    def graph(self) -> tuple[int, int]:
        """Publishers of the tracks, subscriptions of the features."""
        return (self.node.count_publishers('/semfeat/tracks'),
                self.node.count_subscribers('/semfeat/features'))

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture
def managed_matcher(isolated_ros, tmp_path):
    log = (tmp_path / 'matcher_node.log').open('w')
    proc = subprocess.Popen(
        [sys.executable, '-m', 'semfeat_ros.nodes.managed', 'matcher_node', '--ros-args',
         '-p', 'input_timeout_s:=0.0'],
        cwd=REPO, env=ros_env(isolated_ros), stdout=log, stderr=subprocess.STDOUT)
    rclpy.init()
    probe = Probe('matcher_node')
    try:
        yield probe, proc, tmp_path / 'matcher_node.log'
    finally:
        probe.close()
        rclpy.try_shutdown()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
        log.close()


@pytest.mark.ros_domain(170)
@pytest.mark.timeout(600)
def test_lifecycle_transitions_publish_only_when_active(managed_matcher) -> None:
    probe, proc, log = managed_matcher
    assert probe.state() == UNCONFIGURED
    assert probe.graph() == (0, 0)  # nothing built before configure

    assert probe.transition(Transition.TRANSITION_CONFIGURE)
    assert probe.state() == INACTIVE
    assert probe.wait(lambda: probe.graph() == (1, 0)), probe.graph()  # outputs, no inputs
    probe.send(10)
    time.sleep(1.0)
    assert probe.tracks == [], 'inactive node published'

    for cycle in range(2):  # the second cycle: a configure after cleanup builds it all again
        assert probe.transition(Transition.TRANSITION_ACTIVATE)
        assert probe.state() == ACTIVE
        assert probe.wait(lambda: probe.graph() == (1, 1)), probe.graph()
        probe.send(20)
        assert probe.wait(lambda: len(probe.tracks) >= 10), \
            f'cycle {cycle}: {len(probe.tracks)} tracks messages while active'

        assert probe.transition(Transition.TRANSITION_DEACTIVATE)
        assert probe.state() == INACTIVE
        assert probe.wait(lambda: probe.graph() == (1, 0)), probe.graph()
        time.sleep(0.5)  # tracks still in flight
        before = len(probe.tracks)
        probe.send(10)
        time.sleep(1.0)
        assert len(probe.tracks) == before, 'deactivated node published'

        assert probe.transition(Transition.TRANSITION_CLEANUP)
        assert probe.state() == UNCONFIGURED
        assert probe.wait(lambda: probe.graph() == (0, 0)), probe.graph()
        if cycle == 0:
            assert probe.transition(Transition.TRANSITION_CONFIGURE)
            probe.tracks.clear()

    assert not probe.transition(Transition.TRANSITION_ACTIVATE)  # not from unconfigured
    assert probe.transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
    assert probe.state() == FINALIZED
    assert proc.poll() is None  # finalized, still answering until stopped
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=30) == 0, log.read_text()[-3000:]


@pytest.mark.ros_domain(171)
@pytest.mark.timeout(300)
def test_configure_fails_cleanly_on_a_bad_parameter(isolated_ros, tmp_path) -> None:
    """A parameter error fails configure with the reason logged; the node stays
    unconfigured, with nothing built."""
    log_path = tmp_path / 'mapping_node.log'
    with log_path.open('w') as log:
        proc = subprocess.Popen(
            [sys.executable, '-m', 'semfeat_ros.nodes.managed', 'mapping_node', '--ros-args',
             '-p', f'camera_config:={tmp_path / "missing.yaml"}'],
            cwd=REPO, env=ros_env(isolated_ros), stdout=log, stderr=subprocess.STDOUT)
    rclpy.init()
    probe = Probe('mapping_node')
    try:
        assert probe.state() == UNCONFIGURED
        assert not probe.transition(Transition.TRANSITION_CONFIGURE)
        assert probe.state() == UNCONFIGURED
        assert 'configure failed' in log_path.read_text()
        assert probe.node.count_publishers('/semantic_cloud') == 0
    finally:
        probe.close()
        rclpy.try_shutdown()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
