"""mapping_node in-process on the synthetic two-level garage: poses, latched cloud, service."""
from __future__ import annotations

from pathlib import Path
import threading
import time

from nav_msgs.msg import Odometry
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, PointCloud2
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from msg_adapters import (
    model_to_camera_info,
    odometry_from_numpy,
    odometry_to_numpy,
    pointcloud2_to_array,
    semantic_cloud_from_msg,
    tracks_to_msg,
)
from semfeat_ros.camera import FisheyeCamera, load_camera_yaml
from semfeat_ros.labels import load_labels
from semfeat_ros.mapping import align_umeyama, read_tum
from semfeat_ros.mapping.synthetic import DriveConfig, garage_drive
from semfeat_ros.nodes.tf import TF_QOS, TF_STATIC_SUB_QOS, transform_msg, transform_to_matrix

CAM = FisheyeCamera(640, 512, 186.7, 186.7, 320.0, 256.0, k=(0.02, -0.004, 0.0005, -0.0001),
                    fov_deg=190)


def planar(T: np.ndarray) -> np.ndarray:
    """What a wheel odometry reports: x, y, yaw of the pose, z = 0."""
    yaw = np.arctan2(T[1, 0], T[0, 0])
    P = np.eye(4)
    P[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    P[:2, 3] = T[:2, 3]
    return P


class Harness:
    """mapping_node and a probe node (tracks, CameraInfo and odometry publishers) on one
    executor spinning in a thread; ``rclpy`` is initialised here and shut down by close().
    ``reliable``: the sensor inputs reliable, as in a bag replay (the probe publishes reliable;
    a best-effort input may lose a sample on a loaded machine, and these tests count them)."""

    def __init__(self, overrides: list[Parameter], name: str, reliable: bool = True) -> None:
        from semfeat_ros.nodes.mapping_node import MappingNode

        if reliable:
            overrides = [Parameter('input_reliability', value='reliable'), *overrides]
        rclpy.init()
        self.node = MappingNode(parameter_overrides=overrides)
        self.probe = Node(name)
        self.pub_tracks = self.probe.create_publisher(PointCloud2, '/semfeat/tracks', QoSProfile(
            depth=500, reliability=ReliabilityPolicy.RELIABLE))
        self.pub_info = self.probe.create_publisher(CameraInfo, '/camera/front/camera_info', 10)
        self.pub_odom = self.probe.create_publisher(Odometry, '/vehicle/odom', 500)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    @staticmethod
    def wait(cond, timeout: float = 60.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not cond():
            time.sleep(0.01)
        return cond()

    def start(self) -> None:
        """Wait for discovery and send the CameraInfo (the node then has a session)."""
        assert self.wait(lambda: self.pub_tracks.get_subscription_count() > 0
                         and self.pub_info.get_subscription_count() > 0
                         and self.pub_odom.get_subscription_count() > 0)
        self.pub_info.publish(model_to_camera_info(
            CAM, stamp_ns=0, frame_id='camera_front_optical', msg_cls=CameraInfo))
        assert self.wait(lambda: self.node.feeder is not None)

    def send_odom(self, frame, cov: np.ndarray | None = None) -> None:
        self.pub_odom.publish(odometry_from_numpy(
            planar(frame.T_map_base), cov, stamp_ns=frame.tracks.stamp_ns, frame_id='odom',
            child_frame_id='base_link', msg_cls=Odometry))

    def send_tracks(self, frame) -> None:
        tr = frame.tracks
        self.pub_tracks.publish(tracks_to_msg(
            tr.pixel, tr.bearing, tr.label, tr.track_id, np.full(len(tr), 2), np.ones(len(tr)),
            stamp_ns=tr.stamp_ns, frame_id='camera_front_optical', msg_cls=PointCloud2))

    def settle_tracks_topic(self) -> None:
        """Both ends of the tracks topic matched: a burst right after discovery can lose its
        head."""
        assert self.wait(lambda: self.node.count_publishers('/semfeat/tracks') > 0)
        time.sleep(0.5)

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=10.0)  # the spin thread must be out before the node is destroyed
        self.node.destroy_node()
        self.probe.destroy_node()
        rclpy.try_shutdown()


def drive_frames(n: int | None = None) -> list:
    _, ext = load_camera_yaml()
    frames = list(garage_drive(CAM, ext.T_base_cam, DriveConfig(seed=3)).frames())
    return frames if n is None else frames[:n]


@pytest.mark.ros_domain(96)
def test_mapping_node_on_synthetic_garage(isolated_ros, tmp_path: Path) -> None:
    h = Harness([Parameter('output_dir', value=str(tmp_path / 'map')),
                 Parameter('cloud_period_s', value=0.2), Parameter('use_gnss', value=False)],
                'probe_mapping')
    poses: list[Odometry] = []
    h.probe.create_subscription(Odometry, '/semfeat/odometry', poses.append, 500)
    tf: list[TFMessage] = []
    tf_static: list[TFMessage] = []
    h.probe.create_subscription(TFMessage, '/tf', tf.append, TF_QOS)
    h.probe.create_subscription(TFMessage, '/tf_static', tf_static.append, TF_STATIC_SUB_QOS)
    node, probe, wait = h.node, h.probe, h.wait
    try:
        h.start()
        gt = {}
        n = 0
        for frame in drive_frames():
            gt[frame.tracks.stamp_ns] = frame.T_map_base
            h.send_odom(frame, np.eye(6) * 1e-4)
            h.send_tracks(frame)
            n += 1
            assert wait(lambda k=n: node.health.counters.processed >= k, 30)
        assert node.health.counters.rejected == 0
        assert wait(lambda: len(poses) >= n * 0.8)
        est = {}
        for m in poses:
            s = odometry_to_numpy(m)
            est[s.stamp_ns] = s.T
        common = sorted(set(est) & set(gt))
        E = np.array([est[s][:3, 3] for s in common])
        G = np.array([gt[s][:3, 3] for s in common])
        sim = align_umeyama(E, G, with_scale=True)
        err = np.linalg.norm(sim.apply(E) - G, axis=1)
        assert np.sqrt(np.mean(err**2)) < 0.3, f'ATE {np.sqrt(np.mean(err**2)):.3f} m'
        assert abs(sim.s - 1.0) < 0.05  # metric from wheel odometry

        # TF: map -> odom -> base_link at each pose's image stamp; the chain is the pose, and
        # odom -> base_link the wheel odometry sent at that stamp; base_link -> camera static
        assert wait(lambda: len(tf) >= len(poses))
        chains = {}
        for m in tf:
            (a, b) = m.transforms
            assert (a.header.frame_id, a.child_frame_id) == ('map', 'odom')
            assert (b.header.frame_id, b.child_frame_id) == ('odom', 'base_link')
            assert a.header.stamp == b.header.stamp
            stamp = a.header.stamp.sec * 10**9 + a.header.stamp.nanosec
            chains[stamp] = (transform_to_matrix(a), transform_to_matrix(b))
        assert set(chains) == set(est)
        for stamp, (T_map_odom, T_odom_base) in chains.items():
            np.testing.assert_allclose(T_map_odom @ T_odom_base, est[stamp], atol=1e-6)
            np.testing.assert_allclose(T_odom_base, planar(gt[stamp]), atol=1e-6)
        assert wait(lambda: len(tf_static) >= 1)
        (static,) = tf_static[-1].transforms
        assert (static.header.frame_id, static.child_frame_id) == ('base_link',
                                                                   'camera_front_optical')
        np.testing.assert_allclose(transform_to_matrix(static), load_camera_yaml()[1].T_base_cam,
                                   atol=1e-9)
        assert node.extrinsic_source == 'camera_config'

        # A late subscriber still gets the latched map.
        clouds: list[PointCloud2] = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        probe.create_subscription(PointCloud2, '/semantic_cloud', clouds.append, latched)
        assert wait(lambda: len(clouds) >= 1, 20)
        msg = clouds[-1]
        assert msg.header.frame_id == 'map'
        names = [f.name for f in msg.fields]
        assert names == ['x', 'y', 'z', 'rgb', 'label', 'floor', 'landmark_id', 'n_obs']
        cloud = semantic_cloud_from_msg(msg)
        labels = load_labels()
        assert len(cloud.xyz) > 200
        assert labels.static[cloud.labels].all()
        assert len(np.unique(cloud.floors)) >= 2
        assert np.isfinite(pointcloud2_to_array(msg)['x']).all()

        client = probe.create_client(Trigger, '/mapping_node/save_map')
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        assert wait(future.done, 30)
        assert future.result().success, future.result().message
        assert (tmp_path / 'map' / 'cloud.ply').stat().st_size > 1000
        assert len((tmp_path / 'map' / 'trajectory.tum').read_text().splitlines()) > 10
    finally:
        h.close()


@pytest.mark.ros_domain(81)
def test_frames_wait_for_odometry_that_arrives_after_them(isolated_ros) -> None:
    # live, tracks can reach mapping_node before the wheel odometry around their stamp: every
    # frame must still be mapped with its own motion (without it the keyframe chain breaks)
    frames = drive_frames(60)
    h = Harness([Parameter('use_gnss', value=False)], 'probe_odom_late')
    node = h.node
    try:
        h.start()
        h.send_odom(frames[0], np.eye(6) * 1e-4)
        assert h.wait(lambda: node.feeder.last_odom >= 0)
        h.settle_tracks_topic()
        lag = 2  # frames
        for i, f in enumerate(frames):
            h.send_tracks(f)
            time.sleep(0.02)
            if i >= lag:
                h.send_odom(frames[i - lag + 1], np.eye(6) * 1e-4)
            if i == 3 * lag:  # frames 0 .. i - lag + 1 have their odometry; the rest wait
                assert h.wait(lambda k=i: node.health.counters.received == k + 1)
                assert h.wait(lambda k=i: node.health.counters.processed == k - lag + 2)
                time.sleep(0.3)
                assert node.health.counters.processed == i - lag + 2
        for i in range(len(frames) - lag + 1, len(frames)):
            h.send_odom(frames[i], np.eye(6) * 1e-4)
        assert h.wait(lambda: node.health.counters.processed >= len(frames), 60)
        with node._lock:
            missing = dict(node.session.odometry_missing)
            stamps, poses = node.session.mapper.trajectory()
        assert missing == {'ahead': 0, 'gap': 0, 'behind': 0}
        assert node.health.counters.rejected == 0 and node.health.counters.dropped == 0
        gt = {f.tracks.stamp_ns: f.T_map_base for f in frames}
        E = poses[:, :3, 3]
        G = np.array([gt[int(s)][:3, 3] for s in stamps])
        assert abs(align_umeyama(E, G, with_scale=True).s - 1.0) < 0.05  # metric: odometry used
    finally:
        h.close()


@pytest.mark.ros_domain(84)
def test_backlog_is_bounded_when_the_odometry_stalls(isolated_ros, tmp_path: Path) -> None:
    frames = drive_frames(12)
    h = Harness([Parameter('use_gnss', value=False), Parameter('odom_wait_s', value=10.0),
                 Parameter('max_backlog', value=3), Parameter('output_dir', value=str(tmp_path))],
                'probe_backlog')
    node, wait = h.node, h.wait
    try:
        h.start()
        h.send_odom(frames[0])
        assert wait(lambda: node.feeder.last_odom >= 0)
        h.settle_tracks_topic()
        for f in frames:  # the odometry stalls after the first frame: every later frame waits
            h.send_tracks(f)
            time.sleep(0.02)  # a 50 Hz stream: a burst beyond the subscription's depth (10)
            #                   could be overwritten before the executor takes it
        assert wait(lambda: node.health.counters.received == len(frames))
        assert wait(lambda: node.health.counters.processed + node.health.counters.dropped
                    + len(node.feeder.pending) == len(frames))
        assert node.health.counters.processed == 1  # frame 0: its odometry was in
        assert len(node.feeder.pending) == 3  # the newest max_backlog frames wait
        assert node.health.counters.dropped == len(frames) - 4
        assert [t.stamp_ns for t, _ in node.feeder.pending] == \
            [f.tracks.stamp_ns for f in frames[-3:]]
        client = h.probe.create_client(Trigger, '/mapping_node/save_map')
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())  # maps the waiting frames first
        assert wait(future.done, 30) and future.result().success
        assert len(node.feeder.pending) == 0 and node.health.counters.processed == 4
    finally:
        h.close()


