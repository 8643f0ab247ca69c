"""Write a rendered drive as a rosbag2 recording (``rosbags`` writer, metadata version 9).

Topics (all stamps from the simulation clock, ``STAMP0_NS`` + sim time):

===================================== ============================= ==========================
topic                                 type                          frame_id
===================================== ============================= ==========================
/camera/front/image_raw               sensor_msgs/Image (rgb8)      camera_front_optical
/camera/front/image_raw/compressed    sensor_msgs/CompressedImage   camera_front_optical
/camera/front/camera_info             sensor_msgs/CameraInfo        camera_front_optical
/gnss/fix                             sensor_msgs/NavSatFix         gnss_link
/vehicle/odom                         nav_msgs/Odometry             odom -> base_link
/ground_truth/pose                    geometry_msgs/PoseStamped     map (pose of base_link)
/ground_truth/semantic                sensor_msgs/Image (mono8)     camera_front_optical
/ground_truth/depth                   sensor_msgs/Image (32FC1)     camera_front_optical
===================================== ============================= ==========================

Only one of the two image topics is written (``compressed``). There is no ``/tf_static``: the
camera's extrinsic (base_link -> camera_front_optical) is the one of the calibration YAML the
bag was rendered with (``config/camera_front.yaml``; also stored in the bag's ``custom_data``),
the frame is named by CameraInfo's ``frame_id``. The GNSS antenna sits at
:data:`~semfeat_ros.sim.sensors.ANTENNA_OFFSET` in base_link. Ground-truth semantic labels use
255 outside the image circle; ground-truth depth is the range along the ray (m), +inf for sky
and NaN outside the image circle (REP 118 conventions).
"""
from __future__ import annotations

from dataclasses import dataclass
import json
from pathlib import Path

import numpy as np
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from tqdm import tqdm

from msg_adapters import model_to_camera_info, numpy_to_compressed, numpy_to_image
from msg_adapters.stamp import make_header
from semfeat_ros.rotations import matrix_to_quaternion, rpy_to_matrix
from semfeat_ros.sim.errors import BagWriteError, SimConfigError
from semfeat_ros.sim.scenario import Scenario
from semfeat_ros.sim.sensors import (
    ANTENNA_OFFSET,
    COVARIANCE_TYPE_DIAGONAL_KNOWN,
    SERVICE_GPS_GLONASS_GALILEO,
    STATUS_NO_FIX,
    GnssModel,
    WheelOdometry,
)

STAMP0_NS = 1_704_067_200 * 10 ** 9
"""Header stamp of simulation time 0 (2024-01-01T00:00:00Z), ns."""

TOPIC_IMAGE = '/camera/front/image_raw'
TOPIC_COMPRESSED = '/camera/front/image_raw/compressed'
TOPIC_INFO = '/camera/front/camera_info'
TOPIC_GNSS = '/gnss/fix'
TOPIC_ODOM = '/vehicle/odom'
TOPIC_GT_POSE = '/ground_truth/pose'
TOPIC_GT_SEMANTIC = '/ground_truth/semantic'
TOPIC_GT_DEPTH = '/ground_truth/depth'

CAMERA_FRAME = 'camera_front_optical'
GNSS_FRAME = 'gnss_link'
BASE_FRAME = 'base_link'
ODOM_FRAME = 'odom'
MAP_FRAME = 'map'

_LARGE_VAR = 1.0e6  # variance of unobserved odometry components
_INFINITE = QosTime(9223372036, 854775807)
OFFERED_QOS = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
                  _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False)
"""QoS stored as the recorded publishers' offered profile (a default reliable publisher)."""


