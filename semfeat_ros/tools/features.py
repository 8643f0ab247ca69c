"""``semfeat-features``: feature_node's front end over a recorded bag, offline (no DDS).

usage: semfeat-features BAG --out OUT [--frontend semfeat|xfeat|sift|orb] [--topic T]
                        [--weights W] [--config config/feature_node.yaml] [--max-frames N]
                        [--quiet]

Decodes every camera frame of BAG (raw ``Image`` or ``CompressedImage``), runs the same front
end as feature_node (:func:`~semfeat_ros.offline.frontends.make_frontend`, keypoints labelled
by the network's segmentation whatever the front end) with the node's parameters (read from
the node YAML; ``--frontend`` overrides its ``frontend``), and writes a new rosbag2 (MCAP) OUT
with ``/semfeat/features`` (PointCloud2, contract layout; ORB's bytes as float32 0..255),
``/semfeat/semantic_mask`` (mono8) -- input header stamps and frame ids -- and the
CameraInfo passed through. Errors (wrong path, broken bag, missing topic, missing weights) are
one line on stderr and a non-zero exit status.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
import sys

from semfeat_ros.nodes.feature_node import frontend_config
from semfeat_ros.offline.bag import BagSource, one_line
from semfeat_ros.offline.config import node_config, read_node_params
from semfeat_ros.offline.errors import OfflineConfigError, OfflineError
from semfeat_ros.offline.features_bag import (
    FeaturesBagConfig,
    check_new_output,
    summary_dict,
    write_features_bag,
)
from semfeat_ros.offline.frontends import FRONTEND_KINDS, make_frontend

PROG = 'semfeat-features'


@dataclass
class FeaturesToolConfig:
    """Options of ``semfeat-features`` (``config`` = feature_node parameter YAML)."""

    config: Path | None = None
    frontend: str | None = None  # None: the node parameter
    topic: str | None = None
    weights: str | None = None
    max_frames: int | None = None
    progress: bool = True


def main(conf: FeaturesToolConfig, bag: Path, out: Path) -> dict:
    """Write the features bag ``out`` for ``bag``; returns the summary (counts, timing)."""
    from semfeat_ros.nodes.feature_node import FeatureNodeConfig
    from semfeat_ros.paths import config_path

    path = conf.config if conf.config is not None else config_path('feature_node.yaml')
    params = node_config(FeatureNodeConfig, read_node_params(path, 'feature_node'), str(path))
    if conf.max_frames is not None and conf.max_frames < 1:
        raise OfflineConfigError(f'--max-frames must be >= 1, got {conf.max_frames}')
    if conf.frontend is not None and conf.frontend not in FRONTEND_KINDS:
        raise OfflineConfigError(
            f'--frontend: expected one of {", ".join(FRONTEND_KINDS)}, got {conf.frontend!r}')
    check_new_output(out)
    with BagSource(bag) as source:
        bag_conf = FeaturesBagConfig(
            image_topic=conf.topic, default_image_topic=params.image_topic,
            camera_info_topic=params.camera_info_topic, features_topic=params.features_topic,
            mask_topic=params.mask_topic, require_camera_info=params.require_camera_info,
            fov_deg=params.fov_deg, max_image_pixels=params.max_image_pixels,
            max_frames=conf.max_frames)
        source.image_topic(bag_conf.image_topic, bag_conf.default_image_topic)  # fail early
        frontend = make_frontend(conf.frontend or params.frontend,
                                 frontend_config(params, conf.weights), params.max_keypoints,
                                 network_labels=True)
        summary = write_features_bag(source, out, frontend, bag_conf, progress=conf.progress)
    return summary_dict(summary)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Run feature_node's front end over a bag (offline, no DDS) and "
        'write /semfeat/features, /semfeat/semantic_mask and the CameraInfo to a new bag.')
    p.add_argument('bag', type=Path, help='input rosbag2 directory or .mcap/.db3 file')
    p.add_argument('--out', type=Path, required=True, help='output bag directory (must not '
                   'exist)')
    p.add_argument('--frontend', choices=FRONTEND_KINDS, default=None,
                   help="default: the node's frontend parameter (semfeat: the network; xfeat, "
                   "sift, orb: their keypoints labelled by the network's segmentation)")
    p.add_argument('--topic', default=None, help='camera topic (Image or CompressedImage); '
                   "default: the node's image_topic or its /compressed, whichever is recorded")
    p.add_argument('--weights', default=None, help='network weights (.safetensors); default: '
                   'the node parameter, else the shipped weights')
    p.add_argument('--config', type=Path, default=None,
                   help='feature_node parameter YAML (default: config/feature_node.yaml)')
    p.add_argument('--max-frames', type=int, default=None, help='stop after N camera frames')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    conf = FeaturesToolConfig(config=args.config, frontend=args.frontend, topic=args.topic,
                              weights=args.weights, max_frames=args.max_frames,
                              progress=not args.quiet)
    try:
        s = main(conf, args.bag, args.out)
    except (OfflineError, ValueError, OSError) as exc:  # incl. missing / unreadable weights
        print(f'{PROG}: error: {one_line(exc)}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    print(f'{PROG}: wrote {s["out"]}: {s["frames_written"]} of {s["frames_read"]} frames '
          f'({s["frames_rejected"]} rejected), {s["keypoints_per_frame"]:.0f} keypoints/frame, '
          f'front end median {s["frontend_ms"]["median"]} ms, {s["camera_infos"]} CameraInfo '
          f'passed through')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