def call_save_map(h: Harness) -> Trigger.Response:
    client = h.probe.create_client(Trigger, '/mapping_node/save_map')
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(Trigger.Request())
    assert h.wait(future.done, 30)
    return future.result()


@pytest.mark.ros_domain(68)
def test_save_map_service_never_writes_through_symlinks(isolated_ros, tmp_path: Path) -> None:
    out, outside = tmp_path / 'map', tmp_path / 'outside'
    out.mkdir()
    outside.mkdir()
    (outside / 'victim.txt').write_text('keep me')
    (out / 'cloud.ply').symlink_to(outside / 'victim.txt')
    (out / 'trajectory.tum').symlink_to(outside / 'created.tum')  # dangling
    h = Harness([Parameter('output_dir', value=str(out)), Parameter('use_gnss', value=False)],
                'probe_save_symlink')
    try:
        h.start()
        res = call_save_map(h)
        assert not res.success and 'symlink' in res.message, res.message
        assert (outside / 'victim.txt').read_text() == 'keep me'
        assert sorted(p.name for p in outside.iterdir()) == ['victim.txt']
        (out / 'cloud.ply').unlink()
        (out / 'trajectory.tum').unlink()
        res = call_save_map(h)
        assert res.success, res.message
        assert sorted(p.name for p in out.iterdir()) == ['cloud.ply', 'map.json',
                                                          'trajectory.tum']
    finally:
        h.close()


