"""Seeded fuzzing of the three nodes with malformed messages, and of the message adapters.

Node level: each node runs in-process on an executor thread of its own isolated ROS domain; a
probe publishes a few thousand generated bad messages of every input type the node reads (each
one invalid by construction, cycling through the mutations below), paced so that no queue
overflows. Asserted: the executor thread is alive (no callback raised), no processing error, every
bad message counted (rejected, or replaced while the network was busy for feature_node's
images), a good input processed afterwards, and the process's resident memory grew by less than
``RSS_GROWTH_MAX_MB``. Adapter level: hypothesis feeds random headers and bytes to the parsers,
which must return or raise a ``MessageError``, nothing else.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
import copy
import math
from pathlib import Path
import threading
import time
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, NavSatFix, PointCloud2

from msg_adapters import (
    camera_info_to_model,
    features_from_msg,
    features_to_msg,
    model_to_camera_info,
    navsatfix_to_numpy,
    numpy_to_image,
    odometry_from_numpy,
    odometry_to_numpy,
    tracks_from_msg,
    tracks_to_msg,
)
from msg_adapters.errors import MessageError
from msg_adapters.image import to_rgb_or_mono
from semfeat_ros.camera import FisheyeCamera

SEED = 33
PER_INPUT = 1000  # bad messages per input type of a node
BATCH = 8  # published before waiting for the node to count them (queues hold 10)
RSS_GROWTH_MAX_MB = 150.0
W, H = 320, 256
CAM = FisheyeCamera(W, H, 93.35, 93.35, 160.0, 128.0, k=(0.02, -0.004, 0.0005, -0.0001),
                    fov_deg=190)


def rss_mb() -> float:
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024
    raise RuntimeError('no VmRSS in /proc/self/status')


# ------------------------------------------------------------------------ bad messages

def good_info(stamp_ns: int = 1) -> CameraInfo:
    return model_to_camera_info(CAM, stamp_ns=stamp_ns, frame_id='camera_front_optical',
                                msg_cls=CameraInfo)


def bad_infos(rng: np.random.Generator) -> Iterator[CameraInfo]:
    """CameraInfo that camera_info_to_model rejects."""
    def nan_k(m: CameraInfo) -> None:
        m.k[int(rng.choice([0, 2, 4, 5]))] = float(rng.choice([math.nan, math.inf, -math.inf]))

    def bad_focal(m: CameraInfo) -> None:
        m.k[int(rng.choice([0, 4]))] = -float(rng.uniform(0, 1e6))

    def empty(m: CameraInfo) -> None:
        if rng.random() < 0.5:
            m.width = 0
        else:
            m.height = 0

    def model(m: CameraInfo) -> None:
        m.distortion_model = ''.join(rng.choice(list('abcxyz_'), int(rng.integers(1, 12))))

    def short_d(m: CameraInfo) -> None:
        m.d = [float(x) for x in rng.normal(size=int(rng.integers(1, 4)))]

    def wild_d(m: CameraInfo) -> None:  # theta_d falls off the axis: not monotonic
        m.d = [-float(rng.uniform(1e3, 1e9))] + [float(x) for x in rng.normal(size=3) * 1e3]

    mutations = [nan_k, bad_focal, empty, model, short_d, wild_d]
    k = 0
    while True:
        m = good_info(stamp_ns=k + 2)
        mutations[k % len(mutations)](m)
        k += 1
        yield m


def bad_images(rng: np.random.Generator) -> Iterator[Image]:
    """Images that feature_node rejects (by the adapters, or against the 5:4 CameraInfo)."""
    pixels = (rng.random((H, W, 3)) * 255).astype(np.uint8)

    def base(k: int) -> Image:
        return numpy_to_image(pixels, 'rgb8', stamp_ns=10**9 + k, frame_id='camera_front_optical',
                              msg_cls=Image)

    def short_step(m: Image) -> None:
        m.step = int(rng.integers(0, W * 3))

    def truncated(m: Image) -> None:
        m.data = bytes(m.data)[: int(rng.integers(0, W * H * 3))]

    def encoding(m: Image) -> None:
        m.encoding = str(rng.choice(['32FC1', '8UC3', 'weird', '', 'rgb8 ', 'bayer_xxxx8']))

    def header_lie(m: Image) -> None:
        m.width, m.height = int(rng.integers(20_000, 100_000)), int(rng.integers(20_000, 100_000))
        m.step = m.width * 3

    def aspect(m: Image) -> None:
        w = int(rng.integers(16, 64))
        m.width, m.height, m.step = w * 4, w, w * 12
        m.data = bytes(m.data)[: m.height * m.step]

    mutations = [short_step, truncated, encoding, header_lie, aspect]
    k = 0
    while True:
        m = base(k)
        mutations[k % len(mutations)](m)
        k += 1
        yield m


def bad_clouds(rng: np.random.Generator, good: Callable[[int], PointCloud2]
               ) -> Iterator[PointCloud2]:
    """PointCloud2 whose layout the features / tracks readers reject."""
    def truncated(m: PointCloud2) -> None:
        m.data = bytes(m.data)[: int(rng.integers(0, len(m.data)))]

    def missing_field(m: PointCloud2) -> None:
        drop = int(rng.integers(0, len(m.fields)))
        m.fields = [f for i, f in enumerate(m.fields) if i != drop]

    def datatype(m: PointCloud2) -> None:
        f = m.fields[int(rng.integers(0, len(m.fields)))]
        f.datatype = int(rng.choice([t for t in range(1, 9) if t != f.datatype]))

    def point_step(m: PointCloud2) -> None:
        m.point_step = int(rng.integers(0, m.point_step))

    def row_step(m: PointCloud2) -> None:
        m.row_step = int(rng.integers(0, m.row_step))

    def width_lie(m: PointCloud2) -> None:
        m.width = int(rng.integers(m.width + 1, 10**9))

    def offset(m: PointCloud2) -> None:
        m.fields[int(rng.integers(0, len(m.fields)))].offset = int(rng.integers(10**3, 10**6))

    mutations = [truncated, missing_field, datatype, point_step, row_step, width_lie, offset]
    k = 0
    while True:
        m = copy.deepcopy(good(k))
        mutations[k % len(mutations)](m)
        k += 1
        yield m


def good_features(k: int, rng: np.random.Generator | None = None) -> PointCloud2:
    r = rng or np.random.default_rng(k)
    n = 50
    d = r.normal(size=(n, 64))
    return features_to_msg(r.uniform([60, 40], [260, 216], (n, 2)), np.ones(n),
                           np.zeros(n, np.uint8), d / np.linalg.norm(d, axis=1, keepdims=True),
                           stamp_ns=10**9 + k * 10**6, frame_id='camera_front_optical',
                           msg_cls=PointCloud2)


def good_tracks(k: int) -> PointCloud2:
    n = 30
    b = np.random.default_rng(k).normal(size=(n, 3)) + [0, 0, 3]
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return tracks_to_msg(np.zeros((n, 2)), b, np.zeros(n, np.uint8), np.arange(n),
                         np.ones(n), np.ones(n), stamp_ns=10**9 + k * 10**6,
                         frame_id='camera_front_optical', msg_cls=PointCloud2)


def bad_odometry(rng: np.random.Generator) -> Iterator[Odometry]:
    k = 0
    while True:
        m = odometry_from_numpy(np.eye(4), None, stamp_ns=10**9 + k, frame_id='odom',
                                child_frame_id='base_link', msg_cls=Odometry)
        if k % 2:
            m.pose.pose.orientation.w = 0.0  # zero quaternion
        else:
            setattr(m.pose.pose.position, str(rng.choice(['x', 'y', 'z'])),
                    float(rng.choice([math.nan, math.inf])))
        k += 1
        yield m


def bad_fixes(rng: np.random.Generator) -> Iterator[NavSatFix]:
    while True:
        m = NavSatFix(latitude=float(rng.uniform(90.5, 1e6) * rng.choice([-1, 1])),
                      longitude=float(rng.uniform(-180, 180)), altitude=10.0)
        if rng.random() < 0.5:
            m.latitude, m.longitude = 45.0, float(rng.uniform(180.5, 1e6))
        yield m


# ------------------------------------------------------------------------ the harness

class Fuzz:
    """One node and a probe on an executor thread of their own context and domain."""

    def __init__(self, make_node: Callable[[Context], Node], domain: int) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = make_node(self.context)
        self.probe = Node('fuzz_probe', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def publisher(self, msg_type: type, topic: str) -> Any:
        pub = self.probe.create_publisher(msg_type, topic, QoSProfile(
            depth=10, reliability=ReliabilityPolicy.RELIABLE))
        assert self.wait(lambda: pub.get_subscription_count() > 0), topic
        return pub

    @staticmethod
    def wait(cond: Callable[[], bool], timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if cond():
                return True
            time.sleep(0.002)
        return cond()

    def send(self, pub: Any, messages: Iterator[Any], n: int,
             counted: Callable[[], int]) -> None:
        """Publish ``n`` of ``messages``; every one must raise ``counted()`` by one."""
        start = counted()
        for i in range(n):
            pub.publish(next(messages))
            if (i + 1) % BATCH == 0 or i + 1 == n:
                assert self.wait(lambda k=i + 1: counted() - start >= k), (
                    f'{counted() - start} of {i + 1} bad messages counted')
                assert self.thread.is_alive(), 'the executor died'
        assert counted() - start == n

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=10.0)
        self.node.destroy_node()
        self.probe.destroy_node()
        rclpy.try_shutdown(context=self.context)


def check_healthy(f: Fuzz) -> None:
    assert f.thread.is_alive()
    assert f.node.health.counters.errors == 0, f.node.health.last_error


@pytest.fixture(scope='module')
def untrained_weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import torch

    from semfeat_ros.labels import load_labels
    from semfeat_ros.model.semfeatnet import SemFeatNet
    from semfeat_ros.model.weights_io import save_weights

    torch.manual_seed(0)
    return save_weights(SemFeatNet(), tmp_path_factory.mktemp('w') / 'untrained.safetensors',
                        {'class_names': list(load_labels().names), 'input_size': [W, H]})


@pytest.mark.ros_domain(64)
def test_fuzz_feature_node(isolated_ros: int, untrained_weights: Path) -> None:
    from semfeat_ros.nodes.feature_node import FeatureNode

    rng = np.random.default_rng(SEED)
    f = Fuzz(lambda ctx: FeatureNode(context=ctx, parameter_overrides=[
        Parameter('weights', value=str(untrained_weights)),
        Parameter('input_reliability', value='reliable'), Parameter('input_depth', value=10),
        Parameter('warmup_size', value=[W, H])]), isolated_ros)
    node = f.node
    c = node.health.counters
    try:
        features: list[PointCloud2] = []
        f.probe.create_subscription(PointCloud2, '/semfeat/features', features.append, 10)
        pub_info, pub_img = f.publisher(CameraInfo, '/camera/front/camera_info'), \
            f.publisher(Image, '/camera/front/image_raw')
        pub_info.publish(good_info())
        assert f.wait(lambda: node._camera is not None)
        rss0 = rss_mb()
        f.send(pub_info, bad_infos(rng), PER_INPUT, lambda: c.rejected)
        f.send(pub_img, bad_images(rng), PER_INPUT,
               lambda: c.rejected + node._worker.dropped)
        assert f.wait(node._worker.idle)
        assert c.processed == 0 and c.received == PER_INPUT
        assert c.rejected + node._worker.dropped == 2 * PER_INPUT
        check_healthy(f)
        pixels = (rng.random((H, W, 3)) * 255).astype(np.uint8)
        pub_img.publish(numpy_to_image(pixels, 'rgb8', stamp_ns=2 * 10**9,
                                       frame_id='camera_front_optical', msg_cls=Image))
        assert f.wait(lambda: len(features) == 1 and c.processed == 1, 60)
        assert rss_mb() - rss0 < RSS_GROWTH_MAX_MB, f'RSS {rss0:.0f} -> {rss_mb():.0f} MB'
        check_healthy(f)
    finally:
        f.close()


@pytest.mark.ros_domain(65)
def test_fuzz_matcher_node(isolated_ros: int) -> None:
    from semfeat_ros.nodes.matcher_node import MatcherNode

    rng = np.random.default_rng(SEED + 1)
    # CameraInfo is a best-effort input; reliable here (a QoS override) so that no bad message
    # is lost on a loaded machine: every one is counted
    f = Fuzz(lambda ctx: MatcherNode(context=ctx, parameter_overrides=[Parameter(
        'qos_overrides./camera/front/camera_info.subscription.reliability', value='reliable')]),
        isolated_ros)
    node = f.node
    c = node.health.counters
    try:
        tracks: list[PointCloud2] = []
        f.probe.create_subscription(PointCloud2, '/semfeat/tracks', tracks.append, 10)
        pub_info = f.publisher(CameraInfo, '/camera/front/camera_info')
        pub_feat = f.publisher(PointCloud2, '/semfeat/features')
        (sub,) = [i for i in f.probe.get_subscriptions_info_by_topic('/camera/front/camera_info')
                  if i.node_name == 'matcher_node']
        assert sub.qos_profile.reliability == ReliabilityPolicy.RELIABLE  # the override applied
        pub_info.publish(good_info())
        assert f.wait(lambda: node._camera is not None)
        rss0 = rss_mb()
        f.send(pub_info, bad_infos(rng), PER_INPUT, lambda: c.rejected)
        f.send(pub_feat, bad_clouds(rng, good_features), PER_INPUT, lambda: c.rejected)
        assert c.received == PER_INPUT and c.processed == 0
        check_healthy(f)
        pub_feat.publish(good_features(PER_INPUT + 1))
        assert f.wait(lambda: len(tracks) == 1 and c.processed == 1)
        assert c.rejected == 2 * PER_INPUT and node.resets == 0
        assert rss_mb() - rss0 < RSS_GROWTH_MAX_MB, f'RSS {rss0:.0f} -> {rss_mb():.0f} MB'
        check_healthy(f)
    finally:
        f.close()


@pytest.mark.ros_domain(66)
def test_fuzz_mapping_node(isolated_ros: int, tmp_path: Path) -> None:
    from semfeat_ros.nodes.mapping_node import MappingNode

    rng = np.random.default_rng(SEED + 2)
    f = Fuzz(lambda ctx: MappingNode(context=ctx, parameter_overrides=[
        Parameter('output_dir', value=str(tmp_path)), Parameter('use_odometry', value=False),
        Parameter('input_reliability', value='reliable')]),
        isolated_ros)
    node = f.node
    c = node.health.counters
    try:
        pub_info = f.publisher(CameraInfo, '/camera/front/camera_info')
        pub_tracks = f.publisher(PointCloud2, '/semfeat/tracks')
        pub_fix = f.publisher(NavSatFix, '/gnss/fix')
        pub_info.publish(good_info())
        assert f.wait(lambda: node.feeder is not None)
        rss0 = rss_mb()
        f.send(pub_info, bad_infos(rng), PER_INPUT, lambda: c.rejected)
        f.send(pub_tracks, bad_clouds(rng, good_tracks), PER_INPUT, lambda: c.rejected)
        f.send(pub_fix, bad_fixes(rng), PER_INPUT // 2, lambda: c.rejected)
        assert c.received == PER_INPUT and c.processed == 0
        check_healthy(f)
        pub_tracks.publish(good_tracks(PER_INPUT + 1))
        assert f.wait(lambda: c.processed == 1)
        assert c.rejected == 2 * PER_INPUT + PER_INPUT // 2
        assert node.resets == {'camera': 0, 'time': 0}
        assert rss_mb() - rss0 < RSS_GROWTH_MAX_MB, f'RSS {rss0:.0f} -> {rss_mb():.0f} MB'
        check_healthy(f)
    finally:
        f.close()


@pytest.mark.ros_domain(67)
def test_fuzz_mapping_node_odometry(isolated_ros: int) -> None:
    from semfeat_ros.nodes.mapping_node import MappingNode

    rng = np.random.default_rng(SEED + 3)
    f = Fuzz(lambda ctx: MappingNode(context=ctx, parameter_overrides=[
        Parameter('output_dir', value=''), Parameter('input_reliability', value='reliable')]),
        isolated_ros)
    c = f.node.health.counters
    try:
        pub_odom = f.publisher(Odometry, '/vehicle/odom')
        f.send(pub_odom, bad_odometry(rng), PER_INPUT // 2, lambda: c.rejected)
        check_healthy(f)
        good = odometry_from_numpy(np.eye(4), None, stamp_ns=5 * 10**9, frame_id='odom',
                                   child_frame_id='base_link', msg_cls=Odometry)
        pub_odom.publish(good)  # taken, not rejected (it waits for a camera's session)
        time.sleep(0.2)
        assert c.rejected == PER_INPUT // 2
        check_healthy(f)
    finally:
        f.close()


# ------------------------------------------------------------------------ the adapters

FUZZ = settings(max_examples=300, derandomize=True, deadline=None, database=None)


@FUZZ
@given(width=st.integers(-2, 5000), height=st.integers(-2, 5000), step=st.integers(-2, 20000),
       encoding=st.sampled_from(['rgb8', 'bgr8', 'mono8', 'mono16', 'rgba8', 'bayer_rggb8',
                                 'yuv422', '32FC1', 'x']),
       data=st.binary(max_size=4096))
def test_image_parser_raises_only_message_errors(width: int, height: int, step: int,
                                                 encoding: str, data: bytes) -> None:
    m = Image(encoding=encoding, data=data)
    m.width, m.height, m.step = max(width, 0), max(height, 0), max(step, 0)
    try:
        out = to_rgb_or_mono(m, max_pixels=10**6)
    except MessageError:
        return
    assert out.dtype == np.uint8 and out.shape[:2] == (m.height, m.width)


@FUZZ
@given(k=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=9, max_size=9),
       d=st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=9),
       size=st.tuples(st.integers(0, 10**6), st.integers(0, 10**6)),
       model=st.sampled_from(['equidistant', 'plumb_bob', 'rational_polynomial', 'fisheye',
                              '']))
def test_camera_info_parser_raises_only_message_errors(k: list[float], d: list[float],
                                                       size: tuple[int, int],
                                                       model: str) -> None:
    m = CameraInfo(k=k, d=d, distortion_model=model, width=size[0], height=size[1])
    try:
        cam = camera_info_to_model(m, fov_deg=190.0)
    except MessageError:
        return
    assert cam.width == size[0] and np.isfinite(cam.K).all()


@FUZZ
@given(data=st.binary(max_size=2048), width=st.integers(0, 10**6),
       point_step=st.integers(0, 1024), row_step=st.integers(0, 10**6),
       mutate=st.integers(0, 3), which=st.booleans())
def test_cloud_parsers_raise_only_message_errors(data: bytes, width: int, point_step: int,
                                                 row_step: int, mutate: int,
                                                 which: bool) -> None:
    m = copy.deepcopy(good_features(0) if which else good_tracks(0))
    if mutate & 1:
        m.data = data
    if mutate & 2:
        m.width, m.point_step, m.row_step = width, point_step, row_step
    try:
        (features_from_msg if which else tracks_from_msg)(m)
    except MessageError:
        return


@FUZZ
@given(lat=st.floats(), lon=st.floats(), alt=st.floats(), status=st.integers(-3, 3),
       pos=st.tuples(st.floats(), st.floats(), st.floats(), st.floats()))
def test_nav_parsers_raise_only_message_errors(lat: float, lon: float, alt: float, status: int,
                                               pos: tuple[float, ...]) -> None:
    import warnings

    fix = NavSatFix(latitude=lat, longitude=lon, altitude=alt)
    fix.status.status = status
    odom = Odometry()
    odom.pose.pose.position.x, odom.pose.pose.orientation.x, odom.pose.pose.orientation.w, \
        odom.pose.covariance[0] = pos
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # no raw numpy warning for a node's log either
        for parse, msg in ((navsatfix_to_numpy, fix), (odometry_to_numpy, odom)):
            try:
                parse(msg)
            except MessageError:
                pass
