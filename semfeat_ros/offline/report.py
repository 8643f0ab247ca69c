"""Files of a mapping run: ``cloud.ply``, ``trajectory.tum``, ``metrics.json`` and figures.

``metrics.json`` holds the headline numbers at the top level (``null`` when not measurable, with
the reason in ``evaluation_error``) and the details in nested sections; see
:mod:`semfeat_ros.offline.metrics` for the definitions.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from semfeat_ros.labels import load_labels
from semfeat_ros.mapping import write_ply, write_tum
from semfeat_ros.offline import figures
from semfeat_ros.offline.errors import EvaluationError
from semfeat_ros.offline.mapping_run import FrameRecord, MapRun
from semfeat_ros.offline.metrics import (
    RAMP_PITCH_RAD,
    DepthView,
    TrajectoryEvaluation,
    anchor_points,
    evaluate_trajectory,
    floor_accuracy,
    gt_levels,
    max_altitude_step_m,
    pitch_of,
    point_errors,
    storey_of,
    surface_accuracy,
    timing_stats,
    travelled,
)
from semfeat_ros.offline.paths import confined

#: Output file names (inside --out).
FILES = {
    'cloud': 'cloud.ply',
    'trajectory': 'trajectory.tum',
    'trajectory_online': 'trajectory_online.tum',
    'metrics': 'metrics.json',
    'figure_trajectory': 'trajectory_top.png',
    'figure_altitude': 'altitude.png',
    'figure_cloud': 'cloud.png',
}

#: Keys always present at the top level of metrics.json.
HEADLINE_KEYS = (
    'ate_sim3_rmse_m', 'ate_se3_rmse_m', 'scale_sim3', 'ramp_altitude_rmse_sim3_m',
    'ramp_altitude_max_sim3_m', 'ramp_altitude_rmse_se3_m', 'ramp_altitude_max_se3_m',
    'floor_accuracy', 'dynamic_points', 'cloud_points', 'frames_read', 'frames_processed',
    'keyframes', 'keyframe_update_ms', 'frontend_ms', 'matcher_ms', 'track_length_frames',
)


def json_safe(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars to Python, NaN/inf to None."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.integer | np.bool_):
        return obj.item()
    if isinstance(obj, float | np.floating):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


def track_lengths(records: Sequence[FrameRecord]) -> list[float]:
    """Frames each track id was seen in, over the records' tracks (one value per track)."""
    ids = [np.asarray(r.track_ids, np.int64) for r in records if r.track_ids is not None]
    if not ids:
        return []
    return np.unique(np.concatenate(ids), return_counts=True)[1].astype(float).tolist()


def run_summary(run: MapRun) -> dict[str, Any]:
    """Counts and timings of a run (no ground truth needed)."""
    mapped = run.mapped
    kf = [r.result for r in mapped if r.result.keyframe]
    states = Counter(r.result.state for r in mapped)
    mapper = run.mapper
    cloud = mapper.cloud()
    labels = mapper.labels
    dyn = np.zeros(256, bool)
    dyn[:len(labels.names)] = labels.dynamic
    per_class = Counter(int(c) for c in cloud.label.tolist())
    feats = [r for r in run.records if r.n_features or r.frontend_ms]
    return {
        'frontend': run.frontend, 'frontend_description': run.frontend_description,
        'labels_source': run.labels_source, 'image_topic': run.image_topic,
        'odometry_used': run.used_odometry, 'gnss_used': run.used_gnss,
        'frames_read': run.counts.get('frames_read', 0), 'frames_processed': len(mapped),
        'keyframes': len(kf), 'final_state': mapped[-1].result.state if mapped else None,
        'metric_scale': bool(mapper.metric), 'gnss_aligned': bool(mapper.gnss_aligned),
        'map_in_enu': None if mapper.map_in_enu is None else mapper.map_in_enu.tolist(),
        'states': dict(states), 'counts': dict(run.counts),
        'cloud_points': len(cloud), 'dynamic_points': int(dyn[cloud.label].sum()),
        'cloud_per_class': {labels.names[c] if c < len(labels.names) else str(c): n
                            for c, n in sorted(per_class.items())},
        'cloud_per_floor': {str(k): int(v) for k, v in sorted(
            Counter(int(f) for f in cloud.floor.tolist()).items())},
        'keyframe_update_ms': timing_stats([r.update_ms for r in kf]),
        'frame_update_ms': timing_stats([r.result.update_ms for r in mapped]),
        'decode_ms': timing_stats([r.decode_ms for r in feats]),
        'frontend_ms': timing_stats([r.frontend_ms for r in feats]),
        'matcher_ms': timing_stats([r.matcher_ms for r in feats]),
        'features_per_frame': timing_stats([float(r.n_features) for r in feats]),
        'tracks_per_frame': timing_stats([float(r.n_tracks) for r in run.records]),
        'track_length_frames': timing_stats(track_lengths(run.records)),
        'mapper_stats': dict(mapper.stats), 'wall_s': round(run.wall_s, 3),
        'odometry_calibration': mapper.odometry_calibration,
    }


