"""Geometric verification of bearing correspondences on the unit sphere.

Works on unit bearings (from the fisheye model), so rays more than 90 degrees off the optical axis
(``z < 0``) are handled like any other: nothing here divides by ``z``.

Convention: ``b0`` are bearings in the previous camera, ``b1`` in the current camera, and a
3-D point ``X0`` in camera-0 coordinates is ``X1 = R @ X0 + t`` in camera-1 coordinates. The
essential matrix is ``E = [t]x R`` with ``b1^T E b0 = 0``; ``t`` is a unit vector (scale is not
observable). The camera-1 centre in camera-0 coordinates is ``-R^T t``.

Pipeline of :func:`verify_bearings`:

1. RANSAC with a batched minimal 5-point solver (Stewenius' Groebner-basis formulation, all
   hypotheses of a batch solved at once in numpy), MSAC scoring of the angular epipolar error,
   adaptive number of iterations, deterministic from ``seed``.
2. Decomposition of the best ``E`` into ``R, t`` with a cheirality test on bearings (positive
   depth along both rays, not ``z > 0``), then Levenberg-Marquardt refinement of ``R, t`` on the
   inliers and re-classification (twice).
3. Degeneracy test: a rotation-only model (2-point RANSAC + Kabsch) is fitted too. When it
   explains nearly all essential inliers (pure rotation or a stopped vehicle: no parallax) the
   translation is unobservable and the rotation model is returned, so tracks survive a stop.
   Its inliers are the rotation inliers plus the essential inliers with a small parallax
   (``rotation_max_parallax_rad``), so near points are kept while the vehicle creeps.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
import math
from typing import Any

import numpy as np

from semfeat_ros.matching.config import check_range, merge_conf
from semfeat_ros.matching.errors import FeatureInputError
from semfeat_ros.rotations import skew, so3_exp

default_conf: dict[str, Any] = {
    # Inlier threshold on the angle between a bearing and its epipolar plane (rad). For an
    # equidistant fisheye 1 px at the image centre is 1/fx rad: 0.005 rad is ~1 px at fx=187
    # (640 px wide image) and ~2.8 px at fx=560 (1920 px wide image).
    'threshold_rad': 0.01,
    # Inlier threshold of the rotation-only model: angle between b1 and R b0 (rad). It measures a
    # 2-D error, so it is larger than the 1-D epipolar threshold.
    'rotation_threshold_rad': 0.015,
    # Probability that at least one all-inlier sample is drawn (adaptive iteration count).
    'confidence': 0.999,
    # Minimal samples (5-point) drawn at least / at most.
    'min_iterations': 16,
    'max_iterations': 1000,
    # Minimal samples solved together in one vectorised batch.
    'batch_size': 32,
    # Fewer inliers than this (or fewer correspondences) -> verification fails (ok False).
    'min_inliers': 12,
    # Rotation-only (no observable translation) when the rotation model's inliers are at least
    # this fraction of the essential model's inliers.
    'rotation_fraction': 0.9,
    # In rotation-only mode, essential inliers whose parallax (angle between b1 and R b0) is
    # below this are inliers too (rad): creeping at a high frame rate gives near points some
    # parallax, and those tracks must not be dropped.
    'rotation_max_parallax_rad': 0.05,
    # A point triangulated behind a camera is an outlier when its parallax exceeds this (rad);
    # below it the depth sign is not reliable (far points, points near the epipole).
    'cheirality_min_parallax_rad': 0.02,
    # Levenberg-Marquardt iterations of each refinement on the inliers (0 disables refinement);
    # it usually converges in 2-3.
    'refine_iterations': 5,
    # Seed of the random sampler: the same input always gives the same result.
    'seed': 0,
}


def _check_conf(conf: Mapping[str, Any]) -> None:
    name = 'verification'
    check_range(conf, 'threshold_rad', 0.0, 0.5, name, lo_open=True)
    check_range(conf, 'rotation_threshold_rad', 0.0, 0.5, name, lo_open=True)
    check_range(conf, 'confidence', 0.0, 1.0, name, lo_open=True)
    if conf['confidence'] >= 1.0:
        check_range(conf, 'confidence', 0.0, 0.999999, name, lo_open=True)
    check_range(conf, 'min_iterations', 1, None, name, integer=True)
    check_range(conf, 'max_iterations', conf['min_iterations'], None, name, integer=True)
    check_range(conf, 'batch_size', 1, 4096, name, integer=True)
    check_range(conf, 'min_inliers', 5, None, name, integer=True)
    check_range(conf, 'rotation_fraction', 0.0, 10.0, name, lo_open=True)
    check_range(conf, 'rotation_max_parallax_rad', 0.0, math.pi, name)
    check_range(conf, 'cheirality_min_parallax_rad', 0.0, math.pi, name)
    check_range(conf, 'refine_iterations', 0, 1000, name, integer=True)
    check_range(conf, 'seed', 0, None, name, integer=True)


@dataclass
class Verification:
    """Result of :func:`verify_bearings` for ``N`` correspondences."""

    ok: bool
    """At least ``min_inliers`` inliers of a valid model."""
    model: str
    """'essential' (general motion), 'rotation' (translation not observable) or 'none'."""
    inliers: np.ndarray
    """(N,) bool."""
    residuals: np.ndarray
    """(N,) rad: epipolar angle (essential) or angle of b1 to R b0 (rotation); inf if none."""
    R: np.ndarray
    """(3, 3) rotation camera 0 -> camera 1 (``X1 = R X0 + t``)."""
    t: np.ndarray
    """(3,) unit translation direction in camera 1; zeros for ``'rotation'`` and ``'none'``."""
    E: np.ndarray | None
    """(3, 3) essential matrix ``[t]x R`` (Frobenius norm sqrt(2)) or None."""
    n_iterations: int
    """Minimal samples drawn (5-point plus 2-point)."""
    n_essential_inliers: int
    n_rotation_inliers: int
    parallax_rad: float
    """Median angle between b1 and R b0 over the inliers (rad); 0 without inliers."""

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def inlier_ratio(self) -> float:
        n = self.inliers.shape[0]
        return float(self.inliers.sum()) / n if n else 0.0


# ---------------------------------------------------------------------------------------------
# small helpers


def _check_bearings(b0: np.ndarray, b1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for name, b in (('bearings0', b0), ('bearings1', b1)):
        arr = np.asarray(b, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise FeatureInputError(f'{name}: expected shape (N, 3), got {arr.shape}')
        if not np.isfinite(arr).all():
            raise FeatureInputError(f'{name}: contains NaN or inf')
        norm = np.linalg.norm(arr, axis=1, keepdims=True)
        if (norm < 1e-9).any():
            raise FeatureInputError(f'{name}: contains zero-length bearings')
        out.append(arr / norm)
    if out[0].shape[0] != out[1].shape[0]:
        raise FeatureInputError(
            f'bearings0 and bearings1 must have the same length, got {out[0].shape[0]} '
            f'and {out[1].shape[0]}')
    return out[0], out[1]


def _needed_iterations(inlier_ratio: float, sample_size: int, confidence: float,
                       limit: int) -> int:
    """Samples needed to draw an all-inlier sample with probability ``confidence``."""
    p = inlier_ratio ** sample_size
    if p <= 0.0:
        return limit
    if p >= 1.0 - 1e-12:
        return 1
    return int(min(limit, math.ceil(math.log(1.0 - confidence) / math.log(1.0 - p))))


def _draw_samples(rng: np.random.Generator, n: int, k: int, count: int) -> np.ndarray:
    """(count, k) sample indices into ``range(n)``, distinct within each row."""
    idx = rng.integers(0, n, size=(count, k))
    while True:
        s = np.sort(idx, axis=1)
        bad = (np.diff(s, axis=1) == 0).any(axis=1)
        if not bad.any():
            return idx
        idx[bad] = rng.integers(0, n, size=(int(bad.sum()), k))


# ---------------------------------------------------------------------------------------------
# epipolar geometry


def epipolar_sines(E: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Sine of the angular epipolar error of (K, 3, 3) or (3, 3) models on N bearing pairs.

    For each pair the error is the larger of the angles between ``b1`` and its epipolar plane
    (normal ``E b0``) and between ``b0`` and its plane (normal ``E^T b1``). Returns (K, N) or (N,).
    """
    single = E.ndim == 2
    Es = E[None] if single else E
    k = Es.shape[0]
    b0t = np.ascontiguousarray(b0.T)
    b1t = np.ascontiguousarray(b1.T)
    ef0 = (Es.reshape(3 * k, 3) @ b0t).reshape(k, 3, -1)
    etf1 = (Es.transpose(0, 2, 1).reshape(3 * k, 3) @ b1t).reshape(k, 3, -1)
    num = np.abs(ef0[:, 0] * b1t[0] + ef0[:, 1] * b1t[1] + ef0[:, 2] * b1t[2])
    den = np.sqrt(np.minimum(np.einsum('kin,kin->kn', ef0, ef0),
                             np.einsum('kin,kin->kn', etf1, etf1)))
    with np.errstate(divide='ignore', invalid='ignore'):
        s = np.where(den > 1e-12, num / np.maximum(den, 1e-300), np.where(num > 1e-12, 1.0, 0.0))
    s = np.minimum(s, 1.0)
    return s[0] if single else s


