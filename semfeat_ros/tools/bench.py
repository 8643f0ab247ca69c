"""``semfeat-bench``: speed and resource benchmark of the pipeline against OpenCV ORB and SIFT.

usage: semfeat-bench [--bag BAG] [--out out/bench] [--doc docs/BENCHMARKS.md] [--frames N]
                     [--hires-frames N] [--hires-size WxH] [--e2e-frames N]
                     [--soak-minutes M] [--keyframes K] [--warmup N]
                     [--forward-repeats N] [--weights W] [--threads T] [--quick] [--quiet]

A command, not a test: it measures, in one process and one run,

1. per-stage latency (p50 / p95, ms) at the bag's 640x512 and at 1920x1536 (real frames
   rendered by the simulator at that size, JPEG-encoded so decoding is real): decode, network
   (resize + forward), NMS / top-k / descriptors / mask / bearings, descriptor matching,
   geometric verification, the sequential matcher; next to OpenCV ORB and SIFT (1000 features,
   ``cv2.BFMatcher`` cross-check matching, the same verification) on the SAME decoded frames,
   interleaved frame by frame, with the ratios of the medians;
2. the end-to-end sustained rate (Hz, wall clock) of decode -> front end -> matcher -> mapping
   session over the bag, for the network and for the ORB / SIFT front ends (the code of
   ``semfeat-map``, configured from the nodes' YAML files), with the mapping update time;
3. a soak: the bag replayed in a loop through one persistent in-process pipeline for
   ``--soak-minutes``, sampling the process's CPU % and RSS every second (``/proc``), with the
   RSS slope (MB/min) and the frame-time slope (ms/min), least squares;
4. the iSAM2 update time against the keyframe count
   (:func:`semfeat_ros.mapping.benchmark.benchmark_update_time`);
5. the pure network forward variants (:func:`semfeat_ros.model.benchmark.time_forward`).

Writes ``--doc`` (Markdown: machine, command, tables) atomically and the figures
``bench_*.png`` into the ``img/`` directory next to it; the raw numbers go to
``<out>/results.json`` and the rendered 1920x1536 frames are cached in ``<out>/frames_WxH/``.
Nothing is written anywhere else.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
import datetime
import json
import os
from pathlib import Path
import platform
import shlex
import sys
import threading
import time
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from msg_adapters import navsatfix_to_numpy, odometry_to_numpy, stamp_to_ns, to_rgb_or_mono
from msg_adapters.errors import MessageError
from msg_adapters.stamp import make_header
from semfeat_ros.camera import CameraModel
from semfeat_ros.offline.bag import BagSource, one_line, resolve_bag_path, typestore
from semfeat_ros.offline.errors import OfflineConfigError, OfflineError, OutputPathError
from semfeat_ros.offline.paths import confined, prepare_out_dir

PROG = 'semfeat-bench'
FRONTENDS = ('semfeat', 'orb', 'sift')
JPEG_QUALITY = 80  # quality of the bundled bag's frames (semfeat-sim --jpeg-quality 80)
CAMERA_FRAME = 'camera_front_optical'
COMPRESSED_FORMAT = 'rgb8; jpeg compressed bgr8'
FRAME_PERIOD_NS = 100_000_000  # 10 Hz, the bundled bag's rate
IMAGE_DELAY_NS = 50_000_000  # soak: a frame is mapped once odometry 50 ms past it is read
CACHE_VERSION = 1


def default_bag() -> Path:
    """The bundled bag ``bags/garage_ramp_seed0`` of a source checkout."""
    from semfeat_ros.paths import share_dir

    return share_dir() / 'bags' / 'garage_ramp_seed0'


@dataclass
class BenchConfig:
    """What to measure (counts of samples, frames, minutes, keyframes)."""

    frames: int = 100  # timed samples per stage and resolution
    hires_frames: int = 8  # rendered frames at hires_size (cached in <out>)
    hires_size: tuple[int, int] = (1920, 1536)  # px
    hires_seed: int = 0  # simulator seed of the rendered frames (the bag's seed)
    e2e_frames: int = 0  # frames of the end-to-end runs; 0 = the whole bag
    soak_minutes: float = 10.0  # 0 skips the soak
    keyframes: int = 2000  # iSAM2 scaling run; 0 skips it
    forward_repeats: int = 10  # timed forwards per network variant; 0 skips them
    warmup: int = 2  # untimed iterations before every timed series
    weights: str | None = None  # None: the shipped weights
    threads: int | None = None  # torch and OpenCV threads; None: feature_node.yaml num_threads
    progress: bool = True
    command: str = PROG  # the command line written into the document

    def validate(self) -> None:
        """Raise :class:`OfflineConfigError` naming the first invalid option."""
        checks = [('--frames', self.frames, 2), ('--hires-frames', self.hires_frames, 2),
                  ('--e2e-frames', self.e2e_frames, 0), ('--keyframes', self.keyframes, 0),
                  ('--warmup', self.warmup, 0), ('--forward-repeats', self.forward_repeats, 0)]
        for name, value, low in checks:
            if not isinstance(value, int) or value < low:
                raise OfflineConfigError(f'{name} must be an integer >= {low}, got {value!r}')
        if 0 < self.keyframes < 10:
            raise OfflineConfigError(f'--keyframes must be 0 or >= 10, got {self.keyframes}')
        if not 0.0 <= self.soak_minutes <= 24 * 60:
            raise OfflineConfigError(
                f'--soak-minutes must be in [0, 1440], got {self.soak_minutes}')
        w, h = self.hires_size
        if not (64 <= w <= 4096 and 64 <= h <= 4096):
            raise OfflineConfigError(f'--hires-size must be within 64..4096 px, got {w}x{h}')
        if self.threads is not None and not 1 <= self.threads <= 256:
            raise OfflineConfigError(f'--threads must be in 1..256, got {self.threads}')


@dataclass
class BenchPaths:
    """Input bag, output directory (results, frame cache) and the Markdown document."""

    bag: Path = field(default_factory=default_bag)
    out: Path = Path('out/bench')
    doc: Path = Path('docs/BENCHMARKS.md')

    @property
    def img_dir(self) -> Path:
        """Directory of the figures: ``img/`` next to the document."""
        return self.doc.parent / 'img'


# --------------------------------------------------------------------------------- statistics

def summarize(values: Sequence[float]) -> dict[str, float | int | None]:
    """``{'n', 'p50', 'p95', 'mean'}`` of ``values`` (ms); None entries without values."""
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {'n': 0, 'p50': None, 'p95': None, 'mean': None}
    return {'n': int(a.size), 'p50': float(np.median(a)), 'p95': float(np.percentile(a, 95)),
            'mean': float(a.mean())}


def ratio(a: float | None, b: float | None) -> float | None:
    """``a / b`` or None when either is missing or ``b`` is not positive."""
    if a is None or b is None or not b > 0:
        return None
    return float(a) / float(b)


def rolling_median(x: np.ndarray, window: int) -> np.ndarray:
    """Centred rolling median of ``x``, same length; the window shrinks at the ends."""
    x = np.asarray(x, dtype=np.float64)
    window = max(1, min(int(window), x.size))
    if x.size == 0 or window == 1:
        return x.copy()
    left = window // 2
    padded = np.pad(x, (left, window - 1 - left), constant_values=np.nan)
    return np.nanmedian(np.lib.stride_tricks.sliding_window_view(padded, window), axis=1)


def linear_slope(t: np.ndarray, y: np.ndarray) -> float | None:
    """Least-squares slope dy/dt, or None with fewer than 2 distinct ``t``."""
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if t.size < 2 or np.ptp(t) <= 0:
        return None
    return float(np.polyfit(t, y, 1)[0])


# ------------------------------------------------------------------------------ the machine

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


# ------------------------------------------------------------------------ /proc sampling

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


# ----------------------------------------------------------------------------------- frames

@dataclass
class FrameSet:
    """Compressed frames of one resolution (rosbags CompressedImage messages) and the camera
    model at that resolution."""

    name: str
    size: tuple[int, int]  # (W, H) px
    msgs: list[Any]
    camera: CameraModel
    source: str


def compressed_msg(data: bytes, stamp_ns: int) -> Any:
    """A rosbags ``sensor_msgs/CompressedImage`` holding the JPEG bytes ``data``."""
    ts = typestore()
    cls = ts.types['sensor_msgs/msg/CompressedImage']
    return cls(header=make_header(stamp_ns, CAMERA_FRAME, cls, typestore=ts),
               format=COMPRESSED_FORMAT, data=np.frombuffer(data, dtype=np.uint8).copy())


def bag_frames(source: BagSource, n: int, fov_deg: float,
               topics: Any) -> FrameSet:
    """The first ``n`` camera frames of the bag and its (first) CameraInfo model."""
    from semfeat_ros.offline.mapping_run import read_cameras

    topic = source.image_topic(topics.image, topics.image_default)
    camera = read_cameras(source, topics.camera_info, fov_deg).models[0]
    msgs = []
    for m in source.messages([topic]):
        msgs.append(m.msg)
        if len(msgs) >= n:
            break
    if len(msgs) < 2:
        raise OfflineConfigError(f'{topic}: the bag has {len(msgs)} frame(s), need at least 2')
    h, w = to_rgb_or_mono(msgs[0]).shape[:2]
    return FrameSet(f'{w}x{h}', (w, h), msgs, camera, f'{source.path.name} {topic}')


def rendered_frames(out: Path, n: int, size: tuple[int, int], seed: int,
                    progress: bool) -> FrameSet:
    """``n`` consecutive 10 Hz frames of the simulator's drive (seed ``seed``, starting where
    the bundled bag starts: 6 s before the ramp's top) rendered at ``size`` and JPEG-encoded
    (quality 80, as the bag); cached in ``<out>/frames_WxH/`` and reused when present."""
    from semfeat_ros.camera import load_camera_yaml

    w, h = size
    cache = confined(out, f'frames_{w}x{h}')
    meta_path = cache / 'frames.json'
    want = {'version': CACHE_VERSION, 'seed': seed, 'size': [w, h], 'frames': n,
            'jpeg_quality': JPEG_QUALITY}
    files = [cache / f'frame_{k:03d}.jpg' for k in range(n)]
    meta: dict[str, Any] = {}
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            meta = {}
    valid = ({k: meta.get(k) for k in want} == want and isinstance(meta.get('start_s'), float)
             and len(meta.get('stamps_ns') or ()) == n and all(f.is_file() for f in files))
    if not valid:
        meta = _render(cache, files, want, progress)
    msgs = [compressed_msg(f.read_bytes(), int(s)) for f, s in zip(files, meta['stamps_ns'])]
    camera = load_camera_yaml()[0].scaled(w, h)
    return FrameSet(f'{w}x{h}', (w, h), msgs, camera,
                    f'simulator seed {seed}, t = {meta["start_s"]:.2f} s + k / 10 Hz '
                    f'(cached in {cache.name}/)')


def _render(cache: Path, files: list[Path], want: dict[str, Any],
            progress: bool) -> dict[str, Any]:
    from msg_adapters import numpy_to_compressed
    from semfeat_ros.sim.bag import STAMP0_NS, resolve_start
    from semfeat_ros.sim.scenario import Scenario

    cache.mkdir(parents=True, exist_ok=True)
    sc = Scenario.create(seed=want['seed'], size=tuple(want['size']))
    try:
        t0 = resolve_start(sc, 'ramp')
        stamps = []
        ts = typestore()
        for k, path in enumerate(tqdm(files, desc=f'render {want["size"][0]}x'
                                      f'{want["size"][1]}', unit='frame', disable=not progress)):
            t = t0 + k * FRAME_PERIOD_NS * 1e-9
            stamp = STAMP0_NS + int(round(t * 1e9))
            frame = sc.renderer.render(sc.camera_pose(t), t)
            rgb, _ = sc.sensor.expose(frame, sc.camera, k)
            msg = numpy_to_compressed(rgb, 'jpeg', stamp_ns=stamp, frame_id=CAMERA_FRAME,
                                      msg_cls=ts, quality=JPEG_QUALITY)
            _atomic_write(path, np.asarray(msg.data, dtype=np.uint8).tobytes())
            stamps.append(stamp)
    finally:
        sc.renderer.close()
    meta = {**want, 'start_s': t0, 'stamps_ns': stamps}
    _atomic_write(cache / 'frames.json', (json.dumps(meta, indent=1) + '\n').encode())
    return meta


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f'.{path.name}.tmp{os.getpid()}')
    tmp.write_bytes(data)
    os.replace(tmp, path)


# ------------------------------------------------------------------------ per-stage latency

class _Timed:
    """Wraps a callable and keeps the wall time of its last call (ms)."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        self.fn = fn
        self.last_ms = 0.0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        out = self.fn(*args, **kwargs)
        self.last_ms = (time.perf_counter() - t0) * 1e3
        return out


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


