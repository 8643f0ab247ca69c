"""Trajectory evaluation: Umeyama alignment and absolute trajectory error (ATE)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.mapping.errors import AlignmentError


@dataclass(frozen=True)
class Similarity:
    """``x_gt ~ s R x_est + t`` (scale, 3x3 rotation, translation in m)."""

    s: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points (N, 3) m."""
        return self.s * np.asarray(points, dtype=np.float64) @ self.R.T + self.t


def _positions(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 3 and a.shape[1:] == (4, 4):
        a = a[:, :3, 3]
    if a.ndim != 2 or a.shape[1] != 3:
        raise AlignmentError(
            f'{name}: expected positions (N, 3) or poses (N, 4, 4), got {a.shape}')
    if not np.isfinite(a).all():
        raise AlignmentError(f'{name}: contains NaN or inf')
    return a


def align_umeyama(est: np.ndarray, gt: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity (Sim(3)) or rigid (SE(3), ``with_scale=False``) alignment.

    ``est`` and ``gt`` are matching positions (N, 3) m or poses (N, 4, 4); Umeyama (1991).
    """
    X = _positions(est, 'est')
    Y = _positions(gt, 'gt')
    if len(X) != len(Y):
        raise AlignmentError(f'est has {len(X)} samples, gt has {len(Y)}')
    if len(X) < 3:
        raise AlignmentError(f'need at least 3 samples to align, got {len(X)}')
    mx, my = X.mean(axis=0), Y.mean(axis=0)
    Xc, Yc = X - mx, Y - my
    var_x = float(np.mean(np.sum(Xc * Xc, axis=1)))
    if var_x < 1e-12:
        raise AlignmentError('est positions are all identical: alignment undefined')
    C = Yc.T @ Xc / len(X)
    U, D, Vt = np.linalg.svd(C)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_x) if with_scale else 1.0
    t = my - s * R @ mx
    return Similarity(s, R, t)


def ate_rmse(est: np.ndarray, gt: np.ndarray, with_scale: bool = True,
             align: bool = True) -> float:
    """RMSE (m) of positions after Sim(3) (``with_scale``) or SE(3) alignment (``align``)."""
    X = _positions(est, 'est')
    Y = _positions(gt, 'gt')
    if len(X) != len(Y):
        raise AlignmentError(f'est has {len(X)} samples, gt has {len(Y)}')
    if align:
        X = align_umeyama(X, Y, with_scale).apply(X)
    return float(np.sqrt(np.mean(np.sum((X - Y) ** 2, axis=1))))
