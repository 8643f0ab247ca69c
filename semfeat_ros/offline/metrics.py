"""Trajectory and map metrics against the ground truth of a recording.

All positions are in metres. The estimate is compared at its own stamps with the ground-truth
pose at the same stamp (interpolated between ground-truth samples at most ``max_gap_s`` apart;
estimates outside the ground truth's time span are left out).

* ATE: RMSE of positions after a Sim(3) Umeyama alignment (scale free: always reported) and
  after an SE(3) alignment (only when the estimate claims metric scale).
* Ramp altitude: on the samples where the ground-truth pitch exceeds ``ramp_pitch_rad``
  (sloped ramp sections), RMSE and maximum of |aligned estimated z - ground-truth z|.
* Floors: the ground-truth levels are the plateaus of the ground-truth altitude profile
  (:func:`semfeat_ros.mapping.detect_floors`, the mapper's own rule, on the ground-truth
  trajectory). The ground-truth floor of a point is the level whose storey contains it: the
  highest level whose altitude is at most ``floor_tolerance_m`` above the point (a ceiling point
  of a covered level hangs below the deck slab and belongs to the level beneath it; points below
  the lowest level belong to it). The point is the landmark's true position when the recording
  has ground-truth range images: the rendered surface point at the pixel where the landmark was
  triangulated (:func:`anchor_points`), independent of the estimate; otherwise (and in the
  ``floors_aligned`` reading) its estimated position aligned into the ground-truth frame, which
  also counts an altitude error of the estimate near a level boundary as a wrong floor. The
  estimated floor indices are translated into ground-truth levels through the keyframes: each
  estimated level maps to the ground-truth level most of its plateau keyframes stand on.
* Point error: distance of a map point (aligned into the ground-truth frame) to its true
  position, the rendered surface point at the pixel where it was triangulated (recordings with
  ground-truth range images only; the along-ray depth error of a triangulation dominates it).
* Surfaces: a map point (aligned into the ground-truth frame) lies on the rendered geometry when,
  in some ground-truth range image it projects into, its range along the ray differs from the
  rendered range by at most ``tolerance_m`` (the smallest difference over the images counts:
  occluded in one view, seen in another).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from semfeat_ros.mapping import (
    AlignmentError,
    FloorLevels,
    SemanticCloud,
    Similarity,
    align_umeyama,
    detect_floors,
)
from semfeat_ros.mapping.config import default_conf
from semfeat_ros.mapping.session import interpolate_pose
from semfeat_ros.offline.errors import EvaluationError

#: Ground-truth pitch (rad) above which a sample lies on a ramp (the sim's ramps: 0.06..0.12).
RAMP_PITCH_RAD = 0.02
#: A point at most this far below a level's surface still belongs to that level (m).
FLOOR_TOLERANCE_M = 0.2


def associate(est_stamps: np.ndarray, gt_stamps: np.ndarray, gt_poses: np.ndarray,
              max_gap_s: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth poses at ``est_stamps`` (ns): ``(indices (M,) into est_stamps, poses
    (M, 4, 4))``.

    Exact stamps are used as they are; others are interpolated between the bracketing
    ground-truth samples when those are at most ``max_gap_s`` apart.
    """
    est = np.asarray(est_stamps, dtype=np.int64).ravel()
    gts = np.asarray(gt_stamps, dtype=np.int64).ravel()
    gtp = np.asarray(gt_poses, dtype=np.float64).reshape(-1, 4, 4)
    idx, out = [], []
    if len(gts) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    pos = np.searchsorted(gts, est, side='left')
    gap = int(max_gap_s * 1e9)
    for i, (s, j) in enumerate(zip(est.tolist(), pos.tolist())):
        if j < len(gts) and gts[j] == s:
            idx.append(i)
            out.append(gtp[j])
        elif 0 < j < len(gts) and gts[j] - gts[j - 1] <= gap:
            a = (s - gts[j - 1]) / (gts[j] - gts[j - 1])
            idx.append(i)
            out.append(interpolate_pose(gtp[j - 1], gtp[j], float(a)))
    return np.asarray(idx, dtype=np.int64), np.asarray(out).reshape(-1, 4, 4)


