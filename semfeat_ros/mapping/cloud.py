"""The semantic point cloud of the map and its voxel-bounded store of marginalised landmarks."""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SemanticCloud:
    """Map points in the ``map`` frame (z up, m), one per landmark.

    ``rgb`` is the class colour from labels.yaml; ``floor`` the level index (0 = lowest);
    ``n_obs`` the number of keyframes that observed the landmark.
    """

    xyz: np.ndarray  # (N, 3) float32 m
    label: np.ndarray  # (N,) uint8 class id
    floor: np.ndarray  # (N,) uint8 level index
    landmark_id: np.ndarray  # (N,) uint32
    n_obs: np.ndarray  # (N,) uint16
    rgb: np.ndarray  # (N, 3) uint8

    def __len__(self) -> int:
        return len(self.xyz)

    @staticmethod
    def empty() -> SemanticCloud:
        return SemanticCloud(np.zeros((0, 3), np.float32), np.zeros(0, np.uint8),
                             np.zeros(0, np.uint8), np.zeros(0, np.uint32),
                             np.zeros(0, np.uint16), np.zeros((0, 3), np.uint8))

    @staticmethod
    def build(xyz: np.ndarray, label: np.ndarray, floor: np.ndarray, landmark_id: np.ndarray,
              n_obs: np.ndarray, colors: np.ndarray) -> SemanticCloud:
        """Cast the columns to the contract's dtypes; ``colors`` (C, 3) uint8 per class id."""
        label = np.asarray(label, np.uint8)
        lut = np.zeros((256, 3), np.uint8)
        lut[: len(colors)] = colors
        return SemanticCloud(
            np.asarray(xyz, np.float32).reshape(-1, 3), label, np.asarray(floor, np.uint8),
            np.asarray(landmark_id, np.uint32),
            np.clip(np.asarray(n_obs), 0, np.iinfo(np.uint16).max).astype(np.uint16),
            lut[label])

    def concat(self, other: SemanticCloud) -> SemanticCloud:
        return SemanticCloud(*(np.concatenate([a, b]) for a, b in zip(
            (self.xyz, self.label, self.floor, self.landmark_id, self.n_obs, self.rgb),
            (other.xyz, other.label, other.floor, other.landmark_id, other.n_obs, other.rgb))))


class VoxelMap:
    """Marginalised landmarks, at most one per (voxel, floor, class); memory grows with area only.

    On a collision the landmark with more observations stays. Beyond ``max_points`` the oldest
    inserted voxels are dropped first.
    """

    def __init__(self, voxel_size: float, max_points: int) -> None:
        self.voxel_size = float(voxel_size)
        self.max_points = int(max_points)
        self._index: dict[tuple[int, int, int, int, int], int] = {}
        self._cap = 1024
        self._xyz = np.zeros((self._cap, 3))
        self._label = np.zeros(self._cap, np.uint8)
        self._lid = np.zeros(self._cap, np.uint32)
        self._nobs = np.zeros(self._cap, np.int64)
        self._alt = np.zeros(self._cap)  # highest plateau pose that observed it (m; NaN: none)
        self._anchor_ns = np.full(self._cap, -1, np.int64)  # keyframe stamp it was created at
        self._anchor_px = np.full((self._cap, 2), np.nan)  # its pixel there (px)
        self._used = np.zeros(self._cap, bool)
        self._free: list[int] = []
        self._n = 0  # rows ever allocated
        self._order: deque[tuple[int, int, int, int, int]] = deque()

    def __len__(self) -> int:
        return len(self._index)

    def _key(self, xyz: np.ndarray, floor: int, label: int) -> tuple[int, int, int, int, int]:
        q = np.floor(np.asarray(xyz) / self.voxel_size).astype(np.int64)
        return int(q[0]), int(q[1]), int(q[2]), int(floor), int(label)

    def _grow(self) -> None:
        self._cap *= 2
        for name in ('_xyz', '_label', '_lid', '_nobs', '_alt', '_anchor_ns', '_anchor_px',
                     '_used'):
            old = getattr(self, name)
            new = np.zeros((self._cap,) + old.shape[1:], old.dtype)
            new[: len(old)] = old
            setattr(self, name, new)

    def insert(self, xyz: np.ndarray, label: int, landmark_id: int, n_obs: int,
               observer_alt: float, floor: int,
               anchor: tuple[int, float, float] = (-1, np.nan, np.nan)) -> None:
        """Add a landmark (m); ``floor`` keeps points of different levels apart; ``anchor`` is
        ``(stamp ns, u px, v px)`` of the observation it was triangulated at (evaluation)."""
        key = self._key(xyz, floor, label)
        row = self._index.get(key)
        if row is not None:
            if n_obs <= self._nobs[row]:
                return
        else:
            if len(self._index) >= self.max_points:
                self._evict_oldest()
            if self._free:
                row = self._free.pop()
            else:
                if self._n >= self._cap:
                    self._grow()
                row = self._n
                self._n += 1
            self._index[key] = row
            self._order.append(key)
        self._xyz[row] = xyz
        self._label[row] = label
        self._lid[row] = landmark_id
        self._nobs[row] = n_obs
        self._alt[row] = observer_alt
        self._anchor_ns[row] = anchor[0]
        self._anchor_px[row] = anchor[1:]
        self._used[row] = True

    def _evict_oldest(self) -> None:
        while self._order:
            key = self._order.popleft()
            row = self._index.pop(key, None)
            if row is not None:
                self._used[row] = False
                self._free.append(row)
                return

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(xyz, label, landmark_id, n_obs, observer_altitude)`` of the stored landmarks
        (observer altitude: of the highest plateau pose that saw it, m; NaN: none)."""
        m = self._used[: self._n]
        return (self._xyz[: self._n][m], self._label[: self._n][m], self._lid[: self._n][m],
                self._nobs[: self._n][m], self._alt[: self._n][m])

    def anchors(self) -> tuple[np.ndarray, np.ndarray]:
        """``(stamp ns (N,), pixel (N, 2) px)`` of the stored landmarks' anchor observations, in
        the order of :meth:`arrays` (stamp -1: unknown)."""
        m = self._used[: self._n]
        return self._anchor_ns[: self._n][m], self._anchor_px[: self._n][m]

    def transform(self, s: float, R: np.ndarray, t: np.ndarray,
                  floor_of: Callable[[np.ndarray, float, int], int]) -> None:
        """Apply ``x -> s R x + t`` to every point (and altitude); voxels are re-keyed by
        ``floor_of(xyz, observer_altitude, label)`` of the moved point."""
        xyz, label, lid, nobs, alt = self.arrays()
        a_ns, a_px = self.anchors()
        xyz = s * xyz @ R.T + t
        alt = s * alt + t[2]
        self.__init__(self.voxel_size, self.max_points)
        for i in range(len(xyz)):
            self.insert(xyz[i], int(label[i]), int(lid[i]), int(nobs[i]), float(alt[i]),
                        int(floor_of(xyz[i], float(alt[i]), int(label[i]))),
                        (int(a_ns[i]), float(a_px[i, 0]), float(a_px[i, 1])))
