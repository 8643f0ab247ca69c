"""Live rate of feature_node with matcher_node beside it (the issue-6 benchmark).

Starts ``feature_node`` and ``matcher_node`` as processes with their shipped configs, replays a
bag through ``semfeat-play`` (with ``/clock``) and reads their ``/diagnostics``: frames received,
processed and dropped, the rate of processed frames over the replay, and latency (header stamp
-> publish) p50 / p95. Nothing else runs, so the two nodes share the 2 cores only with the
player. A command, not a test::

    python -m semfeat_ros.tools.node_rate [--bag bags/garage_ramp_seed0] [--rate 1.0]
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import json
from pathlib import Path
import sys
import time
from typing import Any

from semfeat_ros.offline.bag import one_line
from semfeat_ros.tools.demo import DEFAULT_BAG, GraphClient, player_argv
from semfeat_ros.tools.launcher import Pipeline, PipelineConfig, wait_for_nodes

PROG = 'python -m semfeat_ros.tools.node_rate'
NODES = ('feature_node', 'matcher_node')


@dataclass
class NodeRateConfig:
    bag: Path = DEFAULT_BAG
    out: Path = Path('out/node_rate')  # logs of the child processes
    rate: float = 1.0  # replay speed
    domain_id: int = 58
    settle_s: float = 3.0  # after the replay: the last diagnostics arrive


def measure(conf: NodeRateConfig) -> dict[str, Any]:
    """Replay ``conf.bag`` through the two nodes; returns their last diagnostics and the rate
    of processed frames (Hz) over the replay's wall time."""
    pcfg = PipelineConfig(domain_id=conf.domain_id, output_dir=conf.out)
    client = GraphClient(conf.domain_id)
    try:
        with Pipeline(pcfg) as pipe:
            for node in NODES:
                pipe.start(node, pipe.node_argv(node))
            wait_for_nodes(NODES, pipe)
            player = pipe.start('player', player_argv(conf.bag, conf.rate, len(NODES)))
            t0 = None
            while player.poll() is None:
                pipe.check_alive()
                client.spin_for(0.2)
                if t0 is None and client.processed('feature_node') > 0:
                    t0 = time.monotonic()
            t_end = time.monotonic()
            if player.returncode != 0:
                raise RuntimeError(f'semfeat-play failed (see {pipe.log_path("player")})')
            client.spin_for(conf.settle_s)
            codes = pipe.stop_all()
    finally:
        client.close()
    status = client.status
    f = status.get('feature_node', {})
    processed = int(float(f.get('frames_processed', 0)))
    wall = (t_end - t0) if t0 is not None else float('nan')
    return {'bag': str(conf.bag), 'rate': conf.rate, 'exit_codes': codes,
            'feature_node_hz': processed / wall if wall and wall > 0 else float('nan'),
            'replay_s': wall, 'diagnostics': {n: status.get(n, {}) for n in NODES}}


def summary(res: dict[str, Any]) -> str:
    lines = [f'feature_node + matcher_node on {Path(res["bag"]).name} at {res["rate"]}x']
    for node in NODES:
        d = res['diagnostics'][node]
        lines.append(
            f'  {node:13s} frames {d.get("frames_processed", "?")}/'
            f'{d.get("frames_received", "?")} processed, {d.get("frames_dropped", "?")} dropped;'
            f' latency p50 {float(d.get("latency_p50_s", "nan")) * 1e3:.0f} ms p95 '
            f'{float(d.get("latency_p95_s", "nan")) * 1e3:.0f} ms; compute p50 '
            f'{float(d.get("compute_p50_s", "nan")) * 1e3:.0f} ms')
    lines.append(f'  feature_node processed {res["feature_node_hz"]:.2f} Hz over '
                 f'{res["replay_s"]:.1f} s of replay')
    return '\n'.join(lines)


def cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument('--bag', type=Path, default=DEFAULT_BAG, help='rosbag2 directory')
    p.add_argument('--out', type=Path, default=Path('out/node_rate'),
                   help='directory for the logs and results.json')
    p.add_argument('--rate', type=float, default=1.0, help='replay speed (default 1.0)')
    p.add_argument('--domain-id', type=int, default=58, help='ROS_DOMAIN_ID (default 58)')
    args = p.parse_args(argv)
    if not args.bag.exists():
        print(f'{PROG}: bag not found: {args.bag}', file=sys.stderr)
        return 2
    if not args.rate > 0:
        print(f'{PROG}: --rate must be > 0, got {args.rate}', file=sys.stderr)
        return 2
    conf = NodeRateConfig(bag=args.bag, out=args.out, rate=args.rate, domain_id=args.domain_id)
    try:
        res = measure(conf)
    except (RuntimeError, OSError) as exc:
        print(f'{PROG}: {one_line(exc)}', file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'results.json').write_text(json.dumps(res, indent=1, default=str) + '\n')
    print(summary(res))
    return 0


if __name__ == '__main__':
    sys.exit(cli())
