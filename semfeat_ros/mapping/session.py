"""Feeds a :class:`Mapper` from time-stamped streams, as mapping_node and ``semfeat-map`` do.

Tracks arrive once per frame; wheel odometry and GNSS arrive at their own rates. The session
interpolates the odometry pose at each frame's stamp and hands the mapper the motion since the
previous frame with a distance-proportional covariance, converts GNSS fixes to east-north-up
metres around the first fix (the datum) and attaches to each frame the newest fix stamped at or
before it (within ``gnss_max_dt_s``). Fixes are buffered by stamp, so the result does not depend
on how late the frame arrives: live, tracks reach the mapper 0.1-0.5 s after their stamp, when
newer fixes are already in (a session that kept only the newest fix attached it to the wrong
frame, 0.1 s and 0.3 m off on the demo bag, or to none).
"""
from __future__ import annotations

from bisect import bisect_left
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from semfeat_ros.geodesy import geodetic_to_enu
from semfeat_ros.mapping.errors import MapperInputError, MappingError
from semfeat_ros.mapping.mapper import Mapper
from semfeat_ros.mapping.types import GnssFix, MapperResult, OdometryDelta, Tracks
from semfeat_ros.rotations import rotation_angle, so3_exp, so3_log


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
    gnss_max_dt_s: float = 0.15  # a fix is attached to a frame at most this much later (s)
    gnss_buffer: int = 50  # fixes kept for frames still to come (the newest)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """Pose a fraction ``a`` in [0, 1] of the way from ``T0`` to ``T1`` (4x4)."""
    T = np.eye(4)
    T[:3, :3] = T0[:3, :3] @ so3_exp(a * so3_log(T0[:3, :3].T @ T1[:3, :3]))
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
        self._fixes: deque[GnssFix] = deque()  # by stamp, not yet attached
        self.datum: tuple[float, float, float] | None = None
        # frames that found no odometry around their stamp, by reason: 'ahead' (the frame is
        # newer than the newest odometry sample: it arrived late), 'gap' (the bracketing
        # samples are more than odom_max_gap_s apart: samples were lost), 'behind' (older than
        # the buffer)
        self.odometry_missing: dict[str, int] = {'ahead': 0, 'gap': 0, 'behind': 0}

    def reset(self) -> None:
        """Forget the map and the buffered streams (e.g. time went backwards)."""
        self.mapper.reset()
        self._odom.clear()
        self._last_odom_pose = None
        self._fixes.clear()

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
        if self._fixes and stamp_ns <= self._fixes[-1].stamp_ns:
            if stamp_ns == self._fixes[-1].stamp_ns:
                return
            self._fixes.clear()  # time went backwards: start the buffer again
        self._fixes.append(GnssFix(int(stamp_ns), enu, cov))
        while len(self._fixes) > self.conf.gnss_buffer:
            self._fixes.popleft()

    def _take_fix(self, stamp_ns: int) -> GnssFix | None:
        """The newest buffered fix stamped at or before ``stamp_ns`` and at most
        ``gnss_max_dt_s`` older; it and every older fix leave the buffer, newer ones stay."""
        fix = None
        while self._fixes and self._fixes[0].stamp_ns <= stamp_ns:
            fix = self._fixes.popleft()
        if fix is None or (stamp_ns - fix.stamp_ns) * 1e-9 > self.conf.gnss_max_dt_s:
            return None
        return fix

    def odometry_at(self, stamp_ns: int) -> np.ndarray | None:
        """Odometry pose interpolated at ``stamp_ns``, or None without bracketing samples."""
        pose, _ = self._odometry_at(stamp_ns)
        return pose

    def _odometry_at(self, stamp_ns: int) -> tuple[np.ndarray | None, str | None]:
        """``(pose, None)``, or ``(None, reason)`` with a key of :attr:`odometry_missing`
        (reason None: no odometry stream yet)."""
        if len(self._odom) < 2:
            return None, None
        stamps = [s for s, _ in self._odom]
        i = bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self._odom[i][1], None
        if i == 0 or i == len(stamps):
            return None, 'behind' if i == 0 else 'ahead'
        (s0, T0), (s1, T1) = self._odom[i - 1], self._odom[i]
        if (s1 - s0) * 1e-9 > self.conf.odom_max_gap_s:
            return None, 'gap'
        return interpolate_pose(T0, T1, (stamp_ns - s0) / (s1 - s0)), None

    def _delta(self, T_now: np.ndarray | None) -> OdometryDelta | None:
        prev, self._last_odom_pose = self._last_odom_pose, T_now
        if prev is None or T_now is None:
            return None
        T = np.linalg.inv(prev) @ T_now
        c = self.conf
        dist = float(np.linalg.norm(T[:3, 3]))
        angle = rotation_angle(T[:3, :3])
        s_rot = max(c.odom_sigma_floor, c.odom_sigma_rad_per_rad * angle
                    + c.odom_sigma_rad_per_m * dist)
        s_trans = max(c.odom_sigma_floor, c.odom_sigma_per_m * dist)
        s_tilt = max(s_rot, c.odom_sigma_tilt_rad_per_m * dist)
        # GTSAM order: rotation (roll, pitch, yaw of base_link), translation
        cov = np.diag([s_tilt**2, s_tilt**2, s_rot**2] + [s_trans**2] * 3)
        return OdometryDelta(T, cov)

    def process(self, tracks: Tracks) -> MapperResult:
        """Run the mapper on one frame's tracks with the odometry and GNSS around its stamp."""
        pose, missing = self._odometry_at(tracks.stamp_ns)
        if missing is not None:
            self.odometry_missing[missing] += 1
        odometry = self._delta(pose)
        return self.mapper.update(tracks, odometry=odometry, gnss=self._take_fix(tracks.stamp_ns))


