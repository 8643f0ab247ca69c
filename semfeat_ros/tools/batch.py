"""``semfeat-batch``: the offline cores over many recordings, in parallel on Ray.

usage: semfeat-batch BAG_OR_DIR... --out DIR [--address auto|HOST:PORT|ray://HOST:PORT]
                     [--steps features,map,eval] [--cpus-per-task N] [--memory-per-task-mb M]
                     [--max-retries K] [--num-cpus N] [--frontend semfeat|orb|sift]
                     [--weights W] [--feature-config Y] [--mapping-config Y] [--topic T]
                     [--max-frames N]
                     [--no-figures] [--eval-methods M,...] [--eval-stride K]
                     [--eval-max-pairs N] [--quiet]

Each BAG_OR_DIR is a recording (rosbag2 directory, ``.mcap`` or ``.db3`` file) or a directory
whose entries are recordings. One Ray task runs per recording and step, through the same core
functions as the single-bag tools, each writing into ``DIR/<recording>/<step>/`` what that tool
writes into its ``--out``: ``features/`` the bag of ``semfeat-features``, ``map/`` the files of
``semfeat-map``, ``eval/`` the files of ``semfeat-eval sequence``. The network runs with
``--cpus-per-task`` threads at feature_node's ``resize_max`` in every step. A step writes
``DIR/<recording>/<step>.done.json`` (its results) last; a later run skips the steps whose marker
matches the options and the recording, and redoes the others. ``DIR/summary.json`` and
``DIR/summary.md`` hold one row per recording.

Without ``--address`` the tool starts a local Ray instance and stops it at the end; with
``--address`` it joins that cluster and leaves it running. A recording that fails (broken bag,
missing topic) is reported with its one-line error and does not stop the others; Ray re-runs a
task whose worker died (``--max-retries``), never one that raised an error. Exit status: 0 when
every recording is complete, 1 when one failed (summary written) or on bad input, 2 for a bad
command line, 130 when interrupted (Ctrl-C or SIGTERM: tasks cancelled, a local Ray stopped).
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
import datetime
import hashlib
import json
import os
from pathlib import Path
import re
import shutil
import signal
import sys
import tempfile
import time
from types import FrameType
from typing import Any

from semfeat_ros.offline.bag import STORAGE_SUFFIXES, one_line
from semfeat_ros.offline.errors import OutputPathError
from semfeat_ros.offline.paths import confined, prepare_out_dir
from semfeat_ros.paths import write_text_atomic
from semfeat_ros.tools.cli import OneLineParser

PROG = 'semfeat-batch'
STEPS = ('features', 'map', 'eval')
FRONTENDS = ('semfeat', 'orb', 'sift')
EVAL_METHODS = ('orb_nn', 'semfeat_nn')
#: Memory declared to Ray per task (MiB): above the peak RSS measured for the steps on the
#: simulator's full-size 640x512 recordings (docs/BATCH.md, 'Memory').
DEFAULT_MEMORY_MB = 2048
#: Object store of the local Ray instance (bytes): tasks exchange small result records only.
LOCAL_OBJECT_STORE = 200 * 2**20
SUMMARY_JSON = 'summary.json'
SUMMARY_MD = 'summary.md'
MARKER_SUFFIX = '.done.json'
#: Characters of an error kept in the summary.
MAX_ERROR_CHARS = 400


class BatchError(Exception):
    """Base class of the errors of ``semfeat-batch`` (one-line messages)."""


class BatchInputError(BatchError, ValueError):
    """An input path is missing or holds no recording, or two recordings share a name."""


class BatchConfigError(BatchError, ValueError):
    """An option is invalid, or no node of the cluster can run a task of the declared size."""


class BatchRayError(BatchError, RuntimeError):
    """Ray could not be started or reached."""


class BatchInterrupted(KeyboardInterrupt):
    """SIGTERM or SIGHUP received; handled like Ctrl-C."""


@dataclass(frozen=True)
class BatchConfig:
    """Options of ``semfeat-batch``; the step options are those of the single-bag tools."""

    steps: tuple[str, ...] = STEPS
    address: str | None = None
    """None: a local Ray instance started and stopped by the tool; else a cluster address
    (``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``)."""
    num_cpus: int | None = None
    """CPUs of the local Ray instance (None: all cores); only without ``address``."""
    cpus_per_task: int = 1
    memory_per_task_mb: int = DEFAULT_MEMORY_MB
    max_retries: int = 2
    frontend: str = 'semfeat'
    weights: str | None = None
    feature_config: Path | None = None
    mapping_config: Path | None = None
    topic: str | None = None
    max_frames: int | None = None
    figures: bool = True
    eval_methods: tuple[str, ...] = EVAL_METHODS
    eval_stride: int = 1
    eval_max_pairs: int | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        unknown = [s for s in self.steps if s not in STEPS]
        if unknown or not self.steps or len(set(self.steps)) != len(self.steps):
            raise BatchConfigError(f'--steps: expected distinct names among '
                                   f'{",".join(STEPS)}, got {",".join(self.steps) or "none"}')
        if self.frontend not in FRONTENDS:
            raise BatchConfigError(f'--frontend: expected one of {", ".join(FRONTENDS)}, got '
                                   f'{self.frontend!r}')
        for name, value, low in (('--cpus-per-task', self.cpus_per_task, 1),
                                 ('--memory-per-task-mb', self.memory_per_task_mb, 64),
                                 ('--max-retries', self.max_retries, 0),
                                 ('--eval-stride', self.eval_stride, 1),
                                 ('--num-cpus', self.num_cpus, 1),
                                 ('--max-frames', self.max_frames, 1),
                                 ('--eval-max-pairs', self.eval_max_pairs, 1)):
            if value is not None and value < low:
                raise BatchConfigError(f'{name} must be >= {low}, got {value}')
        if self.address is not None and self.num_cpus is not None:
            raise BatchConfigError('--num-cpus sets the local Ray instance; a cluster given by '
                                   '--address has its own CPUs')
        if self.address is not None and not self.address.strip():
            raise BatchConfigError('--address must not be empty')
        if 'eval' in self.steps:
            from semfeat_ros.evaluation.methods import method_names

            known = method_names()
            unknown = [m for m in self.eval_methods if m not in known]
            if unknown or not self.eval_methods:
                raise BatchConfigError(f'--eval-methods: unknown {", ".join(unknown) or "(none)"}'
                                       f'; known: {", ".join(known)}')

    def step_options(self, step: str) -> dict[str, Any]:
        """The options that change what ``step`` writes (stored in its completion marker)."""
        common = {'weights': _file_identity(self.weights), 'topic': self.topic}
        if step == 'features':
            return {**common, 'max_frames': self.max_frames,
                    'feature_config': _file_identity(self.feature_config)}
        if step == 'map':
            return {**common, 'frontend': self.frontend, 'max_frames': self.max_frames,
                    'figures': self.figures,
                    'feature_config': _file_identity(self.feature_config),
                    'mapping_config': _file_identity(self.mapping_config)}
        return {**common, 'methods': list(self.eval_methods), 'stride': self.eval_stride,
                'max_pairs': self.eval_max_pairs}


@dataclass(frozen=True)
class Recording:
    """One input recording: ``name`` (its output folder) and the ``bag`` path (absolute)."""

    name: str
    bag: Path


@dataclass(frozen=True)
class StepJob:
    """One Ray task: ``step`` of ``recording`` writing under ``out_root``."""

    step: str
    recording: Recording
    out_root: Path
    conf: BatchConfig
    options_digest: str
    bag_fingerprint: str


@dataclass
class StepOutcome:
    """What a step task returns (and its marker stores): ``status`` ok | failed | skipped."""

    step: str
    status: str
    result: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    wall_s: float = 0.0
    peak_rss_mb: float | None = None
    host: str = ''
    started: float | None = None
    """Start and end of the task (s since the epoch, the worker's clock)."""
    finished: float | None = None


@dataclass
class RecordingRow:
    """One row of the summary."""

    recording: str
    bag: str
    status: str = 'pending'
    error: str | None = None
    frames: int | None = None
    duration_s: float | None = None
    keyframes: int | None = None
    ate_sim3_rmse_m: float | None = None
    floors: int | None = None
    floor_accuracy: float | None = None
    points: int | None = None
    eval_pairs: int | None = None
    wall_s: float = 0.0
    peak_rss_mb: float | None = None
    steps: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass
class BatchSummary:
    """The whole run: rows, counts and where things were written."""

    out: str
    steps: list[str]
    cluster: dict[str, Any]
    rows: list[RecordingRow]
    counts: dict[str, int]
    tasks_run: int
    wall_s: float
    interrupted: bool = False
    started_utc: str = ''
    files: dict[str, str] = field(default_factory=dict)


# ----------------------------------------------------------------------------- inputs


def _is_bag_dir(p: Path) -> bool:
    return p.is_dir() and (p / 'metadata.yaml').is_file()


def _recording_name(p: Path) -> str:
    return p.stem if p.is_file() else p.name


def discover(inputs: Sequence[str | os.PathLike[str]]) -> list[Recording]:
    """The recordings of ``inputs``: each a recording (rosbag2 directory or storage file) or a
    directory of them (its rosbag2 sub-directories and ``.mcap``/``.db3`` files, sorted).

    Raises:
        BatchInputError: a path does not exist or holds no recording, or two recordings would
            write into the same output folder.
    """
    found: list[Recording] = []
    if not inputs:
        raise BatchInputError('no input recording given')
    for item in inputs:
        p = Path(item)
        if not p.exists():
            raise BatchInputError(f'input {str(p)!r} does not exist')
        if p.is_file() or _is_bag_dir(p):
            found.append(Recording(_recording_name(p), p.resolve()))
            continue
        entries = sorted(c for c in p.iterdir()
                         if _is_bag_dir(c) or (c.is_file() and c.suffix in STORAGE_SUFFIXES))
        if not entries:
            raise BatchInputError(
                f'{str(p)!r} holds no recording (expected rosbag2 directories with a '
                f'metadata.yaml or {"/".join(STORAGE_SUFFIXES)} files)')
        found += [Recording(_recording_name(c), c.resolve()) for c in entries]
    seen: dict[str, Path] = {}
    for r in found:
        if r.name in seen and seen[r.name] != r.bag:
            raise BatchInputError(f'recordings {str(seen[r.name])!r} and {str(r.bag)!r} would '
                                  f'both write into {r.name!r}; rename one')
        seen[r.name] = r.bag
    return list({r.bag: r for r in found}.values())  # a recording given twice runs once


def check_outputs(recordings: Sequence[Recording], out_dir: Path) -> None:
    """Every recording's output folder stays inside ``out_dir`` and neither contains nor lies
    inside the recording itself.

    Raises:
        OutputPathError: an output folder escapes ``out_dir`` or overlaps a recording.
    """
    for r in recordings:
        target = confined(out_dir, r.name)
        if target == r.bag or r.bag in target.parents or target in r.bag.parents:
            raise OutputPathError(f'output folder {str(target)!r} overlaps the recording '
                                  f'{str(r.bag)!r}; choose another --out')


def bag_fingerprint(bag: Path) -> str:
    """Name, size and modification time of a recording's files, hashed (changes when the
    recording is rewritten)."""
    files = [bag] if bag.is_file() else sorted(
        c for c in bag.iterdir() if c.is_file() and (c.name == 'metadata.yaml'
                                                     or c.suffix in STORAGE_SUFFIXES))
    h = hashlib.sha256()
    for f in files:
        st = f.stat()
        h.update(f'{f.name}\0{st.st_size}\0{st.st_mtime_ns}\n'.encode())
    return h.hexdigest()[:16]


def _file_identity(path: str | os.PathLike[str] | None) -> str | None:
    if path is None:
        return None
    p = Path(path)
    if not p.is_file():
        return str(path)
    st = p.stat()
    return f'{p.resolve()}:{st.st_size}:{st.st_mtime_ns}'


def options_digest(conf: BatchConfig, step: str) -> str:
    blob = json.dumps({'step': step, **conf.step_options(step)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def step_dir(out_root: Path, name: str, step: str) -> Path:
    return confined(out_root, f'{name}/{step}')


def marker_path(out_root: Path, name: str, step: str) -> Path:
    return confined(out_root, f'{name}/{step}{MARKER_SUFFIX}')


def read_marker(job: StepJob) -> StepOutcome | None:
    """The outcome stored by an earlier run of ``job`` when it is complete: marker readable,
    same options and recording, step output present; else None."""
    path = marker_path(job.out_root, job.recording.name, job.step)
    try:
        data = json.loads(path.read_text(encoding='utf-8'))
    except (OSError, ValueError):
        return None
    if (not isinstance(data, dict) or data.get('options_digest') != job.options_digest
            or data.get('bag_fingerprint') != job.bag_fingerprint
            or not step_dir(job.out_root, job.recording.name, job.step).is_dir()):
        return None
    try:
        out = StepOutcome(**data['outcome'])
    except (KeyError, TypeError):
        return None
    out.status = 'skipped'
    return out


def _write_json(path: Path, data: Any) -> None:
    """Write ``data`` to ``path`` as indented JSON, atomically (never half a file)."""
    write_text_atomic(path, json.dumps(data, indent=2) + '\n')


# ----------------------------------------------------------------------------- the task


def _reset_peak_rss() -> None:
    """Restart the kernel's peak-RSS counter of this process (Linux; a Ray worker runs many
    tasks, each measured from its start)."""
    try:
        Path('/proc/self/clear_refs').write_text('5')
    except OSError:
        pass


def _peak_rss_mb() -> float | None:
    try:
        status = Path('/proc/self/status').read_text()
    except OSError:
        return None
    m = re.search(r'^VmHWM:\s+(\d+) kB', status, re.MULTILINE)
    return round(int(m.group(1)) / 1024, 1) if m else None


def _feature_yaml(conf: BatchConfig, folder: Path) -> Path:
    """feature_node's parameters (``--feature-config`` or the shipped file) with
    ``num_threads`` = ``--cpus-per-task``, written into ``folder``."""
    import yaml

    from semfeat_ros.offline.config import read_node_params
    from semfeat_ros.paths import config_path

    base = conf.feature_config or config_path('feature_node.yaml')
    params = read_node_params(base, 'feature_node')
    params['num_threads'] = int(conf.cpus_per_task)
    path = folder / 'feature_node.yaml'
    path.write_text(yaml.safe_dump({'feature_node': {'ros__parameters': params}}),
                    encoding='utf-8')
    return path


def _bag_duration_s(bag: Path) -> float | None:
    from semfeat_ros.offline.bag import BagSource

    with BagSource(bag) as source:
        reader = source._reader  # noqa: SLF001 - AnyReader's end time, not kept by BagSource
        span = int(reader.end_time) - 1 - int(reader.start_time)
    return round(max(span, 0) / 1e9, 3)


def _run_features(job: StepJob, out: Path, feature_yaml: Path) -> dict[str, Any]:
    from semfeat_ros.tools import features as tool

    c = job.conf
    tconf = tool.FeaturesToolConfig(config=feature_yaml, topic=c.topic, weights=c.weights,
                                    max_frames=c.max_frames, progress=False)
    s = tool.main(tconf, job.recording.bag, out)
    keys = ('image_topic', 'frames_read', 'frames_written', 'frames_rejected',
            'keypoints_per_frame', 'camera_infos')
    return {k: s[k] for k in keys}


def _run_map(job: StepJob, out: Path, feature_yaml: Path) -> dict[str, Any]:
    from semfeat_ros.tools import map as tool

    c = job.conf
    tconf = tool.MapToolConfig(frontend=c.frontend, weights=c.weights, topic=c.topic,
                               max_frames=c.max_frames, feature_config=feature_yaml,
                               mapping_config=c.mapping_config, figures=c.figures,
                               progress=False)
    m = tool.main(tconf, job.recording.bag, out)
    return {
        'frames_read': m['frames_read'], 'frames_processed': m['frames_processed'],
        'keyframes': m['keyframes'], 'has_ground_truth': m['has_ground_truth'],
        'ate_sim3_rmse_m': m.get('ate_sim3_rmse_m'), 'ate_se3_rmse_m': m.get('ate_se3_rmse_m'),
        'floors': len(m['run']['cloud_per_floor']), 'floor_accuracy': m.get('floor_accuracy'),
        'cloud_points': m['cloud_points'], 'evaluation_error': m.get('evaluation_error'),
        'files': sorted(m['files'].values())}


def _run_eval(job: StepJob, out: Path, feature_yaml: Path) -> dict[str, Any]:
    from semfeat_ros.evaluation import run_sequence as mod
    from semfeat_ros.evaluation.pipeline import EvalConf
    from semfeat_ros.nodes.feature_node import FeatureNodeConfig
    from semfeat_ros.offline.bag import BagSource
    from semfeat_ros.offline.config import node_config, read_node_params

    c = job.conf
    params = node_config(FeatureNodeConfig, read_node_params(feature_yaml, 'feature_node'),
                         str(feature_yaml))
    with BagSource(job.recording.bag) as source:
        image_topic = source.image_topic(c.topic, params.image_topic)
    econf = EvalConf(methods=c.eval_methods, weights=c.weights, progress=False,
                     network_conf={'num_threads': int(params.num_threads),
                                   'resize_max': int(params.resize_max)})
    topics = mod.SequenceTopics(image=image_topic)
    sconf = mod.SequenceConf(eval=econf, stride=c.eval_stride, max_pairs=c.eval_max_pairs,
                             topics=topics)
    r = mod.main(sconf, mod.SequencePaths(out=out, bag=job.recording.bag))
    methods = {name: {k: m['summary'].get(k) for k in ('inlier_ratio', 'keypoint_recall',
                                                         'n_matches')}
               for name, m in r['methods'].items() if 'summary' in m}
    return {'image_topic': image_topic, 'n_pairs': r['n_pairs'], 'methods': methods}


STEP_FUNCTIONS: dict[str, Callable[[StepJob, Path, Path], dict[str, Any]]] = {
    'features': _run_features, 'map': _run_map, 'eval': _run_eval}


def _remove_output(path: Path, out_root: Path) -> None:
    """Remove a step's incomplete output (``path`` checked to lie inside ``out_root``)."""
    target = confined(out_root, path.relative_to(out_root))
    if target.is_symlink() or target.is_file():
        target.unlink()
    elif target.is_dir():
        shutil.rmtree(target)


def run_step(job: StepJob) -> StepOutcome:
    """Run one step of one recording (the Ray task's body): threads per ``cpus_per_task``, the
    step's incomplete leftovers removed first, the marker written last. Input errors of the
    recording (the single-bag tools' ValueError / OSError family) come back as a failed
    outcome with the one-line message; any other exception propagates to Ray."""
    import socket

    import cv2

    t0, started = time.perf_counter(), time.time()
    _reset_peak_rss()
    cv2.setNumThreads(int(job.conf.cpus_per_task))
    name, step, root = job.recording.name, job.step, job.out_root
    out = step_dir(root, name, step)
    marker = marker_path(root, name, step)
    host = socket.gethostname()
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.unlink(missing_ok=True)
        _remove_output(out, root)
        with tempfile.TemporaryDirectory(prefix='semfeat-batch-') as tmp:
            feature_yaml = _feature_yaml(job.conf, Path(tmp))
            result = STEP_FUNCTIONS[step](job, out, feature_yaml)
            result['duration_s'] = _bag_duration_s(job.recording.bag)
    except (ValueError, OSError) as exc:
        try:
            _remove_output(out, root)
        except OSError:
            pass
        return StepOutcome(step, 'failed', error=_short(f'{step}: {one_line(exc)}'),
                           wall_s=round(time.perf_counter() - t0, 3),
                           peak_rss_mb=_peak_rss_mb(), host=host, started=started,
                           finished=time.time())
    outcome = StepOutcome(step, 'ok', result=result, wall_s=round(time.perf_counter() - t0, 3),
                          peak_rss_mb=_peak_rss_mb(), host=host, started=started,
                          finished=time.time())
    _write_json(marker, {
        'recording': name, 'bag': str(job.recording.bag), 'step': step,
        'options': job.conf.step_options(step), 'options_digest': job.options_digest,
        'bag_fingerprint': job.bag_fingerprint,
        'finished_utc': _utc_now(), 'outcome': asdict(outcome)})
    return outcome


def _short(text: str) -> str:
    text = one_line(text)
    return text if len(text) <= MAX_ERROR_CHARS else text[:MAX_ERROR_CHARS - 3] + '...'


def _utc_now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%dT%H:%M:%SZ')


# ----------------------------------------------------------------------------- Ray


#: Signals that end a run: held back while Ray starts or stops (an instance half started or
#: half stopped would leave its processes behind), raised as an interrupt otherwise.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextmanager
def _signals_held() -> Iterator[list[int]]:
    """Within the block, the stop signals (those not ignored) are recorded instead of acted
    on; the caller reads the list afterwards. The previous handlers come back at the end."""
    import threading

    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def hold(signum: int, frame: FrameType | None) -> None:
        received.append(signum)

    old = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    for s, h in old.items():
        if h is not signal.SIG_IGN:
            signal.signal(s, hold)
    try:
        yield received
    finally:
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def _ray_children() -> list[int]:
    """Ray processes below this one (Linux ``/proc``; empty elsewhere): the services and
    agents a local instance started, found by parent links and Ray's command lines."""
    parents: dict[int, list[int]] = {}
    names: dict[int, str] = {}
    for d in Path('/proc').glob('[0-9]*'):
        try:
            ppid = int((d / 'stat').read_text().rsplit(')', 1)[1].split()[1])
            names[int(d.name)] = (d / 'cmdline').read_bytes().replace(b'\0', b' ').decode(
                errors='replace')
        except (OSError, IndexError, ValueError):
            continue
        parents.setdefault(ppid, []).append(int(d.name))
    found, todo = [], [os.getpid()]
    while todo:
        for child in parents.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return [p for p in found if names.get(p, '').startswith('ray::')
            or '/ray/' in names.get(p, '')]


def _end_ray_children() -> None:
    """End the Ray processes below this one: stopped first (SIGSTOP), so that none starts
    another unseen, until no new one appears; then killed."""
    held: set[int] = set()
    for _ in range(10):
        new = set(_ray_children()) - held
        if not new:
            break
        for pid in new:
            try:
                os.kill(pid, signal.SIGSTOP)
            except (ProcessLookupError, PermissionError):
                pass
        held |= new
        time.sleep(0.1)
    for pid in held:
        try:
            os.kill(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


#: Starts of a local Ray instance tried: Ray gives its node 30 s to register, which an
#: overloaded machine can miss once.
LOCAL_START_ATTEMPTS = 2


def _start_ray(conf: BatchConfig) -> None:
    """``ray.init`` for ``conf``. A local instance whose start failed half-way is ended, its
    processes included (``ray.shutdown`` does not know of them then), and started once more.

    Raises:
        BatchRayError: Ray could not be started or reached.
    """
    import ray

    attempts = LOCAL_START_ATTEMPTS if conf.address is None else 1
    for attempt in range(1, attempts + 1):
        try:
            if conf.address is None:
                ray.init(address='local', num_cpus=conf.num_cpus, include_dashboard=False,
                         log_to_driver=False, configure_logging=False,
                         object_store_memory=LOCAL_OBJECT_STORE, _node_ip_address='127.0.0.1')
            else:
                ray.init(address=conf.address, log_to_driver=False, configure_logging=False)
            return
        except Exception as exc:  # Ray raises a bare Exception too (node start-up time-out)
            if conf.address is None:
                _end_ray_children()
            ray.shutdown()
            if attempt == attempts:
                where = ('a local Ray instance' if conf.address is None
                         else f'Ray at {conf.address}')
                raise BatchRayError(f'cannot start or reach {where}: {_short(str(exc))}'
                                    ) from exc


@contextmanager
def ray_session(conf: BatchConfig) -> Iterator[dict[str, Any]]:
    """Ray for the run: the caller's session when this process already has one, else a local
    instance (started here, stopped on exit) or the cluster at ``conf.address`` (left
    running). Yields a description of the cluster. A stop signal during start-up takes effect
    once Ray is up (it is then stopped again and :class:`BatchInterrupted` raised)."""
    import ray

    own = not ray.is_initialized()
    if own:
        with _signals_held() as received:
            _start_ray(conf)
        if received:
            with _signals_held():
                ray.shutdown()
            raise BatchInterrupted(signal.Signals(received[0]).name)
    try:
        yield cluster_description(conf)
    finally:
        if own:
            with _signals_held():
                ray.shutdown()


def cluster_description(conf: BatchConfig) -> dict[str, Any]:
    """Nodes, CPUs and memory of the connected cluster.

    Raises:
        BatchConfigError: no node has ``cpus_per_task`` CPUs and ``memory_per_task_mb`` memory
            (the tasks could never be scheduled).
    """
    import ray

    nodes = [n.get('Resources', {}) for n in ray.nodes() if n.get('Alive')]
    cpus = [float(r.get('CPU', 0)) for r in nodes]
    mem = [float(r.get('memory', 0)) / 2**20 for r in nodes]
    need_mb = conf.memory_per_task_mb
    if not any(c >= conf.cpus_per_task and m >= need_mb for c, m in zip(cpus, mem)):
        largest = ', '.join(f'{c:g} CPUs / {m:.0f} MiB' for c, m in zip(cpus, mem)) or 'none'
        raise BatchConfigError(
            f'no Ray node can run a task of {conf.cpus_per_task} CPUs and {need_mb} MiB '
            f'(nodes: {largest}); lower --cpus-per-task or --memory-per-task-mb')
    slots = sum(int(min(c // conf.cpus_per_task, m // need_mb)) for c, m in zip(cpus, mem))
    return {'address': conf.address or 'local', 'nodes': len(nodes), 'cpus': sum(cpus),
            'memory_mb': round(sum(mem)), 'cpus_per_task': conf.cpus_per_task,
            'memory_per_task_mb': need_mb, 'concurrent_tasks': slots,
            'ray_version': ray.__version__}


@contextmanager
def _termination_as_interrupt() -> Iterator[None]:
    """SIGTERM and SIGHUP raise :class:`BatchInterrupted` (like Ctrl-C) in the main thread
    while the block runs; the previous handlers come back afterwards."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        raise BatchInterrupted(signal.Signals(signum).name)

    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _failure_text(exc: Exception) -> str:
    """One line for a task that Ray reports failed (an unexpected exception of the step, or a
    worker lost after its retries)."""
    cause = getattr(exc, 'cause', None)
    if isinstance(cause, BaseException):
        return f'{type(cause).__name__}: {one_line(cause)}'
    return f'{type(exc).__name__}: {one_line(exc)}'


# ----------------------------------------------------------------------------- the driver


def main(conf: BatchConfig, inputs: Sequence[str | os.PathLike[str]],
         out: str | os.PathLike[str]) -> BatchSummary:
    """Run ``conf.steps`` on every recording of ``inputs`` into ``out``; writes and returns the
    summary. Raises :class:`KeyboardInterrupt` after writing the summary when interrupted."""
    from tqdm import tqdm

    started, t0 = _utc_now(), time.perf_counter()
    recordings = discover(inputs)
    out_dir = prepare_out_dir(out)
    check_outputs(recordings, out_dir)
    rows = [RecordingRow(r.name, str(r.bag)) for r in recordings]
    jobs: list[StepJob] = []
    for r, row in zip(recordings, rows):
        fingerprint = bag_fingerprint(r.bag)
        for step in conf.steps:
            job = StepJob(step, r, out_dir, conf, options_digest(conf, step), fingerprint)
            done = read_marker(job)
            if done is None:
                jobs.append(job)
            else:
                row.steps[step] = asdict(done)
    cluster: dict[str, Any] = {'address': conf.address or 'local', 'nodes': 0}
    interrupted = False
    if jobs:
        remaining = {r.name: sum(1 for j in jobs if j.recording.name == r.name)
                     for r in recordings}
        bar = tqdm(total=len(recordings), unit='recording', desc=PROG, disable=not conf.progress,
                   initial=sum(1 for n in remaining.values() if n == 0), dynamic_ncols=True)
        by_name = {row.recording: row for row in rows}
        try:
            with ray_session(conf) as cluster, _termination_as_interrupt():
                finished = _run_jobs(conf, jobs)
                try:
                    for outcome, name in finished:
                        by_name[name].steps[outcome.step] = asdict(outcome)
                        remaining[name] -= 1
                        if remaining[name] == 0:
                            bar.update(1)
                            bar.set_postfix(failed=sum(
                                1 for row in rows
                                if any(s['status'] == 'failed' for s in row.steps.values())))
                finally:
                    finished.close()  # cancels what is still queued or running
        except KeyboardInterrupt:
            interrupted = True
        finally:
            bar.close()
    for row in rows:
        _fill_row(row, conf.steps)
    counts = {s: sum(1 for row in rows if row.status == s)
              for s in ('ok', 'skipped', 'failed', 'interrupted')}
    summary = BatchSummary(str(out_dir), list(conf.steps), cluster, rows, counts, len(jobs),
                           round(time.perf_counter() - t0, 3), interrupted, started)
    write_summary(summary, out_dir)
    if interrupted:
        raise KeyboardInterrupt
    return summary


def _run_jobs(conf: BatchConfig, jobs: Sequence[StepJob]) -> Iterator[tuple[StepOutcome, str]]:
    """Submit one Ray task per job and yield ``(outcome, recording name)`` as they finish;
    when interrupted, the tasks still queued or running are cancelled."""
    import ray
    from ray.exceptions import RayError

    task = ray.remote(run_step)
    resources = {'num_cpus': conf.cpus_per_task, 'memory': conf.memory_per_task_mb * 2**20,
                 'max_retries': conf.max_retries, 'retry_exceptions': False}
    pending = {task.options(name=f'{j.step}:{j.recording.name}', **resources).remote(j): j
               for j in jobs}
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                job = pending.pop(ref)
                try:
                    outcome = ray.get(ref)
                except RayError as exc:  # unexpected step exception, or worker lost for good
                    outcome = StepOutcome(job.step, 'failed',
                                          error=_short(f'{job.step}: {_failure_text(exc)}'))
                yield outcome, job.recording.name
    finally:
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except (RayError, ValueError, TypeError):
                pass


def _fill_row(row: RecordingRow, steps: Sequence[str]) -> None:
    """Status, first error and headline numbers of a recording from its step outcomes."""
    outcomes = row.steps
    missing = [s for s in steps if s not in outcomes]
    failed = [o for s, o in outcomes.items() if o['status'] == 'failed']
    if failed:
        row.status, row.error = 'failed', failed[0]['error']
    elif missing:
        row.status = 'interrupted'
        row.error = f'not finished: {", ".join(missing)}'
    elif all(o['status'] == 'skipped' for o in outcomes.values()):
        row.status = 'skipped'
    else:
        row.status = 'ok'
    res = {s: o['result'] for s, o in outcomes.items() if o['status'] in ('ok', 'skipped')}
    feats, mapped, ev = res.get('features', {}), res.get('map', {}), res.get('eval', {})
    row.frames = mapped.get('frames_read', feats.get('frames_read'))
    for r in (mapped, feats, ev):
        if r.get('duration_s') is not None:
            row.duration_s = r['duration_s']
            break
    row.keyframes = mapped.get('keyframes')
    row.ate_sim3_rmse_m = mapped.get('ate_sim3_rmse_m')
    row.floors = mapped.get('floors')
    row.floor_accuracy = mapped.get('floor_accuracy')
    row.points = mapped.get('cloud_points')
    row.eval_pairs = ev.get('n_pairs')
    row.wall_s = round(sum(float(o.get('wall_s') or 0.0) for o in outcomes.values()), 3)
    peaks = [o['peak_rss_mb'] for o in outcomes.values() if o.get('peak_rss_mb')]
    row.peak_rss_mb = max(peaks) if peaks else None


def _cell(v: Any, fmt: str = '') -> str:
    if v is None:
        return 'n/a'
    return format(v, fmt) if fmt else str(v)


def summary_markdown(s: BatchSummary) -> str:
    """summary.md: the run and one table row per recording."""
    c = s.cluster
    lines = [
        f'# {PROG} summary', '',
        f'Steps: {", ".join(s.steps)}. Ray: {c.get("address")}'
        + (f', {c["nodes"]} node(s), {c["cpus"]:g} CPUs, {c["cpus_per_task"]} CPU(s) and '
           f'{c["memory_per_task_mb"]} MiB per task, up to {c["concurrent_tasks"]} tasks at '
           f'once' if c.get('nodes') else ' (not started: nothing to run)')
        + f'. {s.tasks_run} task(s) run, wall time {s.wall_s:.1f} s'
        + (' (interrupted)' if s.interrupted else '') + '.',
        '', ', '.join(f'{k}: {v}' for k, v in s.counts.items()) + '.', '',
        'skipped = complete from an earlier run (outputs kept). ATE: Sim(3)-aligned keyframe '
        'RMSE against the ground truth (n/a without ground truth). floors: floor levels of the '
        "map cloud (floor accuracy in brackets). wall: summed task time of the recording's "
        'steps; peak RSS: the largest of its tasks.', '',
        '| recording | status | frames | duration s | keyframes | ATE m | floors | points | '
        'eval pairs | wall s | peak RSS MiB | error |',
        '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|',
    ]
    for r in s.rows:
        floors = _cell(r.floors)
        if r.floor_accuracy is not None:
            floors += f' ({r.floor_accuracy:.2f})'
        err = (r.error or '').replace('|', '\\|')
        lines.append(
            f'| {r.recording} | {r.status} | {_cell(r.frames)} | {_cell(r.duration_s, ".1f")} | '
            f'{_cell(r.keyframes)} | {_cell(r.ate_sim3_rmse_m, ".3f")} | {floors} | '
            f'{_cell(r.points)} | {_cell(r.eval_pairs)} | {r.wall_s:.1f} | '
            f'{_cell(r.peak_rss_mb, ".0f")} | {err} |')
    return '\n'.join(lines) + '\n'


def write_summary(s: BatchSummary, out_dir: Path) -> None:
    """``summary.json`` and ``summary.md`` inside ``out_dir`` (each replaced whole)."""
    paths = {'json': confined(out_dir, SUMMARY_JSON), 'markdown': confined(out_dir, SUMMARY_MD)}
    s.files = {k: str(p) for k, p in paths.items()}
    _write_json(paths['json'], asdict(s))
    write_text_atomic(paths['markdown'], summary_markdown(s))


# ----------------------------------------------------------------------------- command line


def _csv(text: str) -> tuple[str, ...]:
    return tuple(t.strip() for t in text.split(',') if t.strip())


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser.for_tool(PROG, __doc__)
    p.add_argument('inputs', nargs='+', type=Path, metavar='BAG_OR_DIR',
                   help='recordings, or directories of recordings')
    p.add_argument('--out', type=Path, required=True, help='output directory (created)')
    p.add_argument('--address', default=None,
                   help='Ray cluster to join: auto (the cluster of this node), HOST:PORT (its '
                   'head), ray://HOST:PORT (Ray Client); default: a local Ray instance')
    p.add_argument('--steps', type=_csv, default=STEPS,
                   help=f'comma-separated steps (default: {",".join(STEPS)})')
    p.add_argument('--cpus-per-task', type=int, default=1,
                   help="CPUs declared per task and the network's threads (default 1)")
    p.add_argument('--memory-per-task-mb', type=int, default=DEFAULT_MEMORY_MB,
                   help=f'memory declared per task, MiB (default {DEFAULT_MEMORY_MB})')
    p.add_argument('--max-retries', type=int, default=2,
                   help='re-runs of a task whose worker died (default 2)')
    p.add_argument('--num-cpus', type=int, default=None,
                   help='CPUs of the local Ray instance (default: all cores)')
    p.add_argument('--frontend', choices=FRONTENDS, default='semfeat',
                   help='map step: the network (semfeat) or an OpenCV front end')
    p.add_argument('--weights', default=None, help='network weights (.safetensors)')
    p.add_argument('--feature-config', type=Path, default=None,
                   help='feature_node parameter YAML (default: config/feature_node.yaml); its '
                   "resize_max is also the eval step's network input size")
    p.add_argument('--mapping-config', type=Path, default=None,
                   help='map step: mapping_node parameter YAML (default: '
                   'config/mapping_node.yaml)')
    p.add_argument('--topic', default=None, help="camera topic (default: feature_node's "
                   'image_topic or its /compressed)')
    p.add_argument('--max-frames', type=int, default=None,
                   help='features and map steps: stop after N frames')
    p.add_argument('--no-figures', action='store_true', help='map step: no PNG figures')
    p.add_argument('--eval-methods', type=_csv, default=EVAL_METHODS,
                   help=f'eval step methods (default: {",".join(EVAL_METHODS)})')
    p.add_argument('--eval-stride', type=int, default=1, help='eval step: frame gap of a pair')
    p.add_argument('--eval-max-pairs', type=int, default=None,
                   help='eval step: evaluate at most N pairs')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    """Console-script entry point; returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a command-line error (2, already printed)
        return int(exc.code or 0)
    try:
        conf = BatchConfig(
            steps=args.steps, address=args.address, num_cpus=args.num_cpus,
            cpus_per_task=args.cpus_per_task, memory_per_task_mb=args.memory_per_task_mb,
            max_retries=args.max_retries, frontend=args.frontend, weights=args.weights,
            feature_config=args.feature_config, mapping_config=args.mapping_config,
            topic=args.topic, max_frames=args.max_frames,
            figures=not args.no_figures, eval_methods=args.eval_methods,
            eval_stride=args.eval_stride, eval_max_pairs=args.eval_max_pairs,
            progress=not args.quiet)
        summary = main(conf, args.inputs, args.out)
    except (BatchError, ValueError, OSError) as exc:
        print(f'{PROG}: error: {one_line(exc) or type(exc).__name__}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted; finished steps are kept (their markers), summary in '
              f'{args.out}', file=sys.stderr)
        return 130
    c = summary.counts
    print(f'{PROG}: {len(summary.rows)} recordings: {c["ok"]} ok, {c["skipped"]} skipped '
          f'(complete), {c["failed"]} failed; {summary.tasks_run} tasks in {summary.wall_s:.1f} '
          f's; wrote {summary.files["json"]} and {summary.files["markdown"]}')
    for row in summary.rows:
        if row.status == 'failed':
            print(f'{PROG}: {row.recording}: {row.error}', file=sys.stderr)
    return 1 if c['failed'] else 0


if __name__ == '__main__':
    sys.exit(cli())
