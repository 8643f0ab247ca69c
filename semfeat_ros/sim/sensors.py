"""GNSS receiver and wheel-odometry models driven by the ground-truth drive.

GNSS (``/gnss/fix``): the antenna sits on the roof, :data:`ANTENNA_OFFSET` m in base_link. Its
quality follows the sky visibility (:meth:`World.openness`) at the antenna:

* open sky (deck): RTK fixed, 1.5 cm horizontal / 3 cm vertical noise, ``STATUS_GBAS_FIX``;
* partial cover (ramp trench): single-point fix with a slowly varying multipath bias plus
  white noise, both growing with the cover, ``STATUS_FIX``; the reported covariance is the
  true error variance (bias + noise);
* under the deck slab: no fix, no message.

Positions are geodetic (WGS-84) around the config's ``geo_origin``: map x east, y north, z up
(a local tangent plane; :func:`enu_to_geodetic` / :func:`geodetic_to_enu` convert).

Wheel odometry (``/vehicle/odom``): planar dead reckoning in frame ``odom`` from wheel speed
and yaw rate with a per-run scale error, yaw-rate scale error and bias, and white noise. It has
no notion of altitude (z = 0) and measures the distance along the ramp, not its horizontal
projection. Its covariance grows with the distance travelled and the time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.geodesy import enu_to_geodetic, geodetic_to_enu  # noqa: F401 (re-exported)
from semfeat_ros.sim.errors import SimConfigError
from semfeat_ros.sim.geometry import transform_points
from semfeat_ros.sim.trajectory import Trajectory
from semfeat_ros.sim.world import World

ANTENNA_OFFSET = np.array([1.2, 0.0, 1.5])
"""GNSS antenna position in base_link (m)."""

STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -1, 0, 1, 2
SERVICE_GPS_GLONASS_GALILEO = 1 | 2 | 8
COVARIANCE_TYPE_DIAGONAL_KNOWN = 2


@dataclass(frozen=True)
class GnssFix:
    """One receiver output (or its absence: ``status == STATUS_NO_FIX``)."""

    time_s: float
    status: int
    lat_lon_alt: np.ndarray  # (3,) deg, deg, m
    covariance_enu: np.ndarray  # (3,) variances east, north, up (m^2)
    error_enu: np.ndarray  # (3,) true error of the reported position (m)


class GnssModel:
    """Deterministic GNSS receiver (see module docstring)."""

    rtk_sigma = (0.015, 0.015, 0.03)

    def __init__(self, world: World, trajectory: Trajectory, seed: int, rate_hz: float = 5.0):
        if not 0.1 <= rate_hz <= 50.0:
            raise SimConfigError(f'gnss rate must be in 0.1..50 Hz, got {rate_hz}')
        self.world = world
        self.trajectory = trajectory
        self.rate = rate_hz
        self.rng = np.random.default_rng([seed, 0x6A55])
        self._bias = np.zeros(3)
        self._last_t: float | None = None

    def antenna(self, t: float) -> np.ndarray:
        """Antenna position (3,) in map at time ``t``."""
        T = self.trajectory.sample(t).T_map_base
        return transform_points(T, ANTENNA_OFFSET[None])[0]

    def sky(self, t: float) -> float:
        """Sky visibility at the antenna, 0..1."""
        return float(self.world.openness(self.antenna(t)[None].astype(np.float32))[0])

    def fix(self, t: float) -> GnssFix:
        """The receiver's output at ``t`` (call with increasing times)."""
        pos = self.antenna(t)
        sky = self.sky(t)
        dt = 1.0 / self.rate if self._last_t is None else max(t - self._last_t, 1e-3)
        self._last_t = t
        origin = self.world.config.geo_origin
        if sky >= 0.97:
            sig = np.array(self.rtk_sigma)
            err = self.rng.normal(0.0, sig)
            self._bias[:] = 0.0
            return GnssFix(t, STATUS_GBAS_FIX, enu_to_geodetic(pos + err, origin)[0], sig ** 2,
                           err)
        if sky >= 0.6:
            cover = (0.97 - sky) / 0.37  # 0 .. 1
            sig_b = np.array([0.3, 0.3, 0.6]) + cover * np.array([2.5, 2.5, 4.0])
            sig_w = 0.5 * sig_b
            # first-order Gauss-Markov bias (time constant 8 s) with stationary std sig_b
            a = np.exp(-dt / 8.0)
            self._bias = a * self._bias + np.sqrt(1.0 - a * a) * self.rng.normal(0.0, sig_b)
            err = self._bias + self.rng.normal(0.0, sig_w)
            var = sig_b ** 2 + sig_w ** 2
            return GnssFix(t, STATUS_FIX, enu_to_geodetic(pos + err, origin)[0], var, err)
        self.rng.normal(0.0, 1.0, 3)  # keep the random stream independent of the outcome
        return GnssFix(t, STATUS_NO_FIX, np.full(3, np.nan), np.full(3, np.nan),
                       np.full(3, np.nan))


