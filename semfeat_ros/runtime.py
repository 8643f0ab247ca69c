"""Streaming building blocks of the nodes (no rclpy): rates, latency, latest-frame worker."""
from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
import threading
import time
from typing import Any, Generic, TypeVar

import numpy as np

T = TypeVar('T')
K = TypeVar('K')


class RateMeter:
    """Event rate (Hz) over a sliding time window (s), on a monotonic clock."""

    def __init__(self, window_s: float = 5.0, clock: Callable[[], float] = time.monotonic):
        self._window = float(window_s)
        self._clock = clock
        self._events: deque[float] = deque()
        self._lock = threading.Lock()

    def tick(self) -> None:
        with self._lock:
            now = self._clock()
            self._events.append(now)
            self._trim(now)

    def _trim(self, now: float) -> None:
        while self._events and now - self._events[0] > self._window:
            self._events.popleft()

    def rate(self) -> float:
        """Events per second over the window (0 with fewer than two events)."""
        with self._lock:
            self._trim(self._clock())
            if len(self._events) < 2:
                return 0.0
            span = self._events[-1] - self._events[0]
            return (len(self._events) - 1) / span if span > 0 else 0.0


class LatencyStats:
    """Percentiles of the last ``maxlen`` latencies (s)."""

    def __init__(self, maxlen: int = 500):
        self._values: deque[float] = deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        if np.isfinite(seconds):
            with self._lock:
                self._values.append(float(seconds))

    def percentiles(self, qs: tuple[float, ...] = (50.0, 95.0)) -> tuple[float, ...]:
        """Latency percentiles (s); NaN when empty."""
        with self._lock:
            if not self._values:
                return tuple(float('nan') for _ in qs)
            arr = np.fromiter(self._values, float)
        return tuple(float(np.percentile(arr, q)) for q in qs)

    def __len__(self) -> int:
        return len(self._values)


@dataclass
class Counters:
    """Frame accounting of one node (what /diagnostics reports)."""

    received: int = 0
    processed: int = 0
    dropped: int = 0
    rejected: int = 0
    waiting: int = 0  # inputs skipped before the first CameraInfo (not an input error)
    errors: int = 0


