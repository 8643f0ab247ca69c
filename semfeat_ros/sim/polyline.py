"""2-D polylines with rounded corners, lateral offsets, smoothing and arc-length sampling (m)."""
from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from semfeat_ros.sim.errors import SimConfigError


def round_corners(points: np.ndarray, radius: float, step: float = 0.1,
                  closed: bool = False) -> np.ndarray:
    """Densely sampled polyline (M, 2) through ``points`` (K, 2) with circular fillets of
    ``radius`` m at the corners (shrunk where segments are too short)."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        raise SimConfigError(f'a polyline needs at least 2 points, got {len(pts)}')
    if closed:
        pts = np.concatenate([pts, pts[:1]])
    n = len(pts)
    seg = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    if np.any(seg_len < 1e-9):
        raise SimConfigError('a polyline has repeated consecutive points')
    dirs = seg / seg_len[:, None]
    corners = list(range(n)) if closed else list(range(1, n - 1))
    fillets: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for i in corners:
        d_in = dirs[i - 1] if i > 0 else dirs[-1]
        d_out = dirs[i] if i < n - 1 else dirs[0]
        cosang = float(np.clip(d_in @ d_out, -1.0, 1.0))
        turn = np.arccos(cosang)
        if turn < 1e-6:
            continue
        prev_len = seg_len[i - 1] if i > 0 else seg_len[-1]
        next_len = seg_len[i] if i < n - 1 else seg_len[0]
        r = min(radius, 0.45 * min(prev_len, next_len) / max(np.tan(turn / 2), 1e-9))
        cut = r * np.tan(turn / 2)
        p = pts[i % (n - 1)] if closed else pts[i]
        a = p - d_in * cut
        b = p + d_out * cut
        cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
        fillets[i % (n - 1) if closed else i] = (a, b, np.array([r, turn, np.sign(cross)]))
    out: list[np.ndarray] = []
    m = n - 1 if closed else n
    for i in range(m):
        p = pts[i]
        if i in fillets:
            a, b, (r, turn, sgn) = fillets[i]
            d_in = dirs[i - 1] if i > 0 else dirs[-1]
            normal = np.array([-d_in[1], d_in[0]]) * sgn
            center = a + normal * r
            start = np.arctan2(a[1] - center[1], a[0] - center[0])
            k = max(2, int(np.ceil(r * turn / step)))
            ang = start + sgn * np.linspace(0.0, turn, k + 1)
            out.append(np.stack([center[0] + r * np.cos(ang), center[1] + r * np.sin(ang)], 1))
        else:
            out.append(p[None])
        # straight part to the next corner (start of its fillet or the next point)
        j = i + 1
        if j < n:
            q = pts[j] if j not in fillets and not (closed and j == n - 1 and 0 in fillets) \
                else (fillets[j % (n - 1) if closed else j][0])
            start_pt = out[-1][-1]
            length = np.linalg.norm(q - start_pt)
            k = max(1, int(np.ceil(length / step)))
            t = np.linspace(0.0, 1.0, k + 1)[1:-1]
            out.append(start_pt + (q - start_pt) * t[:, None])
    xy = np.concatenate(out)
    if not closed:
        xy = np.concatenate([xy, pts[-1:]])
    keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9])
    return xy[keep]


def resample(xy: np.ndarray, step: float, closed: bool = False) -> np.ndarray:
    """Resample a polyline at constant arc-length ``step`` (m)."""
    pts = np.concatenate([xy, xy[:1]]) if closed else xy
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    n = max(2, int(round(s[-1] / step)))
    si = np.linspace(0.0, s[-1], n + 1)
    if closed:
        si = si[:-1]
    return np.stack([np.interp(si, s, pts[:, 0]), np.interp(si, s, pts[:, 1])], axis=1)


def smooth(xy: np.ndarray, sigma: float, step: float, closed: bool = False) -> np.ndarray:
    """Gaussian smoothing along a polyline resampled at ``step`` m (``sigma`` in m); the end
    points of an open polyline are kept."""
    pts = resample(xy, step, closed)
    mode = 'wrap' if closed else 'nearest'
    out = gaussian_filter1d(pts, sigma / step, axis=0, mode=mode)
    if not closed:
        out[0], out[-1] = pts[0], pts[-1]
    return out


def offset(xy: np.ndarray, d: float, closed: bool = False) -> np.ndarray:
    """Parallel polyline ``d`` m to the right of the direction of travel."""
    pts = np.asarray(xy, dtype=np.float64)
    if closed:
        tang = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    else:
        tang = np.gradient(pts, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    right = np.stack([tang[:, 1], -tang[:, 0]], axis=1)
    return pts + d * right


class Polyline:
    """Arc-length parameterised polyline (open or closed)."""

    def __init__(self, xy: np.ndarray, closed: bool = False) -> None:
        pts = np.asarray(xy, dtype=np.float64)
        if closed:
            pts = np.concatenate([pts, pts[:1]])
        self.xy = pts
        self.closed = closed
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0),
                                                                 axis=1))])
        self.length = float(self.s[-1])
        heading = np.arctan2(np.gradient(pts[:, 1]), np.gradient(pts[:, 0]))
        self.heading = np.unwrap(heading)

    def at(self, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Position (N, 2) m and heading (N,) rad at arc length ``s`` (wraps if closed)."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        s = np.mod(s, self.length) if self.closed else np.clip(s, 0.0, self.length)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        h = np.interp(s, self.s, self.heading)
        return np.stack([x, y], axis=1), h