@dataclass(frozen=True)
class BagConfig:
    """What to record (rates in Hz, times in s, size in px)."""

    seed: int = 0
    duration: float = 20.0
    rate: float = 10.0
    size: tuple[int, int] = (640, 512)
    start: float = 0.0
    storage: str = 'mcap'  # or 'sqlite3'
    compressed: bool = True
    jpeg_quality: int = 90
    gnss_rate: float = 5.0
    odom_rate: float = 50.0
    semantic_every: int = 1  # write /ground_truth/semantic every N-th frame
    depth_every: int = 1  # write /ground_truth/depth every N-th frame
    depth_quantum: float = 0.0  # round ground-truth depth to multiples of this (m); 0: exact

    def __post_init__(self) -> None:
        if not 0.0 < self.duration <= 3600.0:
            raise SimConfigError(f'duration must be in (0, 3600] s, got {self.duration}')
        if not 0.1 <= self.rate <= 60.0:
            raise SimConfigError(f'rate must be in 0.1..60 Hz, got {self.rate}')
        if self.storage not in ('mcap', 'sqlite3'):
            raise SimConfigError(f'storage must be mcap or sqlite3, got {self.storage!r}')
        if self.start < 0.0:
            raise SimConfigError(f'start must be >= 0 s, got {self.start}')
        if not 1 <= self.jpeg_quality <= 100:
            raise SimConfigError(f'jpeg_quality must be in 1..100, got {self.jpeg_quality}')
        if self.semantic_every < 1 or self.depth_every < 1:
            raise SimConfigError(
                f'semantic_every and depth_every must be >= 1, got {self.semantic_every}, '
                f'{self.depth_every}')
        if not 0.0 <= self.depth_quantum <= 0.1:
            raise SimConfigError(f'depth_quantum must be in [0, 0.1] m, got {self.depth_quantum}')
        if len(self.size) != 2 or min(self.size) < 16:
            raise SimConfigError(f'size must be (width, height) >= 16 px, got {self.size}')


@dataclass(frozen=True)
class BagSummary:
    """What was written."""

    path: Path
    frames: int
    messages: dict[str, int]
    start: float
    end: float
    size_bytes: int
    path_length_m: float


def _stamp(t: float) -> int:
    return STAMP0_NS + int(round(t * 1e9))


def _pose(ts, T: np.ndarray):
    q = matrix_to_quaternion(T[:3, :3])
    Point = ts.types['geometry_msgs/msg/Point']
    Quaternion = ts.types['geometry_msgs/msg/Quaternion']
    Pose = ts.types['geometry_msgs/msg/Pose']
    return Pose(position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                       w=float(q[3])))


def pose_stamped_msg(ts, T_map_base: np.ndarray, stamp_ns: int):
    """``geometry_msgs/PoseStamped`` (rosbags flavour) of base_link in ``map``."""
    cls = ts.types['geometry_msgs/msg/PoseStamped']
    return cls(header=make_header(stamp_ns, MAP_FRAME, cls, typestore=ts),
               pose=_pose(ts, T_map_base))


def navsatfix_msg(ts, fix, stamp_ns: int):
    """``sensor_msgs/NavSatFix`` of a :class:`~semfeat_ros.sim.sensors.GnssFix`."""
    cls = ts.types['sensor_msgs/msg/NavSatFix']
    status_cls = ts.types['sensor_msgs/msg/NavSatStatus']
    cov = np.zeros(9)
    cov[[0, 4, 8]] = fix.covariance_enu
    lat, lon, alt = (float(v) for v in fix.lat_lon_alt)
    return cls(header=make_header(stamp_ns, GNSS_FRAME, cls, typestore=ts),
               status=status_cls(status=int(fix.status), service=SERVICE_GPS_GLONASS_GALILEO),
               latitude=lat, longitude=lon, altitude=alt, position_covariance=cov,
               position_covariance_type=COVARIANCE_TYPE_DIAGONAL_KNOWN)


def odometry_msg(ts, od, stamp_ns: int):
    """``nav_msgs/Odometry`` (odom -> base_link) of an
    :class:`~semfeat_ros.sim.sensors.OdomSample`."""
    cls = ts.types['nav_msgs/msg/Odometry']
    pwc = ts.types['geometry_msgs/msg/PoseWithCovariance']
    twc = ts.types['geometry_msgs/msg/TwistWithCovariance']
    twist_cls = ts.types['geometry_msgs/msg/Twist']
    vec = ts.types['geometry_msgs/msg/Vector3']
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(0.0, 0.0, od.yaw)
    T[:2, 3] = (od.x, od.y)
    pcov = np.zeros(36)
    pcov[[0, 7, 35]] = od.pose_var
    pcov[[14, 21, 28]] = _LARGE_VAR
    tcov = np.zeros(36)
    tcov[0], tcov[35] = od.twist_var
    tcov[[7, 14, 21, 28]] = _LARGE_VAR
    return cls(header=make_header(stamp_ns, ODOM_FRAME, cls, typestore=ts),
               child_frame_id=BASE_FRAME,
               pose=pwc(pose=_pose(ts, T), covariance=pcov),
               twist=twc(twist=twist_cls(linear=vec(x=float(od.speed), y=0.0, z=0.0),
                                         angular=vec(x=0.0, y=0.0, z=float(od.yaw_rate))),
                         covariance=tcov))


