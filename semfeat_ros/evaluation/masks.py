"""Valid-pixel masks: the lens's image circle, estimated from the black border or from a camera.

Pixels outside the mask are never used: detections there are dropped and ground-truth locations
that fall there count as not visible.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from semfeat_ros.evaluation.errors import ConfigError
from semfeat_ros.evaluation.transforms import erode_mask


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image from an (H, W) or (H, W, 3) RGB uint8 image."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise ConfigError(f'image: expected (H, W) or (H, W, 3), got shape {image.shape}')


def estimate_valid_mask(image: np.ndarray, *, dark_threshold: int = 12,
                        min_outside_fraction: float = 0.002, margin_px: int = 0) -> np.ndarray:
    """Estimate the image circle of a fisheye frame from its black border.

    Dark pixels (grey <= ``dark_threshold`` after a 5x5 median filter) connected to the image
    frame are outside. If they cover less than ``min_outside_fraction`` of the image, the whole
    frame is valid (pinhole image or circle larger than the sensor). Dark scene regions that touch
    the frame are excluded too: conservative, never a source of wrong ground truth. The result is
    eroded by ``margin_px`` px. Returns an (H, W) bool mask.
    """
    gray = cv2.medianBlur(to_gray(image), 5)
    dark = (gray <= dark_threshold).astype(np.uint8)
    n, lab = cv2.connectedComponents(dark, connectivity=4)
    if n <= 1:
        return erode_mask(np.ones(gray.shape, bool), margin_px)
    border = np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]])
    touching = np.unique(border[border > 0])
    outside = np.isin(lab, touching)
    if outside.mean() < min_outside_fraction:
        return erode_mask(np.ones(gray.shape, bool), margin_px)
    valid = ~outside
    # Keep the largest valid component: isolated bright specks in the border are noise.
    n, lab, stats, _ = cv2.connectedComponentsWithStats(valid.astype(np.uint8), connectivity=4)
    if n > 2:
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        valid = lab == largest
    return erode_mask(valid, margin_px)


def camera_valid_mask(camera_yaml: str | Path, width: int, height: int, *,
                      distortion_model: str | None = None, fov_deg: float | None = None,
                      margin_px: int = 0) -> np.ndarray:
    """The image circle of a calibrated camera (``semfeat_ros.camera`` YAML), resized to
    ``width x height`` px if the calibration was made at another resolution."""
    from semfeat_ros.camera import load_camera_yaml

    camera, _ = load_camera_yaml(camera_yaml, distortion_model=distortion_model, fov_deg=fov_deg)
    camera = camera_for_size(camera, width, height, f'camera {camera_yaml}')
    return erode_mask(camera.valid_mask(), margin_px)


def camera_for_size(camera: object, width: int, height: int, source: str) -> object:
    """``camera`` (a ``semfeat_ros.camera.CameraModel``) for images of ``width x height`` px:
    itself, or scaled when the calibration was made at another resolution of the same aspect
    ratio; :class:`ConfigError` (naming ``source``) when the aspect ratios differ."""
    if (camera.width, camera.height) == (width, height):
        return camera
    if abs(camera.width / camera.height - width / height) > 0.01:
        raise ConfigError(
            f'{source}: calibration size {camera.width}x{camera.height} px does not match the '
            f'image aspect ratio of {width}x{height} px')
    return camera.scaled(width, height)


class MaskSource:
    """How each image's valid mask is obtained: ``'auto'`` (black border), ``'none'`` (whole
    frame) or ``'camera'`` (the YAML's image circle, cached per image size)."""

    def __init__(self, kind: str = 'auto', *, camera_yaml: str | Path | None = None,
                 distortion_model: str | None = None, fov_deg: float | None = None,
                 margin_px: int = 8) -> None:
        if kind not in ('auto', 'none', 'camera'):
            raise ConfigError(f'image circle source must be auto, none or camera, got {kind!r}')
        if kind == 'camera' and camera_yaml is None:
            raise ConfigError('image circle source "camera" needs a camera YAML (--camera)')
        if margin_px < 0:
            raise ConfigError(f'mask margin must be >= 0 px, got {margin_px}')
        self.kind = kind
        self.camera_yaml = camera_yaml
        self.distortion_model = distortion_model
        self.fov_deg = fov_deg
        self.margin_px = int(margin_px)
        self._cache: dict[tuple[int, int], np.ndarray] = {}

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W) bool valid mask of ``image`` *before* the margin (callers erode it with
        :func:`erode_mask` after warping, so the margin applies once in each image)."""
        h, w = image.shape[:2]
        if self.kind == 'auto':
            return estimate_valid_mask(image)
        if (w, h) not in self._cache:
            if self.kind == 'none':
                self._cache[(w, h)] = np.ones((h, w), bool)
            else:
                self._cache[(w, h)] = camera_valid_mask(
                    self.camera_yaml, w, h, distortion_model=self.distortion_model,
                    fov_deg=self.fov_deg)
        return self._cache[(w, h)]

    def final(self, raw: np.ndarray) -> np.ndarray:
        """A raw mask eroded by the margin."""
        return erode_mask(raw, self.margin_px)

    def describe(self) -> str:
        if self.kind == 'camera':
            return f'camera image circle from {self.camera_yaml}, margin {self.margin_px} px'
        if self.kind == 'auto':
            return f'image circle estimated from the black border, margin {self.margin_px} px'
        return f'whole frame, margin {self.margin_px} px'
