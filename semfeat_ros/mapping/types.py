"""Per-frame inputs and outputs of the mapper (plain numpy, no gtsam)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.mapping.errors import MapperInputError


def _array(x: object, shape: tuple[int | None, ...], name: str, dtype: type = np.float64
           ) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise MapperInputError(f'{name}: not numeric ({exc})') from exc
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = '(' + ', '.join('N' if s is None else str(s) for s in shape) + ')'
        raise MapperInputError(f'{name}: expected shape {want}, got {a.shape}')
    return a


@dataclass(frozen=True)
class Tracks:
    """The tracked keypoints of one frame (matcher output, /semfeat/tracks).

    ``track_id`` (N,) persistent ids; ``bearing`` (N, 3) unit vectors in the camera optical
    frame (any direction); ``pixel`` (N, 2) px; ``label`` (N,) class ids; ``stamp_ns`` in ns.
    """

    stamp_ns: int
    track_id: np.ndarray
    bearing: np.ndarray
    pixel: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return len(self.track_id)

    @staticmethod
    def from_structured(arr: np.ndarray, stamp_ns: int) -> Tracks:
        """From a structured array with fields u v bx by bz label track_id (TRACKS_DTYPE)."""
        names = set(arr.dtype.names or ())
        missing = {'u', 'v', 'bx', 'by', 'bz', 'label', 'track_id'} - names
        if missing:
            raise MapperInputError(f'tracks array lacks fields {sorted(missing)}')
        return Tracks(int(stamp_ns), arr['track_id'], np.stack([arr['bx'], arr['by'], arr['bz']],
                      axis=1), np.stack([arr['u'], arr['v']], axis=1), arr['label'])

    def validated(self) -> tuple[Tracks, int]:
        """Checked copy: rows with non-finite or zero bearings are dropped (their count is
        returned), bearings renormalised; wrong shapes, negative or duplicate ids raise."""
        if isinstance(self.stamp_ns, bool) or not isinstance(self.stamp_ns, int | np.integer):
            raise MapperInputError(f'stamp_ns must be an integer (ns), got {self.stamp_ns!r}')
        ids = _array(self.track_id, (None,), 'track_id', np.float64)
        n = len(ids)
        b = _array(self.bearing, (n, 3), 'bearing')
        px = _array(self.pixel, (n, 2), 'pixel')
        lab = _array(self.label, (n,), 'label', np.float64)
        if n and (not np.isfinite(ids).all() or ids.min() < 0 or (ids != np.round(ids)).any()
                  or ids.max() > np.iinfo(np.uint32).max):
            raise MapperInputError('track_id: expected non-negative integers (uint32)')
        if n and (not np.isfinite(lab).all() or lab.min() < 0 or lab.max() > 255):
            raise MapperInputError('label: expected class ids in 0..255')
        ids_i = ids.astype(np.int64)
        if len(np.unique(ids_i)) != n:
            raise MapperInputError('track_id: duplicate ids in one frame')
        norm = np.linalg.norm(b, axis=1)
        ok = np.isfinite(b).all(axis=1) & np.isfinite(px).all(axis=1) & (norm > 1e-9)
        out = Tracks(int(self.stamp_ns), ids_i[ok], b[ok] / norm[ok, None], px[ok],
                     lab[ok].astype(np.uint8))
        return out, int(n - ok.sum())


def _check_cov(cov: np.ndarray, n: int, name: str) -> np.ndarray:
    c = _array(cov, (n, n), name)
    if not np.isfinite(c).all():
        raise MapperInputError(f'{name}: contains NaN or inf')
    c = 0.5 * (c + c.T)
    if np.linalg.eigvalsh(c).min() <= 0:
        raise MapperInputError(f'{name}: must be positive definite (a zero or negative '
                               f'variance is never valid), eigenvalues {np.linalg.eigvalsh(c)}')
    return c


@dataclass(frozen=True)
class OdometryDelta:
    """Wheel-odometry motion of base_link since the previous frame passed to the mapper.

    ``T`` (4, 4): previous base pose -> current base pose, in the previous base frame (m);
    ``covariance`` (6, 6) in GTSAM's (roll, pitch, yaw-like rotation vector rad, x y z m) order,
    right perturbation (nav_msgs covariances are (x y z, rot): reorder before building).
    """

    T: np.ndarray
    covariance: np.ndarray

    @staticmethod
    def from_se2(dx: float, dy: float, dyaw: float, covariance: np.ndarray, *,
                 sigma_z: float = 0.02, sigma_roll_pitch: float = 0.02) -> OdometryDelta:
        """Planar motion ``dx, dy`` (m), ``dyaw`` (rad) with its 3x3 covariance (x, y, yaw);
        the unobserved z, roll and pitch get ``sigma_z`` (m) and ``sigma_roll_pitch`` (rad)."""
        c3 = _check_cov(covariance, 3, 'odometry covariance (x, y, yaw)')
        T = np.eye(4)
        cy, sy = np.cos(dyaw), np.sin(dyaw)
        T[:2, :2] = [[cy, -sy], [sy, cy]]
        T[:3, 3] = [dx, dy, 0.0]
        cov = np.zeros((6, 6))
        cov[0, 0] = cov[1, 1] = sigma_roll_pitch**2
        cov[5, 5] = sigma_z**2
        idx = [3, 4, 2]  # x, y, yaw in (rot, trans) order
        cov[np.ix_(idx, idx)] = c3
        return OdometryDelta(T, cov)

    def validated(self) -> OdometryDelta:
        T = _array(self.T, (4, 4), 'odometry T')
        if not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]):
            raise MapperInputError('odometry T: expected a finite 4x4 rigid transform')
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise MapperInputError('odometry T: rotation block is not orthonormal')
        return OdometryDelta(T, _check_cov(self.covariance, 6, 'odometry covariance'))


@dataclass(frozen=True)
class GnssFix:
    """A GNSS position of the antenna (m) in the map frame (ENU axes) with its 3x3 covariance.

    ``covariance`` None (unknown) is rejected by the mapper, as is any fix whose covariance is
    not positive definite or too large.
    """

    stamp_ns: int
    position: np.ndarray
    covariance: np.ndarray | None


@dataclass(frozen=True)
class MapperResult:
    """What :meth:`Mapper.update` returns for every frame.

    ``T_map_base`` (4, 4) m; ``covariance`` (6, 6) of the base pose in (rot rad, trans m)
    right-perturbation order, or None when unknown (initialising, lost); ``state`` one of
    'initializing', 'tracking', 'odometry_only', 'lost'; ``events`` short notes of what
    happened in this frame (keyframe, gnss_rejected: ..., update_recovered, ...).
    """

    stamp_ns: int
    T_map_base: np.ndarray | None
    covariance: np.ndarray | None
    state: str
    keyframe: bool
    metric: bool
    n_tracks: int
    n_inliers: int
    n_landmarks: int
    update_ms: float
    events: tuple[str, ...] = ()
