"""``semfeat-eval``: feature-matching evaluation (the paper's Table 1 protocol and more).

Modes (subcommands)::

    semfeat-eval transforms (--images DIR | --bag BAG [--topic T]) --pairs N --seed S --out DIR
    semfeat-eval homography --dataset DIR --out DIR
    semfeat-eval sequence (--bag BAG | --shard NPZ) --stride K --out DIR
    semfeat-eval sequence --images DIR [--camera-xml XML | --pinhole fx,fy,cx,cy] --out DIR

Each writes results.json, results.md (Table 1 layout + extra columns), bar charts and match
figures into ``--out``. Metrics are defined in docs/METRICS.md. Bad input gives one line on
stderr and exit status 1 (2 for a bad command line).
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
import sys

import yaml

from semfeat_ros.evaluation.errors import EvalError
from semfeat_ros.evaluation.methods import method_names
from semfeat_ros.evaluation.pipeline import DEFAULT_METHODS, EvalConf
from semfeat_ros.evaluation.transforms import TransformConf
from semfeat_ros.tools.cli import OneLineParser, error_line

PROG = 'semfeat-eval'


def _methods(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(',') if n.strip())
    known = method_names()
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f'unknown method(s) {", ".join(unknown) or "(none given)"}; known: '
            + ', '.join(known))
    return names


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a number, got {text!r}') from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f'expected a value > 0, got {text}')
    return v


def _pinhole(text: str) -> tuple[float, float, float, float]:
    try:
        vals = tuple(float(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected fx,fy,cx,cy (px), got {text!r}') from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals) or min(vals[:2]) <= 0:
        raise argparse.ArgumentTypeError(
            f'expected four finite numbers fx,fy,cx,cy (px) with fx, fy > 0, got {text!r}')
    return vals


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    g = common.add_argument_group('common options')
    g.add_argument('--out', type=Path, required=True, help='output folder (created)')
    g.add_argument('--methods', type=_methods, default=DEFAULT_METHODS,
                   help='comma-separated methods (default: all: ' + ','.join(DEFAULT_METHODS)
                   + ')')
    g.add_argument('--max-features', type=int, default=1000,
                   help='keypoints per image of every detector (default 1000)')
    g.add_argument('--eps', type=_positive_float, default=3.0,
                   help='correctness threshold eps (px, default 3)')
    g.add_argument('--ransac-px', type=_positive_float, default=3.0,
                   help='geometric verification threshold (px, default 3)')
    g.add_argument('--weights', type=Path, default=None,
                   help='network weights (default: the shipped semfeat_ros/weights)')
    g.add_argument('--glue-weights', type=Path, default=None,
                   help='semfeat_lg: SemfeatGlue weights trained on those network weights '
                   '(.safetensors; default: the shipped semfeat_ros/weights/semfeat_glue)')
    g.add_argument('--resize-max', type=int, default=None,
                   help="network input's longer side (px; default: the extractor's 640)")
    g.add_argument('--extractor-set', metavar='KEY=VALUE', type=_key_value_item,
                   action='append', default=[],
                   help="override a network extractor option (YAML value; repeatable), e.g. "
                   "subpixel=quadratic or nms_radius=2 (config/model.yaml's extractor keys)")
    g.add_argument('--glue-set', metavar='KEY=VALUE', type=_key_value_item,
                   action='append', default=[],
                   help='semfeat_lg: override a SemfeatGlue option (YAML value; repeatable), '
                   'e.g. filter_threshold=0.05 or width_confidence=-1 (semfeat_ros/model/'
                   'glue.py default_conf)')
    g.add_argument('--fill-ratio', type=float, default=None, metavar='R',
                   help="semfeat_lg_nn: ratio test of the added matches (default: "
                   "matcher_node's learned_fill_ratio)")
    g.add_argument('--fill-min-similarity', type=float, default=None, metavar='S',
                   help="semfeat_lg_nn: minimum cosine similarity of the added matches "
                   "(default: matcher_node's learned_fill_min_similarity)")
    g.add_argument('--figures', type=int, default=3,
                   help='match figures per method: the first N pairs (default 3)')
    g.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    g.add_argument('--no-progress', action='store_true', help='no progress bar')

    parser = OneLineParser.for_tool(PROG, __doc__)
    sub = parser.add_subparsers(dest='mode', required=True, parser_class=OneLineParser)

    t = sub.add_parser('transforms', parents=[common],
                       help="paper's protocol: random rotation/translation/scale/homography")
    src = t.add_mutually_exclusive_group(required=True)
    src.add_argument('--images', type=Path, help='folder of JPG/PNG/PPM/PGM images')
    src.add_argument('--bag', type=Path, help='rosbag2 with an Image/CompressedImage topic')
    t.add_argument('--topic', default=None, help='image topic of --bag (default: the only one)')
    t.add_argument('--pairs', type=int, default=48, help='number of pairs (default 48)')
    t.add_argument('--camera', type=Path, default=None,
                   help='calibration YAML: its image circle is the valid region')
    t.add_argument('--distortion-model', default=None,
                   help='override the YAML distortion_model (e.g. equidistant)')
    t.add_argument('--fov-deg', type=_positive_float, default=None,
                   help='lens field of view (deg) for the image circle of --camera')
    t.add_argument('--image-circle', choices=('auto', 'none', 'camera'), default='auto',
                   help='valid region: estimated from the black border (auto, default), whole '
                   'frame (none) or from --camera')
    t.add_argument('--margin', type=int, default=8,
                   help='px removed along the valid region border (default 8)')
    t.add_argument('--labels', type=Path, default=None,
                   help='folder of <stem>.png mono8 GT class ids (segmentation metrics)')
    t.add_argument('--gt-keypoints', type=Path, default=None,
                   help='folder of <stem>.npy/.txt GT keypoints (u v px per row)')
    t.add_argument('--max-rotation', type=float, default=30.0, help='deg (default 30)')
    t.add_argument('--max-translation', type=float, default=15.0, help='px (default 15)')
    t.add_argument('--min-scale', type=float, default=0.8, help='(default 0.8)')
    t.add_argument('--max-scale', type=float, default=1.2, help='(default 1.2)')
    t.add_argument('--max-perspective', type=float, default=0.1,
                   help='perspective bound (default 0.1, see docs/METRICS.md)')

    h = sub.add_parser('homography', parents=[common],
                       help='Oxford/HPatches sequences (img1..imgN + H1to{k}p)')
    h.add_argument('--dataset', type=Path, required=True,
                   help='a sequence folder or a folder of sequences')
    h.add_argument('--max-pairs', type=int, default=None, help='evaluate at most N pairs')
    h.add_argument('--camera', type=Path, default=None,
                   help='calibration YAML: its image circle is the valid region')
    h.add_argument('--image-circle', choices=('auto', 'none', 'camera'), default='none',
                   help='valid region (default none: whole frame)')
    h.add_argument('--margin', type=int, default=0, help='px removed along the border')
    h.add_argument('--gt-keypoints', type=Path, default=None,
                   help='folder of <sequence>.npy/.txt GT keypoints of image 1')

    s = sub.add_parser('sequence', parents=[common],
                       help='frames (i, i+K) of a rendered drive (GT from depth and poses) or of '
                       'a real image sequence (no GT: verified matches)')
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument('--bag', type=Path, help='rosbag2 of a rendered drive')
    src.add_argument('--shard', type=Path, help='simulator shard (.npz)')
    src.add_argument('--images', type=Path,
                     help='folder of the frames of a real sequence (JPG/PNG/PPM/PGM, natural '
                     'order); no ground truth')
    s.add_argument('--glob', default='*',
                   help="--images: glob on file names selecting the frames (default '*')")
    cam = s.add_mutually_exclusive_group()
    cam.add_argument('--camera', type=Path, default=None,
                     help='calibration YAML: extrinsic and intrinsics without CameraInfo '
                     '(default: the shipped config/camera_front.yaml); with --images the '
                     "frames' intrinsics")
    cam.add_argument('--camera-xml', type=Path, default=None,
                     help='--images: ViSP XML with the intrinsics (<camera>: px, py, u0, v0)')
    cam.add_argument('--pinhole', type=_pinhole, default=None,
                     help='--images: pinhole intrinsics fx,fy,cx,cy (px)')
    s.add_argument('--stride', type=int, default=1, help='frame gap K of a pair (default 1)')
    s.add_argument('--max-pairs', type=int, default=None, help='evaluate at most N pairs')
    s.add_argument('--image-topic', default='/camera/front/image_raw')
    s.add_argument('--depth-topic', default='/ground_truth/depth',
                   help='range image along the ray (32FC1 m or 16UC1 mm)')
    s.add_argument('--pose-topic', default='/ground_truth/pose')
    s.add_argument('--labels-topic', default='/ground_truth/semantic',
                   help='GT class ids (mono8), used when present')
    s.add_argument('--camera-info-topic', default='/camera/front/camera_info',
                   help='CameraInfo, used when present (else --camera)')
    s.add_argument('--pose-frame', choices=('base_link', 'camera'), default='base_link',
                   help='the pose topic gives T_map_base (default) or T_map_cam')
    s.add_argument('--fov-deg', type=_positive_float, default=None,
                   help='lens field of view of a fisheye camera (deg; default 190 for --bag / '
                   "--shard, the YAML's own for --images)")
    s.add_argument('--margin', type=int, default=8,
                   help='px removed along the image-circle border (default 8)')
    s.add_argument('--gt-keypoints', default='rendered',
                   help="--bag / --shard: 'rendered' (default: corners of the rendered "
                   "geometry, the training targets' rule), 'none', or a folder of <frame "
                   'index>.npy/.txt (u v px)')
    return parser


def _key_value_item(text: str) -> tuple[str, object]:
    key, sep, value = text.partition('=')
    if not sep or not key:
        raise argparse.ArgumentTypeError(f'expected KEY=VALUE, got {text!r}')
    try:
        return key, yaml.safe_load(value)
    except yaml.YAMLError as exc:
        raise argparse.ArgumentTypeError(f'{key}: not a YAML value ({error_line(exc)})') from exc


def _network_conf(args: argparse.Namespace) -> dict[str, object]:
    conf: dict[str, object] = dict(args.extractor_set)
    if args.resize_max is not None:
        conf['resize_max'] = args.resize_max
    return conf


def _eval_conf(args: argparse.Namespace) -> EvalConf:
    return EvalConf(methods=tuple(args.methods), eps_px=args.eps, ransac_px=args.ransac_px,
                    max_features=args.max_features,
                    weights=None if args.weights is None else str(args.weights),
                    glue_weights=None if args.glue_weights is None else str(args.glue_weights),
                    n_figures=args.figures, seed=args.seed, progress=not args.no_progress,
                    network_conf=_network_conf(args), glue_conf=dict(args.glue_set),
                    fill_conf={k: v for k, v in (('ratio', args.fill_ratio),
                                                 ('min_similarity', args.fill_min_similarity))
                               if v is not None})


def run(args: argparse.Namespace) -> dict:
    """Dispatch a parsed command line to the mode's ``main(conf, paths)``."""
    econf = _eval_conf(args)
    if args.mode == 'transforms':
        from semfeat_ros.evaluation import run_transforms as mod

        conf = mod.TransformsConf(
            eval=econf, pairs=args.pairs,
            transform=TransformConf(args.max_rotation, args.max_translation, args.min_scale,
                                    args.max_scale, args.max_perspective),
            image_circle=args.image_circle, mask_margin_px=args.margin,
            distortion_model=args.distortion_model, fov_deg=args.fov_deg)
        paths = mod.TransformsPaths(out=args.out, images=args.images, bag=args.bag,
                                    topic=args.topic, labels=args.labels,
                                    gt_keypoints=args.gt_keypoints, camera=args.camera)
        return mod.main(conf, paths)
    if args.mode == 'homography':
        from semfeat_ros.evaluation import run_homography as mod

        conf = mod.HomographyConf(eval=econf, image_circle=args.image_circle,
                                  mask_margin_px=args.margin, max_pairs=args.max_pairs)
        paths = mod.HomographyPaths(dataset=args.dataset, out=args.out,
                                    gt_keypoints=args.gt_keypoints, camera=args.camera)
        return mod.main(conf, paths)
    from semfeat_ros.evaluation import run_sequence as mod

    topics = mod.SequenceTopics(args.image_topic, args.depth_topic, args.pose_topic,
                                args.labels_topic or None, args.camera_info_topic or None)
    conf = mod.SequenceConf(eval=econf, stride=args.stride, max_pairs=args.max_pairs,
                            topics=topics, pose_frame=args.pose_frame,
                            mask_margin_px=args.margin, fov_deg=args.fov_deg)
    paths = mod.SequencePaths(out=args.out, bag=args.bag, shard=args.shard, camera=args.camera,
                              gt_keypoints=args.gt_keypoints, images=args.images,
                              pattern=args.glob, camera_xml=args.camera_xml,
                              pinhole=args.pinhole)
    return mod.main(conf, paths)


