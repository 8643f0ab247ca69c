"""Segmentation metrics: confusion matrix, per-class IoU, mIoU, and the confusion-matrix figure."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from semfeat_ros.evaluation.errors import ConfigError

IGNORE = 255
"""GT label of pixels that are not scored (outside the image circle, unlabeled)."""


def confusion_matrix(pred: np.ndarray, gt: np.ndarray, num_classes: int,
                     valid: np.ndarray | None = None) -> np.ndarray:
    """(C, C + 1) int64 counts, rows = GT class, columns = predicted class; the last column
    counts predictions outside ``0..C-1`` (e.g. 255, "no class"), which are misses of the row's
    class. Pixels with GT ``255`` (or any id >= C) or outside ``valid`` are skipped. The one
    confusion matrix of the package (:func:`semfeat_ros.model.metrics.confusion_matrix` is its
    square part)."""
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if gt.shape != pred.shape:
        raise ConfigError(f'segmentation: GT shape {gt.shape} != prediction shape {pred.shape}')
    keep = gt.astype(np.int64) < num_classes
    if valid is not None:
        keep &= np.asarray(valid, bool)
    g = gt[keep].astype(np.int64)
    p = np.minimum(pred[keep].astype(np.int64), num_classes)
    cols = num_classes + 1
    return np.bincount(g * cols + p, minlength=num_classes * cols).reshape(num_classes, cols)


def iou_from_confusion(cm: np.ndarray) -> np.ndarray:
    """Per-class IoU = TP / (TP + FP + FN) from a (C, C) or (C, C + 1) confusion matrix (the
    optional last column counts predictions outside 0..C-1: false negatives). NaN for classes
    absent from both GT and prediction."""
    cm = np.asarray(cm, dtype=np.float64)
    c = cm.shape[0]
    tp = np.diag(cm[:, :c])
    gt_total = cm.sum(axis=1)
    pred_total = cm[:, :c].sum(axis=0)
    union = gt_total + pred_total - tp
    with np.errstate(invalid='ignore', divide='ignore'):
        return np.where(union > 0, tp / np.maximum(union, 1), np.nan)


def mean_iou(cm: np.ndarray) -> float:
    """Mean IoU over the classes present in the GT (row total > 0); NaN if none is."""
    cm = np.asarray(cm, dtype=np.float64)
    present = cm.sum(axis=1) > 0
    if not present.any():
        return float('nan')
    return float(np.nanmean(iou_from_confusion(cm)[present]))


def segmentation_summary(cm: np.ndarray, names: Sequence[str]) -> dict[str, object]:
    """JSON-ready per-class IoU (None where undefined), mIoU, pixel accuracy and the matrix."""
    cm = np.asarray(cm)
    c = cm.shape[0]
    iou = iou_from_confusion(cm)
    total = float(cm.sum())
    return {
        'miou': mean_iou(cm),
        'pixel_accuracy': float(np.trace(cm[:, :c])) / total if total else float('nan'),
        'iou': {str(names[k]): (None if np.isnan(iou[k]) else float(iou[k])) for k in range(c)},
        'gt_pixels': {str(names[k]): int(cm[k].sum()) for k in range(c)},
        'confusion': cm.astype(int).tolist(),
        'confusion_columns': [str(n) for n in names] + ['none'] * (cm.shape[1] - c),
    }


def plot_confusion(cm: np.ndarray, names: Sequence[str], path: str | Path,
                   title: str = 'Segmentation confusion (row-normalised)') -> Path:
    """Write the row-normalised confusion matrix as a PNG; returns its path."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    cm = np.asarray(cm, dtype=np.float64)
    c = cm.shape[0]
    rows = cm.sum(axis=1, keepdims=True)
    norm = np.divide(cm[:, :c], rows, out=np.zeros((c, c)), where=rows > 0)
    fig, ax = plt.subplots(figsize=(0.45 * c + 3, 0.45 * c + 2.5))
    im = ax.imshow(norm, vmin=0.0, vmax=1.0, cmap='viridis')
    ax.set_xticks(range(c), [str(n) for n in names], rotation=90, fontsize=8)
    ax.set_yticks(range(c), [str(n) for n in names], fontsize=8)
    ax.set_xlabel('predicted')
    ax.set_ylabel('ground truth')
    ax.set_title(title)
    fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