def pitch_of(poses: np.ndarray) -> np.ndarray:
    """Pitch (rad, nose up positive) of base poses (N, 4, 4): elevation of the x axis."""
    P = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    return np.arcsin(np.clip(P[:, 2, 0], -1.0, 1.0))


def travelled(positions: np.ndarray) -> np.ndarray:
    """Cumulative travelled distance (m) along positions (N, 3)."""
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])


def _rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(err)))) if len(err) else float('nan')


@dataclass(frozen=True)
class TrajectoryEvaluation:
    """Associated samples and the alignments (see :func:`evaluate_trajectory`)."""

    est_index: np.ndarray  # (M,) index of each associated sample in the estimate
    est: np.ndarray  # (M, 4, 4) estimated poses
    gt: np.ndarray  # (M, 4, 4) ground-truth poses
    sim3: Similarity
    se3: Similarity | None
    ramp: np.ndarray  # (M,) bool: sample on a ramp (ground-truth pitch)
    metrics: dict[str, float | int | None]


def _tag(key: str, alignment: str) -> str:
    """``'ramp_altitude_max_m'`` -> ``'ramp_altitude_max_sim3_m'``."""
    return f'{key[:-2]}_{alignment}_m'


def _altitude(aligned: np.ndarray, gt: np.ndarray, ramp: np.ndarray) -> dict[str, float | None]:
    dz = aligned[:, 2] - gt[:, 2]
    out: dict[str, float | None] = {'altitude_rmse_m': _rmse(dz)}
    if ramp.any():
        out['ramp_altitude_rmse_m'] = _rmse(dz[ramp])
        out['ramp_altitude_max_m'] = float(np.abs(dz[ramp]).max())
    else:
        out['ramp_altitude_rmse_m'] = out['ramp_altitude_max_m'] = None
    return out


def evaluate_trajectory(est_stamps: np.ndarray, est_poses: np.ndarray, gt_stamps: np.ndarray,
                        gt_poses: np.ndarray, *, metric: bool,
                        ramp_pitch_rad: float = RAMP_PITCH_RAD) -> TrajectoryEvaluation:
    """ATE (Sim(3), and SE(3) when ``metric``), scale and ramp altitude errors (m).

    Raises:
        EvaluationError: fewer than 3 associated samples, or no motion to align.
    """
    idx, gt = associate(est_stamps, gt_stamps, gt_poses)
    est = np.asarray(est_poses, dtype=np.float64).reshape(-1, 4, 4)[idx]
    if len(idx) < 3:
        raise EvaluationError(
            f'only {len(idx)} estimated poses fall within the ground truth (need >= 3)')
    try:
        sim3 = align_umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=True)
        se3 = align_umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=False) if metric else None
    except AlignmentError as exc:
        raise EvaluationError(f'cannot align the trajectory: {exc}') from exc
    ramp = np.abs(pitch_of(gt)) > ramp_pitch_rad
    a3 = sim3.apply(est[:, :3, 3])
    m: dict[str, float | int | None] = {
        'n_poses': int(len(idx)),
        'n_ramp_poses': int(ramp.sum()),
        'gt_length_m': float(travelled(gt[:, :3, 3])[-1]),
        'ate_sim3_rmse_m': _rmse(np.linalg.norm(a3 - gt[:, :3, 3], axis=1)),
        'scale_sim3': float(sim3.s),
    }
    for k, v in _altitude(a3, gt[:, :3, 3], ramp).items():
        m[_tag(k, 'sim3')] = v
    if se3 is not None:
        a6 = se3.apply(est[:, :3, 3])
        m['ate_se3_rmse_m'] = _rmse(np.linalg.norm(a6 - gt[:, :3, 3], axis=1))
        for k, v in _altitude(a6, gt[:, :3, 3], ramp).items():
            m[_tag(k, 'se3')] = v
    else:
        m['ate_se3_rmse_m'] = None
        for k in ('altitude_rmse_m', 'ramp_altitude_rmse_m', 'ramp_altitude_max_m'):
            m[_tag(k, 'se3')] = None
    return TrajectoryEvaluation(idx, est, gt, sim3, se3, ramp, m)