def evaluate_run(run: MapRun, gt_stamps: np.ndarray, gt_poses: np.ndarray,
                 depth_views: Sequence[DepthView] = ()
                 ) -> tuple[dict[str, Any], TrajectoryEvaluation | None]:
    """Trajectory and floor metrics of the run's keyframe trajectory against the ground truth.

    Returns ``(metrics, evaluation or None)``; when the trajectory cannot be evaluated the
    metrics are None and ``evaluation_error`` says why.
    """
    mapper = run.mapper
    stamps, poses = mapper.trajectory()
    levels_gt = gt_levels(gt_poses, mapper.conf)
    out: dict[str, Any] = {'gt_levels_m': [round(float(a), 3) for a in levels_gt.altitudes]}
    try:
        ev = evaluate_trajectory(stamps, poses, gt_stamps, gt_poses, metric=mapper.metric)
    except EvaluationError as exc:
        out['evaluation_error'] = str(exc)
        return out, None
    out['trajectory'] = ev.metrics
    online = online_trajectory(run)
    try:
        ev_online = evaluate_trajectory(*online, gt_stamps, gt_poses, metric=mapper.metric)
    except EvaluationError as exc:
        out['trajectory_online'] = {'evaluation_error': str(exc)}
    else:
        out['trajectory_online'] = {**ev_online.metrics,
                                    'max_altitude_step_m': max_altitude_step_m(online[1])}
    cloud = mapper.cloud()
    floor_args = (cloud, ev.sim3, mapper.floor_levels(), poses[:, :3, 3], levels_gt.altitudes)
    out['floors'] = aligned = floor_accuracy(*floor_args)
    if depth_views:
        truth = anchor_points(*mapper.landmark_anchors(cloud.landmark_id), run.camera,
                              (gt_stamps, gt_poses), mapper.T_bc, depth_views)
        out['floors'] = floor_accuracy(*floor_args, truth_xyz=truth)
        out['floors_aligned'] = aligned
        out['point_errors'] = point_errors(cloud, ev.sim3, truth)
        out['surfaces'] = surface_accuracy(cloud, ev.sim3, depth_views)
    return out, ev


def online_trajectory(run: MapRun) -> tuple[np.ndarray, np.ndarray]:
    """The per-frame estimates as they were returned (what mapping_node publishes on
    /semfeat/odometry): ``(stamps_ns (N,) int64, T_map_base (N, 4, 4))`` (m)."""
    online = [(r.stamp_ns, r.result.T_map_base) for r in run.mapped
              if r.result.T_map_base is not None]
    return (np.array([s for s, _ in online], np.int64),
            np.array([T for _, T in online], np.float64).reshape(-1, 4, 4))


def output_paths(out_dir: Path) -> dict[str, Path]:
    """The output files of :data:`FILES` inside ``out_dir`` (checked: none escapes it)."""
    return {k: confined(out_dir, v) for k, v in FILES.items()}