@dataclass
class FedFrame:
    """A frame :class:`FrameFeeder` handed to the session: its result, or the error that
    rejected it (``result`` None)."""

    tracks: Tracks
    tag: Any
    result: MapperResult | None
    error: MappingError | None


class FrameFeeder:
    """Hands frames to a :class:`MappingSession` once the odometry around their stamp is in.

    Frames and odometry arrive on separate streams; a frame that reaches the session before the
    odometry sample after its stamp has no motion to go with it, and the mapper then loses its
    keyframe chain (live on 2 busy cores that happened about twice a run, and the map fell
    apart). So a frame waits until odometry at or after its stamp has
    arrived, or until ``wait_s`` of stream time has passed (``now_ns`` of :meth:`release`: the
    newest stamp or bag time seen), so a stalled odometry stream delays frames by a bounded
    time. Without odometry (``expect_odometry`` False until the first sample arrives) frames
    pass at once. mapping_node and ``semfeat-map`` both feed their sessions through it, so live
    and offline runs hand the mapper the same inputs.
    """

    def __init__(self, session: MappingSession, wait_s: float,
                 expect_odometry: bool = False) -> None:
        self.session = session
        self.wait_ns = int(wait_s * 1e9)
        self.expect_odometry = expect_odometry
        self.last_odom = -1
        self.pending: deque[tuple[Tracks, Any]] = deque()
        self.rejected = 0

    def add_odometry(self, stamp_ns: int, T: np.ndarray) -> None:
        """An odometry pose (see :meth:`MappingSession.add_odometry`)."""
        self.session.add_odometry(stamp_ns, T)
        # the newest sample, not the largest stamp: when a bag loops the odometry restarts
        # earlier, and the new loop's frames must wait for it again
        self.last_odom = int(stamp_ns)
        self.expect_odometry = True

    def add_fix(self, stamp_ns: int, geo: tuple[float, float, float],
                cov: np.ndarray | None) -> None:
        """A GNSS fix (see :meth:`MappingSession.add_gnss`; it is attached by stamp)."""
        self.session.add_gnss(stamp_ns, geo, cov)

    def push(self, tracks: Tracks, tag: Any = None) -> None:
        """Queue a frame (stamps in increasing order); ``tag`` comes back with its result."""
        self.pending.append((tracks, tag))

    def reset(self) -> None:
        """Drop the queued frames (the session was reset)."""
        self.pending.clear()
        self.last_odom = -1

    def trim(self, max_pending: int) -> int:
        """Drop the oldest queued frames beyond ``max_pending``; returns how many."""
        dropped = 0
        while len(self.pending) > max_pending:
            self.pending.popleft()
            dropped += 1
        return dropped

    def release(self, now_ns: int | None) -> list[FedFrame]:
        """Map the queued frames that are ready (all of them when ``now_ns`` is None)."""
        out = []
        while self.pending:
            tracks, tag = self.pending[0]
            if (now_ns is not None and self.expect_odometry and self.last_odom < tracks.stamp_ns
                    and now_ns - tracks.stamp_ns < self.wait_ns):
                break
            self.pending.popleft()
            try:
                out.append(FedFrame(tracks, tag, self.session.process(tracks), None))
            except MappingError as exc:
                self.rejected += 1
                out.append(FedFrame(tracks, tag, None, exc))
        return out