def resolve_start(scenario: Scenario, start: float | str) -> float:
    """Start time (s) of a recording: a number, or ``'ramp'`` (6 s before the car reaches the
    ramp's top, so a 20 s recording covers deck -> ramp -> covered level)."""
    if isinstance(start, str):
        if start != 'ramp':
            try:
                return float(start)
            except ValueError:
                raise SimConfigError(
                    f"start must be seconds or 'ramp', got {start!r}") from None
        return max(0.0, scenario.trajectory.time_at(scenario.trajectory.s_ramp[0]) - 6.0)
    return float(start)


def write_bag(out: str | Path, cfg: BagConfig, *, scenario: Scenario | None = None,
              progress: bool = True, command: str = '') -> BagSummary:
    """Render the drive and write it as a rosbag2 directory ``out`` (must not exist)."""
    out = Path(out)
    if out.exists():
        raise BagWriteError(f'output {out} exists already; choose a new directory')
    sc = scenario or Scenario.create(seed=cfg.seed, size=cfg.size)
    traj = sc.trajectory
    t0 = cfg.start
    t1 = t0 + cfg.duration
    if t0 >= traj.duration:
        raise SimConfigError(f'start {t0:.1f} s is after the end of the drive '
                             f'({traj.duration:.1f} s)')
    if t1 > traj.duration + 1e-6:
        raise SimConfigError(
            f'start + duration = {t1:.1f} s exceeds the drive of {traj.duration:.1f} s '
            f'({traj.length:.0f} m); shorten --duration or --start')
    n_frames = int(np.floor(cfg.duration * cfg.rate + 1e-9))
    frame_times = t0 + np.arange(n_frames) / cfg.rate
    odom_times = t0 + np.arange(int(np.floor(cfg.duration * cfg.odom_rate + 1e-9))
                                ) / cfg.odom_rate
    gnss_times = t0 + np.arange(int(np.floor(cfg.duration * cfg.gnss_rate + 1e-9))
                                ) / cfg.gnss_rate
    ts = get_typestore(Stores.ROS2_JAZZY)
    gnss = GnssModel(sc.world, traj, cfg.seed, cfg.gnss_rate)
    odom = WheelOdometry(traj, cfg.seed, cfg.odom_rate)
    sensor = sc.sensor
    sensor.reset()
    storage = StoragePlugin.MCAP if cfg.storage == 'mcap' else StoragePlugin.SQLITE3
    writer = Writer(out, version=Writer.VERSION_LATEST, storage_plugin=storage)
    if cfg.storage == 'mcap':
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    else:
        writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    ext = sc.T_base_cam
    writer.set_custom_data('semfeat_sim', json.dumps({
        'seed': cfg.seed, 'start_s': t0, 'duration_s': cfg.duration, 'rate_hz': cfg.rate,
        'size': list(cfg.size), 'stamp0_ns': STAMP0_NS, 'command': command,
        'T_base_cam': np.round(ext, 9).tolist(), 'camera_frame': CAMERA_FRAME,
        'gnss_antenna_in_base_link_m': ANTENNA_OFFSET.tolist(),
        'geo_origin': list(sc.world.config.geo_origin),
        'ground_truth_pose': 'T_map_base (base_link: rear-axle centre at road height)',
        'semantic_every': cfg.semantic_every, 'depth_every': cfg.depth_every,
        'depth_quantum_m': cfg.depth_quantum, 'jpeg_quality': cfg.jpeg_quality,
        'labels_outside_image_circle': 255}, sort_keys=True))
    counts: dict[str, int] = {}
    try:
        writer.open()
        conns = {}
        image_topic = TOPIC_COMPRESSED if cfg.compressed else TOPIC_IMAGE
        image_type = ('sensor_msgs/msg/CompressedImage' if cfg.compressed
                      else 'sensor_msgs/msg/Image')
        for topic, msgtype in ((image_topic, image_type),
                               (TOPIC_INFO, 'sensor_msgs/msg/CameraInfo'),
                               (TOPIC_GNSS, 'sensor_msgs/msg/NavSatFix'),
                               (TOPIC_ODOM, 'nav_msgs/msg/Odometry'),
                               (TOPIC_GT_POSE, 'geometry_msgs/msg/PoseStamped'),
                               (TOPIC_GT_SEMANTIC, 'sensor_msgs/msg/Image'),
                               (TOPIC_GT_DEPTH, 'sensor_msgs/msg/Image')):
            conns[topic] = writer.add_connection(topic, msgtype, typestore=ts,
                                                 offered_qos_profiles=[OFFERED_QOS])
            counts[topic] = 0

        def put(topic: str, msg, stamp_ns: int) -> None:
            writer.write(conns[topic], stamp_ns,
                         ts.serialize_cdr(msg, conns[topic].msgtype))
            counts[topic] += 1

        queue = sorted([(t, 0, 'odom') for t in odom_times[1:]]
                       + [(t, 1, 'gnss') for t in gnss_times])
        qi = 0

        def flush(until: float) -> None:
            nonlocal qi
            while qi < len(queue) and queue[qi][0] <= until + 1e-9:
                t, _, kind = queue[qi]
                qi += 1
                if kind == 'odom':
                    put(TOPIC_ODOM, odometry_msg(ts, odom.step(t), _stamp(t)), _stamp(t))
                else:
                    fix = gnss.fix(t)
                    if fix.status != STATUS_NO_FIX:
                        put(TOPIC_GNSS, navsatfix_msg(ts, fix, _stamp(t)), _stamp(t))

        put(TOPIC_ODOM, odometry_msg(ts, odom.step(t0), _stamp(t0)), _stamp(t0))
        bar = tqdm(total=n_frames, desc=f'render {out.name}', unit='frame', disable=not progress)
        for k, t in enumerate(frame_times):
            flush(t)
            stamp = _stamp(t)
            T_base = traj.sample(t).T_map_base
            frame = sc.renderer.render(sc.camera_pose(t), t)
            rgb, _ = sensor.expose(frame, sc.camera, k)
            put(TOPIC_INFO, model_to_camera_info(sc.camera, stamp_ns=stamp,
                                                 frame_id=CAMERA_FRAME, msg_cls=ts), stamp)
            if cfg.compressed:
                msg = numpy_to_compressed(rgb, 'jpeg', stamp_ns=stamp, frame_id=CAMERA_FRAME,
                                          msg_cls=ts, quality=cfg.jpeg_quality)
            else:
                msg = numpy_to_image(rgb, 'rgb8', stamp_ns=stamp, frame_id=CAMERA_FRAME,
                                     msg_cls=ts)
            put(image_topic, msg, stamp)
            put(TOPIC_GT_POSE, pose_stamped_msg(ts, T_base, stamp), stamp)
            if k % cfg.semantic_every == 0:
                put(TOPIC_GT_SEMANTIC, numpy_to_image(frame.label, 'mono8', stamp_ns=stamp,
                                                      frame_id=CAMERA_FRAME, msg_cls=ts), stamp)
            if k % cfg.depth_every == 0:
                depth = frame.depth.astype(np.float32)
                if cfg.depth_quantum > 0:
                    depth = (np.round(depth / cfg.depth_quantum) * cfg.depth_quantum).astype(
                        np.float32)
                put(TOPIC_GT_DEPTH, numpy_to_image(depth, '32FC1', stamp_ns=stamp,
                                                   frame_id=CAMERA_FRAME, msg_cls=ts), stamp)
            bar.update(1)
        bar.close()
        flush(t1 - 1e-9)
        writer.close()
    except BaseException:
        if writer.storage is not None:
            writer.abort()
        raise
    size = sum(f.stat().st_size for f in out.rglob('*') if f.is_file())
    s0, s1 = traj.s_at(t0), traj.s_at(t1)
    return BagSummary(path=out, frames=n_frames, messages=counts, start=t0, end=t1,
                      size_bytes=size, path_length_m=s1 - s0)

