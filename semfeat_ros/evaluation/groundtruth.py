"""Ground-truth pixel correspondences of an image pair, and the pair record itself.

A ground truth maps pixels of image A to image B (and back) and says where the mapping is
*visible*: inside both valid masks, inside both frames and, for rendered scenes, not occluded.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from semfeat_ros.evaluation.transforms import apply_homography


class GroundTruth(Protocol):
    """Exact pixel mapping between the two images of a pair (px -> px)."""

    def a_to_b(self, uv_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """GT location in B (N, 2) px of A's pixels, and (N,) bool visibility."""

    def b_to_a(self, uv_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """GT location in A (N, 2) px of B's pixels, and (N,) bool visibility."""


def sample_mask(mask: np.ndarray | None, uv: np.ndarray) -> np.ndarray:
    """(N,) bool: ``uv`` (px) lies inside the frame of ``mask`` and on a True pixel (rounded)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    finite = np.isfinite(uv).all(axis=1)
    if mask is None:
        return finite
    h, w = mask.shape
    iu = np.full(len(uv), -1, dtype=np.int64)
    iv = np.full(len(uv), -1, dtype=np.int64)
    iu[finite] = np.rint(uv[finite, 0]).astype(np.int64)
    iv[finite] = np.rint(uv[finite, 1]).astype(np.int64)
    inside = finite & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    out = np.zeros(len(uv), dtype=bool)
    out[inside] = mask[iv[inside], iu[inside]]
    return out


@dataclass
class HomographyGroundTruth:
    """Planar ground truth: ``uv_b = H uv_a``; visible where both valid masks hold.

    ``mask_a`` / ``mask_b`` are (H, W) bool valid masks of A and B (the frame of each is implied
    by its mask's shape).
    """

    H: np.ndarray
    mask_a: np.ndarray
    mask_b: np.ndarray

    def __post_init__(self) -> None:
        self.H = np.asarray(self.H, dtype=np.float64)
        self._H_inv = np.linalg.inv(self.H)

    def a_to_b(self, uv_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        uv_b = apply_homography(self.H, uv_a)
        return uv_b, sample_mask(self.mask_a, uv_a) & sample_mask(self.mask_b, uv_b)

    def b_to_a(self, uv_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        uv_a = apply_homography(self._H_inv, uv_b)
        return uv_a, sample_mask(self.mask_b, uv_b) & sample_mask(self.mask_a, uv_a)


WarpFn = Callable[..., tuple[np.ndarray, np.ndarray]]


@dataclass
class DepthGroundTruth:
    """Rendered-scene ground truth: depth + poses, occlusion-checked by the sim's ``warp_pixels``.

    ``warp(uv_a, depth_a, T_map_cam_a, T_map_cam_b, camera, depth_b=depth_b)`` must return
    ``(uv_b (N, 2) px, valid (N,) bool)``; this is ``semfeat_ros.sim.groundtruth.warp_pixels``.
    Poses are 4x4 camera-optical -> map transforms (m).
    """

    depth_a: np.ndarray
    depth_b: np.ndarray
    T_map_cam_a: np.ndarray
    T_map_cam_b: np.ndarray
    camera: object
    warp: WarpFn
    mask_a: np.ndarray | None = None
    mask_b: np.ndarray | None = None

    def a_to_b(self, uv_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        uv_a = np.asarray(uv_a, dtype=np.float64).reshape(-1, 2)
        uv_b, valid = self.warp(uv_a, self.depth_a, self.T_map_cam_a, self.T_map_cam_b,
                                self.camera, depth_b=self.depth_b)
        uv_b = np.asarray(uv_b, dtype=np.float64).reshape(-1, 2)
        valid = np.asarray(valid, dtype=bool) & sample_mask(self.mask_a, uv_a)
        return uv_b, valid & sample_mask(self.mask_b, uv_b)

    def b_to_a(self, uv_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        uv_b = np.asarray(uv_b, dtype=np.float64).reshape(-1, 2)
        uv_a, valid = self.warp(uv_b, self.depth_b, self.T_map_cam_b, self.T_map_cam_a,
                                self.camera, depth_b=self.depth_a)
        uv_a = np.asarray(uv_a, dtype=np.float64).reshape(-1, 2)
        valid = np.asarray(valid, dtype=bool) & sample_mask(self.mask_b, uv_b)
        return uv_a, valid & sample_mask(self.mask_a, uv_a)


@dataclass
class Pair:
    """One evaluation pair: two RGB uint8 images (H, W, 3), their valid masks, the ground truth
    (None for real sequences, which are scored without it).

    ``H`` is the exact homography when the ground truth is planar (homography accuracy is only
    defined then). ``labels_*`` are GT class-id maps (255 = ignore), ``gt_keypoints_a`` a fixed
    ground-truth keypoint set of A (K, 2) px; all optional.
    """

    name: str
    image_a: np.ndarray
    image_b: np.ndarray
    mask_a: np.ndarray
    mask_b: np.ndarray
    gt: GroundTruth | None
    H: np.ndarray | None = None
    labels_a: np.ndarray | None = None
    labels_b: np.ndarray | None = None
    gt_keypoints_a: np.ndarray | None = None
    camera: object | None = None
    meta: dict[str, object] = field(default_factory=dict)
