"""mapping_node: tracks (+ wheel odometry, GNSS) -> poses with altitude, floors, /semantic_cloud.

Feeds ``/semfeat/tracks`` into the incremental factor-graph mapper (GTSAM fixed-lag iSAM2 with
bearing factors) together with the optional ``/vehicle/odom`` and ``/gnss/fix``; publishes
``/semfeat/odometry`` (map -> base_link, z = altitude) and ``/semfeat/path`` every frame and the
labeled map ``/semantic_cloud`` (latched, transient_local depth 1) at a bounded rate.
Services (std_srvs/Trigger): ``~/save_map`` (below; also on shutdown with
``save_on_shutdown``), ``~/reset`` (a new, empty map with the same
camera), ``~/pause`` and ``~/resume`` (tracks ignored and counted in between; odometry and GNSS
still buffered).

TF (REP-105): every mapped frame broadcasts, stamped with its image time, map -> odom and
odom -> base_link (the wheel odometry interpolated at that stamp) once wheel odometry is
received, map -> base_link before. The map frame never jumps: once GNSS fixes align it, the
frame also carries enu -> map (the ENU frame around the first fix is map's parent). The
base_link -> camera extrinsic of a new map comes from /tf_static when another publisher (a
vehicle's URDF, possibly through intermediate frames) carries it, else from ``camera_config``,
which is then broadcast on /tf_static. The service
``~/save_map`` (std_srvs/Trigger) writes ``cloud.ply`` (x y z rgb label floor landmark_id n_obs),
``trajectory.tum`` and their manifest ``map.json`` as one unit into ``output_dir``
(:func:`~semfeat_ros.mapping.io.save_map`: temporary files renamed into place, symlinks
refused, nothing written outside the directory, which is resolved once at start-up).

Threads: the subscription callbacks only parse and queue their inputs; one worker thread applies
them in arrival order to a :class:`~semfeat_ros.mapping.session.FrameFeeder` (a frame waits for
the odometry after its stamp) and runs the mapper. The executor, which takes one message per
subscription each time it wakes, never waits for the mapper, so the 50 Hz odometry is taken as
it arrives. When the mapper cannot keep up, at most ``max_backlog`` frames wait; older ones are
dropped and counted (``frames_dropped``), never queued without bound.

Resets: the map restarts when the camera changes (CameraInfo of another model or frame) or
time goes backwards on the tracks stream (a bag loop), but only when the change persists for
``change_confirm_messages`` consecutive messages and at most once per
``min_change_interval_s``; a lone outlier is ignored and counted as rejected. Before a reset the
map is saved into ``<output_dir>/before_reset``. ``/diagnostics`` reports the resets
(``resets_camera``, ``resets_time``), the ignored outliers and the deferred resets. The wheel
odometry stream is guarded the same way: a lone older stamp is ignored, a persisting one
restarts its buffer.

Solver health: the mapper recovers a failed iSAM2 update by rebuilding the smoother, or, when
that fails too, by resetting the window to the newest keyframe (the map is kept).
``/diagnostics`` is ERROR for ``solver_error_frames`` mapped frames from such a window reset and
while the mapper is lost, WARN for ``solver_warn_frames`` frames from any failed update
(:class:`~semfeat_ros.nodes.diagnostics.SolverHealth`), and reports the counts since start-up
(``solver_update_failures``, ``solver_recoveries``, ``solver_window_resets``,
``solver_smoother_resets``, ``solver_tracking_lost``) and the last failure.

Run-time parameter updates (``ros2 param set``): the keyframe thresholds (``kf_parallax_deg``,
``kf_max_distance_m``; the mapper reads them every frame), ``max_backlog``, the periods of
``/semantic_cloud`` and ``/diagnostics`` and the diagnostics thresholds take effect from the
next frame or timer tick; every other parameter is read-only (topics, frames, the QoS, the
smoother's window and noise models are built into the subscriptions or the map when it starts)
and a set is refused with rclpy's reason; values outside their range are refused naming it.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
from pathlib import Path
import sys
import threading
from typing import Any

from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
import numpy as np
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, NavSatFix, PointCloud2
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from msg_adapters import (
    camera_info_to_model,
    navsatfix_to_numpy,
    odometry_from_numpy,
    odometry_to_numpy,
    path_from_numpy,
    semantic_cloud_to_msg,
    tracks_from_msg,
)
from msg_adapters.errors import MessageError
from semfeat_ros.camera import load_camera_yaml
from semfeat_ros.mapping.errors import MappingError, MapWriteError
from semfeat_ros.mapping.io import save_map
from semfeat_ros.mapping.session import FedFrame, FrameFeeder, MappingSession, SessionConfig
from semfeat_ros.mapping.types import Tracks
from semfeat_ros.nodes.diagnostics import NodeHealth, SolverHealth, spin_node
from semfeat_ros.nodes.params import declare_config, guard_updates, param
from semfeat_ros.nodes.qos import input_qos
from semfeat_ros.nodes.tf import (
    TF_QOS,
    TF_STATIC_PUB_QOS,
    TF_STATIC_SUB_QOS,
    StaticFrames,
    transform_msg,
    transform_to_matrix,
)
from semfeat_ros.runtime import ChangeGate, RateLimit, StampGuard


@dataclass
class MappingNodeConfig:
    """Parameters of mapping_node (shipped as config/mapping_node.yaml)."""

    tracks_topic: str = param('semfeat/tracks', 'Input tracks (matcher_node output)',
                              read_only=True)
    camera_info_topic: str = param('camera/front/camera_info', 'CameraInfo topic',
                                   read_only=True)
    odom_topic: str = param('vehicle/odom', 'Wheel odometry (nav_msgs/Odometry)',
                            read_only=True)
    gnss_topic: str = param('gnss/fix', 'GNSS fixes (sensor_msgs/NavSatFix)', read_only=True)
    cloud_topic: str = param('semantic_cloud', 'Labeled map (PointCloud2, latched)',
                             read_only=True)
    odometry_topic: str = param('semfeat/odometry', 'Pose of base_link in map',
                                read_only=True)
    path_topic: str = param('semfeat/path', 'Keyframe trajectory', read_only=True)
    map_frame: str = param('map', 'Frame of the map (z up)', read_only=True)
    odom_frame: str = param('odom', 'Frame of the wheel odometry (REP-105)', read_only=True)
    enu_frame: str = param('enu', 'East-north-up frame of the GNSS fixes, origin at the first '
                           'fix (the datum); parent of map on /tf once GNSS aligned the map',
                           read_only=True)
    base_frame: str = param('base_link', 'Vehicle frame', read_only=True)
    camera_frame: str = param('', 'Optical frame of the camera on /tf_static; empty = the '
                              "CameraInfo's frame_id", read_only=True)
    publish_tf: bool = param(True, 'Broadcast map -> odom -> base_link on /tf at each mapped '
                             "frame's image stamp (map -> base_link before any wheel odometry) "
                             'and base_link -> camera on /tf_static', read_only=True)
    publish_odom_tf: bool = param(True, 'Broadcast odom -> base_link from the wheel odometry '
                                  '(off where the odometry driver broadcasts it)',
                                  read_only=True)
    camera_config: str = param('', 'Calibration YAML with the base_link -> camera extrinsic, '
                               'used when /tf_static does not carry it (a URDF); empty = the '
                               'shipped config/camera_front.yaml', read_only=True)
    fov_deg: float = param(190.0, 'Field of view of the lens (deg, full cone)',
                           range=(60.0, 240.0), read_only=True)
    input_reliability: str = param('best_effort', 'QoS reliability of the CameraInfo, odometry '
                                   'and GNSS inputs: best_effort (sensor data; matches reliable '
                                   'and best-effort publishers) or reliable',
                                   choices=('best_effort', 'reliable'), read_only=True)
    use_odometry: bool = param(True, 'Use wheel odometry when it is published', read_only=True)
    use_gnss: bool = param(True, 'Use GNSS fixes (gated on their covariance)', read_only=True)
    odom_calibration: bool = param(
        True, "Learn the wheel odometry's yaw-rate bias, yaw scale and distance scale errors "
        'where GNSS anchors the map and remove them from later odometry', read_only=True)
    vehicle_kinematics: bool = param(
        True, 'The camera rides a car (base_link moves along its x axis, no slip): the keyframe '
        'rotations are refined with the translation that motion gives the camera. Off for a '
        'rig that moves sideways (handheld, a robot that strafes)', read_only=True)
    gnss_lever_arm_m: list[float] = param([1.2, 0.0, 1.5], 'GNSS antenna in base_link (m)',
                                          read_only=True)
    window_keyframes: int = param(15, 'Keyframes in the fixed-lag smoother', range=(3, 200),
                                  read_only=True)
    kf_parallax_deg: float = param(4.0, 'Parallax that makes a new keyframe (deg); may change '
                                   'at run time', range=(0.1, 45.0))
    kf_max_distance_m: float = param(1.0, 'Distance that makes a new keyframe (m); may change '
                                     'at run time', range=(0.05, 100.0))
    bearing_sigma_px: float = param(2.5, 'Keypoint noise (px) of the front end',
                                    range=(0.05, 20.0), read_only=True)
    voxel_size_m: float = param(0.1, 'Voxel size bounding the published map (m)',
                                range=(0.01, 5.0), read_only=True)
    odom_sigma_per_m: float = param(0.02, 'Wheel odometry translation noise (m per m)',
                                    range=(1e-5, 1.0), read_only=True)
    odom_sigma_rad_per_rad: float = param(0.02, 'Wheel odometry rotation noise (rad per rad)',
                                          range=(1e-5, 1.0), read_only=True)
    odom_sigma_tilt_rad_per_m: float = param(
        0.02, 'Roll/pitch freedom of planar wheel odometry (rad per m): ramps tilt the car',
        range=(1e-5, 1.0), read_only=True)
    odom_wait_s: float = param(0.5, 'Longest a frame waits for the wheel odometry after its '
                               'stamp (s of stream time); frames are mapped once it is in',
                               range=(0.0, 10.0), read_only=True)
    max_backlog: int = param(50, 'Frames that may wait for the mapper; beyond that the '
                             'oldest are dropped and counted; may change at run time',
                             range=(1, 10000))
    cloud_period_s: float = param(1.0, 'Period of /semantic_cloud (s): the full map, latched; '
                                  'may change at run time', range=(0.05, 3600.0))
    change_confirm_messages: int = param(
        3, 'Consecutive messages that make a change accepted: a CameraInfo of another camera, '
        'or tracks (odometry) stamped before the newest one (a bag loop); a shorter run is '
        'ignored and counted as rejected', range=(1, 1000), read_only=True)
    min_change_interval_s: float = param(
        5.0, 'Shortest time between two resets of the map (s, wall clock); a persisting '
        'change waits for it', range=(0.0, 3600.0), read_only=True)
    output_dir: str = param('semfeat_map', '~/save_map writes cloud.ply, trajectory.tum and '
                            'map.json here (resolved once at start-up; empty = saving off)',
                            read_only=True)
    save_on_shutdown: bool = param(False, 'Save the map into output_dir when the node shuts '
                                   'down (Ctrl-C, ros2 launch stop)', read_only=True)
    input_timeout_s: float = param(
        5.0, 'An input the node needs (tracks, CameraInfo) silent this long is logged and '
        'reported as ERROR on /diagnostics (s); 0 = off; may change at run time',
        range=(0.0, 3600.0))
    drop_warn_ratio: float = param(0.2, 'Share of the frames received since the previous '
                                   '/diagnostics report that, dropped, makes it WARN; may '
                                   'change at run time', range=(0.0, 1.0))
    solver_error_frames: int = param(
        50, '/diagnostics is ERROR for this many mapped frames from one whose failed solver '
        'update could not be recovered (the window was reset), and while the mapper is lost; '
        'may change at run time', range=(1, 100000))
    solver_warn_frames: int = param(
        300, '/diagnostics is WARN for this many mapped frames from any failed solver update '
        '(recovered by rebuilding the smoother or not); may change at run time',
        range=(1, 100000))
    diagnostics_period_s: float = param(1.0, 'Period of /diagnostics (s); may change at run '
                                        'time', range=(0.1, 60.0))


# parameters the mapper reads anew for every frame: the key of its conf
MAPPER_RUNTIME_PARAMS = {'kf_parallax_deg': 'kf_parallax_deg',
                         'kf_max_distance_m': 'kf_max_distance_m'}


def mapper_conf(c: MappingNodeConfig) -> dict[str, Any]:
    """The mapping core's conf for the node parameters."""
    return {'use_odometry': c.use_odometry, 'use_gnss': c.use_gnss,
            'odom_calibration': c.odom_calibration,
            'vision_rotation_kinematic': c.vehicle_kinematics,
            'gnss_lever_arm_m': list(c.gnss_lever_arm_m),
            'window_keyframes': c.window_keyframes, 'kf_parallax_deg': c.kf_parallax_deg,
            'kf_max_distance_m': c.kf_max_distance_m, 'bearing_sigma_px': c.bearing_sigma_px,
            'voxel_size_m': c.voxel_size_m}


