"""The machine a benchmark ran on and what else ran on it: CPU, versions, /proc samples
of the process (CPU %, RSS) and the system load during each named section."""
from __future__ import annotations

import os
import platform
import threading
import time
from typing import Any

import cv2
import numpy as np


def _read_text(path: str) -> str:
    try:
        with open(path, encoding='utf-8') as f:
            return f.read()
    except OSError:
        return ''


def _version(dist: str) -> str:
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return 'not installed'


def machine_info(threads: int) -> dict[str, Any]:
    """CPU model, cores, RAM, OS and library versions (read without importing torch/gtsam)."""
    cpu = 'unknown'
    flags: set[str] = set()
    for line in _read_text('/proc/cpuinfo').splitlines():
        key, _, value = line.partition(':')
        if key.strip() == 'model name' and cpu == 'unknown':
            cpu = value.strip()
        elif key.strip() == 'flags' and not flags:
            flags = set(value.split())
    mem_kb = 0
    for line in _read_text('/proc/meminfo').splitlines():
        if line.startswith('MemTotal:'):
            mem_kb = int(line.split()[1])
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count() or 0
    simd = [f for f in ('avx2', 'avx512f', 'avx512_bf16', 'amx_bf16') if f in flags]
    return {
        'cpu': cpu, 'simd': simd, 'logical_cpus': os.cpu_count(), 'usable_cpus': usable,
        'ram_gb': round(mem_kb / 1024 ** 2, 1), 'kernel': platform.release(),
        'python': platform.python_version(), 'torch': _version('torch'),
        'numpy': np.__version__, 'opencv': cv2.__version__, 'gtsam': _version('gtsam'),
        'threads': threads, 'load_average_start': list(os.getloadavg()),
    }



def read_proc(pid: int) -> tuple[float, float]:
    """``(cpu_s, rss_mb)`` of process ``pid``: user + system CPU time (s) and resident set
    size (MB) from ``/proc/<pid>/stat`` and ``/proc/<pid>/status``.

    Raises:
        OSError: the process does not exist (or /proc is not mounted).
    """
    with open(f'/proc/{pid}/stat', encoding='ascii') as f:
        stat = f.read()
    fields_ = stat.rsplit(')', 1)[1].split()  # after the command name: state is field 3
    ticks = os.sysconf('SC_CLK_TCK')
    cpu_s = (int(fields_[11]) + int(fields_[12])) / ticks  # utime, stime (fields 14, 15)
    rss_kb = 0
    with open(f'/proc/{pid}/status', encoding='ascii') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                rss_kb = int(line.split()[1])
                break
    return cpu_s, rss_kb / 1024.0


class ProcSampler:
    """Samples CPU % and RSS (MB) of a process every ``period_s`` in a background thread."""

    def __init__(self, pid: int | None = None, period_s: float = 1.0) -> None:
        self.pid = os.getpid() if pid is None else int(pid)
        self.period_s = float(period_s)
        self.t_s: list[float] = []
        self.cpu_pct: list[float] = []
        self.rss_mb: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='proc-sampler', daemon=True)
        self._t0 = 0.0
        self._last: tuple[float, float] | None = None

    def _sample(self) -> None:
        now = time.perf_counter()
        cpu_s, rss = read_proc(self.pid)
        if self._last is not None:
            dt = now - self._last[0]
            self.t_s.append(now - self._t0)
            self.cpu_pct.append(100.0 * (cpu_s - self._last[1]) / dt if dt > 0 else 0.0)
            self.rss_mb.append(rss)
        self._last = (now, cpu_s)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self._sample()

    def __enter__(self) -> ProcSampler:
        self._t0 = time.perf_counter()
        self._sample()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()


class LoadMonitor:
    """Records the 1-minute load average every ``period_s`` (background thread) and the wall
    time windows of named sections, to report how busy the machine was during each."""

    def __init__(self, period_s: float = 2.0) -> None:
        self.period_s = float(period_s)
        self.samples: list[tuple[float, float]] = []  # (perf_counter, load1)
        self.sections: dict[str, tuple[float, float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='load-monitor', daemon=True)

    def _run(self) -> None:
        while True:
            self.samples.append((time.perf_counter(), os.getloadavg()[0]))
            if self._stop.wait(self.period_s):
                return

    def start(self) -> LoadMonitor:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def section(self, name: str) -> _Section:
        """Context manager timing the section ``name``."""
        return _Section(self, name)

    def summary(self) -> dict[str, dict[str, float | None]]:
        """``{section: {'minutes', 'load1_mean', 'load1_max'}}``."""
        out: dict[str, dict[str, float | None]] = {}
        for name, (t0, t1) in self.sections.items():
            loads = [v for t, v in self.samples if t0 <= t <= t1]
            if not loads and self.samples:  # a section shorter than the period: nearest one
                loads = [min(self.samples, key=lambda s: abs(s[0] - t1))[1]]
            out[name] = {'minutes': (t1 - t0) / 60.0,
                         'load1_mean': float(np.mean(loads)) if loads else None,
                         'load1_max': float(np.max(loads)) if loads else None}
        return out


class _Section:
    def __init__(self, monitor: LoadMonitor, name: str) -> None:
        self.monitor = monitor
        self.name = name
        self.t0 = 0.0

    def __enter__(self) -> _Section:
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.monitor.sections[self.name] = (self.t0, time.perf_counter())
