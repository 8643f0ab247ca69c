"""Per-node health accounting published on /diagnostics (diagnostic_msgs/DiagnosticArray).

One status per node, its hardware_id the node's fully qualified name. Level: ERROR while an
input the node needs is silent for ``input_timeout_s``; WARN on processing errors, rejected
inputs, more than ``drop_warn_ratio`` of the frames received since the previous report dropped,
incompatible QoS, or no output yet; OK otherwise. A node adds its own conditions
(:attr:`NodeHealth.conditions`, e.g. mapping_node's :class:`SolverHealth`): the status takes
a condition's level when it is higher, and lists every ERROR.
"""
from __future__ import annotations

from collections.abc import Callable
import math
import time
from typing import NoReturn, Protocol

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import rclpy
from rclpy.executors import Executor, ExternalShutdownException
import rclpy.logging
from rclpy.node import Node

from semfeat_ros.nodes.qos import Endpoints
from semfeat_ros.runtime import Counters, LatencyStats, RateMeter


class Condition(Protocol):
    """A node-specific part of the status."""

    def level(self) -> tuple[int, str] | None:
        """(DiagnosticStatus level, message) while the condition holds, else None."""

    def values(self) -> dict[str, str]:
        """Key/values added to the status."""


class SolverHealth:
    """The mapper's solver, judged from its per-frame results (``MapperResult.state`` and
    ``.events``, see :mod:`semfeat_ros.mapping.backend`).

    Level: ERROR while the mapper is 'lost' (poses are predictions until it re-initialises), and
    for ``error_frames`` frames from one whose failed update could not be recovered (event
    'window_reset': the window restarted from the newest keyframe, or 'smoother_reset': the
    smoother started over); WARN for ``warn_frames`` frames from any failed update (event
    'update_failed: ...'; a recovered one rebuilt the smoother, 'update_recovered'); OK
    otherwise. Frames are counted, not seconds, so a replay at any rate reads the same.
    :meth:`new_map` ends both holds (the failure belonged to the map that was discarded); the
    counters run from start-up, over map resets.
    """

    def __init__(self, error_frames: int, warn_frames: int) -> None:
        self.error_frames = error_frames
        self.warn_frames = warn_frames
        self.counts = {'update_failures': 0, 'recoveries': 0, 'window_resets': 0,
                       'smoother_resets': 0, 'tracking_lost': 0}
        self.state = ''
        self.last_failure = ''
        self._frames = 0
        self._failed_at: int | None = None  # frame number of the last failed update
        self._unrecovered_at: int | None = None  # ... of the last window or smoother reset

    def on_result(self, state: str, events: tuple[str, ...]) -> None:
        """One mapped frame: the mapper's state after it and the events it reported."""
        self._frames += 1
        self.state = state
        failures = [e for e in events if e.startswith(('update_failed', 'rebuild_failed',
                                                       'smoother_reset'))]
        self.counts['update_failures'] += sum(e.startswith('update_failed') for e in events)
        self.counts['recoveries'] += events.count('update_recovered')
        self.counts['window_resets'] += events.count('window_reset')
        self.counts['smoother_resets'] += sum(e.startswith('smoother_reset') for e in events)
        self.counts['tracking_lost'] += events.count('tracking_lost')
        if failures:
            self.last_failure = failures[0]
            self._failed_at = self._frames
        if 'window_reset' in events:
            self._unrecovered_at = self._failed_at = self._frames
            if not failures:
                self.last_failure = 'window_reset'

    def new_map(self) -> None:
        """The map was reset: earlier failures no longer hold the level."""
        self._failed_at = self._unrecovered_at = None
        self.state = ''

    def _within(self, at: int | None, frames: int) -> int | None:
        """Frames since ``at`` when fewer than ``frames`` (the frame itself is 0)."""
        if at is None:
            return None
        ago = self._frames - at
        return ago if ago < frames else None

    def level(self) -> tuple[int, str] | None:
        if self.state == 'lost':
            return (DiagnosticStatus.ERROR,
                    'mapper lost: poses are predictions until it re-initialises')
        ago = self._within(self._unrecovered_at, self.error_frames)
        if ago is not None:
            return (DiagnosticStatus.ERROR, f'solver failed {ago} frames ago and could not be '
                    f'recovered: the window was reset ({self.last_failure})')
        ago = self._within(self._failed_at, self.warn_frames)
        if ago is not None:
            return (DiagnosticStatus.WARN,
                    f'solver update failed {ago} frames ago ({self.last_failure})')
        return None

    def values(self) -> dict[str, str]:
        return {**{f'solver_{k}': str(v) for k, v in self.counts.items()},
                'solver_last_failure': self.last_failure}


