"""Poses, odometry, paths and GNSS fixes <-> numpy, for rclpy and rosbags messages alike.

Poses are 4x4 homogeneous transforms (m) mapping child-frame points into the parent frame.
Quaternions follow ROS (x, y, z, w). Covariances keep their message order: ``nav_msgs/Odometry``
pose covariance is (x, y, z, roll, pitch, yaw) (m, rad), ``sensor_msgs/NavSatFix`` position
covariance is ENU (east, north, up) in m^2.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters._flavour import construct, flavour_class, resolve_class
from msg_adapters.errors import NonFiniteError, ValueRangeError
from msg_adapters.stamp import make_header, stamp_to_ns
from semfeat_ros import rotations

POSE_TYPE = 'geometry_msgs/msg/Pose'
POSE_STAMPED_TYPE = 'geometry_msgs/msg/PoseStamped'
ODOMETRY_TYPE = 'nav_msgs/msg/Odometry'
PATH_TYPE = 'nav_msgs/msg/Path'

COVARIANCE_TYPE_UNKNOWN = 0
"""``NavSatFix.position_covariance_type`` meaning the covariance is not known."""

STATUS_NO_FIX = -1
"""``NavSatStatus.status`` of a receiver without a fix."""


def quaternion_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """3x3 rotation of a quaternion (normalised first); a zero quaternion raises."""
    try:
        return rotations.quaternion_to_matrix(np.array([x, y, z, w], dtype=np.float64))
    except ValueError as exc:
        raise NonFiniteError(f'orientation: {exc}') from None


def matrix_to_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation matrix (w >= 0)."""
    q = rotations.matrix_to_quaternion(R)
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def pose_to_matrix(pose: Any) -> np.ndarray:
    """4x4 transform of a ``geometry_msgs/Pose`` (either flavour); non-finite values raise."""
    p, o = pose.position, pose.orientation
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    if not np.isfinite(t).all():
        raise NonFiniteError(f'position: non-finite value {t.tolist()}')
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(o.x, o.y, o.z, o.w)
    T[:3, 3] = t
    return T


def matrix_to_pose(T: np.ndarray, msg_cls: Any, *, typestore: Any | None = None) -> Any:
    """A ``geometry_msgs/Pose`` of ``T`` (4x4, m) in the flavour of ``msg_cls``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise NonFiniteError(f'pose: expected a finite 4x4 transform, got shape {T.shape}')
    pose_cls = flavour_class(msg_cls, POSE_TYPE, typestore)
    point_cls = flavour_class(pose_cls, 'geometry_msgs/msg/Point', typestore)
    quat_cls = flavour_class(pose_cls, 'geometry_msgs/msg/Quaternion', typestore)
    x, y, z, w = matrix_to_quaternion(T[:3, :3])
    return construct(pose_cls,
                     position=construct(point_cls, x=float(T[0, 3]), y=float(T[1, 3]),
                                        z=float(T[2, 3])),
                     orientation=construct(quat_cls, x=x, y=y, z=z, w=w))


@dataclass(frozen=True)
class OdometrySample:
    """A ``nav_msgs/Odometry``: pose of ``child_frame_id`` in ``frame_id`` and its covariance
    (6x6, (x, y, z, roll, pitch, yaw) order, m / rad), twist in the child frame."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    T: np.ndarray
    covariance: np.ndarray
    linear: np.ndarray
    angular: np.ndarray


def odometry_to_numpy(msg: Any) -> OdometrySample:
    """Read a ``nav_msgs/Odometry`` (either flavour)."""
    cov = np.asarray(msg.pose.covariance, dtype=np.float64)
    if cov.size != 36:
        raise ValueRangeError(f'pose.covariance: expected 36 values, got {cov.size}')
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    return OdometrySample(
        stamp_ns=stamp_to_ns(msg), frame_id=str(msg.header.frame_id),
        child_frame_id=str(msg.child_frame_id), T=pose_to_matrix(msg.pose.pose),
        covariance=cov.reshape(6, 6),
        linear=np.array([lin.x, lin.y, lin.z], dtype=np.float64),
        angular=np.array([ang.x, ang.y, ang.z], dtype=np.float64))


