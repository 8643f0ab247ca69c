"""feature_node with ``frontend: xfeat`` / ``orb`` and matcher_node with ``matcher: learned`` /
``mnn`` over DDS.

feature_node publishes XFeat (ORB) keypoints labelled by the network's mask (an untrained
SemFeatNet written to tmp_path: the test checks the wiring and the contract, not the mask's
quality); matcher_node tracks them with LighterGlue (ORB: Hamming mutual nearest neighbour on
the bytes carried as float32). Frames: blurred noise (sigma 1 px, where both detectors find
keypoints) shifted 6 px to the left.
"""
from __future__ import annotations

from pathlib import Path
import threading
import time

import cv2
import numpy as np
import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from msg_adapters import (
    features_from_msg,
    image_to_numpy,
    model_to_camera_info,
    numpy_to_image,
    tracks_from_msg,
)
from semfeat_ros.camera import load_camera_yaml
from semfeat_ros.labels import load_labels

W, H = 320, 256
SHIFT = 6


@pytest.fixture(scope='module')
def untrained_weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import torch

    from semfeat_ros.model.semfeatnet import SemFeatNet
    from semfeat_ros.model.weights_io import save_weights

    torch.manual_seed(0)
    return save_weights(SemFeatNet(), tmp_path_factory.mktemp('w') / 'untrained.safetensors',
                        {'class_names': list(load_labels().names), 'input_size': [W, H]})


def frame(shift: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    wide = cv2.GaussianBlur((rng.random((H, W + 32, 3)) * 255).astype(np.uint8), (0, 0), 1)
    return np.ascontiguousarray(wide[:, 16 + shift:16 + shift + W])


def wait(cond, timeout: float = 120.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


@pytest.fixture
def ros_context(isolated_ros):
    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.mark.parametrize('frontend,matcher_kind', [
    pytest.param('xfeat', 'learned', marks=pytest.mark.ros_domain(150)),
    pytest.param('orb', 'mnn', marks=pytest.mark.ros_domain(151))])
def test_features_and_tracks(ros_context, untrained_weights: Path, frontend: str,
                             matcher_kind: str) -> None:
    from semfeat_ros.nodes.feature_node import FeatureNode
    from semfeat_ros.nodes.matcher_node import MatcherNode

    feature = FeatureNode(parameter_overrides=[
        Parameter('frontend', value=frontend), Parameter('weights', value=str(untrained_weights)),
        Parameter('max_keypoints', value=500), Parameter('warmup_size', value=[0, 0]),
        Parameter('input_reliability', value='reliable'), Parameter('input_depth', value=10)])
    matcher = MatcherNode(parameter_overrides=[
        Parameter('frontend', value=frontend), Parameter('matcher', value=matcher_kind),
        Parameter('min_inliers', value=8)])
    probe = Node('probe')
    features: list[PointCloud2] = []
    masks: list[Image] = []
    tracks: list[PointCloud2] = []
    probe.create_subscription(PointCloud2, '/semfeat/features', features.append, 10)
    probe.create_subscription(Image, '/semfeat/semantic_mask', masks.append, 10)
    probe.create_subscription(PointCloud2, '/semfeat/tracks', tracks.append, 10)
    pub_img = probe.create_publisher(Image, '/camera/front/image_raw',
                                     QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    pub_info = probe.create_publisher(CameraInfo, '/camera/front/camera_info', 10)
    executor = MultiThreadedExecutor(num_threads=3)
    for n in (feature, matcher, probe):
        executor.add_node(n)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    camera = load_camera_yaml()[0].scaled(W, H)
    try:
        assert wait(lambda: pub_img.get_subscription_count() > 0
                    and pub_info.get_subscription_count() >= 2, 30.0)
        info = model_to_camera_info(camera, stamp_ns=1, frame_id='cam', msg_cls=CameraInfo)
        pub_info.publish(info)
        time.sleep(0.3)
        pub_info.publish(info)
        for i, shift in enumerate((0, SHIFT)):
            stamp = 1_700_000_000_000_000_000 + i * 100_000_000
            pub_img.publish(numpy_to_image(frame(shift), 'rgb8', stamp_ns=stamp,
                                           frame_id='cam', msg_cls=Image))
            assert wait(lambda n=i: len(features) > n and len(masks) > n), 'no features'
        assert wait(lambda: len(tracks) >= 2), 'no tracks'
        f = features_from_msg(features[-1])
        assert 50 < len(f.keypoints) <= 500
        if frontend == 'xfeat':
            assert f.descriptors.shape == (len(f.keypoints), 64)  # XFeat's D
            np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)
        else:  # ORB's 32 bytes, one float32 0..255 each
            assert f.descriptors.shape == (len(f.keypoints), 32)
            d = f.descriptors
            assert (d == np.rint(d)).all() and d.min() >= 0 and d.max() <= 255 and d.max() > 1
        mask = image_to_numpy(masks[-1])
        assert mask.shape == (H, W)
        u, v = np.rint(f.keypoints).astype(int).T
        np.testing.assert_array_equal(f.labels, mask[v, u])  # the network's class
        assert not np.isin(f.labels, [16, 17, 18, 255]).any()  # sky, dynamic, outside
        t = tracks_from_msg(tracks[-1])
        assert len(t.track_ids) > 30  # matches verified by the bearing RANSAC
        assert feature.health.counters.rejected == 0 == matcher.health.counters.rejected
    finally:
        executor.shutdown()
        thread.join(timeout=10.0)
        for n in (feature, matcher, probe):
            n.destroy_node()
