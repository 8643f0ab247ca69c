"""GTSAM factors of the mapper (every factor the mapper's parts put in the graph).

Pose variables ``X(k)`` are camera (optical frame) poses in ``map``; landmark variables ``L(j)``
are points in ``map`` (m). Bearing factors (``gtsam.BearingFactor3D``) compare unit bearings on
the whole sphere, so fisheye observations beyond 90 degrees off-axis constrain the graph like
any other.
"""
from __future__ import annotations

import gtsam
import numpy as np


def robust(base: gtsam.noiseModel.Base, kernel: str, k: float) -> gtsam.noiseModel.Base:
    """Wrap a Gaussian noise model in a Huber or Cauchy M-estimator of width ``k`` (sigmas)."""
    est = (gtsam.noiseModel.mEstimator.Huber.Create(k) if kernel == 'huber'
           else gtsam.noiseModel.mEstimator.Cauchy.Create(k))
    return gtsam.noiseModel.Robust.Create(est, base)


def bearing_noise(sigma_rad: float, kernel: str, k: float) -> gtsam.noiseModel.Base:
    """Robust isotropic noise of a 2-D bearing error (rad)."""
    return robust(gtsam.noiseModel.Isotropic.Sigma(2, float(sigma_rad)), kernel, k)


def bearing_factor(x_key: int, l_key: int, bearing: np.ndarray,
                   noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    """Unit bearing (optical frame) of landmark ``l_key`` seen from camera pose ``x_key``."""
    return gtsam.BearingFactor3D(x_key, l_key, gtsam.Unit3(np.asarray(bearing, float)), noise)


def pose_prior(key: int, T: np.ndarray, cov: np.ndarray) -> gtsam.NonlinearFactor:
    """Prior on a pose, ``cov`` (6, 6) in (rot rad, trans m) right-perturbation order."""
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(T), gtsam.noiseModel.Gaussian.Covariance(cov))


def point_prior(key: int, p: np.ndarray, sigma_m: float) -> gtsam.NonlinearFactor:
    """Isotropic prior on a landmark position (m)."""
    return gtsam.PriorFactorPoint3(key, np.asarray(p, float),
                                   gtsam.noiseModel.Isotropic.Sigma(3, float(sigma_m)))


def between(k1: int, k2: int, T_12: np.ndarray, cov: np.ndarray) -> gtsam.NonlinearFactor:
    """Relative pose ``T_12 = T_1^-1 T_2`` with covariance (6, 6) (rot, trans)."""
    return gtsam.BetweenFactorPose3(k1, k2, gtsam.Pose3(T_12),
                                    gtsam.noiseModel.Gaussian.Covariance(cov))


def rotation_between(k1: int, k2: int, T_12: np.ndarray, sigma_rad: float,
                     free_sigma_m: float, kernel: str, k: float) -> gtsam.NonlinearFactor:
    """Relative rotation of pose k2 in pose k1 (two-view geometry of the tracks), as a Pose3
    between factor whose translation part is left free (``free_sigma_m``, m), Huber/Cauchy
    robust. ``T_12`` (4, 4): the measured rotation and any translation (it carries no weight).
    """
    sig = np.array([sigma_rad] * 3 + [free_sigma_m] * 3, dtype=float)
    noise = robust(gtsam.noiseModel.Diagonal.Sigmas(sig), kernel, k)
    return gtsam.BetweenFactorPose3(k1, k2, gtsam.Pose3(np.asarray(T_12, float)), noise)


def level_factor(key: int, up_c: np.ndarray, sigma_rad: float, kernel: str,
                 k: float) -> gtsam.NonlinearFactor:
    """The vehicle stands level: its up axis ``up_c`` (unit, camera optical frame) maps to map
    +z. A 2-D error (rad) on camera pose ``key``: tilt only, yaw and position are free."""
    noise = robust(gtsam.noiseModel.Isotropic.Sigma(2, float(sigma_rad)), kernel, k)
    return gtsam.AttitudeFactorPose3(key, gtsam.Unit3(np.array([0.0, 0.0, 1.0])), noise,
                                     gtsam.Unit3(np.asarray(up_c, float)))


def gnss_factor(key: int, position: np.ndarray, cov: np.ndarray, lever_arm_cam: np.ndarray,
                k: float) -> gtsam.NonlinearFactor:
    """Antenna position (m, map) of camera pose ``key``; the antenna sits at ``lever_arm_cam``
    (m, optical frame). Huber-robust in case a multipath fix slipped through the gate."""
    noise = robust(gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float)), 'huber', k)
    return gtsam.GPSFactorArm(key, np.asarray(position, float),
                              np.asarray(lever_arm_cam, float), noise)


def ground_error(T_w_c: np.ndarray, p_w: np.ndarray, up_c: np.ndarray, height: float
                 ) -> tuple[float, np.ndarray, np.ndarray]:
    """Height error (m) of a ground point above the local ground plane, with Jacobians.

    ``up_c`` is base_link's z axis in the optical frame, ``height`` the camera height (m); the
    error is ``up_c . p_c + height`` with ``p_c`` the point in the camera frame. Returns
    ``(error, d/d pose (1, 6) right perturbation (rot, trans), d/d point (1, 3))``.
    """
    R, t = T_w_c[:3, :3], T_w_c[:3, 3]
    p_c = R.T @ (p_w - t)
    e = float(up_c @ p_c + height)
    # d p_c / d omega = [p_c]_x, d p_c / d v = -I (gtsam.Pose3 retract, first order)
    cross = np.array([[0.0, -p_c[2], p_c[1]], [p_c[2], 0.0, -p_c[0]], [-p_c[1], p_c[0], 0.0]])
    H_pose = np.concatenate([up_c @ cross, -up_c])[None]
    H_point = (up_c @ R.T)[None]
    return e, H_pose, H_point


def ground_factor(x_key: int, l_key: int, up_c: np.ndarray, height: float,
                  noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """Ground landmark ``l_key`` lies ``height`` (m) below camera ``x_key`` along base_link z.

    A local-plane constraint: it gives a camera-only run its metric scale and keeps roll and
    pitch relative to the ground the vehicle stands on (analytic Jacobians).
    """
    up_c = np.asarray(up_c, dtype=np.float64)
    height = float(height)

    def error(this: gtsam.CustomFactor, values: gtsam.Values,
              jacobians: list[np.ndarray] | None) -> np.ndarray:
        keys = this.keys()
        pose = values.atPose3(keys[0])
        if jacobians is None:
            return np.array([up_c @ pose.transformTo(values.atPoint3(keys[1])) + height])
        H_pose = np.zeros((3, 6), order='F')
        H_point = np.zeros((3, 3), order='F')
        p_c = pose.transformTo(values.atPoint3(keys[1]), H_pose, H_point)
        jacobians[0] = (up_c @ H_pose)[None]
        jacobians[1] = (up_c @ H_point)[None]
        return np.array([up_c @ p_c + height])

    return gtsam.CustomFactor(noise, [x_key, l_key], error)