def session_conf(c: MappingNodeConfig) -> SessionConfig:
    return SessionConfig(odom_sigma_per_m=c.odom_sigma_per_m,
                         odom_sigma_rad_per_rad=c.odom_sigma_rad_per_rad,
                         odom_sigma_tilt_rad_per_m=c.odom_sigma_tilt_rad_per_m)


class MappingNode(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__('mapping_node', **kwargs)
        self.declare()
        self.setup()
        self.subscribe_inputs()

    def declare(self) -> None:
        """The parameters and their run-time checks (once per node)."""
        self.conf = declare_config(self, MappingNodeConfig)
        guard_updates(self, MappingNodeConfig)
        self.add_post_set_parameters_callback(self._apply_parameters)

    def _apply_parameters(self, params: list[Any]) -> None:
        """Accepted run-time changes (ranges checked, read-only ones refused before) take
        effect from the next frame or timer tick: the mapper's keyframe thresholds (also in a
        map started later), the backlog bound, the timer periods and the diagnostics
        thresholds. This runs on the executor; the mapper's conf is changed under the worker's
        lock, between frames. Unconfigured (managed variant), configure reads them."""
        for p in params:
            setattr(self.conf, p.name, p.value)
            self.get_logger().info(f'{p.name} = {p.value}')
        if not hasattr(self, 'health'):  # not configured yet
            return
        names = {p.name for p in params}
        with self._lock:
            for name in names & MAPPER_RUNTIME_PARAMS.keys():
                if self.session is not None:
                    self.session.mapper.conf[MAPPER_RUNTIME_PARAMS[name]] = getattr(
                        self.conf, name)
        c, live = self.conf, self.timers  # the managed variant's cleanup destroys the timers
        if 'cloud_period_s' in names and self._cloud_timer in live:
            self._cloud_timer.timer_period_ns = int(c.cloud_period_s * 1e9)
        if 'diagnostics_period_s' in names and self._diagnostics_timer in live:
            self._diagnostics_timer.timer_period_ns = int(c.diagnostics_period_s * 1e9)
        self.health.io.input_timeout_s = c.input_timeout_s
        self.health.drop_warn_ratio = c.drop_warn_ratio
        self.solver.error_frames = c.solver_error_frames
        self.solver.warn_frames = c.solver_warn_frames

    def setup(self) -> None:
        """Everything but the subscriptions, from ``self.conf``: the camera extrinsic,
        publishers, services, timers and the worker thread (the managed variant's
        configure)."""
        c = self.conf
        self.health = NodeHealth(self, input_timeout_s=c.input_timeout_s,
                                 drop_warn_ratio=c.drop_warn_ratio)
        self.solver = SolverHealth(c.solver_error_frames, c.solver_warn_frames)
        self.health.conditions.append(self.solver)
        _, extrinsic = load_camera_yaml(c.camera_config or None)
        self.T_base_cam_config = extrinsic.T_base_cam
        self.T_base_cam = self.T_base_cam_config  # of the current session
        self.extrinsic_source = 'camera_config'
        self.static_frames = StaticFrames()  # what others publish on /tf_static (a URDF)
        self._own_static: dict[tuple[str, str], np.ndarray] = {}  # what this node published
        self._odom_seen = False  # wheel odometry received: TF is map -> odom -> base_link
        self.health.extra.update(extrinsic_source=self.extrinsic_source, tf_published='0',
                                 tf_skipped_no_odometry='0')
        self._tf_counts = {'published': 0, 'skipped': 0}
        self.out_dir = Path(c.output_dir).expanduser().resolve() if c.output_dir else None
        self.session: MappingSession | None = None
        self.feeder: FrameFeeder | None = None
        self._now_ns = 0  # newest stamp seen on the tracks and odometry streams (ns)
        self._camera_key: tuple | None = None  # the newest accepted camera (executor thread)
        self._lock = threading.Lock()
        limit = RateLimit(c.min_change_interval_s)  # shared: camera and time resets
        self._camera_gate: ChangeGate[tuple] = ChangeGate(c.change_confirm_messages, limit)
        self.stamps = StampGuard(confirm=c.change_confirm_messages, limit=limit)
        self._odom_stamps = StampGuard(confirm=c.change_confirm_messages)
        self.resets = {'camera': 0, 'time': 0}
        self.health.extra.update(resets_camera='0', resets_time='0')
        self._dirty = False
        self.last_result = None
        self.paused = False  # ~/pause: tracks are counted and ignored until ~/resume
        self._counts = {'paused': 0, 'service_resets': 0}
        self.health.extra.update(paused='false', frames_paused='0', resets_service='0')
        self._inbox: deque[tuple[str, Any]] = deque()  # parsed inputs, arrival order
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._work, daemon=True, name='mapping-worker')

        io = self.health.io
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_cloud = io.publish(PointCloud2, c.cloud_topic, latched)
        self.pub_odom = io.publish(Odometry, c.odometry_topic, 10)
        self.pub_path = io.publish(PathMsg, c.path_topic, latched)
        if c.publish_tf:
            self.pub_tf = io.publish(TFMessage, '/tf', TF_QOS)
            self.pub_tf_static = io.publish(TFMessage, '/tf_static', TF_STATIC_PUB_QOS)
        self.create_service(Trigger, '~/save_map', self._on_save_map)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/pause', self._on_pause)
        self.create_service(Trigger, '~/resume', self._on_resume)
        self._cloud_timer = self.create_timer(c.cloud_period_s, self._publish_cloud)
        self._diagnostics_timer = self.create_timer(c.diagnostics_period_s,
                                                    self._publish_diagnostics)
        self._worker.start()
        self.get_logger().info(f'mapping_node ready: {c.tracks_topic} -> {c.cloud_topic}')

    def subscribe_inputs(self) -> None:
        """The subscriptions: odometry, GNSS, CameraInfo, tracks and /tf_static (the managed
        variant's activate)."""
        c, io = self.conf, self.health.io
        # odometry and GNSS first: the executor serves ready subscriptions in this order, and a
        # frame waits for the odometry after its stamp (FrameFeeder)
        if c.use_odometry:
            io.subscribe(Odometry, c.odom_topic, self._on_odom,
                         input_qos(c.input_reliability, 100))
        if c.use_gnss:
            io.subscribe(NavSatFix, c.gnss_topic, self._on_gnss,
                         input_qos(c.input_reliability, 20))
        io.subscribe(CameraInfo, c.camera_info_topic, self._on_camera_info,
                     input_qos(c.input_reliability), watch='CameraInfo')
        io.subscribe(PointCloud2, c.tracks_topic, self._on_tracks, input_qos('reliable'),
                     watch='tracks')
        io.subscribe(TFMessage, '/tf_static', self._on_tf_static, TF_STATIC_SUB_QOS)

    # -- inputs -----------------------------------------------------------------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            camera = camera_info_to_model(msg, fov_deg=self.conf.fov_deg)
        except MessageError as exc:
            self.health.on_reject(f'camera_info: {exc}')
            return
        key = (camera, msg.header.frame_id)
        if key == self._camera_key:
            self._count_outliers('CameraInfo of another camera', self._camera_gate.agree())
            return
        if self._camera_key is not None:
            run, dropped = self._camera_gate.offer(key)
            self._count_outliers('CameraInfo of another camera', dropped)
            if run is None:
                return
        self._camera_key = key
        self._queue('camera', key)

    def _count_outliers(self, what: str, n: int) -> None:
        if n:
            self.health.on_reject(f'{n} {what} ignored: the change did not persist for '
                                  f'{self.conf.change_confirm_messages} messages', count=n)

    def _on_odom(self, msg: Odometry) -> None:
        try:
            sample = odometry_to_numpy(msg)
        except MessageError as exc:
            self.health.on_reject(f'odometry: {exc}')
            return
        self._odom_seen = True
        order = self._odom_stamps.check(sample.stamp_ns, sample)
        self._count_outliers('odometry with older stamps', self._odom_stamps.dropped)
        if order == 'ok':
            self._queue('odom', sample)
        elif order == 'backwards':  # the odometry restarted (bag loop): its buffer starts again
            for held in self._odom_stamps.run:
                self._queue('odom', held)

    def _on_gnss(self, msg: NavSatFix) -> None:
        try:
            fix = navsatfix_to_numpy(msg)
        except MessageError as exc:
            self.health.on_reject(f'gnss: {exc}')
            return
        if fix.has_fix:
            self._queue('gnss', fix)

    def _on_tracks(self, msg: PointCloud2) -> None:
        if self.paused:
            self._counts['paused'] += 1
            self.health.extra['frames_paused'] = str(self._counts['paused'])
            return
        self.health.on_input()
        try:
            tr = tracks_from_msg(msg)
        except MessageError as exc:
            self.health.on_reject(f'tracks: {exc}')
            return
        self._queue('tracks', tr)

    def _on_tf_static(self, msg: TFMessage) -> None:
        """Static transforms of other publishers (a vehicle's URDF); this node's own, received
        back, are skipped."""
        for t in msg.transforms:
            try:
                T = transform_to_matrix(t)
            except MessageError as exc:
                self.health.on_reject(f'tf_static: {exc}')
                continue
            key = (t.header.frame_id, t.child_frame_id)
            own = self._own_static.get(key)
            if own is not None and np.allclose(own, T, atol=1e-6):
                continue
            if self.static_frames.add(*key, T) and own is not None:
                self.get_logger().warning(
                    f'/tf_static carries {key[0]} -> {key[1]} unlike camera_config: the map '
                    'uses it from the next camera change or reset')

    def _queue(self, kind: str, item: Any) -> None:
        self._inbox.append((kind, item))
        self._wake.set()

    # -- the worker ---------------------------------------------------------------------------
    def _work(self) -> None:
        while not self._stop.is_set():
            if not self._wake.wait(0.1):
                continue
            self._wake.clear()
            try:
                with self._lock:
                    while self._inbox:
                        self._apply(*self._inbox.popleft())
                    if self.feeder is None:
                        continue
                    fed = self._release(self._now_ns)
                    # of the frames still waiting for their odometry
                    self.health.counters.dropped += self.feeder.trim(self.conf.max_backlog)
                self._publish_frames(*fed)
            except Exception as exc:  # noqa: BLE001 - a bug must not stop the map: counted
                self.health.on_error(exc)

    def _apply(self, kind: str, item: Any) -> None:
        """One queued input into the feeder (call with the lock held)."""
        if kind == 'camera':
            self._start_session(*item)
            return
        if self.feeder is None:
            if kind == 'tracks':
                self.health.on_waiting('no CameraInfo received yet; tracks skipped')
            return
        try:
            if kind == 'odom':
                self.feeder.add_odometry(item.stamp_ns, item.T)
                self._now_ns = max(self._now_ns, item.stamp_ns)
            elif kind == 'gnss':
                self.feeder.add_fix(item.stamp_ns, (item.latitude, item.longitude,
                                                    item.altitude), item.covariance)
            else:
                self._push_tracks(item)
        except MappingError as exc:
            self.health.on_reject(f'{kind}: {exc}')

    def _start_session(self, camera: Any, frame_id: str) -> None:
        """A new map for an accepted camera (call with the lock held)."""
        if self.session is not None:
            self._before_reset('camera', f'camera changed ({camera.width}x{camera.height} px, '
                               f'frame {frame_id!r})')
        self._camera_frame = self.conf.camera_frame or frame_id or 'camera'
        self._choose_extrinsic()
        self.session = MappingSession(camera, self.T_base_cam, mapper_conf(self.conf),
                                      session_conf(self.conf))
        self.solver.new_map()
        self.feeder = FrameFeeder(self.session, self.conf.odom_wait_s)
        self.stamps.reset()
        self._now_ns = 0

    def _choose_extrinsic(self) -> None:
        """base_link -> camera for a new session: from /tf_static when another publisher
        (a URDF) carries it, else camera_config, which is then broadcast on /tf_static (call
        with the lock held)."""
        base, cam = self.conf.base_frame, self._camera_frame
        T = self.static_frames.lookup(base, cam)
        source = 'tf_static' if T is not None else 'camera_config'
        if T is None:
            T = self.T_base_cam_config
            if self.conf.publish_tf and (base, cam) not in self._own_static:
                self._own_static[(base, cam)] = T
                self.pub_tf_static.publish(TFMessage(transforms=[
                    transform_msg(T_, *key, 0) for key, T_ in self._own_static.items()]))
        if source != self.extrinsic_source or T is not self.T_base_cam:
            self.get_logger().info(f'{base} -> {cam} from {source}')
        self.T_base_cam, self.extrinsic_source = T, source
        self.health.extra['extrinsic_source'] = source

    def _before_reset(self, kind: str, reason: str) -> None:
        """Count a reset and save the map it ends into ``<output_dir>/before_reset`` (call
        with the lock held)."""
        self.resets[kind] += 1
        self.health.extra[f'resets_{kind}'] = str(self.resets[kind])
        self.health.extra['last_reset'] = reason
        saved = ''
        stamps, poses = self.session.mapper.trajectory()
        if self.out_dir is not None and len(stamps):
            try:
                done = save_map(self.out_dir, self.session.mapper.cloud(), stamps, poses,
                                subdir='before_reset', stamp_ns=int(stamps[-1]))
                saved = f'; the map was saved to {done.cloud.parent}'
            except MapWriteError as exc:
                saved = f'; the map could not be saved: {exc}'
        self.get_logger().warning(f'{reason}: the map restarts{saved}')

    def _push_tracks(self, tr: Any) -> None:
        order = self.stamps.check(tr.stamp_ns, tr)
        self._count_outliers('tracks with older stamps', self.stamps.dropped)
        self.health.counters.dropped += self.stamps.trimmed  # a loop's frames while it waits
        if order == 'duplicate':
            self.health.on_reject(f'tracks with a repeated stamp {tr.stamp_ns} ns skipped')
            return
        if order == 'held':  # older than the newest frame: mapped only if the jump persists
            return
        if order == 'backwards':
            self._before_reset('time', 'time went backwards (bag loop?)')
            self.session.reset()
            self.solver.new_map()
            self.feeder.reset()
            self._now_ns = 0
        for t in self.stamps.run if order == 'backwards' else [tr]:
            self.feeder.push(Tracks(t.stamp_ns, t.track_ids.astype(np.int64),
                                    t.bearings.astype(np.float64), t.uv.astype(np.float64),
                                    t.labels))
            self._now_ns = max(self._now_ns, t.stamp_ns)

    def _release(self, now_ns: int | None) -> tuple[list[tuple], dict[str, Any]]:
        """Frames the feeder maps now, each with the keyframe path after it and the wheel
        odometry pose at its stamp (None without), and the session's state after the last of
        them (call with the lock held)."""
        out = []
        for f in self.feeder.release(now_ns):
            path = T_odom_base = None
            if f.result is not None:
                self.last_result = f.result
                self._dirty = self._dirty or f.result.keyframe
                if f.result.keyframe:
                    path = self.session.mapper.trajectory()
                T_odom_base = self.session.odometry_at(f.tracks.stamp_ns)
            out.append((f, path, T_odom_base))
        state = {'calibration': self.session.mapper.odometry_calibration,
                 'missing': dict(self.session.odometry_missing),
                 'map_in_enu': self.session.mapper.map_in_enu} if out else {}
        return out, state

    def _publish_frames(self, fed: list[tuple], state: dict[str, Any]) -> None:
        for f, path, T_odom_base in fed:
            if f.result is None:
                self.health.on_reject(f'mapper: {f.error}')
            else:
                self.solver.on_result(f.result.state, f.result.events)
                self._publish_frame(f, path)
                if self.conf.publish_tf and f.result.T_map_base is not None:
                    self._broadcast(f.result.T_map_base, T_odom_base, f.tracks.stamp_ns,
                                    state.get('map_in_enu'))
        if state:
            cal, missing = state['calibration'], state['missing']
            self.health.extra.update(
                odom_yaw_bias_deg_s=f'{math.degrees(cal["yaw_bias_rad_s"]):.4f}',
                odom_yaw_scale=f'{cal["yaw_scale"]:.4f}',
                odom_distance_scale=f'{cal["distance_scale"]:.4f}',
                odom_calibration_pairs=str(cal['pairs']),
                frames_without_odometry=' '.join(f'{k} {v}' for k, v in missing.items()))

    def _publish_frame(self, f: FedFrame, path: tuple | None) -> None:
        result, stamp_ns = f.result, f.tracks.stamp_ns
        if result.T_map_base is not None:
            cov = None
            if result.covariance is not None:  # (rot, trans) -> ROS (trans, rot)
                order = [3, 4, 5, 0, 1, 2]
                cov = result.covariance[np.ix_(order, order)]
            self.pub_odom.publish(odometry_from_numpy(
                result.T_map_base, cov, stamp_ns=stamp_ns, frame_id=self.conf.map_frame,
                child_frame_id=self.conf.base_frame, msg_cls=Odometry))
        if path is not None and len(path[0]):
            self.pub_path.publish(path_from_numpy(path[0], path[1], frame_id=self.conf.map_frame,
                                                  msg_cls=PathMsg, stamp_ns=stamp_ns))
        self.health.on_output(stamp_ns, result.update_ms * 1e-3)  # the mapper's own time
        self.health.extra.update(state=result.state, metric=str(result.metric),
                                 landmarks=str(result.n_landmarks),
                                 update_ms=f'{result.update_ms:.1f}')

    def _broadcast(self, T_map_base: np.ndarray, T_odom_base: np.ndarray | None,
                   stamp_ns: int, T_enu_map: np.ndarray | None = None) -> None:
        """/tf at the frame's image stamp: map -> odom (and odom -> base_link) once wheel
        odometry is received, map -> base_link before; a frame without odometry at its stamp
        after that is skipped and counted (base_link keeps one parent). Once GNSS aligned the
        map (``T_enu_map``, the map frame's pose in ENU), enu -> map too."""
        c = self.conf
        enu = [] if T_enu_map is None else [
            transform_msg(T_enu_map, c.enu_frame, c.map_frame, stamp_ns)]
        if T_odom_base is not None:
            tfs = [transform_msg(T_map_base @ np.linalg.inv(T_odom_base), c.map_frame,
                                 c.odom_frame, stamp_ns)]
            if c.publish_odom_tf:
                tfs.append(transform_msg(T_odom_base, c.odom_frame, c.base_frame, stamp_ns))
        elif not self._odom_seen:
            tfs = [transform_msg(T_map_base, c.map_frame, c.base_frame, stamp_ns)]
        else:
            self._tf_counts['skipped'] += 1
            self.health.extra['tf_skipped_no_odometry'] = str(self._tf_counts['skipped'])
            return
        self.pub_tf.publish(TFMessage(transforms=enu + tfs))
        self._tf_counts['published'] += 1
        self.health.extra['tf_published'] = str(self._tf_counts['published'])

    # -- outputs ----------------------------------------------------------------------------
    def _publish_cloud(self) -> None:
        with self._lock:
            if self.session is None or not self._dirty:
                return
            self._dirty = False
            cloud = self.session.mapper.cloud()
            stamp = self.last_result.stamp_ns if self.last_result is not None else 0
        self.pub_cloud.publish(semantic_cloud_to_msg(
            cloud.xyz, cloud.rgb, cloud.label, cloud.floor, cloud.landmark_id, cloud.n_obs,
            stamp_ns=stamp, frame_id=self.conf.map_frame, msg_cls=PointCloud2))
        self.health.extra.update(cloud_points=str(len(cloud.xyz)),
                                 floors=str(len(np.unique(cloud.floor))))

    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response
                     ) -> Trigger.Response:
        response.success, response.message = self.save()
        return response

    def save(self, publish: bool = True) -> tuple[bool, str]:
        """Write the map into ``output_dir`` (the frames still waiting for their odometry are
        mapped first, and published when ``publish``); whether it was written and what
        happened."""
        if self.out_dir is None:
            return False, 'saving is off (output_dir is empty)'
        with self._lock:
            if self.session is None:
                return False, 'no map yet (no CameraInfo)'
            fed = self._release(None)  # the frames still waiting for their odometry
            cloud = self.session.mapper.cloud()
            stamps, poses = self.session.mapper.trajectory()
            stamp = self.last_result.stamp_ns if self.last_result is not None else 0
        if publish:
            self._publish_frames(*fed)
        try:
            saved = save_map(self.out_dir, cloud, stamps, poses, stamp_ns=stamp)
        except MapWriteError as exc:
            return False, str(exc)
        return True, (f'wrote {saved.cloud} ({saved.n_points} points), {saved.trajectory} '
                      f'({saved.n_poses} poses) and {saved.manifest}')

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        """Forget the map, the trajectory and the frames waiting for odometry; the next
        frame starts a new map with the same camera (the map is not saved: ~/save_map first)."""
        with self._lock:
            if self.session is None:
                response.success, response.message = False, 'no map yet (no CameraInfo)'
                return response
            n = len(self.session.mapper.trajectory()[0])
            self.session.reset()
            self.solver.new_map()
            self.feeder.reset()
            self.stamps.reset()
            self._now_ns = 0
            self.last_result = None
            self._dirty = True  # the latched cloud is replaced by the empty map
        self._counts['service_resets'] += 1
        self.health.extra['resets_service'] = str(self._counts['service_resets'])
        response.success, response.message = True, f'map reset ({n} keyframes discarded)'
        self.get_logger().info(response.message)
        return response

    def _on_pause(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        if self.paused:
            response.success, response.message = False, 'already paused'
            return response
        self.paused = True
        self.health.extra['paused'] = 'true'
        response.success = True
        response.message = ('paused: tracks are ignored (counted as frames_paused) until '
                            '~/resume; odometry and GNSS are still buffered')
        return response

    def _on_resume(self, request: Trigger.Request, response: Trigger.Response
                   ) -> Trigger.Response:
        if not self.paused:
            response.success, response.message = False, 'not paused'
            return response
        self.paused = False
        self.health.extra['paused'] = 'false'
        response.success, response.message = True, 'resumed'
        return response

    def _publish_diagnostics(self) -> None:
        gates = (self._camera_gate.counts, self.stamps.gate.counts)
        self.health.extra.update(
            change_outliers_ignored=str(sum(g.outliers for g in gates)
                                        + self._odom_stamps.gate.counts.outliers),
            resets_deferred=str(sum(g.deferred for g in gates)))
        self.health.publish()

    def _stop_worker(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._worker.is_alive():
            self._worker.join(timeout=10.0)

    def save_on_exit(self) -> None:
        """With ``save_on_shutdown``, stop the worker and save the map (the node is going
        away: destroyed, or the managed variant's shutdown)."""
        self._stop_worker()
        if self.conf.save_on_shutdown and self.session is not None:
            ok, message = self.save(publish=False)  # the context may be shut down (Ctrl-C)
            log = self.get_logger()
            (log.info if ok else log.error)(f'save on shutdown: {message}')

    def release(self) -> None:
        """Stop the worker thread and free the map, unsaved (the managed variant's
        cleanup)."""
        self._stop_worker()
        with self._lock:
            self.session = self.feeder = self.last_result = None
            self._inbox.clear()

    def destroy_node(self) -> None:
        if hasattr(self, '_worker'):
            self.save_on_exit()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    spin_node('mapping_node', MappingNode, SingleThreadedExecutor, args)


if __name__ == '__main__':
    main(sys.argv)