@dataclass(frozen=True)
class OdomSample:
    """One wheel-odometry output (frame ``odom``, child ``base_link``)."""

    time_s: float
    x: float
    y: float
    yaw: float
    speed: float  # m/s, measured
    yaw_rate: float  # rad/s, measured
    pose_var: np.ndarray  # (3,) variances of x, y (m^2) and yaw (rad^2)
    twist_var: np.ndarray  # (2,) variances of speed ((m/s)^2) and yaw rate ((rad/s)^2)


class WheelOdometry:
    """Dead reckoning with systematic and random errors (see module docstring)."""

    speed_noise = 0.02  # m/s
    yaw_rate_noise = 0.004  # rad/s

    def __init__(self, trajectory: Trajectory, seed: int, rate_hz: float = 50.0):
        if not 1.0 <= rate_hz <= 500.0:
            raise SimConfigError(f'odometry rate must be in 1..500 Hz, got {rate_hz}')
        rng = np.random.default_rng([seed, 0x0D0])
        self.trajectory = trajectory
        self.rate = rate_hz
        self.rng = rng
        self.scale_error = float(rng.normal(0.0, 0.01))  # wheel radius / tyre pressure
        self.yaw_scale_error = float(rng.normal(0.0, 0.015))  # track width
        self.yaw_bias = float(rng.normal(0.0, 0.0015))  # rad/s
        self._x = self._y = 0.0
        self._yaw = 0.0
        self._t: float | None = None
        self._dist = 0.0

    def step(self, t: float) -> OdomSample:
        """Advance to time ``t`` (s, increasing) and return the odometry output."""
        st = self.trajectory.sample(t)
        moving = st.speed > 1e-3
        v = st.speed * (1.0 + self.scale_error) + (self.rng.normal(0.0, self.speed_noise)
                                                   if moving else 0.0)
        w = (st.yaw_rate * (1.0 + self.yaw_scale_error) + self.yaw_bias
             + self.rng.normal(0.0, self.yaw_rate_noise)) if moving else 0.0
        if self._t is not None:
            dt = t - self._t
            mid = self._yaw + 0.5 * w * dt
            self._x += v * dt * np.cos(mid)
            self._y += v * dt * np.sin(mid)
            self._yaw += w * dt
            self._dist += abs(v) * dt
        self._t = t
        sig_pos = 0.02 + 0.012 * self._dist
        sig_yaw = 0.002 + 0.0017 * t + 0.0005 * self._dist
        return OdomSample(t, self._x, self._y, self._yaw, v, w,
                          np.array([sig_pos ** 2, sig_pos ** 2, sig_yaw ** 2]),
                          np.array([max(self.speed_noise, 0.01 * abs(v)) ** 2,
                                    (self.yaw_rate_noise + 0.015 * abs(w)) ** 2]))
