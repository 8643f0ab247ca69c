"""Learned against nearest-neighbour matching on consecutive frames of a bag, in one run.

usage: python -m semfeat_ros.tools.match_pairs BAG [--frames N] [--start S] [--out FILE.json]

For the semfeat and xfeat front ends (:func:`~semfeat_ros.offline.frontends.make_frontend`,
xfeat labelled by the network), every frame goes through one
:class:`~semfeat_ros.matching.sequential.SequentialMatcher` per matching method, interleaved
frame by frame so that all see the same machine load: ``mnn`` and ``learned`` (SemfeatGlue
for semfeat, LighterGlue for xfeat), and for semfeat ``learned_all``, SemfeatGlue without its
early exit (every layer). Printed per pair and method: median candidate matches,
median matches verified by the bearing RANSAC, the inlier ratio (verified / candidates over all
frames), the share of frames verified, median tracks, the median matcher time per frame
(``TrackResult.time_ms``: matching, verification and tracking) with its ratio to mnn, and the
ratio of the whole frame's time (the front end's median, incl. xfeat's network pass for the
labels, plus the matcher's) to mnn's.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
import json
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from semfeat_ros.frontend import FrontendConfig
from semfeat_ros.matching.sequential import SequentialMatcher

FRONTENDS = ('semfeat', 'xfeat')
METHODS = ('mnn', 'learned', 'learned_all')


def methods(kind: str) -> tuple[str, ...]:
    """The matching methods measured for front end ``kind`` (early exit: SemfeatGlue only)."""
    return METHODS if kind == 'semfeat' else METHODS[:2]


def matcher_conf(kind: str, method: str) -> dict[str, Any]:
    """SequentialMatcher conf of ``method`` for front end ``kind``."""
    learned = method.startswith('learned')
    return {'matching': {'method': 'learned' if learned else 'mnn', 'features': kind,
                         'learned_early_exit': method != 'learned_all'}}


def read_frames(bag: Path, frames: int, start_s: float) -> tuple[list[tuple[int, Any]], Any]:
    """The first ``frames`` camera frames from ``start_s`` s on (stamp ns, RGB image) and the
    bag's first camera model."""
    from msg_adapters import stamp_to_ns, to_rgb_or_mono
    from semfeat_ros.offline.bag import BagSource
    from semfeat_ros.offline.mapping_run import Topics, read_cameras

    topics = Topics().absolute()
    out = []
    with BagSource(bag) as src:
        topic = src.image_topic(None, topics.image_default)
        camera = read_cameras(src, topics.camera_info, 190.0).models[0]
        start = src.start_ns + int(start_s * 1e9) if start_s > 0 else None
        for m in src.messages([topic], start_ns=start):
            out.append((stamp_to_ns(m.msg), np.ascontiguousarray(to_rgb_or_mono(m.msg))))
            if len(out) >= frames:
                break
    return out, camera


def run(bag: Path, frames: int = 40, start_s: float = 0.0) -> dict[str, Any]:
    from semfeat_ros.offline.frontends import make_frontend, matcher_frame

    images, camera = read_frames(bag, frames, start_s)
    conf = FrontendConfig(num_threads=1)
    result: dict[str, Any] = {'bag': str(bag), 'frames': len(images), 'start_s': start_s}
    for kind in FRONTENDS:
        fe = make_frontend(kind, conf, conf.max_keypoints, network_labels=True)
        matchers = {m: SequentialMatcher(matcher_conf(kind, m)) for m in methods(kind)}
        rows: dict[str, list[tuple[int, int, bool, int, float]]] = {m: [] for m in matchers}
        fe_ms = []
        for stamp, image in images:
            t0 = time.perf_counter()
            out = fe.process(image, camera)
            fe_ms.append((time.perf_counter() - t0) * 1e3)
            frame = matcher_frame(stamp, out, camera, 'camera')
            for m in matchers:
                r = matchers[m].process(frame)
                if r.reset:  # the first frame has nothing to match
                    continue
                rows[m].append((r.n_matches, r.n_inliers, r.verified, r.n_tracks, r.time_ms))
        for m in matchers:
            a = np.asarray(rows[m], dtype=np.float64).reshape(-1, 5)
            result[f'{kind}_{m}'] = {
                'pairs': len(a),
                'matches_median': float(np.median(a[:, 0])),
                'verified_median': float(np.median(a[:, 1])),
                'inlier_ratio': float(a[:, 1].sum() / max(a[:, 0].sum(), 1.0)),
                'verified_frames': float(a[:, 2].mean()),
                'tracks_median': float(np.median(a[:, 3])),
                'matcher_ms_median': float(np.median(a[:, 4])),
            }
        front = float(np.median(fe_ms[1:] or fe_ms))  # the first frame readies the network
        mnn_ms = result[f'{kind}_mnn']['matcher_ms_median']
        for m in methods(kind)[1:]:
            learned = result[f'{kind}_{m}']
            learned['ms_ratio_to_mnn'] = learned['matcher_ms_median'] / mnn_ms if mnn_ms \
                else None
            learned['frame_ms_ratio_to_mnn'] = (front + learned['matcher_ms_median']) / (
                front + mnn_ms)
        result[f'{kind}_frontend_ms_median'] = front
    return result


def format_table(r: dict[str, Any]) -> str:
    lines = ['| front end + matcher | matches | verified | inlier ratio | frames verified | '
             'tracks | front end ms | matcher ms | ratio to mnn: matcher / frame |',
             '|---|---:|---:|---:|---:|---:|---:|---:|---:|']
    for kind in FRONTENDS:
        for m in methods(kind):
            s = r[f'{kind}_{m}']
            ratios = ('1 / 1' if m == 'mnn' else
                      f'{s["ms_ratio_to_mnn"]:.2f} / {s["frame_ms_ratio_to_mnn"]:.2f}')
            lines.append(
                f'| {kind} + {m} | {s["matches_median"]:.0f} | {s["verified_median"]:.0f} | '
                f'{100 * s["inlier_ratio"]:.1f} % | {100 * s["verified_frames"]:.0f} % | '
                f'{s["tracks_median"]:.0f} | {r[f"{kind}_frontend_ms_median"]:.1f} | '
                f'{s["matcher_ms_median"]:.1f} | {ratios} |')
    return '\n'.join(lines)


def cli(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('bag', type=Path)
    p.add_argument('--frames', type=int, default=40, help='consecutive frames (default 40)')
    p.add_argument('--start', type=float, default=0.0, metavar='S',
                   help='skip the first S seconds of the recording')
    p.add_argument('--out', type=Path, default=None, help='also write the numbers as JSON')
    args = p.parse_args(argv)
    if args.frames < 2:
        p.error('--frames must be >= 2')
    r = run(args.bag, args.frames, args.start)
    if args.out is not None:
        args.out.write_text(json.dumps(r, indent=1))
    print(f'{r["bag"]}: {r["frames"]} frames from {r["start_s"]} s')
    print(format_table(r))
    return 0


if __name__ == '__main__':
    sys.exit(cli())