def cli(argv: list[str] | None = None) -> int:
    """Console-script entry point; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a command-line error (2, already printed)
        return int(exc.code or 0)
    if args.figures < 0 or args.max_features < 1:
        print(f'{PROG}: error: --figures must be >= 0 and --max-features >= 1', file=sys.stderr)
        return 2
    try:
        results = run(args)
    except (EvalError, FileNotFoundError, NotADirectoryError, ValueError, OSError) as exc:
        print(f'{PROG}: error: {error_line(exc)}', file=sys.stderr)
        return 1
    from semfeat_ros.evaluation.report import markdown_table

    sys.stdout.write(markdown_table(results))
    print(f'\nwrote {written_summary(Path(args.out))}')
    return 0


def written_summary(out: Path) -> str:
    """The outputs present in ``out``: results.json, results.md, the charts (PNG) and the
    match figures (``matches/``), each named only when written."""
    parts = [str(out / name) for name in ('results.json', 'results.md') if (out / name).is_file()]
    charts = sorted(p.name for p in out.glob('*.png'))
    if charts:
        parts.append(f'{len(charts)} charts ({", ".join(charts)})')
    figures = sorted((out / 'matches').glob('*.png')) if (out / 'matches').is_dir() else []
    if figures:
        parts.append(f'{len(figures)} match figures in {out / "matches"}/')
    return ', '.join(parts) or 'nothing'



if __name__ == '__main__':
    sys.exit(cli())
