"""What the demo writes after the live run: metrics against ground truth, figures, summary."""
from __future__ import annotations

from pathlib import Path
import re
from typing import Any

import cv2
import numpy as np

from msg_adapters import (
    odometry_to_numpy,
    path_to_numpy,
    pose_stamped_to_numpy,
    semantic_cloud_from_msg,
    to_rgb_or_mono,
)
from semfeat_ros.labels import load_labels
from semfeat_ros.offline.bag import BagSource, read_depth_views
from semfeat_ros.offline.errors import EvaluationError
from semfeat_ros.offline.figures import plot_altitude, plot_trajectory_top
from semfeat_ros.offline.metrics import (
    RAMP_PITCH_RAD,
    evaluate_trajectory,
    gt_levels,
    max_altitude_step_m,
    pitch_of,
    surface_accuracy,
    travelled,
)


def read_outputs(bag: Path) -> dict[str, Any]:
    """Estimated poses (odometry), the last keyframe path and cloud, and the message counts of
    the recorded output bag."""
    stamps, poses, counts, cloud, path = [], [], {}, None, None
    with BagSource(bag) as src:
        topics = [t for t in ('/semfeat/odometry', '/semantic_cloud', '/semfeat/tracks',
                              '/semfeat/path', '/diagnostics') if src.has(t)]
        for m in src.messages(topics):
            counts[m.topic] = counts.get(m.topic, 0) + 1
            if m.topic == '/semfeat/odometry':
                s = odometry_to_numpy(m.msg)
                stamps.append(s.stamp_ns)
                poses.append(s.T)
            elif m.topic == '/semantic_cloud':
                cloud = m.msg
            elif m.topic == '/semfeat/path':
                path = m.msg
    return {'stamps': np.array(stamps, np.int64), 'poses': np.array(poses).reshape(-1, 4, 4),
            'counts': counts, 'cloud': semantic_cloud_from_msg(cloud) if cloud else None,
            'path': path_to_numpy(path) if path else None}


def _read_ground_truth(bag: Path) -> tuple[np.ndarray, np.ndarray, list[Any]]:
    """Ground-truth base poses and the compressed camera frames of the input bag."""
    stamps, poses, frames = [], [], []
    with BagSource(bag) as src:
        camera = next((t for t in ('/camera/front/image_raw/compressed',
                                   '/camera/front/image_raw') if src.has(t)), None)
        topics = [t for t in ('/ground_truth/pose', camera) if t and src.has(t)]
        for m in src.messages(topics):
            if m.topic == '/ground_truth/pose':
                s, _, T = pose_stamped_to_numpy(m.msg)
                stamps.append(s)
                poses.append(T)
            elif m.topic.startswith('/camera/front/image_raw'):
                frames.append(m.msg)
    return np.array(stamps, np.int64), np.array(poses).reshape(-1, 4, 4), frames


def cloud_on_surfaces(bag: Path, cloud: Any, sim3: Any, gt: tuple[np.ndarray, np.ndarray]
              ) -> dict[str, Any] | None:
    """Share of the live cloud's points (aligned by the live trajectory's ``sim3``) within
    0.5 m of the bag's rendered range images; None when the bag has none."""
    from semfeat_ros.camera import load_camera_yaml
    from semfeat_ros.offline.mapping_run import MapConfig, read_cameras

    _, ext = load_camera_yaml()
    conf = MapConfig(T_base_cam=ext.T_base_cam)
    with BagSource(bag) as src:
        if not src.has(conf.topics.gt_depth) or not src.has(conf.topics.camera_info):
            return None
        camera = read_cameras(src, conf.topics.camera_info, conf.fov_deg).models[0]
        views = read_depth_views(src, conf.topics.gt_depth, gt, ext.T_base_cam, camera)
    return surface_accuracy(cloud, sim3, views) if views else None


