"""Levels of a multi-storey structure from the altitude profile of the trajectory.

A level is a plateau of the altitude over travelled distance (|dz/ds| small for long enough);
ramps are the sloped stretches between plateaus. Plateaus at similar altitude (revisits) are one
level. Levels are indexed from the lowest (0) upwards.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FloorLevels:
    """Altitudes (m, map z) of the detected levels, ascending; ``flat`` marks plateau samples."""

    altitudes: np.ndarray  # (L,) m
    flat: np.ndarray  # (K,) bool per trajectory sample: on a plateau (False: ramp)

    def assign(self, z: np.ndarray) -> np.ndarray:
        """Level index (uint8) of altitudes ``z`` (m): the nearest level."""
        z = np.asarray(z, dtype=np.float64)
        if len(self.altitudes) == 0:
            return np.zeros(z.shape, np.uint8)
        idx = np.abs(z[..., None] - self.altitudes).argmin(axis=-1)
        return np.minimum(idx, 255).astype(np.uint8)


def storey_altitude(z: np.ndarray, seen: np.ndarray, altitudes: np.ndarray,
                    margin: float, hangs: np.ndarray | None = None) -> np.ndarray:
    """Altitude (m) of the level each point belongs to: the storey its altitude lies in.

    Args:
        z: (N,) point altitudes (m).
        seen: (N,) highest altitude of a plateau pose that observed each point (m; NaN: none).
        altitudes: (L,) level altitudes (m), ascending.
        margin: half-thickness of a level's slab (m).
        hangs: optional (N,) bool, points of classes hung under the slab above their observers
            (ceilings, ceiling lights): they belong to the storey of their highest plateau
            observer whatever their altitude (depth errors of points seen ahead with little
            parallax move them up by metres, above the next level).
    Returns:
        (N,) the altitude of the highest level below each point. Within ``margin`` of a level
        above the lowest (its slab: the deck on top, the lower storey's ceiling underneath)
        the observers decide: a point seen only from below that slab is the lower storey's.
        Points below every level belong to the lowest; with no level, z itself.
    """
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    seen = np.asarray(seen, dtype=np.float64).reshape(-1)
    alts = np.asarray(altitudes, dtype=np.float64).reshape(-1)
    if len(alts) == 0:
        return z.copy()
    below = np.maximum(np.searchsorted(alts, z, side='right') - 1, 0)
    out = alts[below]
    j = np.abs(z[:, None] - alts[None]).argmin(axis=1)
    slab = np.abs(alts[j] - z) <= margin
    from_below = (j > 0) & (seen < alts[j] - margin)  # NaN compares False: the slab's level
    out[slab] = np.where(from_below[slab], alts[np.maximum(j[slab] - 1, 0)], alts[j[slab]])
    if hangs is not None:
        h = np.asarray(hangs, dtype=bool).reshape(-1) & np.isfinite(seen)
        level = np.maximum(np.searchsorted(alts, seen[h] + margin, side='right') - 1, 0)
        out[h] = alts[level]
    return out


def detect_floors(positions: np.ndarray, *, max_slope: float = 0.05,
                  slope_window_m: float = 4.0, min_plateau_m: float = 6.0,
                  merge_m: float = 1.2) -> FloorLevels:
    """Levels from base positions (K, 3) m along the trajectory, in driving order.

    The slope is ``dz/ds`` over ``slope_window_m`` of travelled distance ``s`` (m); samples with
    ``|slope| < max_slope`` are flat; a flat run longer than ``min_plateau_m`` is a plateau whose
    median altitude is a level candidate; candidates within ``merge_m`` merge (weighted by
    length). Without any plateau the whole trajectory is one level at its median altitude.
    """
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    k = len(P)
    if k == 0:
        return FloorLevels(np.zeros(0), np.zeros(0, bool))
    step = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(step)])
    z = P[:, 2]
    half = slope_window_m / 2.0
    lo = np.searchsorted(s, s - half, side='left')
    hi = np.searchsorted(s, s + half, side='right') - 1
    ds = s[hi] - s[lo]
    with np.errstate(invalid='ignore', divide='ignore'):
        slope = np.where(ds > 0.25 * half, (z[hi] - z[lo]) / np.maximum(ds, 1e-9), 0.0)
    flat = np.abs(slope) < max_slope
    candidates: list[tuple[float, float]] = []  # (altitude, length)
    edges = np.diff(np.concatenate([[0], flat.astype(np.int8), [0]]))
    for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        length = s[stop - 1] - s[start]
        if length >= min_plateau_m:
            candidates.append((float(np.median(z[start:stop])), float(length)))
    if not candidates:
        return FloorLevels(np.array([float(np.median(z))]), flat)
    candidates.sort()
    levels: list[list[float]] = []  # [weighted sum, weight, last altitude]
    for alt, length in candidates:
        if levels and alt - levels[-1][2] < merge_m:
            levels[-1][0] += alt * length
            levels[-1][1] += length
            levels[-1][2] = alt
        else:
            levels.append([alt * length, length, alt])
    return FloorLevels(np.array([w / n for w, n, _ in levels]), flat)
