"""Timing benchmark of the matching core on synthetic fisheye data.

``python -m semfeat_ros.matching.bench [--n 1000] [--repeat 30]`` prints the median and 90th
percentile times (ms) of

* descriptor matching of n x n features (D = 64 and 128, with and without the semantic filter),
* geometric verification of about n matches (10 % and 30 % outliers, 190 deg lens, bearings
  beyond 90 deg included),
* one :meth:`SequentialMatcher.process` call for a frame of about n features.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
import json
import sys
import time
from typing import Any

import numpy as np

from semfeat_ros.camera import FisheyeCamera
from semfeat_ros.matching.geometry import verify_bearings
from semfeat_ros.matching.nn import compatibility_from_labels, match_float
from semfeat_ros.matching.sequential import FrameFeatures, SequentialMatcher
from semfeat_ros.rotations import so3_exp

BENCH_CAMERA = FisheyeCamera(640, 512, 186.7, 186.7, 320, 256,
                             k=(0.02, -0.004, 0.0005, -0.0001), fov_deg=190)


def _timeit(fn: Callable[[], Any], repeat: int) -> dict[str, float]:
    fn()  # warm-up
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return {'median_ms': float(np.median(ts)), 'p90_ms': float(np.percentile(ts, 90))}


def synthetic_pair(rng: np.random.Generator, n: int, out_frac: float,
                   noise_px: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """About ``n`` bearing correspondences (b0, b1, inlier mask) for a 0.5 m forward motion."""
    cam = BENCH_CAMERA
    R = so3_exp(np.array([0.02, 0.1, -0.03]))
    t = np.array([0.05, -0.02, 0.5])
    b0s, b1s = [], []
    while sum(len(b) for b in b0s) < n:
        m = 2 * n
        th = np.arccos(rng.uniform(np.cos(np.radians(94.0)), 1.0, m))
        ph = rng.uniform(0.0, 2 * np.pi, m)
        d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
        X0 = d * rng.uniform(2.0, 15.0, (m, 1))
        p0, v0 = cam.project(X0)
        p1, v1 = cam.project(X0 @ R.T + t)
        ok = v0 & v1 & cam.in_image(p0) & cam.in_image(p1)
        b0s.append(cam.unproject(p0[ok] + rng.normal(0, noise_px, (ok.sum(), 2)), check=False))
        b1s.append(cam.unproject(p1[ok] + rng.normal(0, noise_px, (ok.sum(), 2)), check=False))
    b0 = np.concatenate(b0s)[:n]
    b1 = np.concatenate(b1s)[:n]
    good = np.isfinite(b0).all(axis=1) & np.isfinite(b1).all(axis=1)
    b0, b1 = b0[good], b1[good]
    inl = np.ones(len(b0), dtype=bool)
    out = rng.choice(len(b0), int(out_frac * len(b0)), replace=False)
    b1[out] = b1[rng.permutation(out)]
    inl[out] = False
    return b0, b1, inl


def main(n: int = 1000, repeat: int = 30, seed: int = 0) -> dict[str, dict[str, float]]:
    """Run the benchmark; returns ``{name: {'median_ms', 'p90_ms'}}``."""
    rng = np.random.default_rng(seed)
    out: dict[str, dict[str, float]] = {}
    compat = compatibility_from_labels()
    labels = rng.integers(0, 17, n).astype(np.uint8)
    for dim in (64, 128):
        d0 = rng.normal(size=(n, dim)).astype(np.float32)
        d1 = d0[rng.permutation(n)] + rng.normal(0, 0.05, (n, dim)).astype(np.float32)
        out[f'match_float {n}x{n} D={dim}'] = _timeit(
            lambda d0=d0, d1=d1: match_float(d0, d1), repeat)
        out[f'match_float {n}x{n} D={dim} semantic'] = _timeit(
            lambda d0=d0, d1=d1: match_float(d0, d1, labels0=labels, labels1=labels,
                                             compatibility=compat), repeat)
    for frac in (0.1, 0.3):
        pairs = [synthetic_pair(rng, n, frac) for _ in range(5)]
        it = iter(range(10**9))
        out[f'verify_bearings {n} matches {int(frac * 100)}% outliers'] = _timeit(
            lambda pairs=pairs, it=it: verify_bearings(*pairs[next(it) % 5][:2]), repeat)
    # One sequential step: features of frame 1 matched to frame 0 (state reset each time).
    b0, b1, _ = synthetic_pair(rng, n, 0.0)
    desc = rng.normal(size=(len(b0), 128)).astype(np.float32)
    kp0 = BENCH_CAMERA.project(b0)[0]
    kp1 = BENCH_CAMERA.project(b1)[0]
    lab = rng.integers(0, 17, len(b0)).astype(np.uint8)
    f0 = FrameFeatures(stamp_ns=0, keypoints=kp0, descriptors=desc, labels=lab, bearings=b0)
    f1 = FrameFeatures(stamp_ns=100_000_000, keypoints=kp1,
                       descriptors=desc + rng.normal(0, 0.05, desc.shape).astype(np.float32),
                       labels=lab, bearings=b1)
    matcher = SequentialMatcher()

    def step() -> None:
        matcher.reset()
        matcher.process(f0)
        matcher.process(f1)

    step_t = _timeit(step, max(3, repeat // 3))
    out[f'SequentialMatcher 2 frames x {len(b0)} features'] = step_t
    return out


def cli(argv: list[str] | None = None) -> int:
    """Command line entry point; prints one line per measurement (or JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--n', type=int, default=1000, help='features / matches (default 1000)')
    parser.add_argument('--repeat', type=int, default=30, help='timed runs per measurement')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--json', action='store_true', help='print JSON instead of text')
    args = parser.parse_args(argv)
    if args.n < 50 or args.repeat < 1:
        print('error: --n must be >= 50 and --repeat >= 1', file=sys.stderr)
        return 2
    res = main(args.n, args.repeat, args.seed)
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        for name, r in res.items():
            print(f'{name:55s} median {r["median_ms"]:7.2f} ms   p90 {r["p90_ms"]:7.2f} ms')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