def _sample_figures(frames: list[Any], out: Path) -> dict[str, str]:
    """A frame with keypoints and semantic overlay, and a match view of two consecutive frames,
    computed with the same front end and matcher as the nodes."""
    from semfeat_ros.camera import load_camera_yaml
    from semfeat_ros.frontend import SemanticFrontend
    from semfeat_ros.matching.draw import draw_track_result
    from semfeat_ros.matching.sequential import SequentialMatcher
    from semfeat_ros.pipeline import frame_features

    if len(frames) < 2:
        return {}
    labels = load_labels()
    frontend = SemanticFrontend()
    k = len(frames) // 2
    images = [to_rgb_or_mono(frames[i]) for i in (k, k + 1)]
    h, w = images[0].shape[:2]
    camera = load_camera_yaml()[0].scaled(w, h)
    results = [frontend.process(img, camera) for img in images]
    view = results[0].overlay(images[0], labels)
    for u, v in results[0].features.keypoints:
        cv2.circle(view, (int(round(u)), int(round(v))), 2, (255, 255, 0), -1, cv2.LINE_AA)
    files = {'sample_frame': str(out / 'sample_frame.png')}
    cv2.imwrite(files['sample_frame'], cv2.cvtColor(view, cv2.COLOR_RGB2BGR))
    matcher = SequentialMatcher()
    track = None
    for i, res in enumerate(results):
        f = res.features
        track = matcher.process(frame_features(i * 100_000_000 + 1, f.keypoints, f.descriptors,
                                               f.labels, f.scores, camera))
    match_view = draw_track_result(track, images[0], images[1])
    files['matches'] = str(out / 'matches.png')
    cv2.imwrite(files['matches'], cv2.cvtColor(match_view, cv2.COLOR_RGB2BGR))
    return files


LEVEL_KEY = re.compile(r'light_frames_(\d+)px')
"""feature_node's /diagnostics key of the frames at one light level (its input size, px)."""


def _diag_value(diag: dict[str, dict[str, str]], node: str, key: str) -> float | None:
    try:
        return float(diag[node][key])
    except (KeyError, ValueError):
        return None


def write_report(bag: Path, out: Path, run: dict[str, Any]) -> dict[str, Any]:
    """Evaluate the recorded run, write figures into ``out``, print and return the summary."""
    outputs = read_outputs(out / 'output_bag')
    gt_stamps, gt_poses, frames = _read_ground_truth(bag)
    summary: dict[str, Any] = {'bag': str(bag), 'wall_time_s': round(run['wall_s'], 1),
                               'startup_s': round(run['startup_s'], 1),
                               'exit_codes': run['exit_codes'], 'save_map': run['save_map'],
                               'recorded_messages': outputs['counts'],
                               'node_params': run.get('node_params', {})}
    diag = run['diagnostics']
    nodes = {}
    for node in ('feature_node', 'matcher_node', 'mapping_node'):
        nodes[node] = {k: _diag_value(diag, node, k) for k in (
            'frames_received', 'frames_processed', 'frames_dropped', 'errors_rejected',
            'latency_p50_s', 'latency_p95_s', 'compute_p50_s', 'compute_p95_s')}
        per_level = [k for k in diag.get(node, {}) if LEVEL_KEY.fullmatch(k)]  # node's order
        for k in ('queued_p50_s', 'queued_p95_s', 'light_frames', *per_level):
            if (v := _diag_value(diag, node, k)) is not None:  # feature_node's own
                nodes[node][k] = v
    summary['nodes'] = nodes
    files: dict[str, str] = {}
    ev = None
    if len(gt_stamps) and len(outputs['stamps']) >= 3:
        try:
            ev = evaluate_trajectory(outputs['stamps'], outputs['poses'], gt_stamps, gt_poses,
                                     metric=True)
            summary['trajectory'] = {**ev.metrics,
                                     'max_altitude_step_m': max_altitude_step_m(ev.est)}
            levels = gt_levels(gt_poses)
            gt_xyz = gt_poses[:, :3, 3]
            est_xyz = ev.sim3.apply(ev.est[:, :3, 3])
            gt_floor = levels.assign(gt_xyz[:, 2]) if len(levels.altitudes) else np.zeros(
                len(gt_xyz), int)
            est_floor = levels.assign(est_xyz[:, 2]) if len(levels.altitudes) else None
            files['trajectory'] = str(plot_trajectory_top(
                out / 'trajectory.png', gt_xyz, gt_floor, est_xyz, est_floor,
                'semfeat_ros live pipeline vs ground truth (Sim(3) aligned)'))
            gt_s = travelled(gt_xyz)
            est_s = np.interp(ev.est_index, np.arange(len(ev.est_index)),
                              travelled(ev.gt[:, :3, 3]))
            ramp_gt = np.abs(pitch_of(gt_poses)) > RAMP_PITCH_RAD
            files['altitude'] = str(plot_altitude(
                out / 'altitude.png', gt_s, gt_xyz[:, 2], ramp_gt, est_s, est_xyz[:, 2],
                'Altitude over distance (live pipeline)', levels.altitudes,
                est_label='/semfeat/odometry (every mapped frame, Sim(3) aligned)'))
        except EvaluationError as exc:
            summary['trajectory'] = {'error': str(exc)}
    path_ev = None
    if len(gt_stamps) and outputs['path'] is not None and len(outputs['path'][0]) >= 3:
        try:
            path_ev = evaluate_trajectory(*outputs['path'], gt_stamps, gt_poses, metric=True)
            summary['keyframe_path'] = path_ev.metrics
        except EvaluationError as exc:
            summary['keyframe_path'] = {'error': str(exc)}
    cloud = outputs['cloud']
    if cloud is not None:
        labels = load_labels()
        summary['cloud'] = {
            'points': int(len(cloud.xyz)), 'floors': int(len(np.unique(cloud.floors))),
            'dynamic_points': int(labels.dynamic[cloud.labels].sum()),
            'classes': {labels.names[c]: int(n) for c, n in zip(
                *np.unique(cloud.labels, return_counts=True))}}
        if path_ev is not None and len(cloud.xyz):  # the cloud and the path: one estimate
            summary['cloud']['surfaces'] = cloud_on_surfaces(bag, cloud, path_ev.sim3,
                                                             (gt_stamps, gt_poses))
    files.update(_sample_figures(frames, out))
    summary['files'] = files
    _print(summary)
    return summary


