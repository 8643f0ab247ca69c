"""The evaluation loop shared by all modes: extract, match, verify, score, draw, write.

Every method sees the same pairs in the same run. Extractors with the same ``key`` run once per
image (the two semfeat methods share the network's output). Geometric verification is done by
the method itself when it returns ``verified``; otherwise by OpenCV RANSAC homography when the
pair's ground truth is planar, else by essential-matrix RANSAC on the camera's bearings when the
pair has a camera, else by a fundamental matrix (OpenCV USAC_MAGSAC, px). Pairs without ground
truth (real sequences) are scored by counts only: proposed, verified, verified / proposed.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
import time

import cv2
import numpy as np
from tqdm import tqdm

from semfeat_ros.evaluation.errors import ConfigError, MethodUnavailableError
from semfeat_ros.evaluation.groundtruth import Pair
from semfeat_ros.evaluation.methods import (
    Features,
    MatchResult,
    Method,
    MethodConf,
    build_method,
    method_label,
)
from semfeat_ros.evaluation.metrics import (
    estimate_homography,
    match_errors,
    pair_metrics,
    summarize,
    verify_fundamental,
)
from semfeat_ros.evaluation.report import draw_matches, write_outputs
from semfeat_ros.evaluation.segmentation import confusion_matrix, segmentation_summary

DEFAULT_METHODS: tuple[str, ...] = (
    'sift_nn', 'orb_nn', 'akaze_nn', 'brisk_nn', 'semfeat_nn', 'semfeat_semantic', 'semfeat_seq')
"""Methods of a default run (those that cannot run here are skipped with the reason)."""


@dataclass(frozen=True)
class EvalConf:
    """Options common to all modes (px thresholds in image pixels)."""

    methods: tuple[str, ...] = DEFAULT_METHODS
    eps_px: float = 3.0
    ransac_px: float = 3.0
    max_features: int = 1000
    weights: str | None = None
    n_figures: int = 3
    seed: int = 0
    progress: bool = True
    network_conf: dict[str, object] = field(default_factory=dict)
    """Overrides of the network's ``FeatureExtractor`` options (e.g. ``resize_max`` px)."""
    glue_weights: str | None = None
    """SemfeatGlue weights of ``semfeat_lg`` (None: the shipped ones)."""
    glue_conf: dict[str, object] = field(default_factory=dict)
    """Overrides of SemfeatGlue's options for ``semfeat_lg`` (e.g. ``filter_threshold``)."""
    fill_conf: dict[str, float] = field(default_factory=dict)
    """``semfeat_lg_nn``'s fill thresholds ``ratio`` / ``min_similarity`` (missing:
    matcher_node's ``learned_fill_ratio`` / ``learned_fill_min_similarity``)."""
    seq_threshold_from_ransac_px: bool = False
    """``semfeat_seq`` verifies at ``ransac_px`` (``ransac_px / fx`` rad) also on pairs with a
    camera; False: with a camera it uses the matcher's own thresholds."""

    def __post_init__(self) -> None:
        if self.eps_px <= 0:
            raise ConfigError(f'eps must be > 0 px, got {self.eps_px}')
        if self.ransac_px <= 0:
            raise ConfigError(f'RANSAC threshold must be > 0 px, got {self.ransac_px}')
        if self.n_figures < 0:
            raise ConfigError(f'figures per method must be >= 0, got {self.n_figures}')
        if not self.methods:
            raise ConfigError('no method selected')


