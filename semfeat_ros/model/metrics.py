"""Validation metrics: segmentation mIoU, keypoint repeatability, descriptor matching precision.

All functions take numpy arrays; pixel coordinates in px of the validation views.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from semfeat_ros.evaluation import segmentation

Correspond = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``pts_a (N, 2) -> (pts_b (N, 2), valid (N,))`` ground-truth mapping of a pair."""


def confusion_matrix(pred: np.ndarray, gt: np.ndarray, num_classes: int) -> np.ndarray:
    """(C, C) int64 counts ``[gt, pred]`` over pixels whose ``gt`` is not 255: the scored
    columns of :func:`semfeat_ros.evaluation.segmentation.confusion_matrix` (``pred`` holds class
    ids ``0..C-1``, an argmax of the logits)."""
    return segmentation.confusion_matrix(pred, gt, num_classes)[:, :num_classes]


def mean_iou(conf: np.ndarray) -> tuple[float, np.ndarray]:
    """``(mIoU, per-class IoU)`` of a confusion matrix; classes absent from both gt and
    prediction are NaN and excluded from the mean (mIoU NaN if nothing is labelled)."""
    tp = np.diag(conf).astype(np.float64)
    union = conf.sum(0) + conf.sum(1) - tp
    with np.errstate(invalid='ignore', divide='ignore'):
        iou = np.where(union > 0, tp / union, np.nan)
    return _nan_mean(iou), iou


def subset_iou(iou: np.ndarray, classes: np.ndarray) -> float:
    """Mean of the per-class ``iou`` (:func:`mean_iou`) over the bool mask ``classes`` (e.g.
    the static classes; a mask shorter than ``iou`` covers its first entries), NaN-aware."""
    mask = np.asarray(classes, dtype=bool)
    return _nan_mean(np.asarray(iou)[: len(mask)][mask])


def _nan_mean(values: np.ndarray) -> float:
    return float(np.nanmean(values)) if np.isfinite(values).any() else float('nan')


def repeatability(kp_a: np.ndarray, kp_b: np.ndarray, corr_ab: Correspond, corr_ba: Correspond,
                  tol: float) -> tuple[float, int]:
    """Symmetric repeatability of two keypoint sets.

    For each keypoint of a whose ground-truth position in b is valid, it is repeated when some
    keypoint of b lies within ``tol`` px of that position; likewise from b to a. Returns
    ``(repeated / checked over both directions, checked)``; NaN if nothing could be checked.
    """
    hits, checked = 0, 0
    for src, dst, corr in ((kp_a, kp_b, corr_ab), (kp_b, kp_a, corr_ba)):
        if len(src) == 0:
            continue
        mapped, ok = corr(np.asarray(src, np.float64))
        checked += int(ok.sum())
        if len(dst) == 0 or not ok.any():
            continue
        d2 = ((mapped[ok][:, None, :] - np.asarray(dst, np.float64)[None]) ** 2).sum(-1)
        hits += int((d2.min(axis=1) <= tol * tol).sum())
    return (hits / checked if checked else float('nan')), checked


def mutual_nn(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """(M, 2) index pairs of mutual nearest neighbours by cosine similarity (unit descriptors)."""
    if len(desc_a) == 0 or len(desc_b) == 0:
        return np.zeros((0, 2), np.int64)
    sim = desc_a @ desc_b.T
    ab = sim.argmax(axis=1)
    ba = sim.argmax(axis=0)
    ia = np.flatnonzero(ba[ab] == np.arange(len(desc_a)))
    return np.stack([ia, ab[ia]], axis=1)


def matching_precision(kp_a: np.ndarray, kp_b: np.ndarray, desc_a: np.ndarray,
                       desc_b: np.ndarray, corr_ab: Correspond, tol: float
                       ) -> tuple[float, int, int]:
    """Precision of mutual-nearest-neighbour descriptor matches.

    Only matches whose keypoint in a has a valid ground-truth position in b are scored; a match
    is correct when the keypoint of b lies within ``tol`` px of it. Returns
    ``(correct / scored, correct, scored)`` (NaN precision if nothing is scored).
    """
    m = mutual_nn(desc_a, desc_b)
    if len(m) == 0:
        return float('nan'), 0, 0
    mapped, ok = corr_ab(np.asarray(kp_a, np.float64)[m[:, 0]])
    err = np.linalg.norm(mapped - np.asarray(kp_b, np.float64)[m[:, 1]], axis=1)
    correct = int((ok & (err <= tol)).sum())
    scored = int(ok.sum())
    return (correct / scored if scored else float('nan')), correct, scored
