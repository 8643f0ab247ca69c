"""``semfeat-train``: train the multi-task network on rendered shards (+ shipped real photos).

    semfeat-train --config config/train.yaml --out out/train [--resume] [--export DIR]

Writes into ``--out``: ``train_log.csv``, ``val_log.csv``, ``plots/losses.png``,
``plots/metrics.png``, ``checkpoints/last.pt`` (resumable with ``--resume``), ``config.json``,
``summary.json`` and the final ``semfeat.safetensors`` + ``semfeat.json``. ``--export
semfeat_ros/weights`` also installs them as the shipped weights with a generated MODEL_CARD.md.
Bad input gives one line on stderr and exit status 1 (2 for a bad command line).
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys
from typing import Any

import yaml

from semfeat_ros.tools.cli import OneLineParser, error_line

PROG = 'semfeat-train'


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser.for_tool(PROG, __doc__)
    p.add_argument('--config', type=Path, required=True,
                   help='training YAML (see config/train.yaml)')
    p.add_argument('--out', type=Path, required=True, help='output directory (created)')
    p.add_argument('--resume', action='store_true',
                   help='continue from OUT/checkpoints/last.pt if present')
    p.add_argument('--export', type=Path, default=None,
                   help='copy the final weights + MODEL_CARD.md here (e.g. semfeat_ros/weights)')
    p.add_argument('--steps', type=int, default=None, help='override the number of steps')
    p.add_argument('--stop-after', type=int, default=None,
                   help='pause after this step (checkpoint written); continue with --resume')
    p.add_argument('--no-progress', action='store_true', help='no progress bar')
    return p


def _load_yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise FileNotFoundError(f'config file not found: {path}')
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f'{path}: invalid YAML ({exc})') from exc
    if not isinstance(data, dict):
        raise ValueError(f'{path}: expected a mapping at the top level')
    return data


def _with_bases(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The YAML at ``path`` over its ``base`` file (relative to ``path``, recursively): keys set
    here replace the base's, mappings (loss, data, network_overrides, ...) are merged key by
    key."""
    path = path.resolve()
    if path in seen:
        raise ValueError(f'{path}: config bases form a cycle')
    conf = _load_yaml(path)
    base = conf.pop('base', None)
    if base is None:
        return conf
    if not isinstance(base, str):
        raise ValueError(f'{path}: base must be a file name, got {base!r}')
    merged = _with_bases(path.parent / base, (*seen, path))
    for key, value in conf.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged


def read_config(path: Path) -> dict[str, Any]:
    """Training YAML -> dict. ``base`` names a config (relative to ``path``) whose keys this one
    overrides (a fine-tuning stage over the main recipe). ``network`` may name a YAML file
    (relative to ``path``) whose ``network`` mapping is used, so config/model.yaml stays the one
    place of the architecture; ``network_overrides`` then changes single keys of it. Shard globs
    stay relative to the current directory."""
    conf = _with_bases(path)
    net = conf.get('network')
    if isinstance(net, str):
        npath = (path.parent / net).resolve()
        if not npath.is_file():
            raise FileNotFoundError(f'{path}: network file not found: {npath}')
        ndata = _load_yaml(npath)
        if not isinstance(ndata.get('network'), dict):
            raise ValueError(f'{npath}: expected a "network" mapping')
        conf['network'] = ndata['network']
    over = conf.pop('network_overrides', None) or {}
    if not isinstance(over, dict) or not isinstance(conf.get('network', {}), dict):
        raise ValueError(f'{path}: network_overrides must be a mapping over a network mapping')
    if over:
        conf['network'] = {**conf.get('network', {}), **over}
    return conf


def cli(argv: list[str] | None = None) -> int:
    """Console-script entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        conf = read_config(args.config)
        if args.steps is not None:
            conf['steps'] = args.steps
        from semfeat_ros.model.training import main
        summary = main(conf, args.out, resume=args.resume, export=args.export,
                       progress=not args.no_progress, stop_after=args.stop_after,
                       config_name=str(args.config))
    except (OSError, ValueError, RuntimeError) as exc:
        print(f'{PROG}: error: {error_line(exc)}', file=sys.stderr)
        return 1
    if summary.get('stopped'):
        print(f'{PROG}: paused at step {summary["steps"]}; continue with --resume')
        return 0
    print(f'{PROG}: wrote {summary["weights"]} (mIoU {summary.get("val_miou", float("nan")):.3f}'
          f', repeatability {summary.get("val_repeatability", float("nan")):.3f}, precision '
          f'{summary.get("val_precision", float("nan")):.3f})')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