def verify_bearings_opencv(kpts_a: np.ndarray, kpts_b: np.ndarray, matches: np.ndarray,
                           camera: object, threshold_px: float = 3.0,
                           min_z: float = 0.1) -> np.ndarray:
    """Essential-matrix RANSAC (OpenCV) on the camera's unit bearings of the matches.

    Bearings are mapped to the normalised plane ``(x/z, y/z)``, so only rays with ``z > min_z``
    (within ~84 deg of the axis) can be verified; others count as rejected. The threshold is
    ``threshold_px / fx``. Returns (M,) bool.
    """
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    out = np.zeros(len(matches), dtype=bool)
    if len(matches) < 5:
        return out
    ba = camera.unproject(np.asarray(kpts_a)[matches[:, 0]], check=False)
    bb = camera.unproject(np.asarray(kpts_b)[matches[:, 1]], check=False)
    ok = (np.isfinite(ba).all(axis=1) & np.isfinite(bb).all(axis=1)
          & (ba[:, 2] > min_z) & (bb[:, 2] > min_z))
    if ok.sum() < 5:
        return out
    xa = ba[ok, :2] / ba[ok, 2:3]
    xb = bb[ok, :2] / bb[ok, 2:3]
    E, mask = cv2.findEssentialMat(xa, xb, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                   threshold=float(threshold_px) / float(camera.fx))
    if E is None or mask is None:
        return out
    out[np.flatnonzero(ok)] = mask.ravel()[: int(ok.sum())].astype(bool)
    return out


BearingVerifier = Callable[[np.ndarray, np.ndarray, np.ndarray, object, float], np.ndarray]


def default_bearing_verifier() -> tuple[BearingVerifier, str]:
    """The product matcher's bearing verification (``semfeat_ros.matching.geometry.
    verify_bearings``, valid over the whole fisheye field of view) when importable, else
    :func:`verify_bearings_opencv`. Returns ``(verifier, description)``."""
    try:
        from semfeat_ros.matching.geometry import verify_bearings as matcher_verify
    except ImportError:
        return verify_bearings_opencv, 'essential-matrix RANSAC on bearings (OpenCV)'

    def verify(kpts_a: np.ndarray, kpts_b: np.ndarray, matches: np.ndarray, camera: object,
               threshold_px: float) -> np.ndarray:
        matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
        out = np.zeros(len(matches), dtype=bool)
        if len(matches) == 0:
            return out
        ba = camera.unproject(np.asarray(kpts_a)[matches[:, 0]], check=False)
        bb = camera.unproject(np.asarray(kpts_b)[matches[:, 1]], check=False)
        ok = np.isfinite(ba).all(axis=1) & np.isfinite(bb).all(axis=1)
        if ok.sum() == 0:
            return out
        res = matcher_verify(ba[ok], bb[ok],
                             {'threshold_rad': min(0.4, float(threshold_px) / camera.fx)})
        if res.ok:
            out[np.flatnonzero(ok)] = res.inliers
        return out

    return verify, "matcher's bearing verification (semfeat_ros.matching.geometry)"


@dataclass
class _MethodState:
    method: Method
    per_pair: list[dict] = field(default_factory=list)
    figures: list[str] = field(default_factory=list)
    error: str | None = None
    verifications: Counter[str] = field(default_factory=Counter)
    """Pairs verified by each kind of verification."""


def build_methods(conf: EvalConf) -> tuple[list[Method], dict[str, str]]:
    """Instantiate the configured methods; returns the runnable ones and, for the others, the
    reason they are skipped."""
    mconf = MethodConf(max_features=conf.max_features, weights=conf.weights,
                      extra={'ransac_px': conf.ransac_px, 'network_conf': conf.network_conf,
                             'glue_weights': conf.glue_weights, 'glue_conf': conf.glue_conf,
                             'fill_conf': conf.fill_conf,
                             'seq_threshold_from_ransac_px': conf.seq_threshold_from_ransac_px})
    runnable: list[Method] = []
    skipped: dict[str, str] = {}
    for name in conf.methods:
        try:
            runnable.append(build_method(name, mconf))
        except MethodUnavailableError as exc:
            skipped[name] = str(exc)
    return runnable, skipped


