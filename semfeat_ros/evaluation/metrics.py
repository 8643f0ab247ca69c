"""Matching metrics (definitions and formulas: docs/METRICS.md).

Notation for one pair: keypoints ``A`` (N, 2) px in image A, ``B`` (M, 2) px in image B, matches
``(i, j)`` index pairs, ground truth ``gt`` with ``gt.a_to_b(A) -> (P, visible)``. A match is
*correct* when ``visible[i]`` and ``||P[i] - B[j]|| <= eps``. All distances are in px of the
image the comparison happens in. Undefined ratios (0 / 0) are NaN and skipped when averaging.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree

from semfeat_ros.evaluation.errors import ConfigError
from semfeat_ros.evaluation.groundtruth import GroundTruth
from semfeat_ros.evaluation.transforms import apply_homography

MMA_THRESHOLDS: tuple[int, ...] = tuple(range(1, 11))
"""Thresholds (px) of the mean matching accuracy curve."""
HOMOGRAPHY_THRESHOLDS: tuple[int, ...] = (1, 3, 5)
"""Corner-error thresholds (px) of homography accuracy."""


def _points(arr: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    if a.size == 0:
        return a.reshape(0, 2)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ConfigError(f'{name}: expected shape (N, 2) px, got {a.shape}')
    return a


def _matches(matches: np.ndarray, n_a: int, n_b: int) -> np.ndarray:
    m = np.asarray(matches, dtype=np.int64)
    if m.size == 0:
        return m.reshape(0, 2)
    if m.ndim != 2 or m.shape[1] != 2:
        raise ConfigError(f'matches: expected shape (M, 2) indices, got {m.shape}')
    if m.min() < 0 or m[:, 0].max() >= n_a or m[:, 1].max() >= n_b:
        raise ConfigError(f'matches: indices out of range for {n_a} and {n_b} keypoints')
    return m


def nearest_distance(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(N,) distance (px) from each point to its nearest target; inf without targets or for
    non-finite points."""
    points = _points(points, 'points')
    targets = _points(targets, 'targets')
    out = np.full(len(points), np.inf)
    finite = np.isfinite(points).all(axis=1)
    targets = targets[np.isfinite(targets).all(axis=1)]
    if len(targets) == 0 or not finite.any():
        return out
    d, _ = cKDTree(targets).query(points[finite], k=1)
    out[finite] = d
    return out


def match_errors(proj_a: np.ndarray, visible_a: np.ndarray, kpts_b: np.ndarray,
                 matches: np.ndarray) -> np.ndarray:
    """(M,) reprojection error (px) ``||P[i] - B[j]||`` of each match; inf when ``P[i]`` is not
    visible in B."""
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    err = np.full(len(matches), np.inf)
    if len(matches) == 0:
        return err
    i, j = matches[:, 0], matches[:, 1]
    ok = np.asarray(visible_a, bool)[i]
    err[ok] = np.linalg.norm(np.asarray(proj_a)[i[ok]] - np.asarray(kpts_b)[j[ok]], axis=1)
    return err


def matchable_keypoints(proj_a: np.ndarray, visible_a: np.ndarray, kpts_b: np.ndarray,
                        eps: float) -> np.ndarray:
    """(N,) bool: A's keypoint is GT-matchable, i.e. its GT location is visible in B and some
    keypoint of B lies within ``eps`` px of it."""
    d = nearest_distance(np.asarray(proj_a)[np.asarray(visible_a, bool)], kpts_b)
    out = np.zeros(len(visible_a), dtype=bool)
    out[np.asarray(visible_a, bool)] = d <= eps
    return out


def keypoint_recall(matches: np.ndarray, correct: np.ndarray, matchable: np.ndarray) -> float:
    """Distinct A keypoints with a correct match / GT-matchable A keypoints (NaN if none)."""
    n = int(np.count_nonzero(matchable))
    if n == 0:
        return float('nan')
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    hit = np.unique(matches[np.asarray(correct, bool), 0])
    return float(len(hit)) / n


def inlier_ratio(correct: np.ndarray) -> float:
    """Correct matches / proposed matches (NaN without matches)."""
    c = np.asarray(correct, bool)
    return float(c.mean()) if c.size else float('nan')