class NodeHealth:
    """Counts and rates of one node; ``publish()`` sends them as one DiagnosticStatus.

    Latency is measured from the input message's header stamp to the moment the output is
    published, on the node's clock (sim time during bag replay with /clock).
    """

    def __init__(self, node: Node, *, input_timeout_s: float = 0.0,
                 drop_warn_ratio: float = 1.0):
        self._node = node
        self._hardware_id = node.get_fully_qualified_name()
        self.io = Endpoints(node, input_timeout_s)
        self.drop_warn_ratio = drop_warn_ratio
        self._reported = (0, 0)  # received, dropped at the previous publish()
        self._window = (0, 0)  # received, dropped between the two previous publish() calls
        self.counters = Counters()
        self.input_rate = RateMeter()
        self.output_rate = RateMeter()
        self.latency = LatencyStats()
        self.compute = LatencyStats()
        self.last_error = ''
        self.extra: dict[str, str] = {}
        self.conditions: list[Condition] = []
        self._pub = self.io.publish(DiagnosticArray, '/diagnostics', 10, managed=False)

    def on_input(self) -> None:
        self.counters.received += 1
        self.input_rate.tick()

    def on_output(self, stamp_ns: int, compute_s: float | None = None) -> None:
        self.counters.processed += 1
        self.output_rate.tick()
        now_ns = self._node.get_clock().now().nanoseconds
        if stamp_ns > 0:
            self.latency.add((now_ns - stamp_ns) * 1e-9)
        if compute_s is not None:
            self.compute.add(compute_s)

    def on_reject(self, reason: str, count: int = 1) -> None:
        """Count ``count`` rejected inputs and log the reason, throttled (the node keeps
        running)."""
        self.counters.rejected += count
        self.last_error = reason
        self._node.get_logger().warning(f'rejected input: {reason}', throttle_duration_sec=2.0)

    def on_waiting(self, reason: str) -> None:
        """Count an input skipped before the node can use it (no CameraInfo yet): not an
        error of the input, e.g. the first frame of a replay racing its camera's discovery."""
        self.counters.waiting += 1
        self._node.get_logger().info(f'skipped input: {reason}', throttle_duration_sec=2.0)

    def on_error(self, exc: BaseException) -> None:
        """Count an internal error (processing failed on an accepted input)."""
        self.counters.errors += 1
        self.last_error = f'{type(exc).__name__}: {exc}'
        self._node.get_logger().error(f'processing failed: {self.last_error}',
                                      throttle_duration_sec=2.0)

    def status(self) -> DiagnosticStatus:
        c = self.counters
        p50, p95 = self.latency.percentiles()
        c50, c95 = self.compute.percentiles()
        level = DiagnosticStatus.OK
        message = 'ok'
        if c.errors:
            level, message = DiagnosticStatus.WARN, f'{c.errors} processing errors'
        elif c.rejected:
            level, message = DiagnosticStatus.WARN, f'{c.rejected} inputs rejected'
        received, dropped = self._window
        if received and dropped > self.drop_warn_ratio * received:
            level, message = (DiagnosticStatus.WARN,
                              f'{dropped} of {received} frames dropped since the last report')
        if self.io.incompatible:
            level, message = (DiagnosticStatus.WARN,
                              f'{self.io.incompatible} incompatible QoS events')
        if c.received and not c.processed:
            level, message = DiagnosticStatus.WARN, 'no output yet'
            if c.waiting:  # e.g. a wrong camera_info topic: say so where operators look
                message += f': {c.waiting} inputs waiting for CameraInfo'
        silent = self.io.silent()
        errors = list(silent)
        for condition in self.conditions:
            found = condition.level()
            if found is not None and found[0] == DiagnosticStatus.ERROR:
                errors.append(found[1])
            elif found is not None and found[0] > level:
                level, message = found
        if errors:
            level, message = DiagnosticStatus.ERROR, '; '.join(errors)

        def fmt(x: float) -> str:
            return 'nan' if math.isnan(x) else f'{x:.4f}'

        values = {
            'input_hz': f'{self.input_rate.rate():.2f}',
            'output_hz': f'{self.output_rate.rate():.2f}',
            'latency_p50_s': fmt(p50), 'latency_p95_s': fmt(p95),
            'compute_p50_s': fmt(c50), 'compute_p95_s': fmt(c95),
            'frames_received': str(c.received), 'frames_processed': str(c.processed),
            'frames_dropped': str(c.dropped), 'errors_rejected': str(c.rejected),
            'frames_waiting_camera_info': str(c.waiting),
            'processing_errors': str(c.errors), 'last_error': self.last_error,
            'qos_incompatible': str(self.io.incompatible), 'silent_inputs': str(len(silent)),
            **{k: v for condition in self.conditions for k, v in condition.values().items()},
            **self.extra,
        }
        return DiagnosticStatus(
            level=level, name=f'{self._node.get_name()}: pipeline', message=message,
            hardware_id=self._hardware_id,
            values=[KeyValue(key=k, value=v) for k, v in values.items()])

    def publish(self) -> None:
        now = (self.counters.received, self.counters.dropped)
        self._window = (now[0] - self._reported[0], now[1] - self._reported[1])
        self._reported = now
        msg = DiagnosticArray()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.status = [self.status()]
        self._pub.publish(msg)


def startup_failed(node_name: str, exc: BaseException) -> NoReturn:
    """Report a node that cannot start (one clear line, no traceback) and exit with status 1."""
    rclpy.logging.get_logger(node_name).fatal(f'cannot start: {exc}')
    rclpy.try_shutdown()
    raise SystemExit(1)


def spin_node(name: str, make_node: Callable[[], Node],
              make_executor: Callable[[], Executor], args: list[str] | None = None) -> None:
    """``main()`` of every node: init, build, spin until Ctrl-C or shutdown, clean up."""
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = make_node()
        except (OSError, ValueError) as exc:  # missing weights, bad parameters or config files
            startup_failed(name, exc)
        executor = make_executor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


def wall_time() -> float:
    """Monotonic seconds for compute-time measurements."""
    return time.perf_counter()
