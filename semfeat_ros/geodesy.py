"""WGS-84 geodetic <-> local east-north-up (m) on a tangent plane at an origin.

The small-area approximation (meridional and prime-vertical radii at the origin's latitude) is
exact to millimetres over the few hundred metres of a parking structure.
"""
from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0
"""Semi-major axis (m)."""
WGS84_E2 = 6.69437999014e-3
"""First eccentricity squared."""


def _radii(lat_deg: float) -> tuple[float, float]:
    """Meridional and prime-vertical radii of curvature (m) at a latitude (deg)."""
    s = np.sin(np.radians(lat_deg))
    w = np.sqrt(1.0 - WGS84_E2 * s * s)
    return WGS84_A * (1.0 - WGS84_E2) / w ** 3, WGS84_A / w


def enu_to_geodetic(enu: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """Points (N, 3) m (x east, y north, z up) -> (lat deg, lon deg, alt m)."""
    lat0, lon0, alt0 = origin
    m, n = _radii(lat0)
    p = np.atleast_2d(np.asarray(enu, dtype=np.float64))
    lat = lat0 + np.degrees(p[:, 1] / m)
    lon = lon0 + np.degrees(p[:, 0] / (n * np.cos(np.radians(lat0))))
    return np.stack([lat, lon, alt0 + p[:, 2]], axis=1)


def geodetic_to_enu(geo: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """(lat deg, lon deg, alt m) (N, 3) -> points (N, 3) m east, north, up of ``origin``."""
    lat0, lon0, alt0 = origin
    m, n = _radii(lat0)
    g = np.atleast_2d(np.asarray(geo, dtype=np.float64))
    x = np.radians(g[:, 1] - lon0) * n * np.cos(np.radians(lat0))
    y = np.radians(g[:, 0] - lat0) * m
    return np.stack([x, y, g[:, 2] - alt0], axis=1)