def epipolar_angles(E: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Angular epipolar error (rad) of a (3, 3) essential matrix on (N, 3) bearing pairs."""
    b0, b1 = _check_bearings(b0, b1)
    return np.arcsin(epipolar_sines(np.asarray(E, dtype=np.float64), b0, b1))


def _normalize_essential(E: np.ndarray) -> np.ndarray:
    """Closest essential matrix (singular values 1, 1, 0) to a (..., 3, 3) matrix."""
    U, _, Vt = np.linalg.svd(E)
    d = np.zeros(E.shape[:-2] + (3,))
    d[..., 0] = 1.0
    d[..., 1] = 1.0
    return (U * d[..., None, :]) @ Vt


def essential_8pt(b0: np.ndarray, b1: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Linear (weighted) least-squares essential matrix from >= 8 bearing pairs.

    Unit bearings are already well conditioned, so no Hartley normalisation is needed.
    Returns a (3, 3) essential matrix with singular values (1, 1, 0).
    """
    b0, b1 = _check_bearings(b0, b1)
    if b0.shape[0] < 8:
        raise FeatureInputError(f'essential_8pt needs >= 8 pairs, got {b0.shape[0]}')
    A = (b1[:, :, None] * b0[:, None, :]).reshape(-1, 9)
    if weights is not None:
        A = A * np.asarray(weights, dtype=np.float64)[:, None]
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    return _normalize_essential(Vt[-1].reshape(3, 3))


# Monomials x^a y^b z^c of the 5-point solver (E = x X + y Y + z Z + W).
_DEG1 = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 0)]
_CUBIC = [(3, 0, 0), (2, 1, 0), (2, 0, 1), (1, 2, 0), (1, 1, 1), (1, 0, 2), (0, 3, 0),
          (0, 2, 1), (0, 1, 2), (0, 0, 3)]
