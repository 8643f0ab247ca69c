"""Debug view of matches: previous | current side by side, rgb8 (/semfeat/matches/image)."""
from __future__ import annotations

import cv2
import numpy as np

from semfeat_ros.matching.errors import FeatureInputError
from semfeat_ros.matching.sequential import TrackResult

INLIER_COLOR = (0, 220, 0)  # RGB green
REJECTED_COLOR = (230, 0, 0)  # RGB red
KEYPOINT_COLOR = (255, 210, 0)  # RGB yellow


def _as_rgb(image: np.ndarray | None, size: tuple[int, int] | None, name: str) -> np.ndarray:
    if image is None:
        if size is None:
            raise FeatureInputError(f'{name}: give an image or the image size (width, height)')
        w, h = int(size[0]), int(size[1])
        if w <= 0 or h <= 0:
            raise FeatureInputError(f'{name}: image size must be positive, got {w}x{h}')
        return np.full((h, w, 3), 32, dtype=np.uint8)
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise FeatureInputError(f'{name}: expected uint8 pixels, got {img.dtype}')
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.ndim == 3 and img.shape[2] == 3:
        return np.ascontiguousarray(img)
    if img.ndim == 3 and img.shape[2] == 1:
        return cv2.cvtColor(img[:, :, 0], cv2.COLOR_GRAY2RGB)
    raise FeatureInputError(f'{name}: expected (H, W) mono8 or (H, W, 3) rgb8, got {img.shape}')


def _check_kp(kp: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(kp, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise FeatureInputError(f'{name}: expected shape (N, 2), got {arr.shape}')
    return arr


def draw_matches(image0: np.ndarray | None, image1: np.ndarray | None, keypoints0: np.ndarray,
                 keypoints1: np.ndarray, matches: np.ndarray, inliers: np.ndarray | None = None,
                 *, size: tuple[int, int] | None = None, scale: float = 1.0,
                 draw_keypoints: bool = True, max_lines: int = 2000,
                 thickness: int = 1) -> np.ndarray:
    """Side-by-side rgb8 image: previous (left) | current (right).

    ``keypoints*`` (N, 2) are pixel coordinates (px) of each image, ``matches`` (M, 2) index
    pairs (previous, current), ``inliers`` (M,) bool (None: all inliers). Inliers are drawn as
    green lines, rejected matches as red lines, keypoints as small yellow dots. A missing image
    (None) is replaced by a dark canvas of ``size`` = (width, height) px. ``scale`` resizes the
    output (e.g. 0.5 for a lighter topic). At most ``max_lines`` matches are drawn (rejected
    first so inliers stay on top); the choice is deterministic.
    """
    img0 = _as_rgb(image0, size, 'image0')
    img1 = _as_rgb(image1, size if image1 is None else None, 'image1')
    kp0 = _check_kp(keypoints0, 'keypoints0')
    kp1 = _check_kp(keypoints1, 'keypoints1')
    m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    inl = np.ones(m.shape[0], dtype=bool) if inliers is None else np.asarray(inliers, bool)
    if inl.shape != (m.shape[0],):
        raise FeatureInputError(f'inliers: expected shape ({m.shape[0]},), got {inl.shape}')
    if m.size and ((m[:, 0] < 0).any() or (m[:, 0] >= len(kp0)).any()
                   or (m[:, 1] < 0).any() or (m[:, 1] >= len(kp1)).any()):
        raise FeatureInputError('matches: indices outside the keypoint arrays')
    if not 0.01 <= scale <= 4.0:
        raise FeatureInputError(f'scale: expected in [0.01, 4], got {scale}')

    h = max(img0.shape[0], img1.shape[0])
    w0 = img0.shape[1]
    canvas = np.zeros((h, w0 + img1.shape[1], 3), dtype=np.uint8)
    canvas[:img0.shape[0], :w0] = img0
    canvas[:img1.shape[0], w0:] = img1
    if scale != 1.0:
        out_size = (round(canvas.shape[1] * scale), round(canvas.shape[0] * scale))
        canvas = cv2.resize(canvas, out_size,
                            interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    shift = 4  # sub-pixel precision of cv2 drawing
    f = scale * (1 << shift)

    def pt(p: np.ndarray, dx: float) -> tuple[int, int]:
        return int(round((p[0] + dx) * f)), int(round(p[1] * f))

    if draw_keypoints:
        for p in kp0:
            cv2.circle(canvas, pt(p, 0.0), int(2 * f), KEYPOINT_COLOR, -1, cv2.LINE_AA, shift)
        for p in kp1:
            cv2.circle(canvas, pt(p, w0), int(2 * f), KEYPOINT_COLOR, -1, cv2.LINE_AA, shift)
    order = np.concatenate([np.flatnonzero(~inl), np.flatnonzero(inl)])
    if order.size > max_lines:
        keep = np.linspace(0, order.size - 1, max_lines).round().astype(np.int64)
        order = order[np.unique(keep)]
    for k in order:
        i, j = m[k]
        color = INLIER_COLOR if inl[k] else REJECTED_COLOR
        cv2.line(canvas, pt(kp0[i], 0.0), pt(kp1[j], w0), color, thickness, cv2.LINE_AA, shift)
    return canvas


def draw_track_result(result: TrackResult, image0: np.ndarray | None = None,
                      image1: np.ndarray | None = None, *, size: tuple[int, int] | None = None,
                      scale: float = 1.0) -> np.ndarray:
    """:func:`draw_matches` for a :class:`TrackResult` (previous | current frame).

    Without images a dark canvas of ``size`` = (width, height) px is used.
    """
    return draw_matches(image0, image1, result.prev_frame_keypoints, result.frame_keypoints,
                        result.matches, result.match_inliers, size=size, scale=scale)
