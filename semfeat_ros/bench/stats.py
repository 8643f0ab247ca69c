"""Summary statistics of the benchmark: percentiles, ratios, rolling medians, slopes."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def summarize(values: Sequence[float]) -> dict[str, float | int | None]:
    """``{'n', 'p50', 'p95', 'mean'}`` of ``values`` (ms); None entries without values."""
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {'n': 0, 'p50': None, 'p95': None, 'mean': None}
    return {'n': int(a.size), 'p50': float(np.median(a)), 'p95': float(np.percentile(a, 95)),
            'mean': float(a.mean())}


def ratio(a: float | None, b: float | None) -> float | None:
    """``a / b`` or None when either is missing or ``b`` is not positive."""
    if a is None or b is None or not b > 0:
        return None
    return float(a) / float(b)


def rolling_median(x: np.ndarray, window: int) -> np.ndarray:
    """Centred rolling median of ``x``, same length; the window shrinks at the ends."""
    x = np.asarray(x, dtype=np.float64)
    window = max(1, min(int(window), x.size))
    if x.size == 0 or window == 1:
        return x.copy()
    left = window // 2
    padded = np.pad(x, (left, window - 1 - left), constant_values=np.nan)
    return np.nanmedian(np.lib.stride_tricks.sliding_window_view(padded, window), axis=1)


def linear_slope(t: np.ndarray, y: np.ndarray) -> float | None:
    """Least-squares slope dy/dt, or None with fewer than 2 distinct ``t``."""
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if t.size < 2 or np.ptp(t) <= 0:
        return None
    return float(np.polyfit(t, y, 1)[0])