@pytest.mark.ros_domain(85)
def test_lone_outliers_never_reset_the_map_and_a_persisting_change_does(
        isolated_ros, tmp_path: Path) -> None:
    frames = drive_frames(40)
    h = Harness([Parameter('use_gnss', value=False), Parameter('output_dir', value=str(tmp_path)),
                 Parameter('min_change_interval_s', value=1.0)], 'probe_outliers')
    node, wait = h.node, h.wait
    other = CAM.scaled(320, 256)

    def info(cam: FisheyeCamera, frame_id: str = 'camera_front_optical') -> CameraInfo:
        return model_to_camera_info(cam, stamp_ns=0, frame_id=frame_id, msg_cls=CameraInfo)

    def feed(fs: list) -> None:
        for f in fs:
            h.send_odom(f, np.eye(6) * 1e-4)
            h.send_tracks(f)
            time.sleep(0.02)

    try:
        h.start()
        h.settle_tracks_topic()
        feed(frames[:25])
        assert wait(lambda: node.health.counters.processed >= 25)
        session = node.session
        with node._lock:
            n_before = len(session.mapper.trajectory()[0])
        assert n_before > 3
        # lone outliers: another size, another frame, an older tracks stamp, each followed by
        # the normal stream
        h.pub_info.publish(info(other))
        h.pub_info.publish(info(CAM))
        h.pub_info.publish(info(CAM, 'another_frame'))
        h.pub_info.publish(info(CAM))
        h.send_tracks(frames[3])
        feed(frames[25:30])
        assert wait(lambda: node.health.counters.processed >= 30)
        assert wait(lambda: node.health.counters.rejected == 3)
        assert node.session is session and node.resets == {'camera': 0, 'time': 0}
        with node._lock:
            assert len(session.mapper.trajectory()[0]) >= n_before
        assert not (tmp_path / 'before_reset').exists()
        values = {kv.key: kv.value for kv in node.health.status().values}
        assert values['resets_camera'] == '0' and values['resets_time'] == '0'
        # a bag loop: the older stamps persist, the map restarts (saved first) and the loop's
        # frames are mapped
        processed = node.health.counters.processed
        feed(frames[:6])
        assert wait(lambda: node.resets['time'] == 1)
        assert wait(lambda: node.health.counters.processed >= processed + 5)
        assert len(read_tum(tmp_path / 'before_reset' / 'trajectory.tum')[0]) >= n_before
        # a camera swap persists: the map restarts, at most once per min_change_interval_s
        for _ in range(100):  # CameraInfo comes with every frame; the reset may wait 1 s
            h.pub_info.publish(info(other))
            if wait(lambda: node.resets['camera'] == 1, 0.1):
                break
        assert node.resets['camera'] == 1
        assert wait(lambda: node.session is not session and node._camera_key[0].width == 320)
        node._publish_diagnostics()
        values = {kv.key: kv.value for kv in node.health.status().values}
        assert values['resets_camera'] == '1' and values['resets_time'] == '1'
        assert values['change_outliers_ignored'] == '3'
        assert node.health.counters.rejected == 3
    finally:
        h.close()