def _levels(v: dict[str, Any]) -> str:
    """`` (512 px: 20, 448 px: 168)``: feature_node's frames at each light level."""
    levels = [f'{m[1]} px: {n:.0f}' for k, n in v.items() if (m := LEVEL_KEY.fullmatch(k))]
    return f' ({", ".join(levels)})' if levels else ''


def _print(s: dict[str, Any]) -> None:
    def ms(x: float | None) -> str:
        return 'n/a' if x is None or not np.isfinite(x) else f'{1000 * x:.0f} ms'

    print('\nsemfeat_ros demo summary')
    for node, params in (s.get('node_params') or {}).items():
        print(f'  {node:13s} ' + ', '.join(f'{k}:={v}' for k, v in params.items()))
    for node, v in s['nodes'].items():
        print(f'  {node:13s} frames {v["frames_processed"] or 0:.0f}/'
              f'{v["frames_received"] or 0:.0f} processed, {v["frames_dropped"] or 0:.0f} '
              f'dropped, {v["errors_rejected"] or 0:.0f} rejected; latency p50 '
              f'{ms(v["latency_p50_s"])} p95 {ms(v["latency_p95_s"])}' + (
                  f'; queued p95 {ms(v["queued_p95_s"])}, {v["light_frames"]:.0f} light frames'
                  + _levels(v) if 'queued_p95_s' in v and 'light_frames' in v else ''))
    t = s.get('trajectory', {})
    if 'ate_sim3_rmse_m' in t:
        se3 = t.get('ate_se3_rmse_m')
        print(f'  odometry      ATE RMSE {t["ate_sim3_rmse_m"]:.3f} m (Sim(3)), '
              f'{se3:.3f} m (SE(3), metric), scale {t["scale_sim3"]:.3f}, '
              f'{t["gt_length_m"]:.0f} m driven' if se3 is not None else
              f'  odometry      ATE RMSE {t["ate_sim3_rmse_m"]:.3f} m (Sim(3))')
        ramp = t.get('ramp_altitude_rmse_sim3_m')
        print('                ramp altitude RMSE '
              + ('n/a' if ramp is None else f'{ramp:.3f} m (Sim(3))')
              + f', largest altitude step between estimates {t["max_altitude_step_m"]:.3f} m')
    elif t:
        print(f'  trajectory    {t.get("error")}')
    else:
        print('  trajectory    no pose estimates: the mapper did not initialise on this run')
    k = s.get('keyframe_path', {})
    if 'ate_sim3_rmse_m' in k:
        print(f'  keyframes     ATE RMSE {k["ate_sim3_rmse_m"]:.3f} m (Sim(3)) of the final '
              f'/semfeat/path ({k["n_poses"]} keyframes, smoothed)')
    c = s.get('cloud')
    if c:
        sf = c.get('surfaces') or {}
        on = sf.get('on_surface')
        print(f'  map           {c["points"]} points, {c["floors"]} floors, '
              f'{c["dynamic_points"]} dynamic'
              + (f', {100 * on:.0f} % within {sf["tolerance_m"]} m of the rendered surfaces'
                 if on is not None else ''))
    else:
        print('  map           no /semantic_cloud was published (no keyframes)')
    print(f'  wall time     {s["wall_time_s"]:.0f} s; files: '
          + ', '.join(Path(p).name for p in s['files'].values()))
