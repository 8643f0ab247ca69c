"""``semfeat-map``: features -> matcher -> mapper over a recorded bag, offline (no DDS).

usage: semfeat-map BAG --out DIR [--frontend semfeat|xfeat|sift|orb] [--matcher mnn|learned]
                   [--weights W] [--no-odometry]
                   [--no-gnss] [--tracks-topic T] [--topic T] [--max-frames N] [--start S]
                   [--labels auto|network|groundtruth|none] [--set KEY=VALUE ...]
                   [--feature-config Y] [--matcher-config Y] [--mapping-config Y]
                   [--camera-config Y] [--no-figures] [--quiet]

The same cores as feature_node, matcher_node and mapping_node, configured from the nodes'
parameter YAML files (``config/<node>.yaml``), so an offline run and a live run on the same bag
agree. ``--frontend`` (default: feature_node's ``frontend`` parameter) and ``--matcher``
(default: matcher_node's ``matcher``) choose as the nodes' parameters do: ``xfeat`` (XFeat),
``sift`` or ``orb`` (OpenCV; ORB through the matcher's binary mode) replace the network's
keypoints and descriptors (1000 a frame), labelled by the network's segmentation when its
weights are found, else by the bag's ground-truth class masks when recorded (``--labels``);
``--matcher learned`` runs SemfeatGlue (semfeat) or LighterGlue (xfeat). ``--tracks-topic``
maps recorded ``/semfeat/tracks`` (e.g. of a live run) instead. Writes into DIR: ``cloud.ply``,
``trajectory.tum`` (keyframes), ``trajectory_online.tum`` (every mapped frame, as published
live), ``metrics.json`` (with ground-truth metrics when the bag has ``/ground_truth/pose``) and
the figures ``trajectory_top.png``, ``altitude.png``, ``cloud.png``. Every file stays inside DIR.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
import sys
from typing import Any

from semfeat_ros.nodes.feature_node import frontend_config
from semfeat_ros.offline.bag import BagSource, one_line, read_depth_views, read_poses
from semfeat_ros.offline.config import (
    node_config,
    parse_overrides,
    read_node_params,
)
from semfeat_ros.offline.errors import NoFramesError, OfflineConfigError, OfflineError
from semfeat_ros.offline.frontends import FRONTEND_KINDS, OPENCV_BEARING_SIGMA_PX, OPENCV_KINDS
from semfeat_ros.offline.mapping_run import LABEL_SOURCES, MapConfig, Topics, run_mapping
from semfeat_ros.offline.paths import prepare_out_dir
from semfeat_ros.offline.report import output_paths, write_map_outputs

PROG = 'semfeat-map'
FRONTENDS = FRONTEND_KINDS


@dataclass
class MapToolConfig:
    """Options of ``semfeat-map`` (config paths None = the shipped ``config/`` files)."""

    frontend: str | None = None  # None: feature_node's frontend parameter
    matcher: str | None = None  # None: matcher_node's matcher parameter
    weights: str | None = None
    use_odometry: bool = True
    use_gnss: bool = True
    tracks_topic: str | None = None
    topic: str | None = None
    max_frames: int | None = None
    start_s: float = 0.0
    labels: str = 'auto'
    overrides: dict[str, Any] = field(default_factory=dict)
    feature_config: Path | None = None
    matcher_config: Path | None = None
    mapping_config: Path | None = None
    camera_config: Path | None = None
    figures: bool = True
    progress: bool = True


def _shipped(name: str) -> Path | None:
    from semfeat_ros.paths import share_dir

    p = share_dir() / 'config' / name
    return p if p.is_file() else None


def build_map_config(conf: MapToolConfig) -> tuple[MapConfig, list[str]]:
    """The :class:`MapConfig` of the tool options and the node YAML files; also returns notes
    (e.g. which files were read) for the log."""
    from semfeat_ros.camera import load_camera_yaml
    from semfeat_ros.mapping import default_conf
    from semfeat_ros.matching.sequential import MATCH_METHODS
    from semfeat_ros.nodes.feature_node import FeatureNodeConfig
    from semfeat_ros.nodes.mapping_node import MappingNodeConfig, session_conf
    from semfeat_ros.nodes.mapping_node import mapper_conf as mapping_conf
    from semfeat_ros.nodes.matcher_node import MatcherNodeConfig, matcher_conf

    if conf.frontend is not None and conf.frontend not in FRONTENDS:
        raise OfflineConfigError(
            f'--frontend: expected one of {", ".join(FRONTENDS)}, got {conf.frontend!r}')
    if conf.matcher is not None and conf.matcher not in MATCH_METHODS:
        raise OfflineConfigError(
            f'--matcher: expected one of {", ".join(MATCH_METHODS)}, got {conf.matcher!r}')
    if conf.labels not in LABEL_SOURCES:
        raise OfflineConfigError(
            f'--labels: expected one of {", ".join(LABEL_SOURCES)}, got {conf.labels!r}')
    if conf.max_frames is not None and conf.max_frames < 1:
        raise OfflineConfigError(f'--max-frames must be >= 1, got {conf.max_frames}')
    if not conf.start_s >= 0:
        raise OfflineConfigError(f'--start must be >= 0 s, got {conf.start_s}')
    notes = []
    fpath = conf.feature_config or _shipped('feature_node.yaml')
    fparams = (node_config(FeatureNodeConfig, read_node_params(fpath, 'feature_node'),
                           str(fpath)) if fpath else FeatureNodeConfig())
    mpath = conf.matcher_config or _shipped('matcher_node.yaml')
    mparams = (node_config(MatcherNodeConfig, read_node_params(mpath, 'matcher_node'),
                           str(mpath)) if mpath else MatcherNodeConfig())
    notes.append(f'feature_node parameters: {fpath or "defaults"}; matcher_node parameters: '
                 f'{mpath or "defaults"}')
    frontend = conf.frontend or fparams.frontend
    matcher = conf.matcher or mparams.matcher
    gpath = conf.mapping_config or _shipped('mapping_node.yaml')
    gparams = (node_config(MappingNodeConfig, read_node_params(gpath, 'mapping_node'),
                           str(gpath)) if gpath else MappingNodeConfig())
    notes.append(f'mapping_node parameters: {gpath or "defaults"}')
    mapper_conf = mapping_conf(gparams)
    if frontend in OPENCV_KINDS:  # --set bearing_sigma_px=... below still wins
        mapper_conf['bearing_sigma_px'] = OPENCV_BEARING_SIGMA_PX
        notes.append(f'{frontend}: bearing_sigma_px {OPENCV_BEARING_SIGMA_PX} px (OpenCV '
                     'keypoints)')
    for key, value in conf.overrides.items():
        if key not in default_conf:
            raise OfflineConfigError(f'--set {key}: not a mapping config key')
        mapper_conf[key] = value
    camera_yaml = conf.camera_config or (gparams.camera_config or None)
    try:
        _, extrinsic = load_camera_yaml(camera_yaml)
    except (OSError, ValueError) as exc:
        raise OfflineConfigError(f'camera calibration: {one_line(exc)}') from exc
    topics = Topics(image=conf.topic, image_default=fparams.image_topic,
                    camera_info=fparams.camera_info_topic, odometry=gparams.odom_topic,
                    gnss=gparams.gnss_topic)
    mc = MapConfig(
        T_base_cam=extrinsic.T_base_cam, frontend=frontend,
        frontend_conf=frontend_config(fparams, conf.weights), labels=conf.labels,
        matcher_conf=matcher_conf(mparams, frontend, matcher), mapper_conf=mapper_conf,
        session_conf=session_conf(gparams),
        use_odometry=conf.use_odometry and gparams.use_odometry,
        use_gnss=conf.use_gnss and gparams.use_gnss, tracks_topic=conf.tracks_topic,
        fov_deg=fparams.fov_deg,
        max_image_pixels=fparams.max_image_pixels, max_frames=conf.max_frames,
        start_s=conf.start_s, topics=topics)
    return mc, notes


def main(conf: MapToolConfig, bag: Path, out: Path) -> dict[str, Any]:
    """Map ``bag`` into the directory ``out``; returns the metrics written to metrics.json."""
    from semfeat_ros.mapping import merge_conf

    mc, notes = build_map_config(conf)
    merge_conf({**mc.mapper_conf, 'use_odometry': mc.use_odometry,
                'use_gnss': mc.use_gnss})  # validate before reading the bag
    with BagSource(bag) as source:
        out_dir = prepare_out_dir(out)
        output_paths(out_dir)  # fail before the long run if an output would escape --out
        run = run_mapping(source, mc, progress=conf.progress)
        read, rejected = run.counts['frames_read'], run.counts['frames_rejected']
        if read and rejected == read:
            raise NoFramesError(f'no frame of the bag could be processed: all {read} read were '
                                'rejected (undecodable images or a size that does not match '
                                'the CameraInfo)')
        gt = read_poses(source, mc.topics.ground_truth)
        views = read_depth_views(source, mc.topics.gt_depth, gt, mc.T_base_cam, run.camera)
    config = {'frontend': mc.frontend, 'matcher': mc.matcher_conf['matching']['method'],
              'labels': conf.labels, 'use_odometry': mc.use_odometry,
              'use_gnss': mc.use_gnss, 'max_frames': conf.max_frames, 'start_s': conf.start_s,
              'tracks_topic': conf.tracks_topic, 'mapper_overrides': mc.mapper_conf,
              'matcher_conf': mc.matcher_conf, 'sources': notes}
    return write_map_outputs(run, out_dir, gt if len(gt[0]) else None, str(bag),
                             make_figures=conf.figures, extra={'config': config},
                             depth_views=views)


def _fmt(v: Any, unit: str = '') -> str:
    if v is None:
        return 'n/a'
    if isinstance(v, float):
        return f'{v:.3f}{unit}'
    return f'{v}{unit}'


def format_table(m: dict[str, Any]) -> str:
    """A short human-readable table of the headline metrics."""
    rows = [
        ('frames processed / read', f'{m["frames_processed"]} / {m["frames_read"]}'),
        ('keyframes', _fmt(m['keyframes'])),
        ('ATE RMSE Sim(3)', _fmt(m.get('ate_sim3_rmse_m'), ' m')),
        ('ATE RMSE SE(3)', _fmt(m.get('ate_se3_rmse_m'), ' m')),
        ('scale (Sim(3))', _fmt(m.get('scale_sim3'))),
        ('ramp altitude RMSE / max (Sim(3))',
         f'{_fmt(m.get("ramp_altitude_rmse_sim3_m"), " m")} / '
         f'{_fmt(m.get("ramp_altitude_max_sim3_m"), " m")}'),
        ('per-frame estimates: ATE Sim(3) / max altitude step',
         f'{_fmt(m.get("trajectory_online", {}).get("ate_sim3_rmse_m"), " m")} / '
         f'{_fmt(m.get("trajectory_online", {}).get("max_altitude_step_m"), " m")}'),
        ('floor accuracy (true / aligned positions)',
         f'{_fmt(m.get("floor_accuracy"))} / {_fmt(m.get("floor_accuracy_aligned"))}'),
        ('cloud point error median (true positions)',
         _fmt(m.get('cloud_point_error_median_m'), ' m')),
        ('cloud points on rendered surfaces (0.5 m)', _fmt(m.get('cloud_on_surfaces'))),
        ('cloud points (dynamic)', f'{m["cloud_points"]} ({m["dynamic_points"]})'),
        ('keyframe update median / p95', f'{_fmt(m["keyframe_update_ms"]["median"], " ms")} / '
         f'{_fmt(m["keyframe_update_ms"]["p95"], " ms")}'),
        ('front end median / p95', f'{_fmt(m["frontend_ms"]["median"], " ms")} / '
         f'{_fmt(m["frontend_ms"]["p95"], " ms")}'),
        ('matcher median / p95', f'{_fmt(m["matcher_ms"]["median"], " ms")} / '
         f'{_fmt(m["matcher_ms"]["p95"], " ms")}'),
    ]
    width = max(len(k) for k, _ in rows)
    return '\n'.join(f'  {k:<{width}}  {v}' for k, v in rows)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Map a bag offline with the nodes' cores (front end, matcher, "
        'mapper) and evaluate against its ground truth.')
    p.add_argument('bag', type=Path, help='input rosbag2 directory or .mcap/.db3 file')
    p.add_argument('--out', type=Path, required=True, help='output directory (created)')
    p.add_argument('--frontend', choices=FRONTENDS, default=None,
                   help="default: feature_node's frontend parameter. semfeat: the network; "
                        'xfeat: XFeat; sift / orb: OpenCV baselines (the mapper then assumes '
                        '1 px keypoint noise); xfeat, sift and orb keypoints are labelled as '
                        '--labels says')
    p.add_argument('--matcher', choices=('mnn', 'learned'), default=None,
                   help="default: matcher_node's matcher parameter. mnn: mutual nearest "
                        'neighbour; learned: SemfeatGlue (--frontend semfeat) or LighterGlue '
                        '(--frontend xfeat)')
    p.add_argument('--weights', default=None, help='network weights (.safetensors)')
    p.add_argument('--no-odometry', action='store_true', help='ignore wheel odometry')
    p.add_argument('--no-gnss', action='store_true', help='ignore GNSS fixes')
    p.add_argument('--tracks-topic', default=None,
                   help='map recorded tracks (e.g. /semfeat/tracks) instead of camera frames')
    p.add_argument('--topic', default=None, help="camera topic (default: feature_node's "
                   'image_topic or its /compressed)')
    p.add_argument('--max-frames', type=int, default=None, help='stop after N frames')
    p.add_argument('--start', type=float, default=0.0, metavar='S',
                   help='skip the first S seconds of the recording')
    p.add_argument('--labels', choices=LABEL_SOURCES, default='auto',
                   help='labels of xfeat / sift / orb keypoints: network (its segmentation, '
                   "as feature_node), groundtruth (the bag's class masks), none, or auto: the "
                   'network when its weights are found, else the ground truth when recorded')
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='override a mapping config key (YAML value), e.g. '
                   'gnss_lever_arm_m=[1.2,0,1.5]')
    p.add_argument('--feature-config', type=Path, default=None)
    p.add_argument('--matcher-config', type=Path, default=None)
    p.add_argument('--mapping-config', type=Path, default=None)
    p.add_argument('--camera-config', type=Path, default=None,
                   help='calibration YAML with the base_link -> camera extrinsic '
                   '(default: config/camera_front.yaml)')
    p.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        conf = MapToolConfig(
            frontend=args.frontend, matcher=args.matcher, weights=args.weights,
            use_odometry=not args.no_odometry, use_gnss=not args.no_gnss,
            tracks_topic=args.tracks_topic, topic=args.topic,
            max_frames=args.max_frames, start_s=args.start, labels=args.labels,
            overrides=parse_overrides(args.set), feature_config=args.feature_config,
            matcher_config=args.matcher_config, mapping_config=args.mapping_config,
            camera_config=args.camera_config, figures=not args.no_figures,
            progress=not args.quiet)
        metrics = main(conf, args.bag, args.out)
    except (OfflineError, ValueError, OSError) as exc:  # incl. missing / unreadable weights
        print(f'{PROG}: error: {one_line(exc)}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    print(f'{PROG}: {metrics["run"]["frontend_description"]}; wrote '
          f'{", ".join(metrics["files"].values())} to {args.out}')
    if metrics.get('evaluation_error'):
        print(f'{PROG}: not evaluated: {metrics["evaluation_error"]}')
    print(format_table(metrics))
    return 0


if __name__ == '__main__':
    sys.exit(cli())
