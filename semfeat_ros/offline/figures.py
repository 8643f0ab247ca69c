"""Figures of a mapping run (matplotlib, Agg backend: no display needed).

* :func:`plot_trajectory_top`: estimated and ground-truth trajectories from above, coloured by
  floor.
* :func:`plot_altitude`: altitude over travelled distance against the ground truth, ramps
  shaded (the paper's Figure 4).
* :func:`plot_cloud`: oblique 3-D view of the semantic cloud coloured by class (the paper's
  Figure 3).
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

_FLOOR_COLORS = ('#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#ff7f0e', '#8c564b')


def _floor_color(k: int) -> str:
    return _FLOOR_COLORS[int(k) % len(_FLOOR_COLORS)]


def _legend(ax: object, **kwargs: object) -> None:
    """A legend when something is labelled (an empty one only warns)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kwargs)


def _finish(fig: Any, ax: Any, title: str, path: Path, **legend: object) -> Path:
    """Legend, title, layout; write ``path`` and close the figure."""
    _legend(ax, **legend)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _spans(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index ranges of the True runs of a bool mask."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask, np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def plot_trajectory_top(path: Path, gt_xyz: np.ndarray, gt_floor: np.ndarray,
                        est_xyz: np.ndarray | None, est_floor: np.ndarray | None,
                        title: str, est_label: str = 'estimate (keyframes)') -> Path:
    """Top view (x east, y north, m): ground truth as a line, the aligned estimate as dots,
    both coloured by floor index."""
    fig, ax = plt.subplots(figsize=(8, 6), dpi=110)
    gt_xyz = np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3)
    gt_floor = np.asarray(gt_floor, dtype=np.int64).ravel()
    for k in np.unique(gt_floor).tolist():
        sel = gt_floor == k
        for a, b in _spans(sel):
            ax.plot(gt_xyz[max(a - 1, 0):b, 0], gt_xyz[max(a - 1, 0):b, 1], '-',
                    color=_floor_color(k), lw=3, alpha=0.35,
                    label=f'ground truth, level {k}' if a == _spans(sel)[0][0] else None)
    if est_xyz is not None and len(est_xyz):
        est_xyz = np.asarray(est_xyz, dtype=np.float64).reshape(-1, 3)
        ef = np.zeros(len(est_xyz), np.int64) if est_floor is None else np.asarray(est_floor)
        ax.plot(est_xyz[:, 0], est_xyz[:, 1], '-', color='0.3', lw=0.8)
        for k in np.unique(ef).tolist():
            sel = ef == k
            ax.scatter(est_xyz[sel, 0], est_xyz[sel, 1], s=10, color=_floor_color(k),
                       edgecolors='k', linewidths=0.3, zorder=3,
                       label=f'{est_label}, level {k}')
    ax.set_xlabel('x (m, east)')
    ax.set_ylabel('y (m, north)')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(True, alpha=0.3)
    return _finish(fig, ax, title, path, loc='best', fontsize=8)


def plot_altitude(path: Path, gt_s: np.ndarray, gt_z: np.ndarray, gt_ramp: np.ndarray,
                  est_s: np.ndarray | None, est_z: np.ndarray | None, title: str,
                  levels: Sequence[float] = (),
                  est_label: str = 'estimate (keyframes, aligned)') -> Path:
    """Altitude (m) over travelled distance (m): ground truth line, aligned estimate dots,
    ramp sections (ground-truth pitch) shaded, ground-truth levels dashed."""
    fig, ax = plt.subplots(figsize=(9, 4), dpi=110)
    gt_s = np.asarray(gt_s, dtype=np.float64)
    for i, (a, b) in enumerate(_spans(np.asarray(gt_ramp, bool))):
        ax.axvspan(gt_s[a], gt_s[b - 1], color='orange', alpha=0.15,
                   label='ramp (ground truth)' if i == 0 else None)
    for i, alt in enumerate(levels):
        ax.axhline(alt, color='0.5', ls='--', lw=0.8, label='levels' if i == 0 else None)
    ax.plot(gt_s, gt_z, '-', color='k', lw=1.5, label='ground truth')
    if est_s is not None and est_z is not None and len(est_s):
        ax.plot(est_s, est_z, 'o-', color='#d62728', ms=3, lw=0.8,
                label=est_label)
    ax.set_xlabel('distance travelled (m)')
    ax.set_ylabel('altitude z (m)')
    ax.grid(True, alpha=0.3)
    return _finish(fig, ax, title, path, loc='best', fontsize=8)


def plot_cloud(path: Path, xyz: np.ndarray, label: np.ndarray, colors: np.ndarray,
               names: Sequence[str], trajectory: np.ndarray | None, title: str,
               max_points: int = 150_000, seed: int = 0) -> Path:
    """Oblique 3-D scatter of map points (m) in class colours (``colors`` (C, 3) uint8 per
    class id) with the trajectory; at most ``max_points`` points (seeded subsample)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    label = np.asarray(label, dtype=np.int64).ravel()
    if len(xyz) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
        xyz, label = xyz[keep], label[keep]
    fig = plt.figure(figsize=(9, 7), dpi=110)
    ax = fig.add_subplot(projection='3d')
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):  # grey panes: white classes stay visible
        axis.set_pane_color((0.82, 0.82, 0.82, 1.0))
    lut = np.zeros((256, 3))
    lut[:len(colors)] = np.asarray(colors, dtype=np.float64) / 255.0
    for c in np.unique(label).tolist():
        sel = label == c
        name = names[c] if c < len(names) else str(c)
        ax.scatter(xyz[sel, 0], xyz[sel, 1], xyz[sel, 2], s=2, color=lut[c], depthshade=False,
                   label=f'{name} ({int(sel.sum())})')
    pts = xyz
    if trajectory is not None and len(trajectory):
        tr = np.asarray(trajectory, dtype=np.float64).reshape(-1, 3)
        ax.plot(tr[:, 0], tr[:, 1], tr[:, 2], '-', color='k', lw=1.5, label='trajectory')
        pts = np.concatenate([pts, tr]) if len(pts) else tr
    if len(pts):
        lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
        centre, half = (lo + hi) / 2.0, max(float((hi - lo).max()) / 2.0, 1.0)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half / 3.0, centre[2] + half / 3.0)
        ax.set_box_aspect((1, 1, 1 / 3))
    ax.view_init(elev=35, azim=-60)
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_zlabel('z (m)')
    return _finish(fig, ax, title, path, loc='upper left', fontsize=7, markerscale=4, ncol=2)