def evaluate(pairs: Iterable[Pair], conf: EvalConf, out_dir: str | Path, *, mode: str,
             source: str, n_pairs: int | None = None, mask_description: str = '',
             notes: list[str] | None = None,
             bearing_verifier: BearingVerifier | None = None,
             bearing_verifier_name: str = '',
             methods: list[Method] | None = None,
             skipped: dict[str, str] | None = None) -> dict:
    """Run every method on every pair, write the outputs into ``out_dir`` and return the results
    dict (the content of results.json)."""
    out = Path(out_dir)
    (out / 'matches').mkdir(parents=True, exist_ok=True)
    if methods is None:
        methods, skipped = build_methods(conf)
    skipped = dict(skipped or {})
    if bearing_verifier is None:
        bearing_verifier, bearing_verifier_name = default_bearing_verifier()
    states = {m.name: _MethodState(m) for m in methods}
    seg_cm: dict[str, np.ndarray] = {}
    seg_count: dict[str, int] = {}
    verifications: set[str] = set()
    count = 0
    has_gt = False
    for k, pair in enumerate(tqdm(pairs, total=n_pairs, desc=f'semfeat-eval {mode}',
                                  unit='pair', disable=not conf.progress)):
        count += 1
        has_gt = has_gt or pair.gt is not None
        feats: dict[str, tuple[Features, Features, float]] = {}
        for st in states.values():
            if st.error is not None:
                continue
            ex = st.method.extractor
            try:
                if ex.key not in feats:
                    t0 = time.perf_counter()
                    fa = ex.extract(pair.image_a, pair.mask_a)
                    fb = ex.extract(pair.image_b, pair.mask_b)
                    feats[ex.key] = (fa, fb, 1000.0 * (time.perf_counter() - t0))
                    _accumulate_segmentation(pair, ex.key, fa, fb, seg_cm, seg_count)
                fa, fb, t_ex = feats[ex.key]
                t0 = time.perf_counter()
                res = st.method.match(fa, fb, pair)
                t_match = 1000.0 * (time.perf_counter() - t0)
            except MethodUnavailableError as exc:
                st.error = str(exc)
                continue
            metrics, verification, verified = _score(pair, fa, fb, res, conf, bearing_verifier,
                                                     bearing_verifier_name)
            verifications.add(verification)
            st.verifications[verification] += 1
            metrics.update(pair=pair.name, extract_ms=t_ex, match_ms=t_match)
            st.per_pair.append(metrics)
            if k < conf.n_figures:
                st.figures.append(_figure(pair, fa, fb, res, verified, conf, out, st.method,
                                          k))
    if count == 0:
        raise ConfigError(f'{mode}: no pairs to evaluate from {source}')
    results: dict = {
        'mode': mode, 'source': source, 'n_pairs': count, 'seed': conf.seed,
        'ground_truth': has_gt,
        'eps_px': conf.eps_px, 'ransac_px': conf.ransac_px, 'max_features': conf.max_features,
        'mask': mask_description, 'verification': ', '.join(sorted(verifications)) or 'none',
        'methods': {}, 'notes': list(notes or []),
    }
    names = list(dict.fromkeys([*conf.methods, *states, *skipped]))
    for name in names:
        label = method_label(name)
        if name in skipped:
            results['methods'][name] = {'label': label, 'summary': None,
                                        'skipped': skipped[name]}
            continue
        st = states.get(name)
        if st is None:
            continue
        if st.error is not None:
            results['methods'][name] = {'label': st.method.label, 'summary': None,
                                        'skipped': st.error}
            continue
        results['methods'][name] = {
            'label': st.method.label, 'summary': summarize(st.per_pair),
            'verification': ', '.join(sorted(st.verifications)) or 'none',
            'verification_pairs': dict(sorted(st.verifications.items())),
            'per_pair': st.per_pair,
            'figures': st.figures}
    seg_figs = []
    if seg_cm:
        from semfeat_ros.labels import load_labels

        names = load_labels().names
        results['segmentation'] = {}
        for key, cm in seg_cm.items():
            summary = segmentation_summary(cm, names)
            summary['n_images'] = seg_count[key]
            results['segmentation'][key] = summary
            seg_figs.append((key, cm, names))
    results['outputs'] = {k: ([str(p) for p in v] if isinstance(v, list) else str(v))
                          for k, v in write_outputs(results, out, seg_figs).items()}
    # Rewrite results.json so it lists its sibling outputs too.
    from semfeat_ros.evaluation.report import write_json

    write_json(results, out / 'results.json')
    return results


