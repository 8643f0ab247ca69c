"""Run the three nodes, the player and the recorder as separate processes (demo, replay tests).

This is what ``ros2 launch semfeat_ros semfeat.launch.py`` plus ``ros2 bag play/record`` do on a
real ROS 2 install; here it is plain subprocesses on an isolated, localhost-only DDS domain.
Every child is stopped with SIGINT (then SIGTERM, then SIGKILL) when the ``Pipeline`` closes,
including on Ctrl-C, so no process is left behind.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import IO

from semfeat_ros.paths import config_path

NODES = ('feature_node', 'matcher_node', 'mapping_node')


@dataclass
class PipelineConfig:
    """How the pipeline processes are started."""

    domain_id: int = 57  # ROS_DOMAIN_ID of every process (isolated from other runs)
    use_sim_time: bool = True  # nodes follow /clock from the player
    input_transport: str = 'compressed'  # camera transport of the bag: raw or compressed
    output_dir: Path = Path('out/demo')  # logs, recorded bag, saved map
    node_params: dict[str, dict[str, str]] = field(default_factory=dict)  # extra -p per node


def ros_environment(domain_id: int) -> dict[str, str]:
    """The environment of a child process: isolated domain, localhost discovery only."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1', OPENBLAS_NUM_THREADS='1', OMP_WAIT_POLICY='PASSIVE',
               RCUTILS_COLORIZED_OUTPUT='0')
    env.pop('ROS_LOCALHOST_ONLY', None)
    return env


class Pipeline:
    """Owns the child processes; use as a context manager."""

    def __init__(self, conf: PipelineConfig):
        self.conf = conf
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: dict[str, IO[str]] = {}
        self.env = ros_environment(conf.domain_id)
        (conf.output_dir / 'logs').mkdir(parents=True, exist_ok=True)

    def __enter__(self) -> Pipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()

    def log_path(self, name: str) -> Path:
        return self.conf.output_dir / 'logs' / f'{name}.log'

    def start(self, name: str, argv: list[str]) -> subprocess.Popen:
        log = open(self.log_path(name), 'w', encoding='utf-8')  # noqa: SIM115 - closed in stop
        self._logs[name] = log
        proc = subprocess.Popen(argv, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
        self.procs[name] = proc
        return proc

    def node_argv(self, node: str) -> list[str]:
        c = self.conf
        params = {'use_sim_time': 'true' if c.use_sim_time else 'false'}
        if node in ('feature_node', 'matcher_node'):
            params['input_transport'] = c.input_transport
        if node in ('feature_node', 'mapping_node'):
            params['input_reliability'] = 'reliable'  # a replayed bag loses nothing at the source
        if node == 'mapping_node':
            params['output_dir'] = str(c.output_dir.resolve())
        params.update(c.node_params.get(node, {}))
        argv = [sys.executable, '-m', f'semfeat_ros.nodes.{node}', '--ros-args',
                '--params-file', str(config_path(f'{node}.yaml'))]
        for key, value in params.items():
            argv += ['-p', f'{key}:={value}']
        return argv

    def start_nodes(self) -> None:
        for node in NODES:
            self.start(node, self.node_argv(node))

    def check_alive(self) -> None:
        """Raise RuntimeError naming a child that died, with the end of its log."""
        for name, proc in self.procs.items():
            if proc.poll() is not None and proc.returncode != 0:
                tail = self.log_path(name).read_text(errors='replace')[-1500:]
                raise RuntimeError(f'{name} exited with status {proc.returncode}:\n{tail}')

    def stop(self, name: str, timeout: float = 15.0) -> int | None:
        proc = self.procs.get(name)
        if proc is None:
            return None
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if proc.poll() is not None:
                break
            proc.send_signal(sig)
            try:
                proc.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        log = self._logs.pop(name, None)
        if log is not None:
            log.close()
        return proc.returncode

    def stop_all(self) -> dict[str, int | None]:
        codes = {}
        for name in reversed(list(self.procs)):
            codes[name] = self.stop(name)
        return codes


def wait_for_nodes(names: tuple[str, ...], pipeline: Pipeline, timeout: float = 120.0) -> None:
    """Block until every node in ``names`` is on the graph (checked from a probe process)."""
    probe = ('import rclpy, sys, time\nrclpy.init()\nn = rclpy.create_node("semfeat_probe")\n'
             f'want = set({list(names)!r})\nt = time.monotonic()\n'
             f'while time.monotonic() - t < {timeout}:\n'
             '    rclpy.spin_once(n, timeout_sec=0.2)\n'
             '    if want <= set(n.get_node_names()):\n'
             '        sys.exit(0)\n'
             'sys.exit(1)\n')
    proc = subprocess.Popen([sys.executable, '-c', probe], env=pipeline.env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout + 30
    while proc.poll() is None and time.monotonic() < deadline:
        pipeline.check_alive()
        time.sleep(0.2)
    if proc.poll() is None:
        proc.kill()
    if proc.wait() != 0:
        pipeline.check_alive()
        raise RuntimeError(f'nodes {names} did not come up within {timeout:.0f} s '
                           f'(logs in {pipeline.conf.output_dir / "logs"})')