_BASIS = [(2, 0, 0), (1, 1, 0), (1, 0, 1), (0, 2, 0), (0, 1, 1), (0, 0, 2), (1, 0, 0),
          (0, 1, 0), (0, 0, 1), (0, 0, 0)]
_ALL = _CUBIC + _BASIS


def _mul_tensor(a: list[tuple[int, int, int]], b: list[tuple[int, int, int]],
                c: list[tuple[int, int, int]]) -> np.ndarray:
    index = {m: i for i, m in enumerate(c)}
    T = np.zeros((len(a), len(b), len(c)))
    for i, ma in enumerate(a):
        for j, mb in enumerate(b):
            T[i, j, index[(ma[0] + mb[0], ma[1] + mb[1], ma[2] + mb[2])]] = 1.0
    return T


_T11 = _mul_tensor(_DEG1, _DEG1, _BASIS)  # deg1 * deg1 -> deg2 (basis order)
_T21 = _mul_tensor(_BASIS, _DEG1, _ALL)  # deg2 * deg1 -> deg3 (all 20)
_T11_MAT = _T11.reshape(16, 10)
_T21_MAT = _T21.reshape(40, 20)


def _action_matrix_layout() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows of the multiplication-by-x action matrix on the quotient basis ``_BASIS``."""
    cubic_rows, cubic_src, unit_rows, unit_cols = [], [], [], []
    for i, m in enumerate(_BASIS):
        prod = (m[0] + 1, m[1], m[2])
        if prod in _CUBIC:
            cubic_rows.append(i)
            cubic_src.append(_CUBIC.index(prod))
        else:
            unit_rows.append(i)
            unit_cols.append(_BASIS.index(prod))
    return (np.array(cubic_rows), np.array(cubic_src), np.array(unit_rows), np.array(unit_cols))


_ACT_CUBIC_ROWS, _ACT_CUBIC_SRC, _ACT_UNIT_ROWS, _ACT_UNIT_COLS = _action_matrix_layout()
_IX, _IY, _IZ, _I1 = (_BASIS.index(m) for m in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 0)))


def _solve_5pt_batch(A: np.ndarray, M_out: np.ndarray) -> np.ndarray:
    """Fill the action matrices; returns a (S,) bool mask of samples that could be solved."""
    ok = np.isfinite(A).all(axis=(1, 2))
    lead = A[:, :, :10]
    rest = A[:, :, 10:]
    G = np.zeros((A.shape[0], 10, 10))
    try:
        G[ok] = np.linalg.solve(lead[ok], rest[ok])
    except np.linalg.LinAlgError:
        for s in np.flatnonzero(ok):
            try:
                G[s] = np.linalg.solve(lead[s], rest[s])
            except np.linalg.LinAlgError:
                ok[s] = False
    ok &= np.isfinite(G).all(axis=(1, 2))
    M_out[:, _ACT_CUBIC_ROWS, :] = -G[:, _ACT_CUBIC_SRC, :]
    M_out[:, _ACT_UNIT_ROWS, _ACT_UNIT_COLS] = 1.0
    return ok


def solve_essential_5pt(b0: np.ndarray, b1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimal 5-point essential matrix solver, vectorised over S samples.

    ``b0, b1``: (S, 5, 3) unit bearings. Returns ``(E, sample)``: (K, 3, 3) real solutions
    (Frobenius norm sqrt(2)) and (K,) the sample each solution belongs to (up to 10 per sample).
    """
    b0 = np.asarray(b0, dtype=np.float64)
    b1 = np.asarray(b1, dtype=np.float64)
    if b0.ndim != 3 or b0.shape[1:] != (5, 3) or b1.shape != b0.shape:
        raise FeatureInputError(
            f'solve_essential_5pt: expected two (S, 5, 3) arrays, got {b0.shape} and {b1.shape}')
    S = b0.shape[0]
    if S == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64)
    Q = (b1[:, :, :, None] * b0[:, :, None, :]).reshape(S, 5, 9)
    _, _, Vt = np.linalg.svd(Q, full_matrices=True)
    null = Vt[:, 5:9, :]  # (S, 4, 9): X, Y, Z, W
    P1 = null.transpose(0, 2, 1).reshape(S, 3, 3, 4)  # entry polynomials in (x, y, z, 1)
    # Polynomial products as outer products of coefficients followed by a fixed linear map.
    EEt = np.einsum('sika,sjkb->sijab', P1, P1).reshape(S, 3, 3, 16) @ _T11_MAT
    tr = EEt[:, 0, 0] + EEt[:, 1, 1] + EEt[:, 2, 2]  # (S, 10)
    EEtE = np.einsum('sika,skjb->sijab', EEt, P1).reshape(S, 3, 3, 40) @ _T21_MAT
    trE = np.einsum('sa,sijb->sijab', tr, P1).reshape(S, 3, 3, 40) @ _T21_MAT
    C = (2.0 * EEtE - trE).reshape(S, 9, 20)
    # det(E) along row 0: cofactors E1a E2b - E1c E2d, then times E0j.
    r1, r2 = P1[:, 1], P1[:, 2]
    cof = (np.einsum('sja,sjb->sjab', r1[:, [1, 2, 0]], r2[:, [2, 0, 1]])
           - np.einsum('sja,sjb->sjab', r1[:, [2, 0, 1]], r2[:, [1, 2, 0]]))
    cof = cof.reshape(S, 3, 16) @ _T11_MAT  # (S, 3, 10)
    det = np.einsum('sja,sjb->sab', cof, P1[:, 0]).reshape(S, 40) @ _T21_MAT
    A = np.concatenate([C, det[:, None, :]], axis=1)  # (S, 10, 20)
    # Scale rows for conditioning (each constraint is homogeneous).
    A /= np.maximum(np.abs(A).max(axis=2, keepdims=True), 1e-300)
    M = np.zeros((S, 10, 10))
    ok = _solve_5pt_batch(A, M)
    if not ok.any():
        return np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64)
    sidx = np.flatnonzero(ok)
    w, v = np.linalg.eig(M[ok])  # right eigenvectors: M b = x b
    real = np.abs(w.imag) <= 1e-8 * np.maximum(1.0, np.abs(w.real))
    den = v[:, _I1, :]
    real &= np.abs(den) > 1e-12
    s_of, k_of = np.nonzero(real)
    if s_of.size == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64)
    vec = v[s_of, :, k_of]
    d = vec[:, _I1]
    xyz = np.stack([(vec[:, _IX] / d).real, (vec[:, _IY] / d).real, (vec[:, _IZ] / d).real,
                    np.ones(s_of.size)], axis=1)  # (K, 4)
    E = np.einsum('ka,kab->kb', xyz, null[sidx[s_of]]).reshape(-1, 3, 3)
    E *= math.sqrt(2.0) / np.maximum(np.linalg.norm(E, axis=(1, 2)), 1e-300)[:, None, None]
    good = np.isfinite(E).all(axis=(1, 2))
    return E[good], sidx[s_of][good]


