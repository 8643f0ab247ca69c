"""The demo: the three nodes as processes on the bundled bag, replayed with /clock.

    python -m semfeat_ros.tools.demo --out out/demo [--bag bags/garage_ramp_seed0]
        [--param feature_node.frontend=xfeat --param matcher_node.matcher=learned ...]

Starts feature_node, matcher_node and mapping_node with their shipped parameter files (and
the ``--param`` overrides, as ``ros2 run ... -p name:=value`` would), records
their outputs with ``semfeat-record``, replays the bag with ``semfeat-play --clock``, saves the
map through ``~/save_map`` and writes into ``--out``: the output bag, ``cloud.ply``,
``trajectory.tum``, figures (trajectory vs ground truth, altitude profile, a sample frame with
keypoints and semantic overlay, a match view) and ``summary.json``; it prints a short summary.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field, fields
import json
import os
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from semfeat_ros.tools.launcher import NODES, Pipeline, PipelineConfig, wait_for_nodes

REPO = Path(__file__).resolve().parents[2]
DEFAULT_BAG = REPO / 'bags' / 'garage_ramp_seed0'
RECORDED_TOPICS = ('/semfeat/tracks', '/semfeat/odometry', '/semfeat/path', '/semantic_cloud',
                   '/diagnostics', '/tf', '/tf_static')


class DemoError(RuntimeError):
    """The demo cannot run (missing weights or bag, a node that died)."""


@dataclass
class DemoConfig:
    bag: Path = DEFAULT_BAG
    out: Path = Path('out/demo')
    domain_id: int = 57
    rate: float = 1.0
    drain_timeout_s: float = 60.0
    node_params: dict[str, dict[str, str]] = field(default_factory=dict)  # --param overrides


def parse_params(items: list[str]) -> dict[str, dict[str, str]]:
    """``NODE.NAME=VALUE`` items as ``{node: {name: value}}``; the node must be one of the
    demo's and the name a parameter of its typed config (docs/PARAMETERS.md)."""
    from semfeat_ros.tools.node_config import config_class

    out: dict[str, dict[str, str]] = {}
    for item in items:
        key, sep, value = item.partition('=')
        node, dot, name = key.partition('.')
        if not sep or not dot or not name or not value:
            raise DemoError(f'--param {item!r}: expected NODE.NAME=VALUE, e.g. '
                            f'feature_node.frontend=xfeat')
        if node not in NODES:
            raise DemoError(f'--param {item!r}: unknown node {node!r} (one of {", ".join(NODES)})')
        if name not in {f.name for f in fields(config_class(node))}:
            raise DemoError(f'--param {item!r}: {node} has no parameter {name!r} '
                            f'(docs/PARAMETERS.md)')
        out.setdefault(node, {})[name] = value
    return out


class GraphClient:
    """An rclpy node inside the demo process: watches /diagnostics and calls ~/save_map."""

    def __init__(self, domain_id: int):
        os.environ['ROS_DOMAIN_ID'] = str(domain_id)
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        from diagnostic_msgs.msg import DiagnosticArray
        import rclpy

        self.rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node('semfeat_demo')
        self.status: dict[str, dict[str, str]] = {}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            self.status[st.name.split(':')[0]] = {kv.key: kv.value for kv in st.values}

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.rclpy.spin_once(self.node, timeout_sec=0.05)

    def processed(self, node: str) -> int:
        return int(self.status.get(node, {}).get('frames_processed', 0))

    def save_map(self, timeout: float = 60.0) -> str:
        from std_srvs.srv import Trigger

        client = self.node.create_client(Trigger, '/mapping_node/save_map')
        if not client.wait_for_service(timeout_sec=10.0):
            raise DemoError('mapping_node/save_map is not available')
        future = client.call_async(Trigger.Request())
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
            self.rclpy.spin_once(self.node, timeout_sec=0.1)
        if not future.done() or not future.result().success:
            raise DemoError(f'save_map failed: {future.result() if future.done() else "timeout"}')
        return future.result().message

    def close(self) -> None:
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def check_ready(conf: DemoConfig) -> None:
    """Fail early, in one line, when something the demo needs is missing."""
    if not (conf.bag / 'metadata.yaml').is_file():
        raise DemoError(f'bag not found: {conf.bag} (no metadata.yaml)')
    from semfeat_ros.model.weights_io import resolve_weights_path

    try:
        resolve_weights_path(None)
    except FileNotFoundError as exc:
        raise DemoError(f'not built yet: {exc}') from exc