def _accumulate_segmentation(pair: Pair, key: str, fa: Features, fb: Features,
                             seg_cm: dict[str, np.ndarray], seg_count: dict[str, int]) -> None:
    from semfeat_ros.labels import NUM_CLASSES

    for labels, f, mask in ((pair.labels_a, fa, pair.mask_a), (pair.labels_b, fb, pair.mask_b)):
        if labels is None or f.segmentation is None:
            continue
        pred = f.segmentation
        if pred.shape != labels.shape:
            pred = cv2.resize(pred, (labels.shape[1], labels.shape[0]),
                              interpolation=cv2.INTER_NEAREST)
        cm = confusion_matrix(pred, labels, NUM_CLASSES, valid=mask)
        seg_cm[key] = seg_cm[key] + cm if key in seg_cm else cm
        seg_count[key] = seg_count.get(key, 0) + 1


def _score(pair: Pair, fa: Features, fb: Features, res: MatchResult, conf: EvalConf,
           bearing_verifier: BearingVerifier | None,
           bearing_verifier_name: str) -> tuple[dict, str, np.ndarray | None]:
    """Per-pair metrics, the verification's description and the (M,) verified mask."""
    matches = np.asarray(res.matches, dtype=np.int64).reshape(-1, 2)
    H_est = None
    t0 = time.perf_counter()
    if res.verified is not None:
        verified = np.asarray(res.verified, bool)
        verification = res.verification or 'method'
    elif pair.H is not None:
        H_est, verified = estimate_homography(fa.keypoints[matches[:, 0]],
                                              fb.keypoints[matches[:, 1]], conf.ransac_px)
        verification = 'RANSAC homography (OpenCV)'
    elif pair.camera is not None:
        fn = bearing_verifier or verify_bearings_opencv
        verified = fn(fa.keypoints, fb.keypoints, matches, pair.camera, conf.ransac_px)
        verification = bearing_verifier_name
    else:
        verified, verification = verify_fundamental(fa.keypoints[matches[:, 0]],
                                                    fb.keypoints[matches[:, 1]], conf.ransac_px)
    verify_ms = 1000.0 * (time.perf_counter() - t0)
    if pair.H is not None and res.verified is not None and len(matches) >= 4:
        # The method verified itself: H for the homography accuracy from all its matches.
        H_est, _ = estimate_homography(fa.keypoints[matches[:, 0]],
                                       fb.keypoints[matches[:, 1]], conf.ransac_px)
    h, w = pair.image_a.shape[:2]
    metrics = pair_metrics(fa.keypoints, fb.keypoints, matches, pair.gt, eps=conf.eps_px,
                           verified=verified, gt_keypoints_a=pair.gt_keypoints_a, H_gt=pair.H,
                           H_est=H_est, image_size=(w, h))
    metrics['verify_ms'] = verify_ms
    return metrics, verification, verified


def _figure(pair: Pair, fa: Features, fb: Features, res: MatchResult,
            verified: np.ndarray | None, conf: EvalConf, out: Path, method: Method,
            k: int) -> str:
    """Match figure of one pair: green correct / red wrong w.r.t. the ground truth, or without
    ground truth green verified / red rejected."""
    matches = np.asarray(res.matches, dtype=np.int64).reshape(-1, 2)
    if pair.gt is None:
        good_name = 'verified'
        correct = (np.zeros(len(matches), bool) if verified is None
                   else np.asarray(verified, bool))
    else:
        good_name = 'correct'
        if len(fa):
            proj, vis = pair.gt.a_to_b(fa.keypoints)
        else:
            proj, vis = np.zeros((0, 2)), np.zeros(0, bool)
        correct = match_errors(proj, vis, fb.keypoints, matches) <= conf.eps_px
    safe = ''.join(c if c.isalnum() or c in '-_.' else '_' for c in pair.name)
    path = out / 'matches' / f'{method.name}_{k:03d}_{safe}.png'
    draw_matches(pair.image_a, pair.image_b, fa.keypoints, fb.keypoints, matches, correct, path,
                 f'{method.label} | {pair.name}', seed=conf.seed + k, good_name=good_name)
    return str(path.relative_to(out))
