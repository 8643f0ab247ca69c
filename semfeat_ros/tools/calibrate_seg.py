"""``semfeat-calibrate-seg``: segmentation prior correction of trained weights.

    semfeat-calibrate-seg --weights semfeat_ros/weights --train-shards 'out/sim_train/*.npz'
        --val-shards 'out/sim_val/*.npz' --out semfeat_ros/weights

Chooses tau on the training shards' full frames (static-class mIoU), folds ``-tau log w_c`` into
the segmentation head's bias and writes ``semfeat.safetensors`` + ``semfeat.json`` (and the
model card's section) into ``--out``; held-out shards are evaluated before and after only. See
``semfeat_ros/model/calibration.py``. Bad input gives one line on stderr and exit status 1 (2 for
a bad command line).
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys

from semfeat_ros.tools.cli import OneLineParser, error_line

PROG = 'semfeat-calibrate-seg'


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser.for_tool(PROG, __doc__)
    p.add_argument('--weights', type=Path, default=None,
                   help='trained weights (.safetensors or its directory; default: shipped)')
    p.add_argument('--train-shards', nargs='+', required=True,
                   help='globs of rendered training shards (tau is fitted on these)')
    p.add_argument('--val-shards', nargs='*', default=[],
                   help='globs of held-out shards (evaluated before / after, never fitted)')
    p.add_argument('--frames-per-shard', type=int, default=3, help='full frames per shard')
    p.add_argument('--out', type=Path, required=True,
                   help='directory for the corrected weights (created; may be the input one)')
    p.add_argument('--no-progress', action='store_true', help='no progress bar')
    return p


def cli(argv: list[str] | None = None) -> int:
    """Console-script entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        from semfeat_ros.model.calibration import main
        cal = main({'train_shards': args.train_shards, 'val_shards': args.val_shards,
                    'frames_per_shard': args.frames_per_shard}, args.weights, args.out,
                   progress=not args.no_progress)
    except (OSError, ValueError, RuntimeError) as exc:
        print(f'{PROG}: error: {error_line(exc)}', file=sys.stderr)
        return 1
    val = ''
    if cal.val_before is not None and cal.val_after is not None:
        val = (f'; held-out static mIoU {cal.val_before[0]:.3f} -> {cal.val_after[0]:.3f} '
               f'({cal.frames[1]} frames)')
    print(f'{PROG}: tau {cal.tau:g} (training static mIoU {cal.train[0.0][0]:.3f} -> '
          f'{cal.train[cal.tau][0]:.3f}, {cal.frames[0]} frames){val}; wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
