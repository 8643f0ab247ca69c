"""The feature front end shared by feature_node and the offline tools (no rclpy).

A decoded camera frame and its camera model go in; keypoints, descriptors, labels, unit bearings
and the class-id mask come out. The node and ``semfeat-features`` call the same code, so a live
run and an offline run on the same bag agree.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.labels import LabelSet

if TYPE_CHECKING:  # torch is imported lazily by the model package
    from semfeat_ros.model.extractor import Features


FRONTEND_KINDS: tuple[str, ...] = ('semfeat', 'xfeat', 'sift', 'orb')
"""Front ends of feature_node and the offline tools (:mod:`semfeat_ros.offline.frontends`)."""
BINARY_FRONTENDS: tuple[str, ...] = ('orb',)
"""Front ends with packed binary descriptors (32 bytes for ORB), matched by Hamming distance.
In ``/semfeat/features`` each byte travels as one float32 holding its value 0..255 (exact)."""
DESCRIPTOR_DIMS: dict[str, int] = {'xfeat': 64, 'sift': 128, 'orb': 32}
"""Descriptor count D in ``/semfeat/features`` per front end (orb: bytes); semfeat's is the
weights' ``descriptor_dim`` (64 for the shipped weights)."""


class FrontendError(ValueError):
    """A frame cannot be processed (e.g. its size does not match the CameraInfo)."""


def check_frame_size(camera: CameraModel, width: int, height: int,
                     tolerance: float = 0.01) -> None:
    """Raise FrontendError unless a ``width x height`` px frame fits ``camera``: the same aspect
    ratio within the relative ``tolerance`` (cheap, so frames are checked before they are
    decoded)."""
    if width <= 0 or height <= 0:
        raise FrontendError(f'image is {width}x{height} px (empty)')
    ratio = (camera.width / camera.height) / (width / height)
    if abs(ratio - 1.0) > tolerance:
        raise FrontendError(
            f'image is {width}x{height} px but CameraInfo describes '
            f'{camera.width}x{camera.height} px (different aspect ratio)')


def overlay_mask(image: np.ndarray, mask: np.ndarray, labels: LabelSet,
                 alpha: float = 0.45) -> np.ndarray:
    """RGB ``image`` (or grey) blended with the class colours of ``mask`` (resized to the image
    by nearest neighbour when its size differs)."""
    rgb = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
    h, w = rgb.shape[:2]
    if mask.shape != (h, w):
        mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_NEAREST)
    return cv2.addWeighted(rgb, 1.0 - alpha, labels.colorize(mask), alpha, 0.0)


@dataclass(frozen=True)
class FrontendConfig:
    """Settings of the front end (see the FeatureExtractor conf for details)."""

    weights: str | None = None  # None: the shipped weights
    num_threads: int = 2  # network intra-op threads (torch or onnxruntime)
    max_keypoints: int = 1000  # top-k by score
    score_threshold: float = 0.15  # minimum heatmap score (config/model.yaml)
    nms_radius: int = 3  # px at network resolution
    border: int = 4  # px at network resolution, from the image and image-circle border
    drop_classes: tuple[str, ...] = ('sky', 'car', 'pedestrian')  # keypoints never returned
    mask_resolution: str = 'input'  # 'seg' (1/4 network), 'network' or 'input'
    resize_max: int = 640  # px, longer side of the network input
    bf16: bool = False  # bfloat16 autocast of the network (FeatureExtractor conf 'bf16')
    backend: str = 'auto'  # network runtime: 'auto', 'onnxruntime' or 'torch' (FeatureExtractor)
    size_tolerance: float = 0.01  # relative aspect mismatch tolerated between image and camera


@dataclass
class FrontendResult:
    """Features of one frame with bearings (N, 3) in the optical frame (NaN-free)."""

    features: Features
    bearings: np.ndarray | None

    @property
    def mask(self) -> np.ndarray:
        return self.features.mask

    def overlay(self, image: np.ndarray, labels: LabelSet, alpha: float = 0.45) -> np.ndarray:
        """RGB image blended with the class colours of the mask (input resolution)."""
        return overlay_mask(image, self.features.mask, labels, alpha)


class SemanticFrontend:
    """Runs the shipped multi-task network on frames of one camera."""

    def __init__(self, conf: FrontendConfig | None = None):
        from semfeat_ros.model import FeatureExtractor  # torch stays out of rclpy-only imports

        self.conf = conf = conf or FrontendConfig()
        self.extractor = FeatureExtractor(conf.weights, {
            'max_keypoints': conf.max_keypoints, 'detection_threshold': conf.score_threshold,
            'nms_radius': conf.nms_radius, 'remove_borders': conf.border,
            'drop_classes': list(conf.drop_classes), 'num_threads': conf.num_threads,
            'mask_resolution': conf.mask_resolution, 'resize_max': conf.resize_max,
            'bf16': conf.bf16, 'backend': conf.backend})
        self.last_count = 0
        self._scaled: dict[tuple, CameraModel] = {}

    def describe(self) -> str:
        return (f'SemFeatNet ({sum(p.numel() for p in self.extractor.model.parameters())} '
                f'parameters) on {self.extractor.backend}, input resized to a longer side of '
                f'{self.conf.resize_max} px')

    def prepare(self, width: int, height: int) -> None:
        """Ready the network for ``width x height`` frames (see FeatureExtractor.prepare)."""
        self.extractor.prepare(width, height)

    def check_size(self, camera: CameraModel, width: int, height: int) -> None:
        """Raise FrontendError unless a ``width x height`` px frame fits ``camera`` (the same
        aspect ratio, within ``size_tolerance``); cheap, so frames are checked before they are
        decoded."""
        check_frame_size(camera, width, height, self.conf.size_tolerance)

    def camera_for(self, camera: CameraModel, width: int, height: int) -> CameraModel:
        """``camera`` rescaled to a ``width x height`` frame (same lens, resized image).

        Raises FrontendError when the aspect ratios disagree (a wrong CameraInfo).
        """
        if (camera.width, camera.height) == (width, height):
            return camera
        key = (camera, width, height)
        if key not in self._scaled:
            self.check_size(camera, width, height)
            self._scaled = {key: camera.scaled(width, height)}
        return self._scaled[key]

    def process(self, image: np.ndarray, camera: CameraModel | None) -> FrontendResult:
        """Features of an (H, W, 3) RGB or (H, W) uint8 frame; bearings when ``camera`` is set.

        Keypoints whose pixel has no bearing (outside the image circle) are removed.
        """
        if image.ndim not in (2, 3) or image.dtype != np.uint8:
            raise FrontendError(f'expected a uint8 HxW or HxWx3 image, got {image.dtype} '
                                f'{image.shape}')
        h, w = image.shape[:2]
        cam = self.camera_for(camera, w, h) if camera is not None else None
        feats = self.extractor.extract(image, camera=cam)
        bearings = None
        if cam is not None:
            bearings = cam.unproject(feats.keypoints.astype(np.float64), check=False)
            ok = np.isfinite(bearings).all(axis=1)
            if not ok.all():
                feats.keypoints, feats.scores = feats.keypoints[ok], feats.scores[ok]
                feats.descriptors, feats.labels = feats.descriptors[ok], feats.labels[ok]
                bearings = bearings[ok]
        self.last_count = len(feats.keypoints)
        return FrontendResult(features=feats, bearings=bearings)
