"""Per-stage latency of the front ends and the matcher on the same decoded frames, and the
network forward variants."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import time
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from msg_adapters import stamp_to_ns, to_rgb_or_mono
from semfeat_ros.bench.frames import CAMERA_FRAME, FrameSet
from semfeat_ros.bench.stats import ratio, summarize

FRONTENDS = ('semfeat', 'orb', 'sift', 'xfeat')  # the front ends compared, in table order
BASELINES = FRONTENDS[1:]  # the front ends the network is compared with (ratios)
LABELS = {'semfeat': 'semfeat', 'orb': 'ORB', 'sift': 'SIFT', 'xfeat': 'XFeat'}  # table names


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
    """Per-stage times (ms) of the network front end and of ORB / SIFT / XFeat on the same
    frames.

    The frames are cycled until ``n_samples`` timed samples exist (after ``warmup`` untimed
    ones); in every sample each front end processes the same decoded frame, one after the
    other. Matching and verification pair each frame with the previous one of the set.
    ``frontend`` is a :class:`~semfeat_ros.frontend.SemanticFrontend`; its extractor's
    ``forward`` (resize + network) is timed in place, the rest of ``process`` (NMS, top-k,
    descriptor sampling, mask, bearings) is the "post" stage. The baselines run without the
    network's labels (their detection and description only): ORB and SIFT on the grey frame,
    XFeat on the frame resized to the network's ``resize_max`` (its ``extract`` and the
    resize are its "features"); their matching is ``cv2.BFMatcher`` with cross-check
    (Hamming for ORB, L2 for SIFT and XFeat).

    Returns ``{'stats': {front end: {stage: summarize(...)}}, 'counts': {front end:
    {'keypoints', 'matches', 'inliers'}: medians}, 'samples': n}``.
    """
    from semfeat_ros.matching.geometry import verify_bearings
    from semfeat_ros.matching.nn import match_float
    from semfeat_ros.matching.sequential import SequentialMatcher
    from semfeat_ros.offline.frontends import OpenCVFrontend, XFeatFrontend
    from semfeat_ros.pipeline import frame_features

    matcher = SequentialMatcher(matcher_conf)
    mconf = matcher.conf['matching']
    vconf = matcher.conf['verification']
    extractor = frontend.extractor
    forward = _Timed(extractor.forward)
    extractor.forward = forward  # instance attribute: extract() calls the timed wrapper
    econf = extractor.conf
    baselines: dict[str, Any] = {
        'orb': OpenCVFrontend('orb', max_features=max_features),
        'sift': OpenCVFrontend('sift', max_features=max_features),
        'xfeat': XFeatFrontend(max_features, resize_max=int(econf['resize_max']),
                               num_threads=int(econf['num_threads']))}
    bf = {'orb': cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True),
          'sift': cv2.BFMatcher(cv2.NORM_L2, crossCheck=True),
          'xfeat': cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)}
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
            # the baselines on the same decoded frame
            for kind in BASELINES:
                t0 = time.perf_counter()
                out = baselines[kind].process(image, cam)
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
    """``{stage: {baseline: p50 ratio}}`` for every front end of :data:`BASELINES` present
    in ``stats``: network front end / baseline."""
    out = {}
    for stage in ('decode', 'features', 'matching', 'verification', 'total'):
        sem = stats['semfeat'].get(stage, {}).get('p50')
        out[stage] = {k: ratio(sem, stats[k].get(stage, {}).get('p50'))
                      for k in BASELINES if k in stats}
    return out


def measure_forward(weights: str | None, size: tuple[int, int], repeats: int, warmup: int,
                    threads: int = 2) -> dict[str, float]:
    """Median forward time (ms) of the plain, fused channels-last, bf16 and onnxruntime
    variants at ``size`` (network input px), by
    :func:`semfeat_ros.model.benchmark.time_forward`."""
    from semfeat_ros.model.benchmark import time_forward
    from semfeat_ros.model.weights_io import load_weights

    model, _ = load_weights(weights)
    return time_forward(model, size, repeats, warmup, threads)
