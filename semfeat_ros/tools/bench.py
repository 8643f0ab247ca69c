"""``semfeat-bench``: speed and resource benchmark of the pipeline against OpenCV ORB and SIFT
and XFeat.

usage: semfeat-bench [--bag BAG] [--out out/bench] [--doc docs/BENCHMARKS.md] [--frames N]
                     [--hires-frames N] [--hires-size WxH] [--e2e-frames N]
                     [--soak-minutes M] [--keyframes K] [--warmup N]
                     [--forward-repeats N] [--weights W] [--threads T] [--quick] [--quiet]

A command, not a test: it measures, in one process and one run (the measurements are the
modules of :mod:`semfeat_ros.bench`; this module is the command line over them),

1. per-stage latency (p50 / p95, ms) at the bag's 640x512 and at 1920x1536 (real frames
   rendered by the simulator at that size, JPEG-encoded so decoding is real): decode, network
   (resize + forward), NMS / top-k / descriptors / mask / bearings, descriptor matching,
   geometric verification, the sequential matcher; next to OpenCV ORB and SIFT and XFeat
   (1000 features, ``cv2.BFMatcher`` cross-check matching, the same verification) on the SAME
   decoded frames, interleaved frame by frame, with the ratios of the medians;
2. the end-to-end sustained rate (Hz, wall clock) of decode -> front end -> matcher -> mapping
   session over the bag, for the network and for the ORB / SIFT / XFeat front ends (the code
   of ``semfeat-map``, configured from the nodes' YAML files; XFeat's keypoints labelled by
   the network), with the mapping update time;
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
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
import datetime
import json
import os
from pathlib import Path
import shlex
import sys
import time
from typing import Any

import cv2

from msg_adapters.errors import MessageError
from semfeat_ros.bench.document import fmt, plot_isam2, plot_soak, plot_stages, render_document
from semfeat_ros.bench.frames import atomic_write, bag_frames, rendered_frames
from semfeat_ros.bench.machine import LoadMonitor, machine_info
from semfeat_ros.bench.pipeline import measure_end_to_end, measure_isam2, read_replay, soak
from semfeat_ros.bench.stages import (
    BASELINES,
    FRONTENDS,
    LABELS,
    measure_forward,
    measure_stages,
    stage_ratios,
)
from semfeat_ros.offline.bag import BagSource, one_line, resolve_bag_path
from semfeat_ros.offline.errors import OfflineConfigError, OfflineError, OutputPathError
from semfeat_ros.offline.paths import confined, prepare_out_dir

PROG = 'semfeat-bench'


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

    atomic_write(confined(out, 'results.json'),
                  (json.dumps(json_safe(results), indent=1) + '\n').encode())
    rel = os.path.relpath(img_dir, doc_dir).replace(os.sep, '/')
    text = render_document(results, rel)
    atomic_write(doc_dir / paths.doc.name, text.encode())
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
        'the pipeline next to OpenCV ORB / SIFT and XFeat; writes docs/BENCHMARKS.md.')
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
        print(f'{PROG}: {name}: frame total p50 {fmt(sem)} ms; ' + ', '.join(
            f'semfeat/{LABELS[b]} {fmt(rat.get(b), 2, "x")}' for b in BASELINES))
    e2e = res['end_to_end']
    print(f'{PROG}: end-to-end ' + ', '.join(
        f'{fe} {fmt(e2e[fe]["sustained_hz"], 2)} Hz' for fe in FRONTENDS))
    if res['soak']:
        sk = res['soak']
        print(f'{PROG}: soak {sk["minutes"]:g} min: RSS slope '
              f'{fmt(sk["rss_slope_mb_per_min"], 2)} MB/min (after warm-up '
              f'{fmt(sk["rss_slope_after_warmup_mb_per_min"], 2)}), frame time slope '
              f'{fmt(sk["frame_ms_slope_per_min"], 2)} ms/min (after warm-up '
              f'{fmt(sk["frame_ms_slope_after_warmup_per_min"], 2)})')
    print(f'{PROG}: wrote {paths.doc} and {paths.out / "results.json"}')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
