"""Per-keyframe update time of the mapper against the keyframe count (a benchmark, not a test).

Runs the mapper on a long synthetic garage drive (serpentine corridor, a 3 m ramp up and down
every 120 m) and records the wall time of every keyframe update. The claim checked: the update
time stays flat (fixed-lag smoother, bounded observations per keyframe) instead of growing with
the map. Example::

    python -m semfeat_ros.mapping.benchmark --keyframes 600 --odometry
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import sys
import time
from typing import Any

import numpy as np
from tqdm import tqdm

from semfeat_ros.camera import Extrinsic, FisheyeCamera
from semfeat_ros.mapping.evaluation import ate_rmse
from semfeat_ros.mapping.mapper import Mapper
from semfeat_ros.mapping.synthetic import (
    MAPPER_SIGMA_PX,
    DriveConfig,
    SyntheticDrive,
    long_drive_segments,
    make_path,
    make_world,
)


@dataclass(frozen=True)
class BenchmarkResult:
    """Keyframe index, update time (ms) and active factor count of every keyframe update."""

    keyframe: np.ndarray  # (K,)
    update_ms: np.ndarray  # (K,) wall time of the whole update() call of the keyframe frame
    update_cpu_ms: np.ndarray  # (K,) CPU time of the same calls (robust on a busy machine)
    frame_ms: np.ndarray  # (F,) wall time of every update() call
    frame_keyframe: np.ndarray  # (F,) bool: that call made a keyframe
    ate_sim3_m: float  # trajectory error after Sim(3) alignment (m)
    stats: dict[str, int]

    def buckets(self, size: int = 100) -> list[tuple[int, int, float, float, float]]:
        """``(first kf, last kf, median ms, p90 ms, median CPU ms)`` per ``size`` keyframes."""
        out = []
        for start in range(0, int(self.keyframe.max(initial=-1)) + 1, size):
            m = (self.keyframe >= start) & (self.keyframe < start + size)
            if m.any():
                out.append((start, start + size - 1, float(np.median(self.update_ms[m])),
                            float(np.percentile(self.update_ms[m], 90)),
                            float(np.median(self.update_cpu_ms[m]))))
        return out


def benchmark_update_time(n_keyframes: int = 600, *, odometry: bool = True, seed: int = 0,
                          conf: dict[str, Any] | None = None, progress: bool = True
                          ) -> BenchmarkResult:
    """Drive until ``n_keyframes`` keyframes exist; time every update (ms).

    ``conf`` overrides the mapper config; its keypoint noise defaults to
    :data:`~semfeat_ros.mapping.synthetic.MAPPER_SIGMA_PX` (the synthetic tracks', not a front
    end's).
    """
    camera = FisheyeCamera(640, 512, 186.7, 186.7, 320, 256,
                           k=(0.02, -0.004, 0.0005, -0.0001), fov_deg=190)
    T_bc = Extrinsic((3.7, 0.0, 0.75), (0.0, 0.12, 0.0)).T_base_cam
    # about one keyframe per metre: make the drive a bit longer than needed
    path = make_path(long_drive_segments(1.3 * n_keyframes + 40.0), step=0.05)
    world = make_world(path, seed)
    drive = SyntheticDrive(world, path, camera, T_bc,
                           DriveConfig(odometry=odometry, seed=seed, frame_step_m=0.3))
    mapper = Mapper(camera, T_bc, {'bearing_sigma_px': MAPPER_SIGMA_PX, **(conf or {})})
    kf, kf_ms, kf_cpu, frame_ms, frame_kf, gt = [], [], [], [], [], {}
    bar = tqdm(total=n_keyframes, disable=not progress, desc='keyframes', unit='kf')
    for frame in drive.frames():
        t0, c0 = time.perf_counter(), time.process_time()
        res = mapper.update(frame.tracks, frame.odometry, frame.gnss)
        dt = (time.perf_counter() - t0) * 1e3
        dc = (time.process_time() - c0) * 1e3
        frame_ms.append(dt)
        frame_kf.append(res.keyframe)
        gt[frame.tracks.stamp_ns] = frame.T_map_base
        if res.keyframe:
            kf.append(mapper.stats['keyframes'] - 1)
            kf_ms.append(dt)
            kf_cpu.append(dc)
            bar.update(1)
            if mapper.stats['keyframes'] >= n_keyframes:
                break
    bar.close()
    stamps, poses = mapper.trajectory()
    ate = ate_rmse(poses, np.array([gt[s] for s in stamps]), True) if len(stamps) >= 3 else np.nan
    return BenchmarkResult(np.array(kf), np.array(kf_ms), np.array(kf_cpu), np.array(frame_ms),
                           np.array(frame_kf, dtype=bool), float(ate), dict(mapper.stats))


def cli(argv: list[str] | None = None) -> int:
    """``python -m semfeat_ros.mapping.benchmark``: print update time per 100 keyframes."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--keyframes', type=int, default=600, help='keyframes to run (default 600)')
    ap.add_argument('--odometry', action='store_true', help='feed simulated wheel odometry')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--window', type=int, default=None, help='override window_keyframes')
    args = ap.parse_args(argv)
    if args.keyframes < 10:
        print('error: --keyframes must be >= 10', file=sys.stderr)
        return 2
    conf = {} if args.window is None else {'window_keyframes': args.window}
    res = benchmark_update_time(args.keyframes, odometry=args.odometry, seed=args.seed,
                                conf=conf)
    print('keyframes      median ms   p90 ms   median CPU ms')
    for a, b, med, p90, cpu in res.buckets():
        print(f'{a:5d}-{b:<5d}   {med:9.1f} {p90:8.1f} {cpu:12.1f}')
    other = res.frame_ms[~res.frame_keyframe]
    rest = (f'median {np.median(other):.1f} ms, p90 {np.percentile(other, 90):.1f} ms'
            if len(other) else 'none')
    print(f'all keyframes: median {np.median(res.update_ms):.1f} ms; other frames: {rest}; '
          f'every frame: mean {np.mean(res.frame_ms):.1f} ms; ATE (Sim3) {res.ate_sim3_m:.3f} m')
    print('stats:', res.stats)
    return 0


if __name__ == '__main__':
    sys.exit(cli())