class LatestWorker(Generic[T]):
    """Runs ``fn`` on a background thread on the newest submitted item only.

    ``submit`` never blocks: an item that arrives while ``fn`` is busy replaces the one waiting,
    and the replaced item is counted in ``dropped``. At most one item waits, so memory is bounded
    whatever the input rate. Exceptions of ``fn`` go to ``on_error`` and the worker keeps going.
    """

    def __init__(self, fn: Callable[[T], None], on_error: Callable[[BaseException], None],
                 name: str = 'latest-worker'):
        self._fn = fn
        self._on_error = on_error
        self._cond = threading.Condition()
        self._pending: T | None = None
        self._has_pending = False
        self._busy = False
        self._stop = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, item: T) -> bool:
        """Queue ``item``; returns False when it replaced (dropped) a waiting item."""
        with self._cond:
            replaced = self._has_pending
            if replaced:
                self.dropped += 1
            self._pending = item
            self._has_pending = True
            self._cond.notify()
        return not replaced

    def idle(self) -> bool:
        """True when nothing is running or waiting."""
        with self._cond:
            return not self._busy and not self._has_pending

    def wait_idle(self, timeout: float) -> bool:
        """Block until idle or ``timeout`` (s); returns whether it became idle."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.idle():
                return True
            time.sleep(0.005)
        return self.idle()

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._has_pending and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                item = self._pending
                self._pending = None
                self._has_pending = False
                self._busy = True
            try:
                self._fn(item)  # type: ignore[arg-type]
            except Exception as exc:  # noqa: BLE001 - a worker must survive any bad frame
                self._on_error(exc)
            finally:
                with self._cond:
                    self._busy = False


class LoadGovernor:
    """Chooses a node's processing level from its compute time against the input frame period,
    so that a node falling behind steps down to its declared lighter levels before frames are
    dropped at random: level 0 is the full mode, each level after it lighter.

    ``costs`` are the levels' relative compute, full mode first (e.g. the network input's pixel
    count against the full mode's: ``[1.0, 0.64, 0.49]`` for 640, 512 and 448 px; ``[1.0]``: no
    light level, the level stays 0). The frame
    period is the median interval between the last ``window`` + 1 arrivals of input frames (wall
    clock: a bag replayed slower than recorded leaves more time per frame). The node steps one
    level down when a frame was dropped while the last one ran, or when the median compute time
    of the last ``window`` frames at the current level exceeds ``enter_ratio`` of the period; it
    steps one level up after ``leave_frames`` frames in a row without a drop whose compute time,
    scaled by the level above's relative cost, is within ``leave_ratio`` of the period (room for
    the level above). It starts at ``start_level``. Until the period is known (``window`` + 1
    arrivals) compute times count for nothing and only a drop changes the level. The
    subscription callback calls :meth:`on_input`, the worker thread :meth:`on_done`.
    """

    def __init__(self, costs: Sequence[float] = (1.0, 0.64), enter_ratio: float = 0.9,
                 leave_ratio: float = 0.75, leave_frames: int = 30, window: int = 8,
                 start_level: int = 0) -> None:
        if not 0.0 < leave_ratio < enter_ratio:
            raise ValueError(f'need 0 < leave_ratio < enter_ratio, got {leave_ratio}, '
                             f'{enter_ratio}')
        costs = [float(c) for c in costs]
        if not costs or costs[-1] <= 0 or any(a <= b for a, b in zip(costs, costs[1:])):
            raise ValueError(f'costs: the full mode first, each level cheaper than the one '
                             f'before and > 0, got {costs}')
        if leave_frames < 1 or window < 2 or not 0 <= start_level < len(costs):
            raise ValueError(f'leave_frames >= 1, window >= 2 and 0 <= start_level < '
                             f'{len(costs)}, got {leave_frames}, {window}, {start_level}')
        self.enter_ratio, self.leave_ratio = enter_ratio, leave_ratio
        self.leave_frames = leave_frames
        self.costs = costs
        self._lock = threading.Lock()
        self._arrivals: deque[int] = deque(maxlen=window + 1)
        self._level_s: deque[float] = deque(maxlen=window)  # compute at the current level
        self._calm = 0  # frames in a row with room for the level above
        self.level = start_level
        self.level_frames = [0] * len(costs)  # frames processed at each level
        self.switches = 0  # changes of level

    @property
    def levels(self) -> int:
        """Number of light levels (below the full mode)."""
        return len(self.costs) - 1

    @property
    def light_frames(self) -> int:
        """Frames processed below the full mode."""
        return sum(self.level_frames[1:])

    @property
    def light(self) -> bool:
        """True below the full mode."""
        return self.level > 0

    @property
    def period_s(self) -> float | None:
        """Median input frame period (s), None until enough arrivals."""
        with self._lock:
            if len(self._arrivals) < self._arrivals.maxlen:
                return None
            d = np.diff(np.asarray(self._arrivals, dtype=np.int64))
        d = d[d > 0]
        return float(np.median(d)) * 1e-9 if len(d) else None

    def on_input(self, t_ns: int) -> None:
        """An input frame arrived at ``t_ns`` (ns, a monotonic clock)."""
        with self._lock:
            if self._arrivals and t_ns <= self._arrivals[-1]:
                self._arrivals.clear()  # the clock went backwards: measure again
            self._arrivals.append(int(t_ns))

    def on_done(self, compute_s: float, dropped: bool) -> None:
        """The frame took ``compute_s`` (s) at the current level; ``dropped``: a newer frame
        replaced a waiting one meanwhile."""
        level = self.level
        self.level_frames[level] += 1
        period = self.period_s
        if period is None:  # warm-up: compute times say nothing yet, a drop does
            if dropped and level < self.levels:
                self._switch(level + 1)
            return
        if level > 0:
            above_s = compute_s * self.costs[level - 1] / self.costs[level]
            calm = not dropped and above_s <= self.leave_ratio * period
            self._calm = self._calm + 1 if calm else 0
            if self._calm >= self.leave_frames:
                self._switch(level - 1)
                return
        if level == self.levels:
            return  # the lightest level: nothing lighter to step down to
        self._level_s.append(compute_s)
        slow = (len(self._level_s) == self._level_s.maxlen
                and float(np.median(self._level_s)) > self.enter_ratio * period)
        if dropped or slow:
            self._switch(level + 1)

    def _switch(self, level: int) -> None:
        self.level = level
        self.switches += 1
        self._calm = 0
        self._level_s.clear()


class RateLimit:
    """At most one event per ``min_interval_s`` (s, on a monotonic clock); one instance can be
    shared by several :class:`ChangeGate` so that all the resets of a node are limited
    together."""

    def __init__(self, min_interval_s: float, clock: Callable[[], float] = time.monotonic):
        if not min_interval_s >= 0:
            raise ValueError(f'RateLimit: min_interval_s must be >= 0 s, got {min_interval_s}')
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._last = -float('inf')

    def ready(self) -> bool:
        """True when an event may happen now."""
        return self._clock() - self._last >= self.min_interval_s

    def mark(self) -> None:
        """An event happened now."""
        self._last = self._clock()


@dataclass
class GateCounts:
    """What a :class:`ChangeGate` decided so far (reported on /diagnostics)."""

    confirmed: int = 0  # changes accepted (each one resets the node's state)
    outliers: int = 0  # messages of runs that did not persist (ignored)
    deferred: int = 0  # confirmations held back by the rate limit
    trimmed: int = 0  # messages of a deferred run dropped to keep only the newest ``confirm``


class ChangeGate(Generic[K]):
    """Accepts a change of a stream's state (a new camera, a new timeline) only when it persists.

    The owner calls :meth:`agree` for a message that agrees with its current state and
    :meth:`offer` for one that does not. A change is confirmed when ``confirm`` consecutive
    messages offered it, each continuing the one before (``continues(previous_key, key)``:
    equal cameras, increasing stamps), and ``limit`` allows a change now (then it is marked).
    A message that agrees, or that does not continue
    the pending run, ends the run: its messages were outliers and are dropped. While the rate
    limit defers a confirmation, the newest ``confirm`` messages of the run are kept.

    Args:
        confirm: consecutive messages that make a change (1 = every message does).
        limit: the rate limit of confirmed changes (None: no limit).
        continues: whether ``key`` continues a run whose last key is ``previous_key``.
    """

    def __init__(self, confirm: int, limit: RateLimit | None = None,
                 continues: Callable[[K, K], bool] = lambda a, b: a == b) -> None:
        if confirm < 1:
            raise ValueError(f'ChangeGate: confirm must be >= 1, got {confirm}')
        self.confirm = int(confirm)
        self.limit = limit or RateLimit(0.0)
        self._continues = continues
        self._pending: list[tuple[K, Any]] = []
        self.counts = GateCounts()

    @property
    def pending(self) -> int:
        """Messages of the run waiting for confirmation."""
        return len(self._pending)

    def agree(self) -> int:
        """A message agreeing with the current state: a pending run was made of outliers.
        Returns how many messages were dropped."""
        dropped = len(self._pending)
        self.counts.outliers += dropped
        self._pending = []
        return dropped

    def offer(self, key: K, item: Any = None) -> tuple[list[Any] | None, int]:
        """A message disagreeing with the current state (``item``: what the owner wants back).

        Returns ``(run, dropped)``: ``run`` is the items of the confirmed run, oldest first (the
        owner resets its state to the new one and uses them), or None while the change waits;
        ``dropped`` counts the outliers discarded by this call (an ended run). While the rate
        limit defers a change, the oldest messages of the run beyond ``confirm`` are dropped and
        counted in ``counts.trimmed`` (they were not outliers).
        """
        dropped = 0
        if self._pending and not self._continues(self._pending[-1][0], key):
            dropped = self.agree()
        self._pending.append((key, item))
        if len(self._pending) < self.confirm:
            return None, dropped
        if not self.limit.ready():
            self.counts.deferred += 1
            extra = len(self._pending) - self.confirm
            if extra > 0:
                self._pending = self._pending[extra:]
                self.counts.trimmed += extra
            return None, dropped
        self.limit.mark()
        self.counts.confirmed += 1
        run, self._pending = [it for _, it in self._pending], []
        return run, dropped

    def clear(self) -> None:
        """Forget a pending run without counting it (the owner reset its state)."""
        self._pending = []


class StampGuard:
    """Orders a stream of stamps (ns): duplicates, and time going backwards (bag loop, clock
    reset) accepted only when it persists (:class:`ChangeGate` over increasing stamps).

    Args:
        tolerance_ns: a stamp at most this much older than the newest is a 'duplicate'.
        confirm: consecutive older stamps (each newer than the one before) that make a new
            timeline; 1 = any older stamp restarts.
        limit: the rate limit of restarts (None: no limit).
    """

    def __init__(self, tolerance_ns: int = 0, confirm: int = 1,
                 limit: RateLimit | None = None) -> None:
        self._last: int | None = None
        self._tol = int(tolerance_ns)
        self.gate: ChangeGate[int] = ChangeGate(confirm, limit, lambda a, b: b > a)
        self.run: list[Any] = []
        self.dropped = 0
        self.trimmed = 0

    def check(self, stamp_ns: int, item: Any = None) -> str:
        """'ok', 'duplicate' (same stamp again), 'held' (older than the newest stamp, kept until
        the jump persists or turns out an outlier) or 'backwards' (the jump persisted: the
        owner restarts and then uses :attr:`run`, the items of the held messages with this one
        last, oldest first). :attr:`dropped` counts the held messages this call found to be
        outliers and discarded, :attr:`trimmed` the held messages it dropped while the rate limit
        defers the restart."""
        last = self._last
        self.run, self.dropped, self.trimmed = [], 0, 0
        trimmed = self.gate.counts.trimmed
        if last is None or stamp_ns > last:
            self.dropped = self.gate.agree()
            self._last = stamp_ns
            return 'ok'
        if last - stamp_ns <= self._tol:
            return 'duplicate'
        run, self.dropped = self.gate.offer(stamp_ns, item)
        self.trimmed = self.gate.counts.trimmed - trimmed
        if run is None:
            return 'held'
        self._last = stamp_ns
        self.run = run
        return 'backwards'

    def reset(self) -> None:
        self._last = None
        self.gate.clear()


def cpu_has_bf16(cpuinfo: str | Path = '/proc/cpuinfo') -> bool:
    """True when the CPU advertises bfloat16 units (``avx512_bf16`` or ``amx_bf16`` flags):
    there bf16 autocast is faster than fp32 (measured here: 39 vs 47 ms per 640x512 forward,
    outputs within 1 px / cosine 0.9999). False when the flags cannot be read (not Linux)."""
    try:
        text = Path(cpuinfo).read_text(errors='replace')
    except OSError:
        return False
    for line in text.splitlines():
        if line.startswith('flags'):
            flags = set(line.split(':', 1)[-1].split())
            return bool(flags & {'avx512_bf16', 'amx_bf16'})
    return False