def odometry_from_numpy(T: np.ndarray, covariance: np.ndarray | None, *, stamp_ns: int,
                        frame_id: str, child_frame_id: str, msg_cls: Any,
                        typestore: Any | None = None) -> Any:
    """A ``nav_msgs/Odometry`` with pose ``T`` (4x4) and its 6x6 covariance in message order
    (x, y, z, roll, pitch, yaw). None means unknown and is written as -1 in the first entry
    (never an all-zero covariance, which would claim a perfect pose)."""
    cls = resolve_class(msg_cls, ODOMETRY_TYPE, typestore)
    pwc_cls = flavour_class(cls, 'geometry_msgs/msg/PoseWithCovariance', typestore)
    twc_cls = flavour_class(cls, 'geometry_msgs/msg/TwistWithCovariance', typestore)
    twist_cls = flavour_class(cls, 'geometry_msgs/msg/Twist', typestore)
    vec_cls = flavour_class(cls, 'geometry_msgs/msg/Vector3', typestore)
    if covariance is None:
        cov = np.zeros((6, 6))
        cov[0, 0] = -1.0
    else:
        cov = np.asarray(covariance, dtype=np.float64)
        if cov.shape != (6, 6):
            raise ValueRangeError(f'covariance: expected (6, 6), got {cov.shape}')
    cov_field = cov.reshape(-1).copy()
    zero = construct(vec_cls, x=0.0, y=0.0, z=0.0)
    return construct(
        cls, header=make_header(stamp_ns, frame_id, cls, typestore=typestore),
        child_frame_id=child_frame_id,
        pose=construct(pwc_cls, pose=matrix_to_pose(T, cls, typestore=typestore),
                       covariance=cov_field),
        twist=construct(twc_cls, twist=construct(twist_cls, linear=zero,
                                                 angular=construct(vec_cls, x=0.0, y=0.0,
                                                                   z=0.0)),
                        covariance=np.zeros(36)))


def pose_stamped_to_numpy(msg: Any) -> tuple[int, str, np.ndarray]:
    """``(stamp_ns, frame_id, T)`` of a ``geometry_msgs/PoseStamped``."""
    return stamp_to_ns(msg), str(msg.header.frame_id), pose_to_matrix(msg.pose)


def path_from_numpy(stamps_ns: np.ndarray, poses: np.ndarray, *, frame_id: str, msg_cls: Any,
                    stamp_ns: int | None = None, typestore: Any | None = None) -> Any:
    """A ``nav_msgs/Path`` of poses (K, 4, 4) with their stamps (K,) ns."""
    cls = resolve_class(msg_cls, PATH_TYPE, typestore)
    ps_cls = flavour_class(cls, POSE_STAMPED_TYPE, typestore)
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(stamps) != len(poses):
        raise ValueRangeError(f'path: {len(stamps)} stamps for {len(poses)} poses')
    items = [construct(ps_cls, header=make_header(int(s), frame_id, ps_cls, typestore=typestore),
                       pose=matrix_to_pose(T, ps_cls, typestore=typestore))
             for s, T in zip(stamps, poses)]
    last = int(stamps[-1]) if len(stamps) else 0
    return construct(cls, header=make_header(last if stamp_ns is None else stamp_ns, frame_id,
                                             cls, typestore=typestore), poses=items)


def path_to_numpy(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps_ns (K,), poses (K, 4, 4))`` of a ``nav_msgs/Path`` (poses in its frame, m)."""
    stamps = np.array([stamp_to_ns(p) for p in msg.poses], dtype=np.int64)
    poses = np.array([pose_to_matrix(p.pose) for p in msg.poses], dtype=np.float64)
    return stamps, poses.reshape(-1, 4, 4)


@dataclass(frozen=True)
class GnssSample:
    """A ``sensor_msgs/NavSatFix``: latitude/longitude (deg), altitude (m), ENU covariance
    (3x3 m^2, None when the message says it is unknown) and the receiver status."""

    stamp_ns: int
    frame_id: str
    latitude: float
    longitude: float
    altitude: float
    covariance: np.ndarray | None
    status: int

    @property
    def has_fix(self) -> bool:
        return self.status > STATUS_NO_FIX and np.isfinite(
            [self.latitude, self.longitude, self.altitude]).all()


def navsatfix_to_numpy(msg: Any) -> GnssSample:
    """Read a ``sensor_msgs/NavSatFix`` (either flavour); latitude must be within +-90 deg and
    longitude within +-180 deg (when finite)."""
    cov = np.asarray(msg.position_covariance, dtype=np.float64)
    if cov.size != 9:
        raise ValueRangeError(f'position_covariance: expected 9 values, got {cov.size}')
    lat, lon, alt = float(msg.latitude), float(msg.longitude), float(msg.altitude)
    if np.isfinite(lat) and not -90.0 <= lat <= 90.0:
        raise ValueRangeError(f'latitude: expected -90..90 deg, got {lat}')
    if np.isfinite(lon) and not -180.0 <= lon <= 180.0:
        raise ValueRangeError(f'longitude: expected -180..180 deg, got {lon}')
    known = int(msg.position_covariance_type) != COVARIANCE_TYPE_UNKNOWN
    return GnssSample(stamp_ns=stamp_to_ns(msg), frame_id=str(msg.header.frame_id),
                      latitude=lat, longitude=lon, altitude=alt,
                      covariance=cov.reshape(3, 3) if known else None,
                      status=int(msg.status.status))