@pytest.mark.ros_domain(86)
def test_extrinsic_from_tf_static_and_tf_without_odometry(isolated_ros) -> None:
    """A URDF's base_link -> mount -> camera chain on /tf_static replaces camera_config (and
    the node then publishes no static transform of its own); without wheel odometry /tf
    carries map -> base_link."""
    T_mount = np.eye(4)
    T_mount[:3, 3] = (2.0, 0.1, 1.2)
    T_cam = np.array([[0, 0, 1, 0.05], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    h = Harness([Parameter('use_gnss', value=False), Parameter('use_odometry', value=False)],
                'probe_tf_static')
    pub = h.probe.create_publisher(TFMessage, '/tf_static', latched)  # the URDF's publisher
    pub.publish(TFMessage(transforms=[
        transform_msg(T_mount, 'base_link', 'camera_mount', 0),
        transform_msg(T_cam, 'camera_mount', 'camera_front_optical', 0)]))
    tf: list[TFMessage] = []
    h.probe.create_subscription(TFMessage, '/tf', tf.append, TF_QOS)
    node = h.node
    try:
        assert h.wait(lambda: node.static_frames.lookup('base_link', 'camera_front_optical')
                      is not None, 20)
        assert h.wait(lambda: h.pub_tracks.get_subscription_count() > 0
                      and h.pub_info.get_subscription_count() > 0)
        h.pub_info.publish(model_to_camera_info(
            CAM, stamp_ns=0, frame_id='camera_front_optical', msg_cls=CameraInfo))
        assert h.wait(lambda: node.feeder is not None)
        assert node.extrinsic_source == 'tf_static'
        np.testing.assert_allclose(node.T_base_cam, T_mount @ T_cam, atol=1e-9)
        assert node._own_static == {}  # camera_config was not broadcast
        h.settle_tracks_topic()
        for f in drive_frames(8):
            h.send_tracks(f)
            time.sleep(0.02)
        assert h.wait(lambda: node.health.counters.processed >= 8)
        assert h.wait(lambda: len(tf) >= 1)
        for m in tf:
            (t,) = m.transforms
            assert (t.header.frame_id, t.child_frame_id) == ('map', 'base_link')
    finally:
        h.close()


@pytest.mark.ros_domain(87)
def test_sensor_qos_silent_inputs_and_diagnostics_levels(isolated_ros) -> None:
    """Best-effort CameraInfo, odometry and GNSS publishers are matched and received; a
    best-effort tracks publisher against the reliable tracks input is an incompatible-QoS event;
    a silent input makes /diagnostics ERROR; drops above drop_warn_ratio make it WARN."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import NavSatFix

    h = Harness([Parameter('input_timeout_s', value=1.0)], 'probe_qos', reliable=False)
    assert h.node.conf.input_reliability == 'best_effort'  # the default
    node, probe, wait = h.node, h.probe, h.wait
    info = probe.create_publisher(CameraInfo, '/camera/front/camera_info',
                                  qos_profile_sensor_data)
    odom = probe.create_publisher(Odometry, '/vehicle/odom', qos_profile_sensor_data)
    gnss = probe.create_publisher(NavSatFix, '/gnss/fix', qos_profile_sensor_data)
    tracks = probe.create_publisher(PointCloud2, '/semfeat/tracks', qos_profile_sensor_data)
    try:
        assert wait(lambda: all(p.get_subscription_count() > 0 for p in (info, odom, gnss)), 20)
        assert tracks.get_subscription_count() == 0  # reliable input, best-effort publisher
        assert wait(lambda: node.health.io.incompatible >= 1, 20)
        frames = drive_frames(2)
        for i in range(50):  # best effort: sent until taken (odometry stamps increasing)
            info.publish(model_to_camera_info(CAM, stamp_ns=0, frame_id='camera_front_optical',
                                              msg_cls=CameraInfo))
            odom.publish(odometry_from_numpy(planar(frames[0].T_map_base), None,
                                             stamp_ns=frames[0].tracks.stamp_ns + i * 10**6,
                                             frame_id='odom', child_frame_id='base_link',
                                             msg_cls=Odometry))
            if wait(lambda: node.feeder is not None and node.feeder.last_odom >= 0, 0.1):
                break
        assert node.feeder is not None and node.feeder.last_odom >= 0
        # nothing on the tracks input since start-up: ERROR, naming the topic
        assert wait(lambda: node.health.status().level == DiagnosticStatus.ERROR, 10)
        status = node.health.status()
        assert status.hardware_id == '/mapping_node'
        assert 'no tracks for' in status.message and '/semfeat/tracks' in status.message
        assert 'since start-up' in status.message, status.message
        h.pub_tracks.publish(tracks_to_msg(  # the reliable publisher: the input is alive
            frames[0].tracks.pixel, frames[0].tracks.bearing, frames[0].tracks.label,
            frames[0].tracks.track_id, np.full(len(frames[0].tracks), 2),
            np.ones(len(frames[0].tracks)), stamp_ns=frames[0].tracks.stamp_ns,
            frame_id='camera_front_optical', msg_cls=PointCloud2))
        assert wait(lambda: node.health.counters.received >= 1, 10)
        assert 'no tracks' not in node.health.status().message
        values = {kv.key: kv.value for kv in node.health.status().values}
        assert int(values['qos_incompatible']) >= 1
        # drops: WARN above drop_warn_ratio (0.2) of the frames received in the last period
        node.health.io.input_timeout_s = 0.0
        node.health.counters.rejected = node.health.counters.errors = 0
        node.health.io.incompatible = 0
        node.health.publish()
        node.health.counters.received += 10
        node.health.counters.processed += 10
        node.health.counters.dropped += 1
        node.health.publish()
        assert node.health.status().level == DiagnosticStatus.OK, node.health.status().message
        node.health.counters.received += 10
        node.health.counters.dropped += 5
        node.health.publish()
        status = node.health.status()
        assert status.level == DiagnosticStatus.WARN and '5 of 10 frames dropped' in \
            status.message, status.message
    finally:
        h.close()


def call(h: Harness, name: str) -> Trigger.Response:
    client = h.probe.create_client(Trigger, f'/mapping_node/{name}')
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(Trigger.Request())
    assert h.wait(future.done, 30)
    return future.result()


@pytest.mark.ros_domain(88)
def test_pause_resume_and_reset_services(isolated_ros) -> None:
    frames = drive_frames(36)
    h = Harness([Parameter('use_gnss', value=False), Parameter('cloud_period_s', value=0.2)],
                'probe_services')
    node, wait = h.node, h.wait
    clouds: list[PointCloud2] = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    h.probe.create_subscription(PointCloud2, '/semantic_cloud', clouds.append, latched)

    def feed(fs: list) -> None:
        for f in fs:
            h.send_odom(f, np.eye(6) * 1e-4)
            h.send_tracks(f)
            time.sleep(0.02)

    def keyframes() -> int:
        with node._lock:
            return len(node.session.mapper.trajectory()[0])

    try:
        assert not call(h, 'reset').success  # no CameraInfo: nothing to reset
        h.start()
        h.settle_tracks_topic()
        feed(frames[:16])
        assert wait(lambda: node.health.counters.processed >= 16)
        assert not call(h, 'resume').success  # not paused
        assert call(h, 'pause').success and not call(h, 'pause').success
        feed(frames[16:22])  # ignored and counted, never mapped
        assert wait(lambda: node.health.extra['frames_paused'] == '6')
        assert node.health.counters.processed == 16 and node.health.counters.received == 16
        assert call(h, 'resume').success
        feed(frames[22:28])
        assert wait(lambda: node.health.counters.processed >= 22)
        n = keyframes()
        assert n > 3
        res = call(h, 'reset')
        assert res.success and f'{n} keyframes' in res.message, res.message
        assert keyframes() == 0
        assert wait(lambda: clouds and semantic_cloud_from_msg(clouds[-1]).xyz.shape[0] == 0)
        feed(frames[28:])  # a new map from the next frames, same camera
        assert wait(lambda: node.health.counters.processed >= 30)
        assert wait(lambda: keyframes() >= 1)
        assert node.resets == {'camera': 0, 'time': 0} and node.health.counters.rejected == 0
        assert node.health.extra['resets_service'] == '1'
    finally:
        h.close()


@pytest.mark.ros_domain(89)
def test_topics_and_services_follow_the_namespace(isolated_ros) -> None:
    from semfeat_ros.nodes.mapping_node import MappingNode

    rclpy.init()
    node = None
    try:
        node = MappingNode(namespace='car1')
        inputs = {w.name: w.topic for w in node.health.io.inputs.values()}
        assert inputs == {'CameraInfo': '/car1/camera/front/camera_info',
                          'tracks': '/car1/semfeat/tracks'}
        assert node.pub_cloud.topic_name == '/car1/semantic_cloud'
        assert node.pub_path.topic_name == '/car1/semfeat/path'
        assert node.pub_tf.topic_name == '/tf'  # TF and /diagnostics stay global
        services = {s.service_name for s in node.services}
        assert {f'/car1/mapping_node/{n}' for n in ('save_map', 'reset', 'pause', 'resume')} \
            <= services
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


@pytest.mark.ros_domain(90)
def test_save_on_shutdown(isolated_ros, tmp_path: Path) -> None:
    h = Harness([Parameter('use_gnss', value=False), Parameter('output_dir', value=str(tmp_path)),
                 Parameter('save_on_shutdown', value=True)], 'probe_shutdown')
    node = h.node
    try:
        h.start()
        h.settle_tracks_topic()
        for f in drive_frames(12):
            h.send_odom(f, np.eye(6) * 1e-4)
            h.send_tracks(f)
            time.sleep(0.02)
        assert h.wait(lambda: node.health.counters.processed >= 11)
        assert not (tmp_path / 'map.json').exists()
        with node._lock:
            n = len(node.session.mapper.trajectory()[0])
    finally:
        h.close()  # destroys the node: the map is saved
    assert (tmp_path / 'map.json').is_file() and (tmp_path / 'cloud.ply').is_file()
    assert len(read_tum(tmp_path / 'trajectory.tum')[0]) == n >= 1