def mean_matching_accuracy(errors: np.ndarray,
                           thresholds: Sequence[float] = MMA_THRESHOLDS) -> np.ndarray:
    """Fraction of matches with error <= t for each threshold t (px); NaN without matches."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        return np.full(len(thresholds), np.nan)
    return np.array([float(np.mean(e <= t)) for t in thresholds])


def repeatability(kpts_a: np.ndarray, kpts_b: np.ndarray, gt: GroundTruth,
                  eps: float) -> float:
    """Symmetric repeatability: keypoints of A visible in B with a B keypoint within ``eps`` of
    their GT location, plus the same from B to A, over all keypoints visible in the other
    image (NaN if none is)."""
    kpts_a = _points(kpts_a, 'kpts_a')
    kpts_b = _points(kpts_b, 'kpts_b')
    pa, va = gt.a_to_b(kpts_a) if len(kpts_a) else (np.zeros((0, 2)), np.zeros(0, bool))
    pb, vb = gt.b_to_a(kpts_b) if len(kpts_b) else (np.zeros((0, 2)), np.zeros(0, bool))
    denom = int(np.count_nonzero(va)) + int(np.count_nonzero(vb))
    if denom == 0:
        return float('nan')
    rep_a = int(np.count_nonzero(nearest_distance(pa[va], kpts_b) <= eps))
    rep_b = int(np.count_nonzero(nearest_distance(pb[vb], kpts_a) <= eps))
    return (rep_a + rep_b) / denom


def gt_keypoint_recall(gt_keypoints_a: np.ndarray, gt: GroundTruth, kpts_a: np.ndarray,
                       matches: np.ndarray, correct: np.ndarray,
                       eps: float) -> tuple[float, float, int]:
    """The paper's reading of recall against a fixed GT keypoint set of A.

    A GT keypoint counts when it is visible in both images (``gt.a_to_b`` visible). It is
    *recalled* when some correct match ``(i, j)`` has ``||A[i] - g|| <= eps``. Returns
    ``(recall, detection_rate, n_visible)``: recalled / visible, detected (any A keypoint within
    ``eps``) / visible, and the number of visible GT keypoints; ratios are NaN if none is
    visible.
    """
    g = _points(gt_keypoints_a, 'gt_keypoints_a')
    if len(g) == 0:
        return float('nan'), float('nan'), 0
    _, vis = gt.a_to_b(g)
    g = g[vis]
    if len(g) == 0:
        return float('nan'), float('nan'), 0
    kpts_a = _points(kpts_a, 'kpts_a')
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    good_a = kpts_a[matches[np.asarray(correct, bool), 0]]
    recalled = nearest_distance(g, good_a) <= eps
    detected = nearest_distance(g, kpts_a) <= eps
    return float(recalled.mean()), float(detected.mean()), int(len(g))


def estimate_homography(pts_a: np.ndarray, pts_b: np.ndarray, threshold_px: float = 3.0,
                        max_iters: int = 2000,
                        confidence: float = 0.999) -> tuple[np.ndarray | None, np.ndarray]:
    """OpenCV RANSAC homography A -> B on matched points (px).

    Returns ``(H or None, inlier (M,) bool)``; None with fewer than 4 matches or on failure.
    """
    pts_a = _points(pts_a, 'pts_a')
    pts_b = _points(pts_b, 'pts_b')
    inl = np.zeros(len(pts_a), dtype=bool)
    if len(pts_a) < 4:
        return None, inl
    H, mask = cv2.findHomography(pts_a.astype(np.float32), pts_b.astype(np.float32),
                                 cv2.RANSAC, float(threshold_px), maxIters=int(max_iters),
                                 confidence=float(confidence))
    if H is None or mask is None or not np.isfinite(H).all():
        return None, inl
    return H, mask.ravel().astype(bool)


FUNDAMENTAL_USAC = 'fundamental-matrix USAC_MAGSAC (OpenCV, px)'
FUNDAMENTAL_RANSAC = ('fundamental-matrix RANSAC (OpenCV, px; USAC_MAGSAC raised on a '
                      'degenerate pair)')


def verify_fundamental(pts_a: np.ndarray, pts_b: np.ndarray, threshold_px: float = 3.0,
                       max_iters: int = 10000,
                       confidence: float = 0.999) -> tuple[np.ndarray, str]:
    """Uncalibrated geometric verification of matched points A -> B (px): OpenCV
    ``findFundamentalMat`` with ``USAC_MAGSAC``, threshold ``threshold_px`` px.

    OpenCV's USAC raises ``cv2.error`` (``!model.empty()``) on some degenerate inputs, e.g. a
    pair where no point moves; those pairs fall back to OpenCV's classic ``FM_RANSAC`` at the
    same threshold. Returns the (M,) bool inlier mask (all False with fewer than 8 matches or
    when no model is found) and the name of the estimator used.
    """
    pts_a = _points(pts_a, 'pts_a').astype(np.float64)
    pts_b = _points(pts_b, 'pts_b').astype(np.float64)
    inl = np.zeros(len(pts_a), dtype=bool)
    if len(pts_a) < 8:
        return inl, FUNDAMENTAL_USAC
    how = FUNDAMENTAL_USAC
    try:
        F, mask = cv2.findFundamentalMat(pts_a, pts_b, cv2.USAC_MAGSAC, float(threshold_px),
                                         float(confidence), int(max_iters))
    except cv2.error:
        how = FUNDAMENTAL_RANSAC
        F, mask = cv2.findFundamentalMat(pts_a, pts_b, cv2.FM_RANSAC, float(threshold_px),
                                         float(confidence), int(max_iters))
    if F is None or mask is None or not np.isfinite(F).all():
        return inl, how
    return mask.ravel()[: len(pts_a)].astype(bool), how


def image_corners(width: int, height: int) -> np.ndarray:
    """The four corner pixel centres (4, 2) px of a ``width x height`` image."""
    return np.array([[0.0, 0.0], [width - 1.0, 0.0], [width - 1.0, height - 1.0],
                     [0.0, height - 1.0]])


def homography_corner_error(H_est: np.ndarray | None, H_gt: np.ndarray, width: int,
                            height: int) -> float:
    """Mean distance (px) between the image-A corners mapped by the estimated and the true H
    (inf if there is no estimate)."""
    if H_est is None:
        return float('inf')
    c = image_corners(width, height)
    e = np.linalg.norm(apply_homography(H_est, c) - apply_homography(H_gt, c), axis=1)
    return float(e.mean()) if np.isfinite(e).all() else float('inf')


def pair_metrics(kpts_a: np.ndarray, kpts_b: np.ndarray, matches: np.ndarray,
                 gt: GroundTruth | None, *, eps: float = 3.0,
                 verified: np.ndarray | None = None,
                 gt_keypoints_a: np.ndarray | None = None, H_gt: np.ndarray | None = None,
                 H_est: np.ndarray | None = None,
                 image_size: tuple[int, int] | None = None) -> dict[str, object]:
    """All per-pair metrics of one method (keys listed in docs/METRICS.md).

    ``verified`` is the (M,) bool inlier mask of geometric verification (None: not run);
    ``H_gt`` / ``H_est`` / ``image_size = (width, height)`` px enable homography accuracy.
    Without ground truth (``gt`` None: real sequences) only the counts and the verified ratio
    (verified / proposed matches) are defined.
    """
    if eps <= 0:
        raise ConfigError(f'eps must be > 0 px, got {eps}')
    kpts_a = _points(kpts_a, 'kpts_a')
    kpts_b = _points(kpts_b, 'kpts_b')
    matches = _matches(matches, len(kpts_a), len(kpts_b))
    v = None
    if verified is not None:
        v = np.asarray(verified, bool).reshape(-1)
        if v.shape != (len(matches),):
            raise ConfigError(f'verified: expected {len(matches)} flags, got {v.shape}')
    if gt is None:
        out: dict[str, object] = {'n_kpts_a': int(len(kpts_a)), 'n_kpts_b': int(len(kpts_b)),
                                  'n_matches': int(len(matches))}
        if v is not None:
            out['n_verified'] = int(np.count_nonzero(v))
            out['verified_ratio'] = inlier_ratio(v)
        return out
    if len(kpts_a):
        proj_a, vis_a = gt.a_to_b(kpts_a)
    else:
        proj_a, vis_a = np.zeros((0, 2)), np.zeros(0, bool)
    err = match_errors(proj_a, vis_a, kpts_b, matches)
    correct = err <= eps
    matchable = matchable_keypoints(proj_a, vis_a, kpts_b, eps)
    out = {
        'n_kpts_a': int(len(kpts_a)), 'n_kpts_b': int(len(kpts_b)),
        'n_matchable': int(np.count_nonzero(matchable)),
        'n_matches': int(len(matches)), 'n_correct': int(np.count_nonzero(correct)),
        'keypoint_recall': keypoint_recall(matches, correct, matchable),
        'inlier_ratio': inlier_ratio(correct),
        'mma': mean_matching_accuracy(err).tolist(),
        'repeatability': repeatability(kpts_a, kpts_b, gt, eps),
    }
    if v is not None:
        out['n_verified'] = int(np.count_nonzero(v))
        out['verified_ratio'] = inlier_ratio(v)
        out['inlier_ratio_verified'] = inlier_ratio(correct[v])
        out['keypoint_recall_verified'] = keypoint_recall(matches[v], correct[v], matchable)
    if gt_keypoints_a is not None:
        rec, det, n_vis = gt_keypoint_recall(gt_keypoints_a, gt, kpts_a, matches, correct, eps)
        out['gt_keypoint_recall'] = rec
        out['gt_keypoint_detection'] = det
        out['n_gt_keypoints'] = n_vis
    if H_gt is not None and image_size is not None:
        out['homography_error'] = homography_corner_error(H_est, H_gt, *image_size)
    return out


SCALAR_KEYS: tuple[str, ...] = (
    'keypoint_recall', 'inlier_ratio', 'keypoint_recall_verified', 'inlier_ratio_verified',
    'gt_keypoint_recall', 'gt_keypoint_detection', 'repeatability', 'verified_ratio',
    'n_matches', 'n_verified', 'n_correct', 'n_matchable', 'n_kpts_a', 'n_kpts_b', 'extract_ms',
    'match_ms', 'verify_ms')
"""Per-pair scalars averaged over pairs (NaN skipped) by :func:`summarize`."""


def _nanmean(values: Iterable[float]) -> tuple[float, int]:
    arr = np.array([float(v) for v in values], dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return (float(arr.mean()) if arr.size else float('nan')), int(arr.size)


def summarize(per_pair: Sequence[dict[str, object]]) -> dict[str, object]:
    """Mean over pairs of each per-pair metric (pairs where it is undefined are skipped; the
    number of pairs that defined it is ``n_<key>``); homography accuracy at 1/3/5 px is the
    fraction of pairs with corner error <= t (failures count as misses)."""
    out: dict[str, object] = {'n_pairs': len(per_pair)}
    for key in SCALAR_KEYS:
        vals = [p[key] for p in per_pair if key in p]
        if vals:
            out[key], out[f'n_{key}'] = _nanmean(vals)
    mmas = [np.asarray(p['mma'], dtype=np.float64) for p in per_pair if 'mma' in p]
    if mmas:
        stack = np.stack(mmas)
        ok = np.isfinite(stack).all(axis=1)
        out['mma'] = (stack[ok].mean(axis=0).tolist() if ok.any()
                      else [float('nan')] * stack.shape[1])
        out['mma_thresholds_px'] = list(MMA_THRESHOLDS)
    herr = [float(p['homography_error']) for p in per_pair if 'homography_error' in p]
    if herr:
        e = np.array(herr)
        out['homography_accuracy'] = {str(t): float(np.mean(e <= t))
                                      for t in HOMOGRAPHY_THRESHOLDS}
        finite = e[np.isfinite(e)]
        out['homography_error_median'] = float(np.median(finite)) if finite.size else float('inf')
    out['pairs_without_matches'] = sum(1 for p in per_pair if p.get('n_matches', 0) == 0)
    return out