@dataclass
class _Prev:
    desc: np.ndarray
    bearings: np.ndarray
    labels: np.ndarray | None = None


def measure_stages(frames: FrameSet, frontend: Any, matcher_conf: dict[str, Any],
                   n_samples: int, warmup: int, max_pixels: int, max_features: int = 1000,
                   progress: bool = True) -> dict[str, Any]:
    """Per-stage times (ms) of the network front end and of ORB / SIFT on the same frames.

    The frames are cycled until ``n_samples`` timed samples exist (after ``warmup`` untimed
    ones); in every sample each front end processes the same decoded frame, one after the
    other. Matching and verification pair each frame with the previous one of the set.
    ``frontend`` is a :class:`~semfeat_ros.frontend.SemanticFrontend`; its extractor's
    ``forward`` (resize + network) is timed in place, the rest of ``process`` (NMS, top-k,
    descriptor sampling, mask, bearings) is the "post" stage.

    Returns ``{'stats': {front end: {stage: summarize(...)}}, 'counts': {front end:
    {'keypoints', 'matches', 'inliers'}: medians}, 'samples': n}``.
    """
    from semfeat_ros.matching.geometry import verify_bearings
    from semfeat_ros.matching.nn import match_float
    from semfeat_ros.matching.sequential import SequentialMatcher
    from semfeat_ros.offline.frontends import OpenCVFrontend
    from semfeat_ros.pipeline import frame_features

    matcher = SequentialMatcher(matcher_conf)
    mconf = matcher.conf['matching']
    vconf = matcher.conf['verification']
    extractor = frontend.extractor
    forward = _Timed(extractor.forward)
    extractor.forward = forward  # instance attribute: extract() calls the timed wrapper
    opencv = {k: OpenCVFrontend(k, max_features=max_features) for k in ('orb', 'sift')}
    bf = {'orb': cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True),
          'sift': cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)}
    w, h = frames.size
    cam = frames.camera if (frames.camera.width, frames.camera.height) == (w, h) \
        else frames.camera.scaled(w, h)
    times: dict[str, dict[str, list[float]]] = {fe: {} for fe in FRONTENDS}
    counts: dict[str, dict[str, list[int]]] = {
        fe: {'keypoints': [], 'matches': [], 'inliers': []} for fe in FRONTENDS}
    prev: dict[str, _Prev | None] = dict.fromkeys(FRONTENDS)
    n_frames = len(frames.msgs)
    bar = tqdm(total=warmup + n_samples, desc=f'stages {frames.name}', unit='sample',
               disable=not progress)

    def verify(b0: np.ndarray, b1: np.ndarray, m: np.ndarray) -> tuple[float, int]:
        ok = np.isfinite(b0[m[:, 0]]).all(axis=1) & np.isfinite(b1[m[:, 1]]).all(axis=1)
        m = m[ok]
        t0 = time.perf_counter()
        ver = verify_bearings(b0[m[:, 0]], b1[m[:, 1]], vconf)
        return _ms(t0), ver.n_inliers

    try:
        for i in range(warmup + n_samples):
            timed = i >= warmup
            k = i % n_frames
            msg = frames.msgs[k]
            rec: dict[str, dict[str, float]] = {fe: {} for fe in FRONTENDS}
            cnt: dict[str, dict[str, int]] = {fe: {} for fe in FRONTENDS}
            t0 = time.perf_counter()
            image = np.ascontiguousarray(to_rgb_or_mono(msg, max_pixels=max_pixels))
            decode_ms = _ms(t0)
            stamp = stamp_to_ns(msg)
            # the network front end, as feature_node runs it
            t0 = time.perf_counter()
            res = frontend.process(image, cam)
            feat_ms = _ms(t0)
            f = res.features
            rec['semfeat'].update(network=forward.last_ms, post=feat_ms - forward.last_ms,
                                  features=feat_ms)
            cnt['semfeat']['keypoints'] = len(f)
            t0 = time.perf_counter()
            matcher.process(frame_features(stamp, f.keypoints, f.descriptors, f.labels,
                                           f.scores, cam, CAMERA_FRAME))
            seq_ms = _ms(t0)
            cur = _Prev(f.descriptors, res.bearings, f.labels)
            p = prev['semfeat']
            if k > 0 and p is not None:
                t0 = time.perf_counter()
                mres = match_float(p.desc, cur.desc, labels0=p.labels, labels1=cur.labels,
                                   compatibility=matcher.compatibility,
                                   mutual=mconf['mutual_check'], ratio=mconf['ratio_threshold'],
                                   min_similarity=mconf['min_similarity'])
                rec['semfeat']['matching'] = _ms(t0)
                rec['semfeat']['verification'], cnt['semfeat']['inliers'] = verify(
                    p.bearings, cur.bearings, mres.indices)
                cnt['semfeat']['matches'] = len(mres)
                rec['semfeat']['sequential'] = seq_ms
            prev['semfeat'] = cur
            # the OpenCV baselines on the same decoded frame
            for kind in ('orb', 'sift'):
                t0 = time.perf_counter()
                out = opencv[kind].process(image, cam)
                rec[kind]['features'] = _ms(t0)
                cnt[kind]['keypoints'] = len(out)
                bear = cam.unproject(out.keypoints.astype(np.float64), check=False) \
                    if len(out) else np.zeros((0, 3))
                cur = _Prev(out.descriptors, bear)
                p = prev[kind]
                if k > 0 and p is not None:
                    t0 = time.perf_counter()
                    dm = bf[kind].match(p.desc, cur.desc) if len(p.desc) and len(cur.desc) \
                        else ()
                    m = np.array([(d.queryIdx, d.trainIdx) for d in dm],
                                 dtype=np.int64).reshape(-1, 2)
                    rec[kind]['matching'] = _ms(t0)
                    rec[kind]['verification'], cnt[kind]['inliers'] = verify(
                        p.bearings, cur.bearings, m)
                    cnt[kind]['matches'] = len(m)
                prev[kind] = cur
            bar.update(1)
            if not timed:
                continue
            for fe in FRONTENDS:
                r = rec[fe]
                r['decode'] = decode_ms
                if 'matching' in r:
                    r['total'] = decode_ms + r['features'] + r['matching'] + r['verification']
                for stage, value in r.items():
                    times[fe].setdefault(stage, []).append(value)
                for key, value in cnt[fe].items():
                    counts[fe][key].append(value)
    finally:
        bar.close()
        del extractor.forward  # the class's method again
    return {
        'samples': n_samples, 'frames': n_frames, 'size': list(frames.size),
        'source': frames.source,
        'stats': {fe: {s: summarize(v) for s, v in st.items()} for fe, st in times.items()},
        'counts': {fe: {k: (float(np.median(v)) if v else None) for k, v in c.items()}
                   for fe, c in counts.items()},
    }