def triangulate_depths(R: np.ndarray, t: np.ndarray, b0: np.ndarray,
                       b1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mid-point depths along the rays for the motion ``X1 = R X0 + t``.

    Returns ``(depth0, depth1, parallax)``: (N,) depths along ``b0`` and ``b1`` in units of |t|
    (positive means in front along the ray, whatever the sign of z) and the parallax angle
    between ``R b0`` and ``b1`` (rad). Parallel rays get depth NaN.
    """
    a = b0 @ R.T
    c = np.einsum('ni,ni->n', a, b1)
    at = a @ t
    bt = b1 @ t
    den = 1.0 - c * c
    with np.errstate(divide='ignore', invalid='ignore'):
        d1 = np.where(den > 1e-12, (bt - c * at) / den, np.nan)
    d0 = c * d1 - at
    parallax = np.arccos(np.clip(c, -1.0, 1.0))
    return d0, d1, parallax


def decompose_essential(E: np.ndarray, b0: np.ndarray,
                        b1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (R, t) of ``E`` with the most correspondences in front of both cameras.

    Cheirality is tested on bearings: positive depth along both rays. Returns ``(R, t,
    in_front)`` with ``in_front`` (N,) bool for the chosen pose.
    """
    U, _, Vt = np.linalg.svd(np.asarray(E, dtype=np.float64))
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    best = None
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            d0, d1, _ = triangulate_depths(R, t, b0, b1)
            front = (d0 > 0) & (d1 > 0)
            n = int(front.sum())
            if best is None or n > best[0]:
                best = (n, R, t.copy(), front)
    return best[1], best[2], best[3]  # type: ignore[index]


def _cross_cols(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of column-stacked vectors: (3, N) x (3, N) -> (3, N)."""
    out = np.empty((3, a.shape[1]))
    np.multiply(a[1], b[2], out=out[0])
    out[0] -= a[2] * b[1]
    np.multiply(a[2], b[0], out=out[1])
    out[1] -= a[0] * b[2]
    np.multiply(a[0], b[1], out=out[2])
    out[2] -= a[1] * b[0]
    return out


def _pose_residuals(R: np.ndarray, t: np.ndarray, b0t: np.ndarray, b1t: np.ndarray,
                    jacobian: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """(2N,) signed sines of the epipolar angles in both images for the pose (R, t).

    ``b0t, b1t`` are the bearings as (3, N) arrays. With ``jacobian`` also the (2N, 5)
    derivatives for the update ``R <- exp(w) R``, ``t <- normalize(t + alpha e1 + beta e2)``
    (``e1, e2`` from :func:`_tangent_basis`). The error of ``b1`` is ``num / |t x a|`` and that
    of ``b0`` is ``num / |t x b1|`` with ``a = R b0`` and ``num = t . (a x b1)``. Products
    with the fixed ``t`` are matrix products with ``[t]x`` (this runs in every LM step).
    """
    a = R @ b0t
    axb = _cross_cols(a, b1t)
    num = t @ axb
    St = skew(t)
    c1 = St @ a  # t x a
    c0 = St @ b1t  # t x b1
    n1 = np.maximum(np.sqrt(np.einsum('in,in->n', c1, c1)), 1e-9)
    n0 = np.maximum(np.sqrt(np.einsum('in,in->n', c0, c0)), 1e-9)
    r = np.concatenate([num / n1, num / n0])
    if not jacobian:
        return r, None
    E12 = np.stack(_tangent_basis(t))  # (2, 3)
    d_num_w = _cross_cols(c0, a)  # a x (b1 x t)
    d_n1_w = _cross_cols(St @ c1, a) / n1  # a x (c1 x t) / |t x a|
    d_num_t = E12 @ axb  # (2, N)
    d_n1_t = E12 @ _cross_cols(a, c1) / n1
    d_n0_t = E12 @ _cross_cols(b1t, c0) / n0
    k1 = num / n1 ** 2
    k0 = num / n0 ** 2
    n = a.shape[1]
    J = np.empty((2 * n, 5))
    J[:n, :3] = (d_num_w / n1 - k1 * d_n1_w).T
    J[:n, 3:] = (d_num_t / n1 - k1 * d_n1_t).T
    J[n:, :3] = (d_num_w / n0).T
    J[n:, 3:] = (d_num_t / n0 - k0 * d_n0_t).T
    return r, J


def _tangent_basis(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to the unit vector ``t``: ``e1`` along
    ``t x (1, 0, 0)`` (``t x (0, 1, 0)`` when ``t`` is near the x axis), ``e2 = t x e1``."""
    tx, ty, tz = float(t[0]), float(t[1]), float(t[2])
    ex, ey, ez = (0.0, tz, -ty) if abs(tx) < 0.9 else (-tz, 0.0, tx)
    norm = math.sqrt(ex * ex + ey * ey + ez * ez)
    ex, ey, ez = ex / norm, ey / norm, ez / norm
    return (np.array([ex, ey, ez]),
            np.array([ty * ez - tz * ey, tz * ex - tx * ez, tx * ey - ty * ex]))


def refine_pose(R: np.ndarray, t: np.ndarray, b0: np.ndarray, b1: np.ndarray,
                iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the angular epipolar error of (N, 3) bearing pairs (inliers).

    Parametrisation: left rotation increment (3) and a tangent step of the unit ``t`` (2),
    analytic Jacobian. Returns the refined ``(R, t)`` (t unit).
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64) / np.linalg.norm(t)
    if b0.shape[0] < 6 or iterations <= 0:
        return R, t

    return _levenberg_marquardt(R, t, b0, b1, iterations, free_t=True)


def refine_rotation(R: np.ndarray, t: np.ndarray, b0: np.ndarray, b1: np.ndarray,
                    iterations: int = 10) -> np.ndarray:
    """Levenberg-Marquardt on the rotation alone, the translation direction ``t`` held fixed.

    Same angular epipolar error and motion convention (``x1 = R x0 + t``) as
    :func:`refine_pose` on (N, 3) bearing pairs (inliers); for a motion whose direction is
    known from elsewhere (a vehicle's kinematics), which removes the ambiguity between a pitch
    (or yaw) rotation and a tilt of the translation. Returns the refined (3, 3) ``R``.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64) / np.linalg.norm(t)
    if b0.shape[0] < 3 or iterations <= 0:
        return R
    return _levenberg_marquardt(R, t, b0, b1, iterations, free_t=False)[0]


def _levenberg_marquardt(R: np.ndarray, t: np.ndarray, b0: np.ndarray, b1: np.ndarray,
                         iterations: int, free_t: bool) -> tuple[np.ndarray, np.ndarray]:
    """The loop of :func:`refine_pose` (``free_t``) and :func:`refine_rotation`: steps in the
    left rotation increment and, with ``free_t``, a tangent step of the unit ``t``."""
    n_par = 5 if free_t else 3

    def apply(p: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not free_t:
            return so3_exp(p[:3]) @ R, t
        e1, e2 = _tangent_basis(t)
        tn = t + p[3] * e1 + p[4] * e2
        return so3_exp(p[:3]) @ R, tn / np.linalg.norm(tn)

    b0t = np.ascontiguousarray(b0.T)
    b1t = np.ascontiguousarray(b1.T)
    r, J = _pose_residuals(R, t, b0t, b1t, jacobian=True)
    J = J[:, :n_par]
    cost = float(r @ r)
    lam = 1e-4
    for _ in range(iterations):
        g = J.T @ r
        H = J.T @ J
        improved = False
        rel = 0.0
        for _ in range(8):
            step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
            Rn, tn = apply(step, R, t)
            rn, _ = _pose_residuals(Rn, tn, b0t, b1t)
            cn = float(rn @ rn)
            if cn < cost:
                rel = (cost - cn) / max(cost, 1e-300)
                R, t, cost = Rn, tn, cn
                lam = max(lam / 10.0, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or rel < 1e-6:
            break
        r, J = _pose_residuals(R, t, b0t, b1t, jacobian=True)
        J = J[:, :n_par]
    return R, t


# ---------------------------------------------------------------------------------------------
# rotation-only model


def rotation_kabsch(b0: np.ndarray, b1: np.ndarray, weights: np.ndarray | None = None,
                    ) -> np.ndarray:
    """Rotation R minimising sum w |b1 - R b0|^2; batched over leading axes ((..., N, 3))."""
    w = 1.0 if weights is None else np.asarray(weights, dtype=np.float64)[..., None]
    H = np.einsum('...ni,...nj->...ij', b0 * w, b1)
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(d.shape + (3,))
    D[..., 0] = 1.0
    D[..., 1] = 1.0
    D[..., 2] = d
    return (V * D[..., None, :]) @ Ut


def _rotation_chords(R: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """(K, N) chord |b1 - R b0| for (K, 3, 3) rotations."""
    k = R.shape[0]
    rb0 = (R.reshape(3 * k, 3) @ b0.T).reshape(k, 3, -1)
    diff = rb0 - b1.T[None]
    return np.sqrt(np.einsum('kin,kin->kn', diff, diff))


def _ransac_rotation(b0: np.ndarray, b1: np.ndarray, conf: Mapping[str, Any],
                     rng: np.random.Generator, min_ratio: float,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """2-point RANSAC of a pure rotation; returns (R, inliers, angles, samples drawn).

    ``min_ratio`` is the smallest inlier ratio that matters to the caller: the sampling stops
    once a model with that ratio would have been found with ``confidence``.
    """
    n = b0.shape[0]
    thr = 2.0 * math.sin(conf['rotation_threshold_rad'] / 2.0)
    best_cost = math.inf
    best_R = np.eye(3)
    drawn = 0
    limit = max(conf['min_iterations'], _needed_iterations(
        min(max(min_ratio, 1e-6), 1.0), 2, conf['confidence'], conf['max_iterations']))
    needed = limit
    batch = conf['batch_size']
    while drawn < needed:
        count = min(batch, limit - drawn)
        if count <= 0:
            break
        idx = _draw_samples(rng, n, 2, count)
        drawn += count
        Rs = rotation_kabsch(b0[idx], b1[idx])
        ch = _rotation_chords(Rs, b0, b1)
        cost = np.minimum(ch, thr) ** 2
        total = cost.sum(axis=1)
        k = int(np.argmin(total))
        if total[k] < best_cost:
            best_cost = float(total[k])
            best_R = Rs[k]
            ratio = float((ch[k] < thr).mean())
            needed = max(conf['min_iterations'],
                         _needed_iterations(ratio, 2, conf['confidence'], limit))
    R = best_R
    for _ in range(2):
        inl = _rotation_chords(R[None], b0, b1)[0] < thr
        if inl.sum() < 2:
            break
        R = rotation_kabsch(b0[inl], b1[inl])
    ch = _rotation_chords(R[None], b0, b1)[0]
    angles = 2.0 * np.arcsin(np.clip(ch / 2.0, 0.0, 1.0))
    return R, ch < thr, angles, drawn


# ---------------------------------------------------------------------------------------------
# essential RANSAC


_PROBE_SIZE = 96  # points of the preemptive scoring subset
_PROBE_KEEP = 4  # hypotheses per batch scored on all points


def _ransac_essential(b0: np.ndarray, b1: np.ndarray, conf: Mapping[str, Any],
                      rng: np.random.Generator) -> tuple[np.ndarray | None, int]:
    """5-point MSAC; returns (best E or None, samples drawn)."""
    n = b0.shape[0]
    thr = math.sin(conf['threshold_rad'])
    best_cost = math.inf
    best_E = None
    drawn = 0
    needed = conf['max_iterations']
    batch = conf['batch_size']
    while drawn < needed:
        count = min(batch, conf['max_iterations'] - drawn)
        if count <= 0:
            break
        idx = _draw_samples(rng, n, 5, count)
        drawn += count
        Es, _ = solve_essential_5pt(b0[idx], b1[idx])
        if Es.shape[0] == 0:
            continue
        if Es.shape[0] > _PROBE_KEEP and n > 2 * _PROBE_SIZE:
            # Preemptive scoring: rank all hypotheses on a random subset, score the best fully.
            probe = rng.choice(n, _PROBE_SIZE, replace=False)
            sp = epipolar_sines(Es, b0[probe], b1[probe])
            keep = np.argsort((np.minimum(sp, thr) ** 2).sum(axis=1))[:_PROBE_KEEP]
            Es = Es[keep]
        s = epipolar_sines(Es, b0, b1)
        total = (np.minimum(s, thr) ** 2).sum(axis=1)
        k = int(np.argmin(total))
        if total[k] < best_cost:
            best_cost = float(total[k])
            best_E = Es[k]
            ratio = float((s[k] < thr).mean())
            needed = max(conf['min_iterations'],
                         _needed_iterations(ratio, 5, conf['confidence'], conf['max_iterations']))
    return best_E, drawn


def _classify(R: np.ndarray, t: np.ndarray, b0: np.ndarray, b1: np.ndarray,
              conf: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inliers of the pose (epipolar angle + cheirality); returns (inliers, angles, parallax)."""
    E = skew(t) @ R
    angles = np.arcsin(epipolar_sines(E, b0, b1))
    d0, d1, parallax = triangulate_depths(R, t, b0, b1)
    behind = ~((d0 > 0) & (d1 > 0))  # NaN depth (parallel rays) counts as not behind below
    behind &= np.isfinite(d0) & np.isfinite(d1)
    behind &= parallax > conf['cheirality_min_parallax_rad']
    return (angles < conf['threshold_rad']) & ~behind, angles, parallax


def _fail(n: int, drawn: int = 0, n_ess: int = 0, n_rot: int = 0) -> Verification:
    return Verification(ok=False, model='none', inliers=np.zeros(n, dtype=bool),
                        residuals=np.full(n, np.inf), R=np.eye(3), t=np.zeros(3), E=None,
                        n_iterations=drawn, n_essential_inliers=n_ess,
                        n_rotation_inliers=n_rot, parallax_rad=0.0)


def verify_bearings(b0: np.ndarray, b1: np.ndarray,
                    conf: Mapping[str, Any] | None = None) -> Verification:
    """Robustly verify N bearing correspondences ``b0[i] <-> b1[i]`` (see the module doc).

    ``conf`` overrides keys of :data:`default_conf`. Deterministic for a given ``conf['seed']``.
    """
    conf = merge_conf(default_conf, conf, 'verification')
    _check_conf(conf)
    b0, b1 = _check_bearings(b0, b1)
    n = b0.shape[0]
    if n < max(conf['min_inliers'], 5):
        return _fail(n)
    rng = np.random.default_rng(conf['seed'])

    E, drawn = _ransac_essential(b0, b1, conf, rng)

    inl_ess = np.zeros(n, dtype=bool)
    ang_ess = np.full(n, np.inf)
    parallax = np.zeros(n)
    R, t = np.eye(3), np.zeros(3)
    if E is not None:
        inl0 = epipolar_sines(E, b0, b1) < math.sin(conf['threshold_rad'])
        if inl0.sum() >= 5:
            R, t, _ = decompose_essential(E, b0[inl0], b1[inl0])
            inl_ess, ang_ess, parallax = _classify(R, t, b0, b1, conf)
            for _ in range(2):
                if inl_ess.sum() < 6 or conf['refine_iterations'] == 0:
                    break
                R, t = refine_pose(R, t, b0[inl_ess], b1[inl_ess], conf['refine_iterations'])
                new_inl, ang_ess, parallax = _classify(R, t, b0, b1, conf)
                changed = bool((new_inl != inl_ess).any())
                inl_ess = new_inl
                if not changed:
                    break
    n_ess = int(inl_ess.sum())

    # The rotation model only matters if it can reach rotation_fraction * n_ess inliers.
    min_ratio = max(conf['rotation_fraction'] * n_ess, conf['min_inliers']) / n
    R_rot, inl_rot, ang_rot, drawn_rot = _ransac_rotation(b0, b1, conf, rng, min_ratio)
    n_rot = int(inl_rot.sum())
    drawn += drawn_rot

    if n_rot >= max(conf['min_inliers'], 2) and n_rot >= conf['rotation_fraction'] * n_ess:
        par = float(np.median(ang_rot[inl_rot]))
        inl_rot = inl_rot | (inl_ess & (ang_rot < conf['rotation_max_parallax_rad']))
        return Verification(ok=True, model='rotation', inliers=inl_rot, residuals=ang_rot,
                            R=R_rot, t=np.zeros(3), E=None, n_iterations=drawn,
                            n_essential_inliers=n_ess, n_rotation_inliers=n_rot,
                            parallax_rad=par)
    if n_ess >= conf['min_inliers']:
        return Verification(ok=True, model='essential', inliers=inl_ess, residuals=ang_ess,
                            R=R, t=t, E=skew(t) @ R, n_iterations=drawn,
                            n_essential_inliers=n_ess, n_rotation_inliers=n_rot,
                            parallax_rad=float(np.median(parallax[inl_ess])))
    return _fail(n, drawn, n_ess, n_rot)
