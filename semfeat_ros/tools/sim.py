"""``semfeat-sim``: render the synthetic fisheye parking garage.

Recording (rosbag2)::

    semfeat-sim --out DIR [--seed N] [--duration S] [--rate HZ] [--size WxH]
                [--format mcap|sqlite3] [--raw|--compressed] [--start S|ramp] ...

Training shards, contact sheet, speed and label-coverage checks::

    semfeat-sim dataset --out DIR --seeds A-B --frames N --size WxH
    semfeat-sim preview --out PNG [--seed N] [--size WxH]
    semfeat-sim bench [--size WxH] [--frames N]
    semfeat-sim coverage [--seed N] [--size WxH] [--step S]
    semfeat-sim info [--seed N]
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
import shlex
import sys
import time

import numpy as np

from semfeat_ros.sim.bag import BagConfig, BagSummary, resolve_start, write_bag
from semfeat_ros.sim.config import GarageConfig, load_config
from semfeat_ros.sim.dataset import DatasetConfig, parse_seeds, write_dataset
from semfeat_ros.sim.errors import BagWriteError, SimError
from semfeat_ros.sim.scenario import Scenario

SUBCOMMANDS = ('dataset', 'preview', 'bench', 'coverage', 'info')


def parse_size(text: str) -> tuple[int, int]:
    """``'WxH'`` -> (W, H) px."""
    try:
        w, h = (int(v) for v in str(text).lower().split('x'))
    except ValueError:
        raise argparse.ArgumentTypeError(f'size must look like 640x512, got {text!r}') from None
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise argparse.ArgumentTypeError(f'size must be within 16..4096 px, got {text!r}')
    return w, h


# ---------------------------------------------------------------------------------- main parts


def main_bag(cfg: BagConfig, out: Path, garage: GarageConfig | None = None,
             start: float | str = 0.0, progress: bool = True, command: str = '') -> BagSummary:
    """Render a recording (see :mod:`semfeat_ros.sim.bag`)."""
    sc = Scenario.create(seed=cfg.seed, size=cfg.size, config=garage)
    t0 = resolve_start(sc, start)
    cfg = BagConfig(**{**cfg.__dict__, 'start': t0})
    return write_bag(out, cfg, scenario=sc, progress=progress, command=command)


def main_coverage(seed: int, size: tuple[int, int], step: float,
                  garage: GarageConfig | None = None, progress: bool = True) -> dict:
    """Render the whole long drive every ``step`` s; count pixels per class and check that
    every pixel inside the image circle has a class in 0..18."""
    from tqdm import tqdm

    from semfeat_ros.labels import load_labels
    from semfeat_ros.sim import materials as mt

    sc = Scenario.create(seed=seed, size=size, config=garage)
    times = np.arange(0.0, sc.trajectory.duration, step)
    counts = np.zeros(256, np.int64)
    valid = sc.renderer.valid
    bad = 0
    for t in tqdm(times, desc='coverage', unit='frame', disable=not progress):
        frame = sc.renderer.render(sc.camera_pose(t), t)
        counts += np.bincount(frame.label.ravel(), minlength=256)
        inside = frame.label[valid]
        bad += int(np.count_nonzero(inside >= mt.NUM_CLASSES))
        bad += int(np.count_nonzero(frame.label[~valid] != mt.IGNORE))
    names = load_labels().names
    per_class = {names[i]: int(counts[i]) for i in range(len(names))}
    return {'frames': len(times), 'per_class': per_class,
            'missing': [n for n, c in per_class.items() if c == 0], 'bad_pixels': bad}


# ----------------------------------------------------------------------------------------- cli


def _bag_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='semfeat-sim',
        description='Render the synthetic fisheye parking garage into a rosbag2 recording. '
                    f'Other modes: semfeat-sim {{{",".join(SUBCOMMANDS)}}} --help.')
    p.add_argument('--out', type=Path, required=True, help='bag directory to create')
    p.add_argument('--seed', type=int, default=0, help='world seed (default 0)')
    p.add_argument('--duration', type=float, default=20.0, help='seconds to record')
    p.add_argument('--rate', type=float, default=10.0, help='camera rate (Hz)')
    p.add_argument('--size', type=parse_size, default=(640, 512), help='image size WxH (px)')
    p.add_argument('--start', default='0',
                   help="start time in the drive (s), or 'ramp' (6 s before the ramp)")
    p.add_argument('--format', choices=('mcap', 'sqlite3'), default='mcap',
                   help='rosbag2 storage (default mcap, zstd chunk compression)')
    g = p.add_mutually_exclusive_group()
    g.add_argument('--compressed', dest='compressed', action='store_true', default=True,
                   help='write /camera/front/image_raw/compressed (jpeg; default)')
    g.add_argument('--raw', dest='compressed', action='store_false',
                   help='write /camera/front/image_raw (rgb8)')
    p.add_argument('--jpeg-quality', type=int, default=90)
    p.add_argument('--semantic-every', type=int, default=1,
                   help='write /ground_truth/semantic every N-th frame')
    p.add_argument('--depth-every', type=int, default=1,
                   help='write /ground_truth/depth every N-th frame')
    p.add_argument('--depth-quantum', type=float, default=0.0,
                   help='round ground-truth depth to multiples of this many metres (0: exact)')
    p.add_argument('--config', type=Path, default=None, help='GarageConfig YAML override')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    return p


def _sub_parser(name: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f'semfeat-sim {name}')
    if name == 'dataset':
        p.description = 'Render training shards (one .npz per seed) with correspondences.'
        p.add_argument('--out', type=Path, required=True)
        p.add_argument('--seeds', required=True, help="'A-B' (inclusive), 'A,B,C' or 'A'")
        p.add_argument('--frames', type=int, default=64, help='frames per seed')
        p.add_argument('--size', type=parse_size, default=(320, 256))
        p.add_argument('--clip', type=int, default=4, help='consecutive frames per clip')
        p.add_argument('--corr', type=int, default=1024, help='correspondences per pair')
        p.add_argument('--fixed-world', action='store_true',
                       help='use the default garage config instead of a random one per seed')
        p.add_argument('--depth-dtype', choices=('float16', 'float32'), default='float16')
    elif name == 'preview':
        p.description = 'Write a contact sheet PNG (image | labels | depth) of sample frames.'
        p.add_argument('--out', type=Path, required=True)
        p.add_argument('--seed', type=int, default=0)
        p.add_argument('--size', type=parse_size, default=(320, 256))
    elif name == 'bench':
        p.description = 'Measure the render speed (frames/s, including the sensor model).'
        p.add_argument('--size', type=parse_size, default=(640, 512))
        p.add_argument('--frames', type=int, default=20)
        p.add_argument('--seed', type=int, default=0)
        p.add_argument('--workers', type=int, default=2, help='render threads')
    elif name == 'coverage':
        p.description = ('Render the whole long drive and check that all 19 classes appear '
                         'and every pixel inside the image circle is labelled.')
        p.add_argument('--seed', type=int, default=0)
        p.add_argument('--size', type=parse_size, default=(160, 128))
        p.add_argument('--step', type=float, default=0.5, help='seconds between frames')
    elif name == 'info':
        p.description = 'Print the drive of a seed (length, duration, ramp, levels).'
        p.add_argument('--seed', type=int, default=0)
        p.add_argument('--config', type=Path, default=None)
    if name in ('preview', 'coverage'):
        p.add_argument('--quiet', action='store_true')
    return p


def _run_sub(name: str, args: argparse.Namespace) -> int:
    if name == 'dataset':
        cfg = DatasetConfig(frames=args.frames, size=args.size, clip=args.clip,
                            corr_per_pair=args.corr, randomize_world=not args.fixed_world,
                            depth_dtype=args.depth_dtype)
        paths = write_dataset(args.out, parse_seeds(args.seeds), cfg)
        total = sum(p.stat().st_size for p in paths)
        print(f'wrote {len(paths)} shard(s) to {args.out} ({total / 1e6:.1f} MB)')
    elif name == 'preview':
        from semfeat_ros.sim.preview import write_preview

        print(f'wrote {write_preview(args.out, args.seed, args.size)}')
    elif name == 'bench':
        from semfeat_ros.sim.scenario import benchmark

        if args.frames < 1:
            raise SimError(f'--frames must be >= 1, got {args.frames}')
        res = benchmark(*args.size, n_frames=args.frames, seed=args.seed,
                        workers=args.workers)
        print(f'{res["fps"]:.2f} frames/s ({res["ms_per_frame"]:.0f} ms/frame) at '
              f'{args.size[0]}x{args.size[1]}, {args.workers} render thread(s), '
              f'{args.frames} frames incl. sensor model')
    elif name == 'coverage':
        if args.step <= 0:
            raise SimError(f'--step must be > 0, got {args.step}')
        res = main_coverage(args.seed, args.size, args.step, progress=not args.quiet)
        width = max(len(n) for n in res['per_class'])
        total = sum(res['per_class'].values())
        for n, c in res['per_class'].items():
            print(f'{n:<{width}}  {c:>10d}  {100.0 * c / max(total, 1):6.2f} %')
        print(f'{res["frames"]} frames; missing classes: {res["missing"] or "none"}; '
              f'unlabelled pixels inside the image circle: {res["bad_pixels"]}')
        return 0 if not res['missing'] and res['bad_pixels'] == 0 else 1
    elif name == 'info':
        sc = Scenario.create(seed=args.seed, size=(64, 48), config=load_config(args.config))
        tr = sc.trajectory
        lay = sc.world.layout
        print(f'seed {args.seed}: drive {tr.length:.1f} m in {tr.duration:.1f} s; ramp from '
              f'{tr.s_ramp[0]:.1f} m to {tr.s_ramp[1]:.1f} m (t = {tr.time_at(tr.s_ramp[0]):.1f}'
              f'..{tr.time_at(tr.s_ramp[1]):.1f} s), rise {lay.deck_z:.2f} m at '
              f'{100 * sc.world.config.ramp_grade:.0f} % grade; footprint '
              f'{lay.length:.1f} x {lay.width:.1f} m; {len(sc.world.boxes)} boxes, '
              f'{len(sc.world.agents)} agents; start for --start ramp: '
              f'{resolve_start(sc, "ramp"):.1f} s')
    return 0


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in SUBCOMMANDS:
            name = argv[0]
            args = _sub_parser(name).parse_args(argv[1:])
            return _run_sub(name, args)
        args = _bag_parser().parse_args(argv)
        garage = load_config(args.config)
        cfg = BagConfig(seed=args.seed, duration=args.duration, rate=args.rate,
                        size=args.size, storage=args.format, compressed=args.compressed,
                        jpeg_quality=args.jpeg_quality, semantic_every=args.semantic_every,
                        depth_every=args.depth_every, depth_quantum=args.depth_quantum)
        t = time.perf_counter()
        # the stored command names the output by its basename (the bag's bytes must not
        # depend on where it was written)
        stored = [args.out.name if a == str(args.out) else a for a in argv]
        summary = main_bag(cfg, args.out, garage, args.start, progress=not args.quiet,
                           command='semfeat-sim ' + shlex.join(stored))
        dt = time.perf_counter() - t
        print(f'wrote {summary.path} ({summary.size_bytes / 1e6:.1f} MB): {summary.frames} '
              f'frames, t = {summary.start:.1f}..{summary.end:.1f} s, '
              f'{summary.path_length_m:.0f} m driven, {dt:.1f} s')
        for topic, n in summary.messages.items():
            print(f'  {topic}: {n}')
        return 0
    except (SimError, BagWriteError, FileNotFoundError, OSError) as exc:
        print(f'semfeat-sim: error: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(cli())