def stage_ratios(stats: dict[str, dict[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """``{stage: {'orb': p50 ratio, 'sift': p50 ratio}}``: network front end / baseline."""
    out = {}
    for stage in ('decode', 'features', 'matching', 'verification', 'total'):
        sem = stats['semfeat'].get(stage, {}).get('p50')
        out[stage] = {k: ratio(sem, stats[k].get(stage, {}).get('p50')) for k in ('orb', 'sift')}
    return out


# -------------------------------------------------------------------- in-process pipeline

@dataclass
class _Event:
    key_ns: int
    order: int
    kind: str
    stamp_ns: int
    payload: Any


@dataclass
class Replay:
    """The bag's frames, odometry and GNSS deserialised in memory, in processing order, and
    its CameraInfo models (:class:`~semfeat_ros.offline.mapping_run.CameraTimeline`)."""

    events: list[_Event]
    cameras: Any
    image_topic: str

    @property
    def n_frames(self) -> int:
        return sum(e.kind == 'image' for e in self.events)


def read_replay(bag: Path, mc: Any) -> Replay:
    """Camera frames, odometry and GNSS of ``bag``, ordered so that each frame comes after the
    odometry that brackets its stamp (frames and fixes delayed by ``IMAGE_DELAY_NS``)."""
    from semfeat_ros.offline.bag import NAVSATFIX_TYPE, ODOMETRY_TYPE
    from semfeat_ros.offline.mapping_run import read_cameras

    names = mc.topics.absolute()  # as recorded in the bag
    with BagSource(bag) as source:
        image_topic = source.image_topic(names.image, names.image_default)
        cameras = read_cameras(source, names.camera_info, mc.fov_deg)
        topics = [image_topic]
        if mc.use_odometry and source.has(names.odometry, (ODOMETRY_TYPE,)):
            topics.append(names.odometry)
        if mc.use_gnss and source.has(names.gnss, (NAVSATFIX_TYPE,)):
            topics.append(names.gnss)
        events = []
        for m in source.messages(topics):
            try:
                if m.topic == image_topic:
                    s = stamp_to_ns(m.msg)
                    events.append(_Event(s + IMAGE_DELAY_NS, 2, 'image', s, m.msg))
                elif m.topic == names.odometry:
                    od = odometry_to_numpy(m.msg)
                    events.append(_Event(od.stamp_ns, 0, 'odom', od.stamp_ns, od.T))
                else:
                    fix = navsatfix_to_numpy(m.msg)
                    if fix.has_fix:
                        events.append(_Event(fix.stamp_ns + IMAGE_DELAY_NS, 1, 'gnss',
                                             fix.stamp_ns,
                                             ((fix.latitude, fix.longitude, fix.altitude),
                                              fix.covariance)))
            except MessageError:
                continue
    events.sort(key=lambda e: (e.key_ns, e.order))
    return Replay(events, cameras, image_topic)


class ReplayPipeline:
    """decode -> front end -> sequential matcher -> mapping session in one process, with the
    objects kept across passes (as the three nodes keep them).

    ``kind`` is 'semfeat' (the network, feature_node's code) or 'orb' / 'sift' (OpenCV front
    ends of ``semfeat-map``, unlabelled keypoints, ORB through the matcher's binary mode).
    Per-frame wall times (ms) are appended to :attr:`times`.
    """

    def __init__(self, replay: Replay, mc: Any, kind: str) -> None:
        from semfeat_ros.mapping.session import MappingSession
        from semfeat_ros.matching.sequential import SequentialMatcher
        from semfeat_ros.offline.frontends import make_frontend

        self.replay = replay
        self.mc = mc
        self.frontend = make_frontend(kind, mc.frontend_conf, mc.max_features)
        matcher_conf = dict(mc.matcher_conf)
        matcher_conf['matching'] = {**matcher_conf.get('matching', {}),
                                    'descriptor_type': self.frontend.descriptor_type}
        self.matcher = SequentialMatcher(matcher_conf)
        mapper_conf = {**mc.mapper_conf, 'use_odometry': bool(mc.use_odometry),
                       'use_gnss': bool(mc.use_gnss)}
        self.session = MappingSession(replay.cameras.models[0], mc.T_base_cam, mapper_conf,
                                      mc.session_conf)
        self.times: dict[str, list[float]] = {
            'decode': [], 'frontend': [], 'matcher': [], 'mapping_update': [], 'frame': []}
        self.frame_done: list[float] = []  # perf_counter at the end of every frame
        self.frames = 0
        self.rejected = 0
        self.keyframes = 0
        self.states: dict[str, int] = {}  # mapper state -> frames

    def _frame(self, ev: _Event) -> None:
        from semfeat_ros.mapping import MappingError
        from semfeat_ros.matching.errors import MatchingError
        from semfeat_ros.offline.frontends import matcher_frame
        from semfeat_ros.offline.mapping_run import tracks_for_mapper

        camera, frame_id = self.replay.cameras.at(ev.stamp_ns)
        t0 = time.perf_counter()
        try:
            image = np.ascontiguousarray(to_rgb_or_mono(ev.payload,
                                                        max_pixels=self.mc.max_image_pixels))
            t1 = time.perf_counter()
            out = self.frontend.process(image, camera, None)
            t2 = time.perf_counter()
            tr = self.matcher.process(matcher_frame(ev.stamp_ns, out, camera, frame_id))
            t3 = time.perf_counter()
            result = self.session.process(tracks_for_mapper(ev.stamp_ns, tr.columns()))
            t4 = time.perf_counter()
        except (MessageError, MatchingError, MappingError, ValueError):
            self.rejected += 1
            return
        finally:
            self.frames += 1
            self.frame_done.append(time.perf_counter())
        self.keyframes += int(result.keyframe)
        self.states[result.state] = self.states.get(result.state, 0) + 1
        for key, a, b in (('decode', t0, t1), ('frontend', t1, t2), ('matcher', t2, t3),
                          ('mapping_update', t3, t4), ('frame', t0, t4)):
            self.times[key].append((b - a) * 1e3)

    def play(self, max_frames: int | None = None, deadline: float | None = None,
             on_frame: Callable[[], None] | None = None) -> bool:
        """One pass over the bag (stops after ``max_frames`` frames or at the perf_counter
        ``deadline``); returns True when the pass completed. The next pass starts the map
        again (its stamps restart), as mapping_node does when time goes backwards."""
        done = 0
        for ev in self.replay.events:
            if ev.kind == 'odom':
                self.session.add_odometry(ev.stamp_ns, ev.payload)
            elif ev.kind == 'gnss':
                self.session.add_gnss(ev.stamp_ns, ev.payload[0], ev.payload[1])
            else:
                if (max_frames is not None and done >= max_frames) or (
                        deadline is not None and time.perf_counter() >= deadline):
                    return False
                self._frame(ev)
                done += 1
                if on_frame is not None:
                    on_frame()
        self.session.reset()
        return True


def measure_end_to_end(replay: Replay, mc: Any, kind: str, max_frames: int | None,
                       progress: bool) -> dict[str, Any]:
    """One pass of :class:`ReplayPipeline` with front end ``kind``; the sustained rate is the
    frames after the first one over the wall time from the end of the first frame (Hz)."""
    pipe = ReplayPipeline(replay, mc, kind)
    total = min(replay.n_frames, max_frames or replay.n_frames)
    with tqdm(total=total, desc=f'end-to-end {kind}', unit='frame',
              disable=not progress) as bar:
        pipe.play(max_frames, on_frame=lambda: bar.update(1))
    done = pipe.frame_done
    hz = (len(done) - 1) / (done[-1] - done[0]) if len(done) >= 2 and done[-1] > done[0] \
        else None
    return {
        'frontend': kind, 'description': pipe.frontend.describe(), 'frames': pipe.frames,
        'frames_mapped': len(pipe.times['frame']), 'frames_rejected': pipe.rejected,
        'keyframes': pipe.keyframes, 'sustained_hz': hz, 'mapper_states': pipe.states,
        'stats': {k: summarize(v) for k, v in pipe.times.items()},
    }


def soak(replay: Replay, mc: Any, minutes: float, progress: bool,
         period_s: float | None = None) -> dict[str, Any]:
    """Replay the bag in a loop through one persistent network pipeline for ``minutes`` of
    wall time, sampling the process's CPU % and RSS (``/proc/self``) and recording every
    mapped frame's time; reports the linear slopes of RSS (MB/min) and frame time (ms/min),
    over the whole soak and after the warm-up."""
    pipe = ReplayPipeline(replay, mc, 'semfeat')
    duration = minutes * 60.0
    period = period_s if period_s is not None else min(1.0, max(0.05, duration / 30.0))
    loops = 0
    bar = tqdm(total=round(duration), desc='soak', unit='s', disable=not progress)
    shown = 0
    frame_t: list[float] = []  # min since the start, of each mapped frame
    frame_ms: list[float] = []

    def tick() -> None:
        nonlocal shown
        times = pipe.times['frame']
        while len(frame_ms) < len(times):
            frame_ms.append(times[len(frame_ms)])
            frame_t.append((time.perf_counter() - t_start) / 60.0)
        elapsed = min(int(time.perf_counter() - t_start), round(duration))
        if elapsed > shown:
            bar.update(elapsed - shown)
            shown = elapsed

    with ProcSampler(period_s=period) as sampler:
        t_start = time.perf_counter()
        deadline = t_start + duration
        while pipe.play(deadline=deadline, on_frame=tick):
            loops += 1
        wall = time.perf_counter() - t_start
    bar.close()
    t = np.asarray(sampler.t_s) / 60.0
    rss = np.asarray(sampler.rss_mb)
    cpu = np.asarray(sampler.cpu_pct)
    warm = min(1.0, 0.2 * minutes)
    late = t >= warm
    ft, fms = np.asarray(frame_t), np.asarray(frame_ms)
    return {
        'minutes': minutes, 'wall_s': wall, 'frames': pipe.frames, 'loops_completed': loops,
        'frames_rejected': pipe.rejected, 'keyframes': pipe.keyframes,
        'sustained_hz': pipe.frames / wall if wall > 0 else None,
        'frame_ms': summarize(pipe.times['frame']), 'sample_period_s': period,
        'samples': int(t.size),
        'cpu_pct': summarize(cpu.tolist()),
        'rss_mb': {'start': float(rss[0]) if rss.size else None,
                   'end': float(rss[-1]) if rss.size else None,
                   'max': float(rss.max()) if rss.size else None},
        'rss_slope_mb_per_min': linear_slope(t, rss),
        'rss_slope_after_warmup_mb_per_min': linear_slope(t[late], rss[late]),
        'frame_ms_slope_per_min': linear_slope(ft, fms),
        'frame_ms_slope_after_warmup_per_min': linear_slope(ft[ft >= warm], fms[ft >= warm]),
        'warmup_min': warm,
        'series': {'t_min': t.tolist(), 'rss_mb': rss.tolist(), 'cpu_pct': cpu.tolist(),
                   'frame_t_min': ft.tolist(), 'frame_ms': fms.tolist()},
    }

# ----------------------------------------------------------------------------------- iSAM2

def measure_isam2(keyframes: int, mapper_conf: dict[str, Any], progress: bool
                  ) -> dict[str, Any]:
    """Update time (ms) of every keyframe of the synthetic long drive of
    :func:`benchmark_update_time` (fixed-lag iSAM2) up to ``keyframes`` keyframes."""
    from semfeat_ros.mapping.benchmark import benchmark_update_time

    # the synthetic tracks have their own keypoint noise (benchmark_update_time's default)
    conf = {k: v for k, v in mapper_conf.items() if k != 'bearing_sigma_px'}
    t0 = time.perf_counter()
    res = benchmark_update_time(keyframes, odometry=True, seed=0, conf=conf, progress=progress)
    wall = time.perf_counter() - t0
    size = max(10, int(round(keyframes / 10.0, -1)) if keyframes >= 100 else keyframes)
    return {
        'keyframes': int(res.keyframe.size), 'wall_s': wall, 'ate_sim3_m': res.ate_sim3_m,
        'update_ms': summarize(res.update_ms), 'update_cpu_ms': summarize(res.update_cpu_ms),
        'frame_ms': summarize(res.frame_ms),
        'buckets': [{'first': a, 'last': b, 'p50_ms': med, 'p90_ms': p90, 'cpu_p50_ms': cpu}
                    for a, b, med, p90, cpu in res.buckets(size)],
        'slope_ms_per_1000_kf': (None if res.keyframe.size < 2 else 1000.0 * linear_slope(
            res.keyframe, rolling_median(res.update_ms, 51))),
        'stats': res.stats,
        'series': {'keyframe': res.keyframe.tolist(), 'update_ms': res.update_ms.tolist(),
                   'update_cpu_ms': res.update_cpu_ms.tolist()},
    }


# ----------------------------------------------------------------------------- network only

def measure_forward(weights: str | None, size: tuple[int, int], repeats: int, warmup: int,
                    threads: int = 2) -> dict[str, float]:
    """Median forward time (ms) of the plain, fused channels-last, bf16 and onnxruntime
    variants at ``size`` (network input px), by
    :func:`semfeat_ros.model.benchmark.time_forward`."""
    from semfeat_ros.model.benchmark import time_forward
    from semfeat_ros.model.weights_io import load_weights

    model, _ = load_weights(weights)
    return time_forward(model, size, repeats, warmup, threads)


# ---------------------------------------------------------------------------------- figures

def _save_figure(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    tmp = path.with_name(f'.{path.stem}.tmp{os.getpid()}.png')
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def plot_stages(stages: dict[str, Any], path: Path) -> None:
    """Grouped bars of the p50 (ms) per stage and front end, one panel per resolution."""
    plt = _pyplot()
    names = list(stages)
    fig, axes = plt.subplots(1, len(names), figsize=(6.0 * len(names), 4.2), squeeze=False)
    order = ('decode', 'features', 'matching', 'verification', 'total')
    for ax, name in zip(axes[0], names):
        st = stages[name]['stats']
        x = np.arange(len(order))
        for j, fe in enumerate(FRONTENDS):
            vals = [st[fe].get(s, {}).get('p50') or 0.0 for s in order]
            ax.bar(x + (j - 1) * 0.27, vals, 0.27, label=fe)
        ax.set_xticks(x, order)
        ax.set_yscale('log')
        ax.set_ylabel('p50 latency (ms, log)')
        ax.set_title(f'{name}: per-stage median')
        ax.grid(axis='y', alpha=0.3)
        ax.legend()
    fig.tight_layout()
    _save_figure(fig, path)


def plot_isam2(res: dict[str, Any], path: Path) -> None:
    """Update time of every keyframe (dots) and its rolling median against the keyframe index."""
    plt = _pyplot()
    kf = np.asarray(res['series']['keyframe'])
    ms = np.asarray(res['series']['update_ms'])
    cpu = np.asarray(res['series']['update_cpu_ms'])
    win = max(5, (len(kf) // 40) | 1)
    fig, ax = plt.subplots(figsize=(8.0, 4.2))
    ax.plot(kf, ms, '.', ms=2, alpha=0.35, color='tab:blue', label='update (wall)')
    ax.plot(kf, rolling_median(ms, win), color='tab:blue', lw=2,
            label=f'rolling median ({win} keyframes), wall')
    ax.plot(kf, rolling_median(cpu, win), color='tab:orange', lw=1.5, ls='--',
            label='rolling median, CPU time')
    top = np.percentile(ms, 99) * 1.3 if ms.size else 1.0
    ax.set_ylim(0, top)
    ax.set_xlabel('keyframe index')
    ax.set_ylabel('mapper update of a keyframe (ms)')
    ax.set_title('iSAM2 (fixed-lag) update time against the keyframe count')
    ax.grid(alpha=0.3)
    ax.legend(loc='upper left')
    fig.tight_layout()
    _save_figure(fig, path)


def plot_soak(res: dict[str, Any], path: Path) -> None:
    """RSS (with its linear fit) and CPU % of the process over the soak."""
    plt = _pyplot()
    t = np.asarray(res['series']['t_min'])
    rss = np.asarray(res['series']['rss_mb'])
    cpu = np.asarray(res['series']['cpu_pct'])
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(8.0, 5.5), sharex=True)
    a0.plot(t, rss, color='tab:purple', lw=1, label='RSS')
    slope = res['rss_slope_mb_per_min']
    if slope is not None and t.size >= 2:
        b = np.polyfit(t, rss, 1)
        a0.plot(t, np.polyval(b, t), 'k--', lw=1, label=f'fit: {slope:+.3f} MB/min')
    a0.set_ylabel('RSS (MB)')
    a0.grid(alpha=0.3)
    a0.legend(loc='lower right')
    a0.set_title(f'Soak: bag replayed in a loop, {res["frames"]} frames, '
                 f'{res["sustained_hz"]:.2f} Hz')
    a1.plot(t, cpu, color='tab:green', lw=1)
    a1.set_ylabel('CPU (% of one core)')
    a1.set_xlabel('time (min)')
    a1.grid(alpha=0.3)
    fig.tight_layout()
    _save_figure(fig, path)


# --------------------------------------------------------------------------------- document

def _f(v: float | None, digits: int = 1, unit: str = '') -> str:
    if v is None or not np.isfinite(v):
        return 'n/a'
    return f'{v:.{digits}f}{unit}'


def _pp(st: dict[str, Any] | None, digits: int = 1) -> tuple[str, str]:
    if not st or not st.get('n'):
        return 'n/a', 'n/a'
    return _f(st['p50'], digits), _f(st['p95'], digits)


STAGE_ROWS = (
    ('decode', 'decode (JPEG -> RGB, `to_rgb_or_mono`)'),
    ('network', 'network (resize + forward)'),
    ('post', 'NMS / top-k / descriptors / mask / bearings'),
    ('features', 'features total (network + post; ORB / SIFT `detectAndCompute`)'),
    ('matching', 'matching (network: `match_float`; ORB / SIFT: `BFMatcher` cross-check)'),
    ('verification', 'verification (`verify_bearings`, same for all)'),
    ('sequential', 'sequential matcher (`SequentialMatcher.process`, tracks)'),
    ('total', 'frame total (decode + features + matching + verification)'),
)


def _stage_table(res: dict[str, Any], e2e: dict[str, Any] | None) -> list[str]:
    st = res['stats']
    lines = ['| stage | semfeat p50 | semfeat p95 | ORB p50 | ORB p95 | SIFT p50 | SIFT p95 |',
             '|---|---:|---:|---:|---:|---:|---:|']
    for key, label in STAGE_ROWS:
        cells = []
        for fe in FRONTENDS:
            cells += _pp(st[fe].get(key), 2 if key in ('decode', 'matching') else 1)
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    if e2e:
        cells = []
        for fe in FRONTENDS:
            cells += _pp(e2e[fe]['stats']['mapping_update'] if fe in e2e else None)
        lines.append('| mapping update (`MappingSession.process`, end-to-end run below) | '
                     + ' | '.join(cells) + ' |')
    c = res['counts']
    lines += ['', 'Medians per frame of the same samples:', '',
              '| | semfeat | ORB | SIFT |', '|---|---:|---:|---:|']
    for key in ('keypoints', 'matches', 'inliers'):
        lines.append(f'| {key} | ' + ' | '.join(_f(c[fe][key], 0) for fe in FRONTENDS) + ' |')
    return lines


def _ratio_table(ratios_by_res: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    head = '| stage | ' + ' | '.join(f'{r} / ORB | {r} / SIFT' for r in ratios_by_res) + ' |'
    lines = [head, '|---|' + '---:|' * (2 * len(ratios_by_res))]
    for stage in ('features', 'matching', 'verification', 'total'):
        cells = []
        for rats in ratios_by_res.values():
            cells += [_f(rats[stage]['orb'], 2, 'x'), _f(rats[stage]['sift'], 2, 'x')]
        lines.append(f'| {stage} | ' + ' | '.join(cells) + ' |')
    return lines


def render_document(results: dict[str, Any], img_rel: str) -> str:
    """The Markdown of ``docs/BENCHMARKS.md`` from the measured ``results`` only."""
    m = results['machine']
    conf = results['config']
    L: list[str] = ['# Benchmarks', '',
                    f'Measured by `semfeat-bench` on {results["date"]} '
                    f'({results["wall_min"]:.1f} min). Generated file: re-run the command to '
                    'update it, do not edit by hand.', '',
                    '```sh', results['command'], '```', '',
                    '## Machine', '',
                    '| item | value |', '|---|---|',
                    f'| CPU | {m["cpu"]} ({", ".join(m["simd"]) or "no AVX2"}) |',
                    f'| cores | {m["logical_cpus"]} logical, {m["usable_cpus"]} usable by the '
                    'process |',
                    f'| RAM | {m["ram_gb"]} GB |',
                    f'| OS | Linux {m["kernel"]} |',
                    f'| Python / torch / numpy | {m["python"]} / {m["torch"]} / {m["numpy"]} |',
                    f'| OpenCV / GTSAM | {m["opencv"]} / {m["gtsam"]} |',
                    f'| threads (torch intra-op and OpenCV) | {m["threads"]} |',
                    '| load average (1/5/15 min) at start | '
                    + ' / '.join(f'{v:.2f}' for v in m['load_average_start']) + ' |',
                    '| load average (1/5/15 min) at end | '
                    + ' / '.join(f'{v:.2f}' for v in m['load_average_end']) + ' |',
                    '',
                    f'Network weights: {results["weights"]}.', '',
                    '1-minute load average sampled every 2 s during each part of the run:', '',
                    '| part | minutes | mean load | max load |', '|---|---:|---:|---:|',
                    *[f'| {name} | {v["minutes"]:.1f} | {_f(v["load1_mean"], 2)} | '
                      f'{_f(v["load1_max"], 2)} |'
                      for name, v in results['load_by_section'].items()],
                    '',
                    'The machine is shared: other jobs ran during the measurement (see the '
                    'load averages, which count runnable processes; with '
                    f'{m["usable_cpus"]} cores a load above {m["usable_cpus"]} means the '
                    'benchmark did not have the CPUs to itself). Absolute times are therefore '
                    'pessimistic; the ratios compare front ends measured interleaved, frame by '
                    "frame, under the same load. Contention can still bias them: torch's "
                    'OpenMP threads meet at a barrier after every layer, so one thread losing '
                    'its core stalls the others, which inflates the network stages more than '
                    'the short OpenCV calls.', '',
                    '## Method', '',
                    '* Per-stage latency: every sample decodes one frame and runs the network '
                    "front end (`SemanticFrontend.process`, feature_node's code and "
                    'parameters), then OpenCV ORB and SIFT (`cv2.ORB_create(1000)`, '
                    '`cv2.SIFT_create(1000)` `detectAndCompute` on the grey frame inside the '
                    'image circle) on the same decoded frame. Matching pairs each frame with the '
                    "previous one: the network with the matcher's `match_float` (mutual, ratio "
                    'test, semantic compatibility), ORB / SIFT with `cv2.BFMatcher` '
                    '(Hamming / L2, cross-check); all matches are verified by the same '
                    '`verify_bearings` (5-point RANSAC on unit bearings, matcher_node '
                    'parameters). "network" is the timed `FeatureExtractor.forward` inside '
                    '`extract` (resize to the network input + forward); "post" is the rest of '
                    '`process` (NMS, top-k, descriptor sampling, class mask at input '
                    'resolution, bearings). Ratios are semfeat / baseline of the medians '
                    '(> 1: the network path is slower).',
                    f'* {conf["warmup"]} untimed warm-up samples precede every series; '
                    f'{conf["frames"]} timed samples per resolution.',
                    '* End-to-end: one pass over the bag per front end through one process '
                    'running decode -> front end -> `SequentialMatcher` -> `MappingSession` '
                    '(wheel odometry and GNSS), configured from `config/*_node.yaml` as '
                    '`semfeat-map` is; the messages are deserialised into memory first (bag '
                    'reading excluded, as a node receives deserialised messages). ORB / SIFT '
                    "are `semfeat-map`'s OpenCV front ends (1000 features, unlabelled "
                    'keypoints, ORB through the binary matcher). Sustained Hz = frames after '
                    'the first / wall time from the end of the first frame to the end of the '
                    'last.',
                    ]
    L += ['', '## Per-stage latency (ms)', '']
    for name, res in results['stages'].items():
        L += [f'### {name}', '',
              f'{res["samples"]} samples over {res["frames"]} frames ({res["source"]}); '
              'matching, verification and the totals over the '
              f'{res["stats"]["semfeat"].get("matching", {}).get("n", 0)} samples whose frame '
              'has a previous one in the set.', '']
        at_bag_size = name == results['bag_size']
        L += _stage_table(res, results.get('end_to_end') if at_bag_size else None)
        L.append('')
        if not at_bag_size:
            L += ['The mapping update sees tracks (bearings), not pixels: its time does not '
                  f'depend on the image size (see {results["bag_size"]}).', '']
    L += ['### Ratios (semfeat / baseline, p50)', '']
    L += _ratio_table({n: r['ratios'] for n, r in results['stages'].items()})
    L += ['', f'![per-stage medians]({img_rel}/bench_stages.png)', '']
    fw = results.get('forward')
    if fw:
        L += [f'### Network forward variants at {fw["size"][0]}x{fw["size"][1]} '
              '(`semfeat_ros.model.benchmark.time_forward`, median ms)', '',
              f'The pure forward on a random input tensor, {fw["repeats"]} timed runs each '
              '(no resize, no post-processing).', '',
              '| fp32 (BatchNorm, NCHW) | fp32 fused, channels-last (torch backend) | '
              'bf16 autocast | onnxruntime (shipped default) |', '|---:|---:|---:|---:|',
              f'| {_f(fw["fp32"])} | {_f(fw["fp32_fused_channels_last"])} | '
              f'{_f(fw["bf16_channels_last"])} | {_f(fw.get("onnxruntime"))} |', '']
    e2e = results.get('end_to_end')
    L += ['## End-to-end sustained rate', '']
    if e2e:
        L += [f'Bag `{results["bag"]}`, {e2e["semfeat"]["frames"]} frames per front end.', '',
              '| front end | sustained Hz | frame p50 / p95 (ms) | decode p50 | '
              'front end p50 / p95 | matcher p50 / p95 | mapping update p50 / p95 | '
              'frames mapped | keyframes |',
              '|---|---:|---:|---:|---:|---:|---:|---:|---:|']
        for fe in FRONTENDS:
            r = e2e[fe]
            s = r['stats']
            L.append(f'| {fe} | {_f(r["sustained_hz"], 2)} | {"/".join(_pp(s["frame"]))} | '
                     f'{_pp(s["decode"], 2)[0]} | {"/".join(_pp(s["frontend"]))} | '
                     f'{"/".join(_pp(s["matcher"]))} | {"/".join(_pp(s["mapping_update"]))} | '
                     f'{r["frames_mapped"]} | {r["keyframes"]} |')
        L += ['', 'Rate ratios (semfeat Hz / baseline Hz): ORB '
              f'{_f(ratio(e2e["semfeat"]["sustained_hz"], e2e["orb"]["sustained_hz"]), 2, "x")}'
              ', SIFT '
              f'{_f(ratio(e2e["semfeat"]["sustained_hz"], e2e["sift"]["sustained_hz"]), 2, "x")}'
              ' (< 1: the network pipeline is slower).', '',
              'Mapper states over the frames: '
              + '; '.join(f'{fe}: ' + ', '.join(f'{k} {v}' for k, v in sorted(
                  e2e[fe].get('mapper_states', {}).items())) for fe in FRONTENDS) + '.', '']
    sk = results.get('soak')
    L += ['## Soak (memory and CPU over a long replay)', '']
    if sk:
        L += [f'The bag replayed in a loop for {sk["minutes"]:g} min through one persistent '
              'in-process pipeline (network front end, sequential matcher, mapping session; '
              'the session restarts at every loop as mapping_node does when time goes '
              'backwards). CPU % and RSS of the process sampled every '
              f'{sk["sample_period_s"]:g} s from `/proc/self`.', '',
              '| item | value |', '|---|---|',
              f'| frames / loops completed | {sk["frames"]} / {sk["loops_completed"]} |',
              f'| sustained rate | {_f(sk["sustained_hz"], 2)} Hz |',
              f'| frame time p50 / p95 | {"/".join(_pp(sk["frame_ms"]))} ms |',
              f'| CPU p50 / p95 (% of one core) | {"/".join(_pp(sk["cpu_pct"], 0))} |',
              f'| RSS start / end / max | {_f(sk["rss_mb"]["start"])} / '
              f'{_f(sk["rss_mb"]["end"])} / {_f(sk["rss_mb"]["max"])} MB |',
              f'| RSS slope (linear fit, whole soak) | '
              f'{_f(sk["rss_slope_mb_per_min"], 3)} MB/min |',
              f'| RSS slope after the first {sk["warmup_min"]:g} min | '
              f'{_f(sk["rss_slope_after_warmup_mb_per_min"], 3)} MB/min |',
              f'| frame time slope (linear fit, whole soak / after the first '
              f'{sk["warmup_min"]:g} min) | {_f(sk.get("frame_ms_slope_per_min"), 3)} / '
              f'{_f(sk.get("frame_ms_slope_after_warmup_per_min"), 3)} ms/min |',
              f'| frames rejected | {sk["frames_rejected"]} |', '',
              f'![soak]({img_rel}/bench_soak.png)', '']
    else:
        L += ['Not run in this measurement (`--soak-minutes 0`).', '']
    isam = results.get('isam2')
    L += ['## iSAM2 update time against the keyframe count', '']
    if isam:
        L += [f'`semfeat_ros.mapping.benchmark.benchmark_update_time`: synthetic long garage '
              f'drive (serpentine, ramps), wheel odometry, {isam["keyframes"]} keyframes in '
              f'{isam["wall_s"] / 60:.1f} min, mapping_node parameters. Median update '
              f'{_f(isam["update_ms"]["p50"])} ms (p95 {_f(isam["update_ms"]["p95"])} ms); '
              'slope of the rolling median '
              f'{_f(isam["slope_ms_per_1000_kf"], 2)} ms per 1000 keyframes; '
              f'ATE (Sim(3)) {_f(isam["ate_sim3_m"], 3)} m.', '',
              '| keyframes | update p50 (ms) | update p90 (ms) | CPU p50 (ms) |',
              '|---|---:|---:|---:|']
        for b in isam['buckets']:
            L.append(f'| {b["first"]}-{b["last"]} | {_f(b["p50_ms"])} | {_f(b["p90_ms"])} | '
                     f'{_f(b["cpu_p50_ms"])} |')
        L += ['', f'![iSAM2 update time]({img_rel}/bench_isam2.png)', '']
    else:
        L += ['Not run in this measurement (`--keyframes 0`).', '']
    return '\n'.join(L) + '\n'


# ------------------------------------------------------------------------------------- main

def _make_dir(path: Path, option: str) -> Path:
    """Create directory ``path`` (with parents) for the output of ``option``; resolved path."""
    if path.exists() and not path.is_dir():
        raise OutputPathError(f'{option}: {str(path)!r} exists and is not a directory')
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputPathError(
            f'{option}: cannot create {str(path)!r}: {exc.strerror or exc}') from exc
    return path.resolve()


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def _map_config(frontend: str, conf: BenchConfig, threads: int | None,
                max_frames: int | None) -> Any:
    """``semfeat-map``'s pipeline configuration (the nodes' YAML files) for ``frontend``."""
    from semfeat_ros.tools.map import MapToolConfig, build_map_config

    mc, _ = build_map_config(MapToolConfig(frontend=frontend, weights=conf.weights,
                                           max_frames=max_frames, figures=False,
                                           progress=conf.progress))
    if threads is not None:
        mc.frontend_conf = replace(mc.frontend_conf, num_threads=threads)
    return mc


def main(conf: BenchConfig, paths: BenchPaths) -> dict[str, Any]:
    """Run every measurement, write ``results.json``, the figures and the document; return the
    results.

    Raises:
        OfflineError: bad bag path, missing topics, invalid options, output path problems.
        semfeat_ros.model.errors.WeightsNotFoundError: no trained weights.
    """
    from semfeat_ros.frontend import SemanticFrontend
    from semfeat_ros.model.weights_io import resolve_weights_path

    conf.validate()
    resolve_bag_path(paths.bag)  # a wrong bag path fails before any work
    if paths.doc.is_dir():
        raise OutputPathError(f'--doc {str(paths.doc)!r} is a directory, expected a file path')
    t_start = time.perf_counter()
    date = datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')
    mc = _map_config('semfeat', conf, conf.threads, None)
    weights = resolve_weights_path(mc.frontend_conf.weights)
    frontend = SemanticFrontend(mc.frontend_conf)
    threads = mc.frontend_conf.num_threads
    cv2.setNumThreads(threads)
    out = prepare_out_dir(paths.out)
    doc_dir = _make_dir(paths.doc.parent, '--doc')
    img_dir = _make_dir(paths.img_dir, '--doc')
    machine = machine_info(threads)
    results: dict[str, Any] = {
        'date': date, 'command': conf.command, 'bag': str(paths.bag),
        'config': {k: v for k, v in asdict(conf).items() if k not in ('command', 'progress')},
        'weights': (f'{"shipped " if mc.frontend_conf.weights is None else ""}`{weights.name}` '
                    f'(sha256 {_sha256(weights)[:12]})'),
        'machine': machine, 'stages': {},
    }
    # 1. per-stage latency at the bag's resolution and at the high resolution
    with BagSource(paths.bag) as source:
        small = bag_frames(source, conf.frames, mc.fov_deg, mc.topics)
    results['bag_size'] = small.name
    big = rendered_frames(out, conf.hires_frames, conf.hires_size, conf.hires_seed,
                          conf.progress)
    load = LoadMonitor().start()
    try:
        for fs in (small, big):
            with load.section(f'per-stage latency {fs.name}'):
                res = measure_stages(fs, frontend, mc.matcher_conf, conf.frames, conf.warmup,
                                     mc.max_image_pixels, mc.max_features, conf.progress)
            res['ratios'] = stage_ratios(res['stats'])
            results['stages'][fs.name] = res
        net_size = frontend.extractor.network_size(*small.size)
        if conf.forward_repeats > 0:
            with load.section('network forward variants'):
                fw = measure_forward(mc.frontend_conf.weights, net_size, conf.forward_repeats,
                                     conf.warmup, mc.frontend_conf.num_threads)
            results['forward'] = {**fw, 'size': list(net_size),
                                  'repeats': conf.forward_repeats}
        del frontend
        # 2. end to end, one pass per front end
        replay = read_replay(paths.bag, mc)
        results['end_to_end'] = {}
        for fe in FRONTENDS:
            with load.section(f'end-to-end {fe}'):
                results['end_to_end'][fe] = measure_end_to_end(
                    replay, mc, fe, conf.e2e_frames or None, conf.progress)
        # 3. soak
        results['soak'] = None
        if conf.soak_minutes > 0:
            with load.section('soak'):
                results['soak'] = soak(replay, mc, conf.soak_minutes, conf.progress)
        # 4. iSAM2 scaling
        results['isam2'] = None
        if conf.keyframes > 0:
            with load.section('iSAM2 scaling'):
                results['isam2'] = measure_isam2(conf.keyframes, dict(mc.mapper_conf),
                                                 conf.progress)
    finally:
        load.stop()
    results['load_by_section'] = load.summary()
    machine['load_average_end'] = list(os.getloadavg())
    results['wall_min'] = (time.perf_counter() - t_start) / 60.0
    # outputs
    plot_stages(results['stages'], confined(img_dir, 'bench_stages.png'))
    if results['soak']:
        plot_soak(results['soak'], confined(img_dir, 'bench_soak.png'))
    if results['isam2']:
        plot_isam2(results['isam2'], confined(img_dir, 'bench_isam2.png'))
    from semfeat_ros.offline.report import json_safe

    _atomic_write(confined(out, 'results.json'),
                  (json.dumps(json_safe(results), indent=1) + '\n').encode())
    rel = os.path.relpath(img_dir, doc_dir).replace(os.sep, '/')
    text = render_document(results, rel)
    _atomic_write(doc_dir / paths.doc.name, text.encode())
    return results


def _size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition('x')
    try:
        if sep:
            return int(w), int(h)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f'expected WIDTHxHEIGHT in px, got {text!r}')


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description='Per-stage latency, sustained rate, soak and iSAM2 scaling of '
        'the pipeline next to OpenCV ORB / SIFT; writes docs/BENCHMARKS.md.')
    p.add_argument('--bag', type=Path, default=None,
                   help='rosbag2 with compressed camera frames, CameraInfo, odometry and GNSS '
                   '(default: bags/garage_ramp_seed0)')
    p.add_argument('--out', type=Path, default=Path('out/bench'),
                   help='results.json and the rendered-frame cache (default out/bench)')
    p.add_argument('--doc', type=Path, default=Path('docs/BENCHMARKS.md'),
                   help='Markdown document to write; figures go to img/ next to it')
    p.add_argument('--frames', type=int, default=None,
                   help='timed samples per stage and resolution (default 100, quick 10)')
    p.add_argument('--hires-frames', type=int, default=None,
                   help='frames rendered at --hires-size (default 8, quick 3)')
    p.add_argument('--hires-size', type=_size, default=(1920, 1536), metavar='WxH',
                   help='size of the rendered frames (default 1920x1536)')
    p.add_argument('--e2e-frames', type=int, default=None,
                   help='frames of each end-to-end run (default: the whole bag; quick 20)')
    p.add_argument('--soak-minutes', type=float, default=None,
                   help='minutes of looped replay for CPU / RSS (default 10, quick 0; 0 skips)')
    p.add_argument('--keyframes', type=int, default=None,
                   help='keyframes of the iSAM2 scaling run (default 2000, quick 100; 0 skips)')
    p.add_argument('--warmup', type=int, default=2,
                   help='untimed samples before every timed series (default 2)')
    p.add_argument('--forward-repeats', type=int, default=None,
                   help='timed forwards per network variant (default frames / 10, 2..20; '
                   '0 skips)')
    p.add_argument('--weights', default=None, help='network weights (default: shipped)')
    p.add_argument('--threads', type=int, default=None,
                   help='torch and OpenCV threads (default: feature_node.yaml num_threads)')
    p.add_argument('--quick', action='store_true',
                   help='small counts for a fast check (explicit options still win)')
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``semfeat-bench``; returns the exit status."""
    args = build_parser().parse_args(argv)
    argv_list = list(sys.argv[1:] if argv is None else argv)
    q = args.quick

    def pick(value: Any, full: Any, quick: Any) -> Any:
        return value if value is not None else (quick if q else full)

    frames = pick(args.frames, 100, 10)
    conf = BenchConfig(
        frames=frames, hires_frames=pick(args.hires_frames, 8, 3),
        hires_size=args.hires_size, e2e_frames=pick(args.e2e_frames, 0, 20),
        soak_minutes=pick(args.soak_minutes, 10.0, 0.0),
        keyframes=pick(args.keyframes, 2000, 100),
        forward_repeats=(args.forward_repeats if args.forward_repeats is not None
                         else max(2, min(20, frames // 10))),
        warmup=args.warmup, weights=args.weights,
        threads=args.threads, progress=not args.quiet,
        command=' '.join([PROG, *map(shlex.quote, argv_list)]))
    paths = BenchPaths(bag=args.bag if args.bag is not None else default_bag(),
                       out=args.out, doc=args.doc)
    from semfeat_ros.model.errors import WeightsFormatError, WeightsNotFoundError

    try:
        res = main(conf, paths)
    except (OfflineError, WeightsNotFoundError, WeightsFormatError, ValueError, OSError,
            MessageError) as exc:
        print(f'{PROG}: error: {one_line(exc)}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    for name, r in res['stages'].items():
        rat = r['ratios']['total']
        sem = r['stats']['semfeat'].get('total', {}).get('p50')
        print(f'{PROG}: {name}: frame total p50 {_f(sem)} ms; semfeat/ORB '
              f'{_f(rat["orb"], 2, "x")}, semfeat/SIFT {_f(rat["sift"], 2, "x")}')
    e2e = res['end_to_end']
    print(f'{PROG}: end-to-end ' + ', '.join(
        f'{fe} {_f(e2e[fe]["sustained_hz"], 2)} Hz' for fe in FRONTENDS))
    if res['soak']:
        sk = res['soak']
        print(f'{PROG}: soak {sk["minutes"]:g} min: RSS slope '
              f'{_f(sk["rss_slope_mb_per_min"], 2)} MB/min (after warm-up '
              f'{_f(sk["rss_slope_after_warmup_mb_per_min"], 2)}), frame time slope '
              f'{_f(sk["frame_ms_slope_per_min"], 2)} ms/min (after warm-up '
              f'{_f(sk["frame_ms_slope_after_warmup_per_min"], 2)})')
    print(f'{PROG}: wrote {paths.doc} and {paths.out / "results.json"}')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
