"""The ego vehicle's drive through the garage: path, speed profile with stops, 6-DoF poses.

The route starts on the open deck, loops through both aisles, takes the ramp down to the covered
level and loops there (about 350 m with the default config). The path is a keep-right lane
offset of the aisles' centrelines with rounded corners, smoothed for continuous curvature. The
speed respects a lateral-acceleration limit in curves, cruise speeds per zone (deck, ramp,
covered level) and acceleration/deceleration limits; the car stops before the ramp and at an
intersection. Height follows the floor (ramp profile); pitch comes from the axle heights plus
braking dive, roll from the lateral acceleration.

``base_link`` is the rear-axle centre at road height (x forward, y left, z up).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.rotations import rpy_to_matrix
from semfeat_ros.sim.errors import SimConfigError
from semfeat_ros.sim.geometry import make_transform
from semfeat_ros.sim.layout import LANE, Layout
from semfeat_ros.sim.polyline import Polyline, offset, round_corners, smooth

WHEELBASE = 2.8  # m
STEP = 0.05  # m, arc-length resolution of the profile


@dataclass(frozen=True)
class DriveLimits:
    """Speed limits (m/s) and acceleration limits (m/s^2) of the drive."""

    deck_speed: float = 6.5
    covered_speed: float = 5.0
    ramp_speed: float = 3.5
    min_speed: float = 2.0
    lateral_accel: float = 2.2
    accel: float = 1.2
    decel: float = 1.8
    stop_time: float = 1.5


def route_corners(lay: Layout) -> tuple[np.ndarray, int]:
    """Centreline corners of the long drive and the index of the corner where the ramp lane
    starts (the car is on the deck before it, on the covered level after the ramp)."""
    a1, a2 = lay.aisles
    xw, xe, yr = lay.x_west, lay.x_east, lay.ramp_yc
    pts = [(lay.x_rows0 + 4.0, a1), (xe, a1), (xe, a2), (xw, a2), (xw, yr), (xe, yr),
           (xe, a1), (xw, a1), (xw, a2), (lay.x_rows1 - 6.0, a2)]
    return np.array(pts, np.float64), 4


@dataclass
class PoseSample:
    """Vehicle state at one time."""

    T_map_base: np.ndarray  # (4, 4)
    speed: float  # m/s along the path
    yaw_rate: float  # rad/s
    accel: float  # m/s^2 along the path
    level: int  # 1 deck, 0 covered (the ramp counts as the level it leads from)
    s: float  # arc length (m)


class Trajectory:
    """Time-parameterised drive along the route (see module docstring)."""

    def __init__(self, layout: Layout, limits: DriveLimits | None = None) -> None:
        self.layout = layout
        self.limits = lim = limits or DriveLimits()
        corners, ramp_corner = route_corners(layout)
        dense = round_corners(corners, 6.0, 0.1)
        lane = offset(dense, LANE)
        xy = smooth(lane, 1.2, STEP)
        self.path = Polyline(xy)
        s = self.path.s
        x, y = self.path.xy[:, 0], self.path.xy[:, 1]
        # level: deck until the path reaches the ramp's lower end
        in_ramp = layout.in_trench(x, y)
        if not in_ramp.any():
            raise SimConfigError('the route does not pass the ramp')
        ramp_idx = np.flatnonzero(in_ramp)
        self.s_ramp = (float(s[ramp_idx[0]]), float(s[ramp_idx[-1]]))
        self.level = np.where(s < self.s_ramp[0], 1, 0)
        self.z = layout.ground_height(x, y, self.level)
        # curvature
        h = self.path.heading
        kappa = np.gradient(h, s)
        self.kappa = kappa
        # speed limits per point
        vmax = np.where(self.level == 1, lim.deck_speed, lim.covered_speed)
        near_ramp = (s > self.s_ramp[0] - 6.0) & (s < self.s_ramp[1] + 4.0)
        vmax = np.where(near_ramp, lim.ramp_speed, vmax)
        vmax = np.minimum(vmax, np.sqrt(lim.lateral_accel / np.maximum(np.abs(kappa), 1e-6)))
        vmax = np.maximum(vmax, lim.min_speed)
        # stops: before the ramp and at the covered level's aisle-2 crossing of the east aisle
        stops = [self.s_ramp[0] - 4.0]
        xe, a2 = layout.x_east, layout.aisles[1]
        cov = np.flatnonzero((self.level == 0) & (np.hypot(x - xe, y - a2) < 4.0))
        if len(cov):
            stops.append(float(s[cov[0]]))
        stops_idx = [int(np.searchsorted(s, st)) for st in stops]
        vmax[0] = 0.0
        vmax[-1] = 0.0
        for i in stops_idx:
            vmax[i] = 0.0
        # forward / backward passes with the acceleration limits
        v = vmax.copy()
        ds = np.diff(s)
        for i in range(1, len(v)):
            v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * lim.accel * ds[i - 1]))
        for i in range(len(v) - 2, -1, -1):
            v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * lim.decel * ds[i]))
        self.v = v
        vm = 0.5 * (v[1:] + v[:-1])
        dt = ds / np.maximum(vm, 1e-3)
        t = np.concatenate([[0.0], np.cumsum(dt)])
        # dwell at the stops: the time after each stop point shifts by stop_time
        for i in sorted(stops_idx, reverse=True):
            t[i + 1:] += lim.stop_time
        # table (time -> arc length) with the dwell intervals
        ts, ss = [t[0]], [s[0]]
        stop_set = set(stops_idx)
        for i in range(1, len(t)):
            if i - 1 in stop_set:
                ts.append(t[i - 1] + lim.stop_time)
                ss.append(s[i - 1])
            ts.append(t[i])
            ss.append(s[i])
        self.t_table = np.array(ts)
        self.s_table = np.array(ss)
        self.duration = float(self.t_table[-1])
        self.length = self.path.length
        acc = np.gradient(v ** 2 / 2.0, s)
        self.a = acc

    def s_at(self, t: float) -> float:
        """Arc length (m) at time ``t`` (s), clamped to the drive."""
        return float(np.interp(t, self.t_table, self.s_table))

    def time_at(self, s: float) -> float:
        """First time (s) at which the car reaches arc length ``s`` (m)."""
        k = int(np.searchsorted(self.s_table, s))
        return float(self.t_table[min(k, len(self.t_table) - 1)])

    def _height(self, s: np.ndarray) -> np.ndarray:
        return np.interp(s, self.path.s, self.z)

    def sample(self, t: float) -> PoseSample:
        """Vehicle pose and motion at time ``t`` (s)."""
        s = self.s_at(t)
        moving = not (np.interp(t + 1e-3, self.t_table, self.s_table) == s
                      and np.interp(t - 1e-3, self.t_table, self.s_table) == s)
        xy, yaw = self.path.at(s)
        v = float(np.interp(s, self.path.s, self.v)) if moving else 0.0
        kappa = float(np.interp(s, self.path.s, self.kappa))
        a = float(np.interp(s, self.path.s, self.a)) if moving else 0.0
        z_r = float(self._height(np.array([s]))[0])
        front = min(s + WHEELBASE, self.length)
        z_f = float(self._height(np.array([front]))[0])
        if front - s < WHEELBASE:  # at the very end: extrapolate with the last grade
            z_f = z_r
        pitch = -np.arctan2(z_f - z_r, WHEELBASE) - 0.004 * a
        roll = 0.005 * v * v * kappa
        R = rpy_to_matrix(roll, pitch, float(yaw[0]))
        T = make_transform(R, np.array([xy[0, 0], xy[0, 1], z_r]))
        level = int(np.interp(s, self.path.s, self.level) > 0.5)
        return PoseSample(T_map_base=T, speed=v, yaw_rate=v * kappa, accel=a, level=level, s=s)