def player_argv(bag: Path, rate: float, subscribers: int) -> list[str]:
    """``semfeat-play`` with ``/clock`` at 100 Hz, starting once ``subscribers`` nodes listen to
    the CameraInfo (every node does)."""
    return [sys.executable, '-m', 'semfeat_ros.tools.play', str(bag), '--clock', '100',
            '--rate', str(rate), '--no-progress', '--wait-topics', '/camera/front/camera_info',
            '--wait-for-subscribers', str(subscribers), '--wait-timeout', '30']


def run_pipeline(conf: DemoConfig) -> dict[str, Any]:
    """Run nodes + recorder + player; returns the last diagnostics per node and timings."""
    out = conf.out
    record_dir = out / 'output_bag'
    if record_dir.exists():
        import shutil
        shutil.rmtree(record_dir)
    pcfg = PipelineConfig(domain_id=conf.domain_id, output_dir=out, node_params=conf.node_params)
    client = GraphClient(conf.domain_id)
    t0 = time.monotonic()
    try:
        with Pipeline(pcfg) as pipe:
            pipe.start_nodes()
            pipe.start('recorder', [sys.executable, '-m', 'semfeat_ros.tools.record',
                                    str(record_dir), '--no-progress', '--topics',
                                    *RECORDED_TOPICS])
            print('waiting for the nodes to come up ...', flush=True)
            wait_for_nodes(NODES, pipe)
            t_up = time.monotonic() - t0
            print(f'nodes up after {t_up:.1f} s; replaying {conf.bag.name} ...', flush=True)
            player = pipe.start('player', player_argv(conf.bag, conf.rate, len(NODES)))
            while player.poll() is None:
                pipe.check_alive()
                client.spin_for(0.2)
            if player.returncode != 0:
                raise DemoError(f'semfeat-play failed (see {pipe.log_path("player")})')
            # Drain: wait until mapping_node stops making progress.
            last, stable_since = -1, time.monotonic()
            deadline = time.monotonic() + conf.drain_timeout_s
            while time.monotonic() < deadline:
                client.spin_for(0.5)
                n = client.processed('mapping_node')
                if n != last:
                    last, stable_since = n, time.monotonic()
                elif time.monotonic() - stable_since > 3.0:
                    break
            message = client.save_map()
            client.spin_for(1.5)  # the last diagnostics and latched cloud reach the recorder
            codes = pipe.stop_all()
    finally:
        client.close()
    return {'diagnostics': client.status, 'save_map': message, 'exit_codes': codes,
            'startup_s': t_up, 'wall_s': time.monotonic() - t0, 'node_params': conf.node_params}


def cli(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', type=Path, default=DEFAULT_BAG, help='rosbag2 to replay')
    parser.add_argument('--out', type=Path, default=Path('out/demo'), help='output directory')
    parser.add_argument('--domain', type=int, default=57, help='ROS_DOMAIN_ID (0-101)')
    parser.add_argument('--rate', type=float, default=1.0, help='replay speed factor')
    parser.add_argument('--param', action='append', default=[], metavar='NODE.NAME=VALUE',
                        help='a node parameter over its shipped file, e.g. '
                             'feature_node.frontend=xfeat (repeatable)')
    args = parser.parse_args(argv)
    try:
        conf = DemoConfig(bag=args.bag, out=args.out, domain_id=args.domain, rate=args.rate,
                          node_params=parse_params(args.param))
        check_ready(conf)
        conf.out.mkdir(parents=True, exist_ok=True)
        run = run_pipeline(conf)
        from semfeat_ros.tools.demo_report import write_report

        summary = write_report(conf.bag, conf.out, run)
    except (DemoError, RuntimeError, OSError) as exc:
        print(f'semfeat demo: {exc}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print('semfeat demo: interrupted; all processes stopped', file=sys.stderr)
        return 130
    (conf.out / 'summary.json').write_text(json.dumps(summary, indent=1, default=_json) + '\n')
    return 0


def _json(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(type(x).__name__)


if __name__ == '__main__':
    sys.exit(cli())

