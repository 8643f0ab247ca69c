"""Feeds a :class:`Mapper` from time-stamped streams, as mapping_node and ``semfeat-map`` do.

Tracks arrive once per frame; wheel odometry and GNSS arrive at their own rates. The session
interpolates the odometry pose at each frame's stamp and hands the mapper the motion since the
previous frame with a distance-proportional covariance, converts GNSS fixes to east-north-up
metres around the first fix (the datum) and attaches the fix nearest in time to the frame.
"""
from __future__ import annotations

from bisect import bisect_left
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from semfeat_ros.geodesy import geodetic_to_enu
from semfeat_ros.mapping.errors import MapperInputError
from semfeat_ros.mapping.mapper import Mapper
from semfeat_ros.mapping.types import GnssFix, MapperResult, OdometryDelta, Tracks


@dataclass(frozen=True)
class SessionConfig:
    """How odometry and GNSS streams are turned into mapper inputs."""

    odom_sigma_per_m: float = 0.02  # translation noise of wheel odometry (m per m travelled)
    odom_sigma_rad_per_rad: float = 0.02  # rotation noise (rad per rad turned)
    odom_sigma_rad_per_m: float = 0.002  # rotation noise from slip (rad per m travelled)
    odom_sigma_tilt_rad_per_m: float = 0.02  # roll and pitch (rad per m travelled): planar wheel
    #   odometry does not measure them, and a ramp's start or end changes the pitch by 6-10 deg
    #   over a few metres; with the yaw's 0.002 rad/m the odometry held the long drive's ramp
    #   17 % too shallow
    odom_sigma_floor: float = 1e-3  # smallest standard deviation (m or rad)
    odom_max_gap_s: float = 0.25  # interpolate only between samples at most this far apart (s)
    odom_buffer_s: float = 10.0  # odometry history kept (s)
    gnss_max_dt_s: float = 0.15  # a fix is attached to a frame within this time (s)


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a 3x3 rotation."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(c)
    if angle < 1e-9:
        return np.zeros(3)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.pi - angle < 1e-6:  # 180 degrees: axis from the symmetric part
        w, v = np.linalg.eigh((R + np.eye(3)) / 2.0)
        return v[:, np.argmax(w)] * angle
    return axis / (2.0 * np.sin(angle)) * angle


def _expmap(w: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(w)
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """Pose a fraction ``a`` in [0, 1] of the way from ``T0`` to ``T1`` (4x4)."""
    T = np.eye(4)
    T[:3, :3] = T0[:3, :3] @ _expmap(a * _rotvec(T0[:3, :3].T @ T1[:3, :3]))
    T[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
    return T


class MappingSession:
    """One mapper plus the odometry and GNSS buffers that feed it."""

    def __init__(self, camera: Any, T_base_cam: np.ndarray, mapper_conf: dict | None = None,
                 conf: SessionConfig | None = None):
        self.mapper = Mapper(camera, T_base_cam, mapper_conf)
        self.conf = conf or SessionConfig()
        self._odom: deque[tuple[int, np.ndarray]] = deque()
        self._last_odom_pose: np.ndarray | None = None
        self._fix: GnssFix | None = None
        self.datum: tuple[float, float, float] | None = None

    def reset(self) -> None:
        """Forget the map and the buffered streams (e.g. time went backwards)."""
        self.mapper.reset()
        self._odom.clear()
        self._last_odom_pose = None
        self._fix = None

    def add_odometry(self, stamp_ns: int, T_odom_base: np.ndarray) -> None:
        """A wheel-odometry pose of base_link in the odometry frame at ``stamp_ns`` (ns)."""
        T = np.asarray(T_odom_base, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise MapperInputError('odometry pose: expected a finite 4x4 transform')
        if self._odom and stamp_ns <= self._odom[-1][0]:
            if stamp_ns < self._odom[-1][0]:
                self._odom.clear()  # time went backwards: start the buffer again
            else:
                return
        self._odom.append((int(stamp_ns), T))
        horizon = stamp_ns - int(self.conf.odom_buffer_s * 1e9)
        while len(self._odom) > 2 and self._odom[0][0] < horizon:
            self._odom.popleft()

    def add_gnss(self, stamp_ns: int, lat_lon_alt: tuple[float, float, float],
                 covariance_enu: np.ndarray | None) -> None:
        """A GNSS fix (deg, deg, m) with its ENU covariance (m^2, None when unknown)."""
        geo = np.asarray(lat_lon_alt, dtype=np.float64)
        if geo.shape != (3,) or not np.isfinite(geo).all():
            raise MapperInputError(f'gnss fix: expected finite (lat, lon, alt), got {geo}')
        if self.datum is None:
            self.datum = (float(geo[0]), float(geo[1]), float(geo[2]))
        enu = geodetic_to_enu(geo[None], self.datum)[0]
        cov = None if covariance_enu is None else np.asarray(covariance_enu, dtype=np.float64)
        self._fix = GnssFix(int(stamp_ns), enu, cov)

    def odometry_at(self, stamp_ns: int) -> np.ndarray | None:
        """Odometry pose interpolated at ``stamp_ns``, or None without bracketing samples."""
        if len(self._odom) < 2:
            return None
        stamps = [s for s, _ in self._odom]
        i = bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self._odom[i][1]
        if i == 0 or i == len(stamps):
            return None
        (s0, T0), (s1, T1) = self._odom[i - 1], self._odom[i]
        if (s1 - s0) * 1e-9 > self.conf.odom_max_gap_s:
            return None
        return interpolate_pose(T0, T1, (stamp_ns - s0) / (s1 - s0))

    def _delta(self, T_now: np.ndarray | None) -> OdometryDelta | None:
        prev, self._last_odom_pose = self._last_odom_pose, T_now
        if prev is None or T_now is None:
            return None
        T = np.linalg.inv(prev) @ T_now
        c = self.conf
        dist = float(np.linalg.norm(T[:3, 3]))
        angle = float(np.linalg.norm(_rotvec(T[:3, :3])))
        s_rot = max(c.odom_sigma_floor, c.odom_sigma_rad_per_rad * angle
                    + c.odom_sigma_rad_per_m * dist)
        s_trans = max(c.odom_sigma_floor, c.odom_sigma_per_m * dist)
        s_tilt = max(s_rot, c.odom_sigma_tilt_rad_per_m * dist)
        # GTSAM order: rotation (roll, pitch, yaw of base_link), translation
        cov = np.diag([s_tilt**2, s_tilt**2, s_rot**2] + [s_trans**2] * 3)
        return OdometryDelta(T, cov)

    def process(self, tracks: Tracks) -> MapperResult:
        """Run the mapper on one frame's tracks with the odometry and GNSS around its stamp."""
        odometry = self._delta(self.odometry_at(tracks.stamp_ns))
        fix = None
        if (self._fix is not None
                and abs(self._fix.stamp_ns - tracks.stamp_ns) * 1e-9 <= self.conf.gnss_max_dt_s):
            fix, self._fix = self._fix, None
        return self.mapper.update(tracks, odometry=odometry, gnss=fix)
