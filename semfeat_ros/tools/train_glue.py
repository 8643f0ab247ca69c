"""``semfeat-train-glue``: fine-tune the attention matcher on the network's features.

    semfeat-train-glue --config config/glue.yaml --out out/glue [--export semfeat_ros/weights]

Writes into ``--out``: ``pairs_{train,val}.npz`` (the features and ground truth, reused by a
run with the same settings), ``train_log.csv``, ``val_log.csv``, ``plots/glue.png``,
``config.json``, ``summary.json`` and ``semfeat_glue.safetensors`` + ``.json``; ``--export``
copies the weights there (see semfeat_ros.model.train_glue). Bad input gives one line on stderr
and exit status 1 (2 for a bad command line).
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys

from semfeat_ros.tools.cli import OneLineParser, error_line
from semfeat_ros.tools.train import read_config

PROG = 'semfeat-train-glue'


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser.for_tool(PROG, __doc__)
    p.add_argument('--config', type=Path, required=True, help='YAML (see config/glue.yaml)')
    p.add_argument('--out', type=Path, required=True, help='output directory (created)')
    p.add_argument('--export', type=Path, default=None,
                   help='copy the final weights here (e.g. semfeat_ros/weights)')
    p.add_argument('--weights', default=None,
                   help="SemFeatNet weights whose features are matched (file or directory; "
                        "default: the config's, else the shipped ones)")
    p.add_argument('--steps', type=int, default=None, help='override the number of steps')
    p.add_argument('--train-pairs', type=int, default=None, help='override train_pairs')
    p.add_argument('--val-pairs', type=int, default=None, help='override val_pairs')
    p.add_argument('--no-progress', action='store_true', help='no progress bars')
    return p


def cli(argv: list[str] | None = None) -> int:
    """Console-script entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        conf = read_config(args.config)
        for key, value in (('steps', args.steps), ('train_pairs', args.train_pairs),
                           ('val_pairs', args.val_pairs), ('weights', args.weights)):
            if value is not None:
                conf[key] = value
        from semfeat_ros.model.train_glue import main
        summary = main(conf, args.out, export=args.export, progress=not args.no_progress,
                       config_name=str(args.config))
    except (OSError, ValueError, RuntimeError) as exc:
        print(f'{PROG}: error: {error_line(exc)}', file=sys.stderr)
        return 1
    first, last = summary['val_step0'], summary['val_final']
    print(f'{PROG}: wrote {summary["weights"]} (held-out pairs: precision / recall '
          f'{last["precision"]:.3f} / {last["recall"]:.3f}; LighterGlue as shipped '
          f'{first["precision"]:.3f} / {first["recall"]:.3f}; mutual NN '
          f'{last["nn_precision"]:.3f} / {last["nn_recall"]:.3f})')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
