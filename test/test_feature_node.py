"""feature_node in-process with a real executor: outputs, header stamps, bad-input barrage.

The wiring tests use an untrained network written to tmp_path (they check the node, not the
model's quality); the shipped weights are exercised by the replay tests.
"""
from __future__ import annotations

from pathlib import Path
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from msg_adapters import (
    features_from_msg,
    image_to_numpy,
    model_to_camera_info,
    numpy_to_compressed,
    numpy_to_image,
)
from semfeat_ros.camera import load_camera_yaml
from semfeat_ros.labels import load_labels
from semfeat_ros.model.semfeatnet import SemFeatNet
from semfeat_ros.model.weights_io import save_weights

W, H = 320, 256


@pytest.fixture(scope='module')
def untrained_weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import torch

    torch.manual_seed(0)
    return save_weights(SemFeatNet(), tmp_path_factory.mktemp('w') / 'untrained.safetensors',
                        {'class_names': list(load_labels().names), 'input_size': [W, H]})


def frame(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = (rng.random((H // 8, W // 8, 3)) * 255).astype(np.uint8)
    return np.ascontiguousarray(np.kron(img, np.ones((8, 8, 1), np.uint8)))


class Harness:
    """feature_node plus a probe node on one executor, spinning in a thread."""

    def __init__(self, weights: Path, transport: str = 'raw',
                 overrides: list[Parameter] | None = None):
        from semfeat_ros.nodes.feature_node import FeatureNode

        overrides = [*(overrides or []), Parameter('weights', value=str(weights)),
                     Parameter('input_transport', value=transport),
                     Parameter('input_reliability', value='reliable'),
                     Parameter('input_depth', value=50),
                     Parameter('diagnostics_period_s', value=0.2)]
        self.node = FeatureNode(parameter_overrides=overrides)
        self.probe = Node('probe')
        self.features: list[PointCloud2] = []
        self.masks: list[Image] = []
        self.colors: list[Image] = []
        self.probe.create_subscription(PointCloud2, '/semfeat/features', self.features.append,
                                       50)
        self.probe.create_subscription(Image, '/semfeat/semantic_mask', self.masks.append, 50)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        topic = '/camera/front/image_raw' + ('/compressed' if transport == 'compressed' else '')
        self.pub_img = self.probe.create_publisher(
            CompressedImage if transport == 'compressed' else Image, topic, qos)
        self.pub_info = self.probe.create_publisher(CameraInfo, '/camera/front/camera_info', 10)
        self.executor = MultiThreadedExecutor(num_threads=3)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        cam, _ = load_camera_yaml()
        self.camera = cam.scaled(W, H)

    def wait(self, cond, timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if cond():
                return True
            time.sleep(0.02)
        return cond()

    def send_info(self, stamp_ns: int = 1) -> None:
        self.pub_info.publish(model_to_camera_info(
            self.camera, stamp_ns=stamp_ns, frame_id='camera_front_optical', msg_cls=CameraInfo))

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=10.0)  # the spin thread must be out before rclpy shuts down
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture
def ros_context(isolated_ros):
    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.mark.ros_domain(76)
def test_outputs_and_stamps(ros_context, untrained_weights: Path) -> None:
    h = Harness(untrained_weights)
    try:
        assert h.wait(lambda: h.pub_info.get_subscription_count() > 0
                      and h.pub_img.get_subscription_count() > 0)
        h.send_info()
        time.sleep(0.2)
        stamps = []
        for i in range(3):
            stamp = 1_700_000_000_000_000_000 + i * 100_000_000
            stamps.append(stamp)
            h.pub_img.publish(numpy_to_image(frame(i), 'rgb8', stamp_ns=stamp,
                                             frame_id='camera_front_optical', msg_cls=Image))
            assert h.wait(lambda n=i: len(h.features) > n), 'no features published'
        assert h.wait(lambda: len(h.masks) >= 3)
        got = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in h.features]
        assert got == stamps
        assert all(m.header.frame_id == 'camera_front_optical' for m in h.features)
        feats = features_from_msg(h.features[-1])
        assert feats.descriptors.shape[1] == 64
        if len(feats.keypoints):
            np.testing.assert_allclose(np.linalg.norm(feats.descriptors, axis=1), 1.0,
                                       atol=1e-4)
            assert (feats.keypoints >= 0).all()
            assert (feats.keypoints <= np.array([W - 1, H - 1])).all()
            assert not np.isin(feats.labels, [16, 17, 18]).any()  # sky and dynamic dropped
        mask = image_to_numpy(h.masks[-1])
        assert mask.shape == (H, W)
        # class ids inside the image circle, 255 ('no class') outside it
        assert set(np.unique(mask).tolist()) <= set(range(19)) | {255}
        assert mask[0, 0] == 255 and mask[H // 2, W // 2] < 19
        assert h.node.health.counters.rejected == 0
        # each frame's wait for the one before it in inference, on /diagnostics
        h.node._publish_diagnostics()
        extra = h.node.health.extra
        assert 0.0 <= float(extra['queued_p50_s']) <= float(extra['queued_p95_s']) < 5.0
        # the node starts at its first light level (no drop, so no step down before the period
        # is known); every frame counted at 512 px
        assert extra['mode'] == 'light' and extra['light_level'] == '1'
        assert extra['light_frames'] == extra['light_frames_512px'] == str(len(stamps))
        assert extra['light_frames_448px'] == '0'
    finally:
        h.close()


@pytest.mark.ros_domain(77)
def test_bad_input_barrage_keeps_node_alive(ros_context, untrained_weights: Path) -> None:
    h = Harness(untrained_weights)
    try:
        assert h.wait(lambda: h.pub_img.get_subscription_count() > 0)
        good = numpy_to_image(frame(0), 'rgb8', stamp_ns=10, frame_id='cam', msg_cls=Image)
        # No CameraInfo yet: skipped and counted, but not an input error.
        h.pub_img.publish(good)
        assert h.wait(lambda: h.node.health.counters.waiting >= 1)
        assert h.node.health.counters.rejected == 0
        h.send_info()
        time.sleep(0.2)
        bad: list[Image] = []
        m = Image(height=H, width=W, encoding='rgb8', step=W * 3 - 1, data=bytes(H * W * 3))
        bad.append(m)  # step too small
        bad.append(Image(height=H, width=W, encoding='rgb8', step=W * 3,
                         data=bytes(W * 3 * 10)))  # truncated
        bad.append(Image(height=4, width=4, encoding='weird42', step=16, data=bytes(64)))
        bad.append(Image(height=100000, width=100000, encoding='mono8', step=100000,
                         data=bytes(16)))  # absurd header
        bad.append(numpy_to_image(frame(1)[:200, :100], 'rgb8', stamp_ns=11, frame_id='cam',
                                  msg_cls=Image))  # size/aspect mismatch with CameraInfo
        for i, msg in enumerate(bad):
            h.pub_img.publish(msg)
            assert h.wait(lambda n=i: h.node.health.counters.rejected >= 1 + n), msg.encoding
        # A NaN CameraInfo is rejected and the previous camera stays in use.
        nan_info = model_to_camera_info(h.camera, stamp_ns=1, frame_id='c', msg_cls=CameraInfo)
        nan_info.k[0] = float('nan')
        h.pub_info.publish(nan_info)
        assert h.wait(lambda: h.node.health.counters.rejected >= 1 + len(bad))
        before = len(h.features)
        h.pub_img.publish(good)
        assert h.wait(lambda: len(h.features) > before), 'next good frame not processed'
        status = h.node.health.status()
        values = {kv.key: kv.value for kv in status.values}
        assert int(values['errors_rejected']) >= 1 + len(bad)
        assert int(values['frames_waiting_camera_info']) >= 1
        assert values['last_error']
    finally:
        h.close()


@pytest.mark.ros_domain(78)
def test_compressed_input_and_corrupt_jpeg(ros_context, untrained_weights: Path) -> None:
    h = Harness(untrained_weights, transport='compressed')
    try:
        assert h.wait(lambda: h.pub_img.get_subscription_count() > 0)
        h.send_info()
        time.sleep(0.2)
        msg = numpy_to_compressed(frame(2), 'jpeg', stamp_ns=5, frame_id='cam',
                                  msg_cls=CompressedImage)
        corrupt = numpy_to_compressed(frame(3), 'jpeg', stamp_ns=6, frame_id='cam',
                                      msg_cls=CompressedImage)
        corrupt.data = bytes(corrupt.data)[: len(corrupt.data) // 3]
        h.pub_img.publish(corrupt)
        assert h.wait(lambda: h.node.health.counters.rejected >= 1)
        h.pub_img.publish(msg)
        assert h.wait(lambda: len(h.features) >= 1)
    finally:
        h.close()


@pytest.mark.ros_domain(80)
def test_network_runtime_and_warmup_parameters(ros_context, untrained_weights: Path) -> None:
    from semfeat_ros.nodes.feature_node import FeatureNode

    base = [Parameter('weights', value=str(untrained_weights))]
    node = FeatureNode(parameter_overrides=base)  # defaults: onnxruntime, readied for 1920x1536
    try:
        assert node.frontend.extractor.backend == 'onnxruntime'
        assert (512, 640) in node.frontend.extractor._ort._sessions  # built before any frame
        assert 'on onnxruntime' in node.frontend.describe()
        # the light levels, readied too: 512 then 448 px
        assert [fe.extractor.conf['resize_max'] for fe in node.light_frontends] == [512, 448]
        assert node.governor.levels == 2
        assert all(fe.extractor._ort._sessions for fe in node.light_frontends)
    finally:
        node.destroy_node()
    # sizes not below the level before them are skipped; none below the full mode: no light mode
    for sizes, kept in (([700, 512, 600, 448], [512, 448]), ([640, 800], [])):
        node = FeatureNode(parameter_overrides=[*base, Parameter('light_resize_max', value=sizes),
                                                Parameter('warmup_size', value=[0, 0])])
        try:
            assert [fe.extractor.conf['resize_max'] for fe in node.light_frontends] == kept
        finally:
            node.destroy_node()
    node = FeatureNode(parameter_overrides=[*base, Parameter('backend', value='torch'),
                                            Parameter('warmup_size', value=[0, 0])])
    try:
        assert node.frontend.extractor.backend == 'torch'
    finally:
        node.destroy_node()
    for bad in ([640], [640, 8]):
        with pytest.raises(ValueError, match='warmup_size'):
            FeatureNode(parameter_overrides=[*base, Parameter('warmup_size', value=bad)])


@pytest.mark.ros_domain(88)
def test_camera_sizes_neither_leak_sessions_nor_threads(ros_context,
                                                        untrained_weights: Path) -> None:
    from semfeat_ros.model.onnx_backend import MAX_SESSIONS

    h = Harness(untrained_weights, overrides=[Parameter('min_change_interval_s', value=0.0)])
    node = h.node
    ort = node.frontend.extractor._ort
    try:
        assert h.wait(lambda: h.pub_info.get_subscription_count() > 0
                      and h.pub_img.get_subscription_count() > 0)
        h.send_info()
        assert h.wait(lambda: node._camera is not None)
        assert h.wait(lambda: node._preparer.idle())
        sessions = dict(ort._sessions)

        def preparers() -> int:
            return sum(t.name == 'feature-prepare' for t in threading.enumerate())

        # 20 lone CameraInfo of other sizes, each followed by the camera's own: all ignored
        for i in range(20):
            other = h.camera.scaled(W + 16 * (i + 1), H)
            h.pub_info.publish(model_to_camera_info(other, stamp_ns=2, frame_id='cam',
                                                    msg_cls=CameraInfo))
            h.send_info()
            time.sleep(0.02)  # within the CameraInfo queue depth (10)
        assert h.wait(lambda: node.health.counters.rejected == 20), node.health.counters
        assert preparers() == 1
        assert node._camera.width == W and dict(ort._sessions) == sessions
        # sizes that persist are accepted, readied by the one preparer; the cache stays bounded
        for i in range(MAX_SESSIONS + 2):
            other = h.camera.scaled(W, H + 32 * (i + 1))
            for _ in range(3):
                h.pub_info.publish(model_to_camera_info(other, stamp_ns=3, frame_id='cam',
                                                        msg_cls=CameraInfo))
                time.sleep(0.02)
            assert h.wait(lambda o=other: node._camera == o)
            assert preparers() == 1
            assert len(ort._sessions) <= MAX_SESSIONS
        assert h.wait(lambda: node._preparer.idle(), 120)
        net_size = node.frontend.extractor.network_size(other.width, other.height)
        assert net_size[::-1] in ort._sessions
        # and a frame of the last size is processed
        before = len(h.features)
        img = np.ascontiguousarray(np.resize(frame(4), (other.height, other.width, 3)))
        h.pub_img.publish(numpy_to_image(img, 'rgb8', stamp_ns=20, frame_id='cam',
                                         msg_cls=Image))
        assert h.wait(lambda: len(h.features) > before, 60)
        assert node.health.counters.rejected == 20 and node.health.counters.errors == 0
    finally:
        h.close()


@pytest.mark.ros_domain(91)
def test_frame_of_another_aspect_is_rejected_before_decoding(
        ros_context, untrained_weights: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from semfeat_ros.nodes import feature_node

    decoded: list[int] = []
    real = feature_node.to_rgb_or_mono

    def counting(msg, **kwargs):  # noqa: ANN001, ANN202
        decoded.append(1)
        return real(msg, **kwargs)

    monkeypatch.setattr(feature_node, 'to_rgb_or_mono', counting)
    h = Harness(untrained_weights, transport='compressed')
    try:
        assert h.wait(lambda: h.pub_img.get_subscription_count() > 0
                      and h.pub_info.get_subscription_count() > 0)
        h.send_info()
        assert h.wait(lambda: h.node._camera is not None)
        wide = np.zeros((500, 4000, 3), np.uint8)  # 4:1 against the camera's 5:4
        h.pub_img.publish(numpy_to_compressed(wide, 'png', stamp_ns=5, frame_id='cam',
                                              msg_cls=CompressedImage))
        assert h.wait(lambda: h.node.health.counters.rejected == 1)
        assert 'different aspect ratio' in h.node.health.last_error and decoded == []
        h.pub_img.publish(numpy_to_compressed(frame(2), 'png', stamp_ns=6, frame_id='cam',
                                              msg_cls=CompressedImage))
        assert h.wait(lambda: len(h.features) >= 1) and decoded == [1]
    finally:
        h.close()
