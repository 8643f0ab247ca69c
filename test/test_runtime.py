"""Streaming building blocks: rates, latency percentiles, newest-frame worker, stamp guard."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from semfeat_ros.runtime import (
    ChangeGate,
    LatencyStats,
    LatestWorker,
    LoadGovernor,
    RateLimit,
    RateMeter,
    StampGuard,
)


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_rate_meter_window() -> None:
    clock = FakeClock()
    meter = RateMeter(window_s=2.0, clock=clock)
    assert meter.rate() == 0.0
    for _ in range(21):
        meter.tick()
        clock.t += 0.1
    assert abs(meter.rate() - 10.0) < 1e-9
    clock.t += 5.0
    assert meter.rate() == 0.0


def test_latency_percentiles() -> None:
    stats = LatencyStats(maxlen=100)
    assert all(np.isnan(stats.percentiles()))
    for v in range(1, 101):
        stats.add(v / 1000)
    stats.add(float('nan'))
    p50, p95 = stats.percentiles()
    assert len(stats) == 100
    assert abs(p50 - 0.0505) < 1e-9 and abs(p95 - 0.09505) < 1e-9


def test_latest_worker_keeps_only_newest_and_counts_drops() -> None:
    gate = threading.Event()
    seen: list[int] = []

    def work(item: int) -> None:
        gate.wait(5)
        seen.append(item)

    worker = LatestWorker(work, on_error=lambda exc: None)
    try:
        assert worker.submit(0)
        time.sleep(0.05)  # 0 is now running and blocked on the gate
        results = [worker.submit(i) for i in range(1, 6)]
        assert results == [True, False, False, False, False]
        assert worker.dropped == 4
        gate.set()
        assert worker.wait_idle(5)
        assert seen == [0, 5]
    finally:
        worker.stop()


def test_latest_worker_survives_errors() -> None:
    errors: list[BaseException] = []
    done: list[int] = []

    def work(item: int) -> None:
        if item == 1:
            raise ValueError('bad frame')
        done.append(item)

    worker = LatestWorker(work, on_error=errors.append)
    try:
        worker.submit(1)
        assert worker.wait_idle(5)
        worker.submit(2)
        assert worker.wait_idle(5)
    finally:
        worker.stop()
    assert done == [2] and len(errors) == 1 and 'bad frame' in str(errors[0])


def test_stamp_guard() -> None:
    guard = StampGuard()
    assert [guard.check(s) for s in (10, 20, 20, 5, 6)] == [
        'ok', 'ok', 'duplicate', 'backwards', 'ok']


def test_stamp_guard_needs_a_persisting_jump_back() -> None:
    clock = FakeClock()
    guard = StampGuard(confirm=3, limit=RateLimit(10.0, clock))
    seen = [guard.check(s, item=s) for s in (100, 110, 50, 120, 130)]
    assert seen == ['ok', 'ok', 'held', 'ok', 'ok']  # a lone older stamp: no restart
    assert guard.dropped == 0 and guard.gate.counts.outliers == 1
    assert [guard.check(s, item=s) for s in (10, 20)] == ['held', 'held']
    assert guard.check(30, item=30) == 'backwards' and guard.run == [10, 20, 30]
    assert guard.check(40) == 'ok'
    # a second loop within min_interval_s waits; the newest `confirm` stamps are kept
    assert [guard.check(s, item=s) for s in (1, 2, 3, 4)] == ['held'] * 4
    assert guard.dropped == 0 and guard.trimmed == 1 and guard.gate.counts.deferred == 2
    assert guard.gate.counts.outliers == 1
    clock.t = 11.0
    assert guard.check(5, item=5) == 'backwards' and guard.run == [2, 3, 4, 5]
    assert guard.gate.counts.confirmed == 2
    # older stamps that are not a timeline of their own (not increasing) never restart
    assert [guard.check(s) for s in (6, 7, 3, 2, 1, 8)] == ['ok', 'ok', 'held', 'held', 'held',
                                                            'ok']
    assert guard.gate.counts.confirmed == 2


def test_change_gate_confirms_only_consecutive_equal_keys() -> None:
    gate: ChangeGate[str] = ChangeGate(confirm=2)
    assert gate.offer('b') == (None, 0)
    assert gate.agree() == 1  # 'b' was a lone outlier
    assert gate.offer('b') == (None, 0)
    assert gate.offer('c') == (None, 1)  # 'c' does not continue 'b'
    assert gate.offer('c', item='x') == ([None, 'x'], 0)
    assert gate.counts.confirmed == 1 and gate.counts.outliers == 2


def test_cpu_has_bf16_reads_the_flags(tmp_path) -> None:
    from semfeat_ros.runtime import cpu_has_bf16

    info = tmp_path / 'cpuinfo'
    info.write_text('processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16\n')
    assert cpu_has_bf16(info)
    info.write_text('processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f\n')
    assert not cpu_has_bf16(info)
    assert not cpu_has_bf16(tmp_path / 'missing')


def _feed(g: LoadGovernor, stamps: range, compute_s: float, dropped: bool = False) -> None:
    for stamp in stamps:
        g.on_input(stamp)
        g.on_done(compute_s, dropped)


def test_load_governor_enters_light_mode_when_slow_and_leaves_with_room() -> None:
    period = 100_000_000  # 10 Hz, ns
    g = LoadGovernor(enter_ratio=0.9, leave_ratio=0.75, leave_frames=5, window=4)  # 1, 0.64
    _feed(g, range(0, 4 * period, period), 0.2)  # slow warm-up frames count for nothing
    assert not g.light and g.period_s is None  # the period is not known yet
    _feed(g, range(4 * period, 8 * period, period), 0.08)
    assert g.period_s == pytest.approx(0.1) and not g.light  # 80 ms of 100: full mode
    _feed(g, range(8 * period, 10 * period, period), 0.095)
    assert not g.light  # median of the last four still 80-95 ms ...
    _feed(g, range(10 * period, 12 * period, period), 0.095)
    assert g.light and g.switches == 1  # ... now above 90 ms: light mode
    _feed(g, range(12 * period, 16 * period, period), 0.045)
    assert g.light  # four calm frames of the five needed (45 ms x 1 / 0.64 <= 75 ms)
    _feed(g, range(16 * period, 17 * period, period), 0.06)
    assert g.light  # 60 ms x 1 / 0.64 leaves no room for the full mode: the count restarts
    _feed(g, range(17 * period, 22 * period, period), 0.045)
    assert not g.light and g.switches == 2 and g.light_frames == 11


def test_load_governor_steps_through_its_levels_one_at_a_time() -> None:
    period = 100_000_000  # 10 Hz, ns
    g = LoadGovernor([1.0, 0.64, 0.49], leave_frames=3, window=2)
    _feed(g, range(0, 2 * period, period), 0.2)  # warm-up: the period is not known yet
    assert g.level == 0 and g.period_s is None
    _feed(g, range(2 * period, 4 * period, period), 0.12)
    assert g.level == 1 and g.light and g.switches == 1  # slow at full: first light level
    _feed(g, range(4 * period, 5 * period, period), 0.095)
    assert g.level == 1  # one slow frame at the new level: its window is not full yet
    _feed(g, range(5 * period, 6 * period, period), 0.095)
    assert g.level == 2 and g.switches == 2  # still slow: the lightest level
    _feed(g, range(6 * period, 8 * period, period), 0.2, dropped=True)
    assert g.level == 2  # nothing lighter to step down to
    _feed(g, range(8 * period, 11 * period, period), 0.04)
    assert g.level == 1 and g.switches == 3  # room for the level above: one step up
    _feed(g, range(11 * period, 12 * period, period), 0.04, dropped=True)
    assert g.level == 2  # a drop at level 1 steps down again
    _feed(g, range(12 * period, 18 * period, period), 0.04)
    assert g.level == 0 and not g.light and g.light_frames == 14
    assert g.level_frames == [4, 6, 8]  # frames at each level, the warm-up at full included
    for bad in ([], [1.0, 1.2], [1.0, 0.0], [1.0, 0.5, 0.5]):
        with pytest.raises(ValueError, match='costs'):
            LoadGovernor(bad)
    with pytest.raises(ValueError, match='start_level'):
        LoadGovernor([1.0, 0.64], start_level=2)


def test_load_governor_steps_down_on_a_warm_up_drop_and_may_start_light() -> None:
    period = 100_000_000
    g = LoadGovernor([1.0, 0.64, 0.49], start_level=1)
    assert g.level == 1 and g.light
    _feed(g, range(0, 2 * period, period), 0.3)  # slow, but the period is not known yet
    assert g.level == 1
    _feed(g, range(2 * period, 3 * period, period), 0.3, dropped=True)
    assert g.level == 2 and g.period_s is None  # a drop needs no period
    assert LoadGovernor([1.0]).levels == 0  # no light level: the level stays 0
    g = LoadGovernor([1.0], window=2)
    _feed(g, range(0, 5 * period, period), 0.3, dropped=True)
    assert g.level == 0 and g.level_frames == [5]


def test_load_governor_switches_on_a_drop_and_restarts_on_a_bag_loop() -> None:
    period = 50_000_000
    g = LoadGovernor(leave_frames=3, window=3)
    _feed(g, range(0, 4 * period, period), 0.01)
    assert not g.light
    _feed(g, range(4 * period, 5 * period, period), 0.01, dropped=True)
    assert g.light and g.period_s == pytest.approx(0.05)
    g.on_input(0)  # the clock went backwards: the period is measured again
    assert g.period_s is None
    with pytest.raises(ValueError):
        LoadGovernor(enter_ratio=0.5, leave_ratio=0.6)