def max_altitude_step_m(poses: np.ndarray) -> float | None:
    """Largest altitude change between consecutive poses (N, 4, 4) (m); None below 2 poses."""
    z = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[:, 2, 3]
    return float(np.abs(np.diff(z)).max()) if len(z) > 1 else None


def gt_levels(gt_poses: np.ndarray, floor_conf: dict | None = None) -> FloorLevels:
    """Levels of the ground-truth trajectory (the mapper's plateau rule and parameters)."""
    c = {**default_conf, **(floor_conf or {})}
    P = np.asarray(gt_poses, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    return detect_floors(P, max_slope=c['floor_max_slope'],
                         slope_window_m=c['floor_slope_window_m'],
                         min_plateau_m=c['floor_min_plateau_m'], merge_m=c['floor_merge_m'])


def storey_of(z: np.ndarray, levels: np.ndarray,
              tolerance_m: float = FLOOR_TOLERANCE_M) -> np.ndarray:
    """Ground-truth floor (index into ascending ``levels``) of altitudes ``z`` (m): the highest
    level at most ``tolerance_m`` above the point, level 0 for points below all levels."""
    z = np.asarray(z, dtype=np.float64)
    lv = np.sort(np.asarray(levels, dtype=np.float64))
    if len(lv) == 0:
        return np.zeros(z.shape, np.int64)
    return np.maximum(np.searchsorted(lv, z + tolerance_m, side='right') - 1, 0)


def floor_accuracy(cloud: SemanticCloud, sim3: Similarity, est_levels: FloorLevels,
                   kf_positions: np.ndarray, gt_level_altitudes: np.ndarray,
                   tolerance_m: float = FLOOR_TOLERANCE_M,
                   truth_xyz: np.ndarray | None = None) -> dict[str, object]:
    """Fraction of map points whose floor matches the ground truth (see the module doc).

    ``kf_positions`` (K, 3) are the estimated keyframe positions the ``est_levels`` were
    detected on (map frame); ``sim3`` maps the estimate into the ground-truth frame.
    ``truth_xyz`` (N, 3): the points' true positions in the ground-truth frame (m; NaN rows are
    not scored); without it the aligned estimated positions decide the true floor.
    """
    n_est = len(est_levels.altitudes)
    gt_alt = np.sort(np.asarray(gt_level_altitudes, dtype=np.float64))
    out: dict[str, object] = {
        'n_points': int(len(cloud)), 'gt_levels_m': [round(float(a), 3) for a in gt_alt],
        'est_levels_m': [round(float(a), 3) for a in est_levels.altitudes],
        'tolerance_m': tolerance_m,
        'truth': 'aligned estimate' if truth_xyz is None else 'rendered surface at the anchor'}
    if len(cloud) == 0 or n_est == 0 or len(gt_alt) == 0:
        out.update(accuracy=None, est_to_gt=[], confusion=[])
        return out
    kf = np.asarray(kf_positions, dtype=np.float64).reshape(-1, 3)
    kf_est_level = est_levels.assign(kf[:, 2]).astype(np.int64)
    kf_gt_level = np.abs(sim3.apply(kf)[:, 2, None] - gt_alt[None]).argmin(axis=1)
    flat = np.asarray(est_levels.flat, dtype=bool)
    if flat.shape != (len(kf),):
        flat = np.ones(len(kf), bool)
    mapping = np.zeros(max(n_est, int(cloud.floor.max()) + 1), np.int64)
    for k in range(len(mapping)):
        sel = (kf_est_level == k) & flat
        if not sel.any():
            sel = kf_est_level == k
        if sel.any():
            mapping[k] = int(np.bincount(kf_gt_level[sel], minlength=len(gt_alt)).argmax())
        else:
            centre = np.append(kf[:, :2].mean(axis=0), est_levels.altitudes[min(k, n_est - 1)])
            mapping[k] = int(np.abs(sim3.apply(centre[None])[0, 2] - gt_alt).argmin())
    if truth_xyz is None:
        pts = sim3.apply(cloud.xyz.astype(np.float64))
    else:
        pts = np.asarray(truth_xyz, dtype=np.float64).reshape(len(cloud), 3)
    scored = np.isfinite(pts[:, 2])
    truth = storey_of(pts[scored, 2], gt_alt, tolerance_m)
    pred = mapping[cloud.floor.astype(np.int64)][scored]
    conf = np.zeros((len(gt_alt), len(gt_alt)), np.int64)
    np.add.at(conf, (truth, np.minimum(pred, len(gt_alt) - 1)), 1)
    out.update(accuracy=float(np.mean(pred == truth)) if scored.any() else None,
               n_scored=int(scored.sum()), est_to_gt=mapping[:n_est].tolist(),
               confusion=conf.tolist())
    return out


def anchor_points(stamps: np.ndarray, pixels: np.ndarray, camera: object,
                  gt: tuple[np.ndarray, np.ndarray], T_base_cam: np.ndarray,
                  views: Sequence[DepthView], *, max_views: int = 2, max_dt_s: float = 1.0,
                  max_range_m: float = 80.0, samples: int = 400) -> np.ndarray:
    """True positions (N, 3) m, ground-truth map frame, of the surfaces seen at ``pixels``
    (N, 2) px of ``camera`` in the frames ``stamps`` (N,) ns.

    Each pixel's ray is posed by the ground truth ``gt`` = ``(stamps ns, T_map_base)`` and
    ``T_base_cam`` (4, 4), and marched through the range image nearest in time (the next one
    when that fails, at most ``max_views`` within ``max_dt_s``): the surface is where the ray
    first passes behind the rendered range, with the rendered range continuous there (a jump
    is an occluding edge in that view). With a range image of the pixel's own frame this is
    the rendered range at the pixel. NaN rows: no ground-truth pose or usable range image,
    outside the image circle, or no surface within ``max_range_m`` (sky).
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    stamps = np.asarray(stamps, dtype=np.int64).reshape(-1)
    out = np.full((len(px), 3), np.nan)
    views = [v for v in views if v.stamp_ns >= 0]
    if not len(px) or not views:
        return out
    v_st = np.array([v.stamp_ns for v in views], dtype=np.int64)
    idx, T_mb = associate(stamps, gt[0], gt[1])
    T_mc = T_mb @ np.asarray(T_base_cam, dtype=np.float64)
    rays = np.full((len(px), 3), np.nan)
    known = np.isfinite(px).all(axis=1)
    rays[known] = camera.unproject(px[known], check=False)
    s = np.geomspace(0.3, max_range_m, samples)
    for i, T in zip(idx.tolist(), T_mc):
        if not np.isfinite(rays[i]).all():
            continue
        P = T[:3, 3] + s[:, None] * (T[:3, :3] @ rays[i])
        dt = np.abs(v_st - stamps[i])
        for j in np.argsort(dt, kind='stable')[:max_views].tolist():
            if dt[j] > max_dt_s * 1e9:
                break
            hit = _first_surface(P, s, views[j])
            if hit is not None:
                out[i] = hit
                break
    return out


def point_errors(cloud: SemanticCloud, sim3: Similarity, truth_xyz: np.ndarray,
                 tolerance_m: float = 0.5) -> dict[str, object]:
    """Distance (m) of each map point, aligned into the ground-truth frame, to its true
    position ``truth_xyz`` (N, 3) (:func:`anchor_points`; NaN rows are not scored)."""
    truth = np.asarray(truth_xyz, dtype=np.float64).reshape(len(cloud), 3)
    ok = np.isfinite(truth).all(axis=1)
    err = np.linalg.norm(sim3.apply(cloud.xyz[ok].astype(np.float64)) - truth[ok], axis=1)
    out: dict[str, object] = {'n_points': int(len(cloud)), 'n_scored': int(ok.sum()),
                              'tolerance_m': tolerance_m}
    if not ok.any():
        out.update(median_m=None, p90_m=None, within_tolerance=None)
        return out
    out.update(median_m=float(np.median(err)), p90_m=float(np.percentile(err, 90)),
               within_tolerance=float(np.mean(err <= tolerance_m)))
    return out


def _first_surface(P: np.ndarray, s: np.ndarray, view: DepthView) -> np.ndarray | None:
    """Where the ray samples ``P`` (S, 3) m, at ranges ``s`` (S,) m from their origin, first
    pass behind ``view``'s rendered range (linear interpolation); None when they never do or
    the crossing is at a range discontinuity of the view."""
    rendered, dist = _rendered_range(P, view)
    f = rendered - dist  # > 0: the sample is in front of the surface
    f[~np.isfinite(f)] = np.nan
    with np.errstate(invalid='ignore'):
        cross = np.flatnonzero((f[:-1] > 0) & (f[1:] <= 0))
    if not len(cross):
        return None
    k = int(cross[0])
    step = s[k + 1] - s[k]
    if f[k] - f[k + 1] > 2.0 * step + 0.3:  # the rendered range jumped: an occluding edge
        return None
    a = f[k] / (f[k] - f[k + 1])
    return P[k] + a * (P[k + 1] - P[k])


@dataclass(frozen=True)
class DepthView:
    """A ground-truth range image: ``depth`` (H, W) m along the ray (inf/NaN: none), the
    camera pose ``T_map_cam`` (4, 4) optical -> map (m), the ``camera`` model it was
    rendered with and its stamp (ns; -1: unknown)."""

    depth: np.ndarray
    T_map_cam: np.ndarray
    camera: object
    stamp_ns: int = -1


def _rendered_range(pts: np.ndarray, view: DepthView) -> tuple[np.ndarray, np.ndarray]:
    """``(rendered range, range)`` (N,) m of map points ``pts`` (N, 3) in ``view``: the range
    image at the nearest pixel each projects to (NaN outside the image or field of view) and
    the point's own distance from the camera."""
    T_cm = np.linalg.inv(view.T_map_cam)
    pc = pts @ T_cm[:3, :3].T + T_cm[:3, 3]
    uv, ok = view.camera.project(pc)
    h, w = view.depth.shape
    ui, vi = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    ok &= (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    rendered = np.full(len(pts), np.nan)
    rendered[ok] = view.depth[vi[ok], ui[ok]]
    return rendered, np.linalg.norm(pc, axis=1)


def surface_errors(xyz: np.ndarray, views: Sequence[DepthView]) -> np.ndarray:
    """(N,) smallest |range - rendered range| (m) of points ``xyz`` (N, 3) (ground-truth map
    frame) over the views they project into; NaN for a point no view sees."""
    pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    best = np.full(len(pts), np.inf)
    for v in views:
        d, dist = _rendered_range(pts, v)
        ok = np.isfinite(d)
        err = np.abs(dist[ok] - d[ok])
        best[ok] = np.minimum(best[ok], err)
    best[~np.isfinite(best)] = np.nan
    return best


def surface_accuracy(cloud: SemanticCloud, sim3: Similarity, views: Sequence[DepthView],
                     tolerance_m: float = 0.5) -> dict[str, object]:
    """Share of map points (aligned by ``sim3``) on the rendered surfaces (see the module
    doc): ``n_seen`` points inside some view, ``on_surface`` the fraction of them within
    ``tolerance_m``, ``median_error_m`` their median error."""
    err = surface_errors(sim3.apply(cloud.xyz.astype(np.float64)), views)
    seen = np.isfinite(err)
    return {'n_points': int(len(err)), 'n_views': len(views), 'n_seen': int(seen.sum()),
            'tolerance_m': tolerance_m,
            'on_surface': float(np.mean(err[seen] <= tolerance_m)) if seen.any() else None,
            'median_error_m': float(np.median(err[seen])) if seen.any() else None}


def timing_stats(values_ms: Sequence[float]) -> dict[str, float | int | None]:
    """``{'n', 'mean', 'median', 'p95', 'max'}`` of durations (ms); None entries when empty."""
    v = np.asarray([x for x in values_ms if x is not None and np.isfinite(x)], dtype=np.float64)
    if len(v) == 0:
        return {'n': 0, 'mean': None, 'median': None, 'p95': None, 'max': None}
    return {'n': int(len(v)), 'mean': round(float(v.mean()), 3),
            'median': round(float(np.median(v)), 3),
            'p95': round(float(np.percentile(v, 95)), 3), 'max': round(float(v.max()), 3)}