def write_map_outputs(run: MapRun, out_dir: Path, gt: tuple[np.ndarray, np.ndarray] | None,
                      bag: str, make_figures: bool = True,
                      extra: dict[str, Any] | None = None,
                      depth_views: Sequence[DepthView] = ()) -> dict[str, Any]:
    """Write the files of :data:`FILES` into ``out_dir``; returns the metrics written
    (``extra`` is added to metrics.json as it is, e.g. the configuration used).

    ``gt`` = ``(stamps_ns, T_map_base)`` of the ground truth (None: no metrics.json
    evaluation part, figures without ground truth are skipped).
    """
    mapper = run.mapper
    paths = output_paths(out_dir)
    cloud = mapper.cloud()
    write_ply(paths['cloud'], cloud)
    stamps, poses = mapper.trajectory()
    write_tum(paths['trajectory'], stamps, poses)
    write_tum(paths['trajectory_online'], *online_trajectory(run))
    summary = run_summary(run)
    metrics: dict[str, Any] = {'bag': bag}
    ev = None
    if gt is not None and len(gt[0]):
        ev_metrics, ev = evaluate_run(run, gt[0], gt[1], depth_views)
        metrics.update(ev_metrics)
    traj = metrics.get('trajectory', {})
    floors = metrics.get('floors', {})
    head = {
        **{k: traj.get(k) for k in HEADLINE_KEYS if k.startswith(('ate_', 'scale_', 'ramp_'))},
        'floor_accuracy': floors.get('accuracy'),
        'floor_accuracy_aligned': metrics.get('floors_aligned', {}).get('accuracy'),
        'cloud_point_error_median_m': metrics.get('point_errors', {}).get('median_m'),
        'cloud_on_surfaces': metrics.get('surfaces', {}).get('on_surface'),
        'dynamic_points': summary['dynamic_points'], 'cloud_points': summary['cloud_points'],
        'frames_read': summary['frames_read'], 'frames_processed': summary['frames_processed'],
        'keyframes': summary['keyframes'],
        'keyframe_update_ms': {k: summary['keyframe_update_ms'][k] for k in ('median', 'p95')},
        'frontend_ms': {k: summary['frontend_ms'][k] for k in ('median', 'p95')},
        'matcher_ms': {k: summary['matcher_ms'][k] for k in ('median', 'p95')},
        'track_length_frames': {k: summary['track_length_frames'][k]
                                for k in ('median', 'p95')},
    }
    result = {**head, 'has_ground_truth': gt is not None and len(gt[0]) > 0, **metrics,
              'run': summary, 'files': dict(FILES), **(extra or {})}
    if make_figures:
        result['figures'] = _figures(run, paths, gt, ev, floors.get('est_to_gt') or [])
    result['files'] = {k: v for k, v in FILES.items()
                       if k == 'metrics' or paths[k].is_file()}  # the files written
    with open(paths['metrics'], 'w', encoding='utf-8') as f:
        json.dump(json_safe(result), f, indent=2, sort_keys=False)
        f.write('\n')
    return json_safe(result)


def _figures(run: MapRun, paths: dict[str, Path], gt: tuple[np.ndarray, np.ndarray] | None,
             ev: TrajectoryEvaluation | None, est_to_gt: list[int]) -> list[str]:
    """The PNGs; keyframes are coloured by the mapper's own floor (translated to the
    ground-truth level index through ``est_to_gt``), the ground truth by its storey rule."""
    mapper = run.mapper
    labels = load_labels(mapper.conf['labels_path'])
    stamps, poses = mapper.trajectory()
    cloud = mapper.cloud()
    title = f'{run.frontend} front end, {len(stamps)} keyframes'
    made = []
    est_xyz = poses[:, :3, 3] if len(poses) else np.zeros((0, 3))
    cloud_xyz = cloud.xyz.astype(np.float64)
    if ev is not None:  # everything in the ground-truth frame
        est_xyz = ev.sim3.apply(est_xyz) if len(est_xyz) else est_xyz
        cloud_xyz = ev.sim3.apply(cloud_xyz) if len(cloud_xyz) else cloud_xyz
    if gt is not None and len(gt[0]):
        gt_xyz = gt[1][:, :3, 3]
        levels = gt_levels(gt[1], mapper.conf).altitudes
        gt_floor = storey_of(gt_xyz[:, 2], levels)
        est_floor = None
        if len(est_xyz) and est_to_gt:
            own = mapper.floor_levels().assign(poses[:, 2, 3]).astype(np.int64)
            est_floor = np.asarray(est_to_gt)[np.minimum(own, len(est_to_gt) - 1)]
        figures.plot_trajectory_top(paths['figure_trajectory'], gt_xyz, gt_floor,
                                    est_xyz if ev is not None else None, est_floor,
                                    f'{title}: Sim(3)-aligned estimate vs ground truth')
        made.append(paths['figure_trajectory'].name)
        gt_s = travelled(gt_xyz)
        ramp = np.abs(pitch_of(gt[1])) > RAMP_PITCH_RAD
        est_s = est_z = None
        if ev is not None:
            est_s = np.interp(stamps[ev.est_index].astype(np.float64),
                              gt[0].astype(np.float64), gt_s)
            est_z = ev.sim3.apply(ev.est[:, :3, 3])[:, 2]
        figures.plot_altitude(paths['figure_altitude'], gt_s, gt_xyz[:, 2], ramp, est_s, est_z,
                              f'{title}: altitude over distance', levels=levels.tolist())
        made.append(paths['figure_altitude'].name)
    frame = 'ground-truth frame' if ev is not None else 'map frame'
    figures.plot_cloud(paths['figure_cloud'], cloud_xyz, cloud.label, labels.colors,
                       labels.names, est_xyz, f'{title}: semantic cloud, {len(cloud)} points '
                       f'({frame})')
    made.append(paths['figure_cloud'].name)
    return made
