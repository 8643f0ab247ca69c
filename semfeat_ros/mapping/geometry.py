"""Numpy geometry of the mapping core: SE(3) in GTSAM's conventions, bearings, two-view geometry.

Conventions
-----------
* Poses are 4x4 homogeneous matrices ``T_a_b`` mapping points in frame ``b`` to frame ``a`` (m).
* Tangent vectors are ``xi = (omega, v)`` (rad, m): rotation first, as ``gtsam.Pose3``, with the
  right perturbation ``T exp(xi)``; covariances of poses use the same order.
* Bearings are unit vectors (any direction, including beyond 90 degrees off the optical axis).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.matching.geometry import epipolar_sines
from semfeat_ros.rotations import rpy_to_matrix, skew, so3_exp, so3_log

_EPS = 1e-12


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    K = skew(w)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K
    return (np.eye(3) + (1 - np.cos(theta)) / theta**2 * K
            + (theta - np.sin(theta)) / theta**3 * K @ K)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 pose of the tangent vector ``xi = (omega, v)`` (gtsam.Pose3.Expmap)."""
    xi = np.asarray(xi, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[:3])
    T[:3, 3] = _left_jacobian(xi[:3]) @ xi[3:]
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Tangent vector ``(omega, v)`` of a 4x4 pose (gtsam.Pose3.Logmap)."""
    w = so3_log(T[:3, :3])
    v = np.linalg.solve(_left_jacobian(w), T[:3, 3])
    return np.concatenate([w, v])


def se3_inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a pose for ``(omega, v)`` tangents: ``T exp(xi) = exp(Ad xi) T``."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


def transform_covariance(cov: np.ndarray, T_a_b: np.ndarray) -> np.ndarray:
    """Covariance of pose ``P T_a_b`` (right perturbation) given the covariance ``cov`` of ``P``.

    ``P exp(xi) T_a_b = P T_a_b exp(Ad(T_b_a) xi)``: the result is ``Ad cov Ad^T``.
    """
    A = adjoint(se3_inv(T_a_b))
    return A @ cov @ A.T


def yaw_of(R: np.ndarray) -> float:
    """Heading (rad) of the x axis of ``R`` projected on the horizontal plane."""
    return float(np.arctan2(R[1, 0], R[0, 0]))


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (broadcasting); faster than ``np.cross`` on small rows."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, _EPS)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between rows of ``a`` and ``b``, accurate for small and obtuse angles."""
    c = np.linalg.norm(cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.arctan2(c, dot)


def tangent_basis(b: np.ndarray) -> np.ndarray:
    """(N, 3, 2) orthonormal bases of the tangent planes of unit vectors ``b`` (N, 3)."""
    b = np.asarray(b, dtype=np.float64)
    helper = np.where(np.abs(b[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = unit(cross(b, helper))
    e2 = cross(b, e1)
    return np.stack([e1, e2], axis=2)


# ------------------------------------------------------------------------------------------------
# Triangulation
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Triangulation:
    """Result of :func:`triangulate_bearings` for ``T`` points from ``M`` observations."""

    points: np.ndarray  # (T, 3) m
    ok: np.ndarray  # (T,) bool: well conditioned and finite
    depth: np.ndarray  # (M,) m along each observation ray (negative: behind the camera)
    error: np.ndarray  # (M,) rad angle between each ray and the direction to its point
    max_parallax: np.ndarray  # (T,) rad largest angle between two rays of a point


def triangulate_bearings(index: np.ndarray, centers: np.ndarray, rays: np.ndarray,
                         n_points: int, min_parallax: float = 0.0) -> Triangulation:
    """Least-squares intersection of world-frame rays, batched over points.

    ``index`` (M,) gives the point of each observation, ``centers`` (M, 3) the camera centres (m)
    and ``rays`` (M, 3) the unit bearings rotated into the world frame. A point is ``ok`` when it
    has >= 2 rays, its normal matrix is well conditioned and its largest ray angle is at least
    ``min_parallax`` (rad).
    """
    index = np.asarray(index, dtype=np.int64)
    rays = unit(np.asarray(rays, dtype=np.float64))
    centers = np.asarray(centers, dtype=np.float64)
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    A = np.zeros((n_points, 3, 3))
    b = np.zeros((n_points, 3))
    np.add.at(A, index, P)
    np.add.at(b, index, np.einsum('mij,mj->mi', P, centers))
    count = np.bincount(index, minlength=n_points)
    eig_min = np.linalg.eigvalsh(A)[:, 0] if n_points else np.zeros(0)
    A_reg = A + np.eye(3)[None] * 1e-12
    pts = np.linalg.solve(A_reg, b[:, :, None])[:, :, 0] if n_points else np.zeros((0, 3))
    # Largest pairwise parallax: angle of each ray to the mean ray direction, doubled bound.
    mean_ray = np.zeros((n_points, 3))
    np.add.at(mean_ray, index, rays)
    mean_ray = unit(mean_ray)
    ang = angle_between(rays, mean_ray[index])
    max_par = np.zeros(n_points)
    np.maximum.at(max_par, index, ang)
    max_par = np.minimum(2.0 * max_par, np.pi)
    diff = pts[index] - centers
    depth = np.sum(diff * rays, axis=1)
    err = angle_between(rays, diff)
    ok = ((count >= 2) & (eig_min > 1e-8 * np.maximum(count, 1)) & np.isfinite(pts).all(axis=1)
          & (max_par >= min_parallax))
    return Triangulation(pts, ok, depth, err, max_par)


# ------------------------------------------------------------------------------------------------
# Pose from bearings to known points
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseEstimate:
    """Result of :func:`refine_pose_bearings`."""

    T_w_c: np.ndarray  # (4, 4) camera pose in the world (m)
    inliers: np.ndarray  # (N,) bool
    covariance: np.ndarray | None  # (6, 6) (omega, v) right-perturbation covariance
    error: np.ndarray  # (N,) rad angle between measured and predicted bearings


def refine_pose_bearings(T_w_c: np.ndarray, points_w: np.ndarray, bearings: np.ndarray,
                         sigma: float, *, huber_k: float = 1.345, chi2: float = 9.21,
                         iterations: int = 10) -> PoseEstimate:
    """Robust Gauss-Newton on the camera pose from unit bearings (N, 3) to world points (N, 3).

    The residual is the predicted bearing in the tangent plane of the measured one (rad), valid
    on the whole sphere; ``sigma`` is its standard deviation (rad). Inliers have a whitened
    squared error below ``chi2`` and lie in the same hemisphere as their measurement.
    """
    T = np.array(T_w_c, dtype=np.float64)
    P = np.asarray(points_w, dtype=np.float64)
    b = unit(np.asarray(bearings, dtype=np.float64))
    B = tangent_basis(b)
    n = len(P)
    if n == 0:
        return PoseEstimate(T, np.zeros(0, bool), None, np.zeros(0))
    info = None
    gated = False  # second phase: gross outliers get zero weight
    for _ in range(iterations):
        R, t = T[:3, :3], T[:3, 3]
        p = (P - t) @ R
        r = np.maximum(np.linalg.norm(p, axis=1), _EPS)
        d = p / r[:, None]
        e = np.einsum('nik,ni->nk', B, d)
        front = np.sum(d * b, axis=1) > 0
        rn = np.linalg.norm(e, axis=1) / sigma
        w = np.where(rn <= huber_k, 1.0, huber_k / np.maximum(rn, _EPS)) * front
        if gated:
            w = w * (rn * rn < chi2)
        # d e / d p = B^T (I - d d^T) / r; d p / d(omega, v) = [[p]x, -I]
        U = (B.transpose(0, 2, 1) - e[:, :, None] * d[:, None, :]) / r[:, None, None]
        J = np.concatenate([cross(U, p[:, None, :]), -U], axis=2).reshape(-1, 6)
        w2 = np.repeat(w, 2)
        H = (J * w2[:, None]).T @ J
        g = (J * w2[:, None]).T @ e.reshape(-1)
        info = H / sigma**2
        try:
            delta = -np.linalg.solve(H + np.eye(6) * 1e-9, g)
        except np.linalg.LinAlgError:
            break
        T = T @ se3_exp(delta)
        if np.linalg.norm(delta) < 1e-8:
            if gated:
                break
            gated = True
    R, t = T[:3, :3], T[:3, 3]
    d = unit((P - t) @ R)
    err = angle_between(d, b)
    e = np.einsum('nik,ni->nk', B, d)
    inl = (np.sum(e * e, axis=1) / sigma**2 < chi2) & (np.sum(d * b, axis=1) > 0)
    cov = None
    if info is not None and np.isfinite(info).all():
        try:
            cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            cov = None
    return PoseEstimate(T, inl, cov, err)


# ------------------------------------------------------------------------------------------------
# Two-view geometry on bearings
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RelativePose:
    """Two-view result: ``x2 = R x1 + t`` (unit ``t``) and the inlier correspondences."""

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray  # (N,) bool: epipolar inlier with positive depth in both views
    points: np.ndarray  # (N, 3) triangulated in view 1 for a unit baseline (NaN if not ok)


def _cheirality(R: np.ndarray, t: np.ndarray, b1: np.ndarray, b2: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    n = len(b1)
    centers = np.concatenate([np.zeros((n, 3)), np.tile(-R.T @ t, (n, 1))])
    rays = np.concatenate([b1, b2 @ R])
    idx = np.concatenate([np.arange(n), np.arange(n)])
    tri = triangulate_bearings(idx, centers, rays, n)
    good = tri.ok & (tri.depth[:n] > 0) & (tri.depth[n:] > 0)
    pts = np.where(good[:, None], tri.points, np.nan)
    return good, pts


def relative_pose_known_motion(R: np.ndarray, t: np.ndarray, b1: np.ndarray, b2: np.ndarray,
                               threshold: float) -> RelativePose:
    """Two-view inliers and points for a motion known from elsewhere (wheel odometry).

    ``x2 = R x1 + t`` with ``t`` of any non-zero length (normalised here); a correspondence is
    an inlier when its epipolar error under ``E = [t]x R`` is below ``threshold`` (rad) and it
    triangulates in front of both views. Points are for a unit baseline (metres once multiplied
    by the baseline length). The motion itself comes from
    :func:`semfeat_ros.matching.geometry.verify_bearings` (5-point RANSAC) or odometry.
    """
    t = np.asarray(t, dtype=np.float64)
    norm = float(np.linalg.norm(t))
    if not norm > 0:
        raise ValueError('relative_pose_known_motion: the translation must not be zero')
    t = t / norm
    b1 = unit(np.asarray(b1, dtype=np.float64))
    b2 = unit(np.asarray(b2, dtype=np.float64))
    epi = epipolar_sines(skew(t) @ R, b1, b2) < threshold  # sine ~ angle at these sizes
    good, pts = _cheirality(R, t, b1, b2)
    return RelativePose(np.asarray(R, dtype=np.float64), t, epi & good, pts)


def vehicle_camera_translation(R: np.ndarray, T_base_cam: np.ndarray, distance: float
                               ) -> np.ndarray:
    """Camera translation of a vehicle whose base moved ``distance`` (m, straight line) along
    a circular arc.

    The base (rear axle) moves along the chord of the arc: its x axis turned by half the
    relative rotation. The camera sits at a lever arm from it (``T_base_cam``, (4, 4)), so that
    a turn or a ramp's change of pitch also moves it sideways or up. ``R`` (3, 3) is the
    camera's relative rotation in the two-view convention ``x_b = R x_a + t``; returns that
    ``t`` (3,) (m, camera b frame).
    """
    R_bc, p_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
    R_ab = R_bc @ R.T @ R_bc.T  # the base's rotation from a to b, in base a axes
    half = so3_exp(0.5 * so3_log(R_ab))
    p_ab = distance * half[:, 0]  # base b's origin in base a
    t_ab_cam = R_bc.T @ (R_ab @ p_bc + p_ab - p_bc)  # camera b's centre in camera a
    return -R @ t_ab_cam


# ------------------------------------------------------------------------------------------------
# Planes and alignment
# ------------------------------------------------------------------------------------------------


def fit_plane_ransac(points: np.ndarray, threshold: float, rng: np.random.Generator, *,
                     iterations: int = 200) -> tuple[np.ndarray, float, np.ndarray] | None:
    """Plane ``n . x = d`` (unit ``n``) through points (N, 3) by RANSAC + least squares.

    Returns ``(n, d, inliers)`` or ``None`` with fewer than 3 points or no plane.
    """
    P = np.asarray(points, dtype=np.float64)
    n = len(P)
    if n < 3:
        return None
    best = np.zeros(n, bool)
    for _ in range(iterations):
        a, b, c = P[rng.choice(n, 3, replace=False)]
        normal = cross(b - a, c - a)
        norm = np.linalg.norm(normal)
        if norm < _EPS:
            continue
        normal /= norm
        inl = np.abs(P @ normal - normal @ a) < threshold
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < 3:
        return None
    for _ in range(2):
        Q = P[best]
        c = Q.mean(axis=0)
        _, _, Vt = np.linalg.svd(Q - c)
        normal = Vt[-1]
        d = float(normal @ c)
        new = np.abs(P @ normal - d) < threshold
        if new.sum() < 3:
            break
        best = new
    return normal, d, best


def align_yaw(src: np.ndarray, dst: np.ndarray, with_scale: bool
              ) -> tuple[float, np.ndarray, np.ndarray]:
    """4-DoF (+ optional scale) alignment ``dst ~ s Rz src + t`` of point sets (N, 3), z kept up.

    Returns ``(s, R (3, 3) rotation about z, t (3,))``.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    # Rotation about z maximising sum b . (R a).
    sxx = np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    sxy = np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    yaw = np.arctan2(sxy, sxx)
    R = rpy_to_matrix(0.0, 0.0, yaw)
    ra = a @ R.T
    s = float(np.sum(b * ra) / max(np.sum(a * a), _EPS)) if with_scale else 1.0
    t = md - s * R @ ms
    return s, R, t
