"""Online calibration of the wheel odometry: yaw-rate bias, yaw scale error, distance scale.

Wheel (or gyro-aided) odometry turns by ``dpsi_odom = (1 + s) dpsi + b dt + noise`` for a true
heading change ``dpsi`` (rad) over a time ``dt`` (s) in motion, and travels
``d_odom = (1 + k) d`` for a true distance ``d`` (m): ``b`` is a yaw-rate bias (rad/s: gyro
bias, unequal tyres), ``s`` a yaw scale error (track width) and ``k`` a distance scale error
(tyre radius). Under a deck slab, without GNSS, the mapper's motion follows the odometry, so
``b`` becomes a steady heading drift (0.1 deg/s is 5 deg over a 50 s level) and ``k`` an
along-track drift (1 % is 1.5 m over 150 m). Where the fused estimate is anchored (GNSS in the
window), its keyframe-to-keyframe motion observes all three: regressions of the residuals
``dpsi_odom - dpsi_est`` on ``(dpsi_est, dt)`` and ``d_odom - d_est`` on ``d_est`` estimate them,
and later odometry is corrected with the estimates.
"""
from __future__ import annotations

import math

import numpy as np

from semfeat_ros.mapping.geometry import yaw_of
from semfeat_ros.mapping.types import OdometryDelta
from semfeat_ros.rotations import rot_z

_CAUCHY_C = 4.0  # width (in noise sigmas) of the Cauchy weight of a sample against the fit


class _Regression:
    """Bayesian linear regression ``y = x . theta + e`` with a zero-mean Gaussian prior on
    ``theta`` (sigmas ``prior``) and the noise sigma of ``e`` estimated from the residuals (never
    below ``sigma_min``). Each sample is Cauchy-weighted against the current fit, so that a
    glitch of the anchoring estimate (a GNSS multipath jump) cannot drag it far."""

    def __init__(self, prior: tuple[float, ...], sigma_min: float) -> None:
        prior_var = np.asarray(prior, dtype=np.float64) ** 2
        self._P = np.diag(1.0 / prior_var)
        n = len(prior)
        self._xx = np.zeros((n, n))
        self._xy = np.zeros(n)
        self._yy = 0.0
        self._n = 0.0
        self._sigma_min = sigma_min
        self._var_min = sigma_min ** 2
        self.var = self._var_min
        self.theta = np.zeros(n)
        self.cov = np.diag(prior_var)

    def add(self, x: np.ndarray, y: float) -> None:
        # Cauchy weight on the residual in units of sigma_min (not of the estimated noise: a
        # burst of outliers would widen its own gate)
        z = (y - float(x @ self.theta)) / (_CAUCHY_C * self._sigma_min)
        w = 1.0 / (1.0 + z * z)
        self._xx += w * np.outer(x, x)
        self._xy += w * y * x
        self._yy += w * y * y
        self._n += w
        rss = self._yy - 2.0 * self.theta @ self._xy + self.theta @ self._xx @ self.theta
        self.var = max(self._var_min, rss / max(self._n - len(x), 1.0))
        A = self._P + self._xx / self.var
        self.cov = np.linalg.inv(A)
        self.theta = self.cov @ self._xy / self.var


class OdometryCalibration:
    """Online regressions of the odometry's errors; see the module docstring.

    ``sigma_rad``, ``sigma_m``: smallest noise of one keyframe pair's heading residual (rad) and
    distance residual (m) (the noise is estimated from the residuals above that);
    ``prior_bias`` (rad/s), ``prior_scale``: prior sigmas of ``b`` and of ``s`` and ``k`` (the
    estimates are posterior means: what a drive does not observe, e.g. ``s`` without turns,
    stays near 0); ``min_pairs``: pairs needed before :meth:`correct` changes anything.
    """

    def __init__(self, sigma_rad: float, sigma_m: float, prior_bias: float,
                 prior_scale: float, min_pairs: int) -> None:
        if not (sigma_rad > 0 and sigma_m > 0 and prior_bias > 0 and prior_scale > 0
                and min_pairs >= 1):
            raise ValueError('OdometryCalibration: sigmas must be > 0 and min_pairs >= 1')
        self._yaw = _Regression((prior_scale, prior_bias), sigma_rad)
        self._dist = _Regression((prior_scale,), sigma_m)
        self._min_pairs = int(min_pairs)
        self.n_pairs = 0
        self._x = np.zeros(3)  # s, b, k as applied

    @property
    def ready(self) -> bool:
        return self.n_pairs >= self._min_pairs

    @property
    def yaw_scale(self) -> float:
        """Yaw scale error ``s`` as applied (0 until ``min_pairs`` pairs were added)."""
        return float(self._x[0])

    @property
    def yaw_bias(self) -> float:
        """Yaw-rate bias ``b`` as applied (rad/s; 0 until ``min_pairs`` pairs were added)."""
        return float(self._x[1])

    @property
    def distance_scale(self) -> float:
        """Distance scale error ``k`` as applied (0 until ``min_pairs`` pairs were added)."""
        return float(self._x[2])

    def add(self, dpsi_odom: float, dpsi_est: float, dt: float, d_odom: float,
            d_est: float) -> None:
        """One keyframe pair: raw odometry and estimated heading change (rad) over ``dt`` (s,
        in motion) and distance (m)."""
        vals = (dpsi_odom, dpsi_est, dt, d_odom, d_est)
        if not all(math.isfinite(v) for v in vals) or dt < 0 or d_odom < 0 or d_est < 0:
            return
        self._yaw.add(np.array([dpsi_est, dt]), math.remainder(dpsi_odom - dpsi_est, math.tau))
        self._dist.add(np.array([d_est]), d_odom - d_est)
        self.n_pairs += 1
        if self.ready:
            self._x = np.concatenate([self._yaw.theta, self._dist.theta])

    def correct(self, delta: OdometryDelta, dt: float) -> OdometryDelta:
        """``delta`` (base motion over ``dt`` s in motion) corrected: heading change
        ``(dpsi_odom - b dt) / (1 + s)``, translation ``/ (1 + k)`` and turned by half the
        heading correction (it was integrated along the mid-interval heading). The covariance
        is kept."""
        if not self._x.any():
            return delta
        dpsi = yaw_of(delta.T[:3, :3])
        fix = (dpsi - self.yaw_bias * dt) / (1.0 + self.yaw_scale) - dpsi
        T = np.array(delta.T)
        T[:3, :3] = T[:3, :3] @ rot_z(fix)
        T[:3, 3] = rot_z(0.5 * fix) @ T[:3, 3] / (1.0 + self.distance_scale)
        return OdometryDelta(T, delta.covariance)
