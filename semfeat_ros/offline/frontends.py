"""Front ends of the offline tools: the shipped network (as feature_node) and OpenCV baselines.

Every front end turns one decoded frame into keypoints (px), descriptors, class labels and
scores that feed the same :class:`~semfeat_ros.matching.sequential.SequentialMatcher` and the
same mapper:

* :class:`NetworkFrontend` wraps :class:`semfeat_ros.frontend.SemanticFrontend`, the code
  feature_node runs (float descriptors, network labels, semantic mask).
* :class:`OpenCVFrontend` runs ORB (packed binary descriptors, Hamming matching) or SIFT
  (L2-normalised float descriptors) on the grey image inside the lens's image circle. OpenCV
  features carry no semantics: their labels are read from a ground-truth class mask when one is
  given (simulated bags record ``/ground_truth/semantic``), else every keypoint gets the
  static non-ground class :data:`UNLABELED_CLASS` (no semantic filtering, no ground-plane scale).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.frontend import FrontendConfig, SemanticFrontend
from semfeat_ros.labels import IGNORE_LABEL, LabelSet, load_labels
from semfeat_ros.matching.sequential import FrameFeatures
from semfeat_ros.offline.errors import OfflineConfigError
from semfeat_ros.pipeline import frame_features

#: Class given to OpenCV keypoints when no ground-truth class mask is available.
UNLABELED_CLASS = 'wall'
OPENCV_KINDS = ('orb', 'sift')


@dataclass
class FrontendOutput:
    """Features of one frame in input-image pixels.

    ``keypoints`` (N, 2) float32 px; ``descriptors`` (N, D) float32 unit-norm or (N, 32) uint8
    packed bits; ``labels`` (N,) uint8 class ids; ``scores`` (N,) float32; ``mask`` (H, W)
    uint8 class ids (network only, else None).
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    labels: np.ndarray
    scores: np.ndarray
    mask: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def matcher_frame(stamp_ns: int, out: FrontendOutput, camera: CameraModel,
                  frame_id: str) -> FrameFeatures:
    """The matcher input of a front-end output, as matcher_node builds it from a message.

    Keypoints as float32, as they travel in ``/semfeat/features``; bearings from ``camera``;
    rows without a bearing dropped; packed ``uint8`` descriptors kept for binary matching.
    """
    return frame_features(stamp_ns, np.asarray(out.keypoints, dtype=np.float32).reshape(-1, 2),
                          out.descriptors, out.labels, out.scores, camera, frame_id)


class NetworkFrontend:
    """The shipped multi-task network through :class:`SemanticFrontend` (feature_node's code)."""

    name = 'semfeat'
    descriptor_type = 'float'
    needs_labels = False

    def __init__(self, conf: FrontendConfig) -> None:
        self.frontend = SemanticFrontend(conf)

    def describe(self) -> str:
        return self.frontend.describe()

    def process(self, image: np.ndarray, camera: CameraModel | None,
                labels: np.ndarray | None = None) -> FrontendOutput:
        """Features of an RGB / grey uint8 frame (``labels`` is ignored: the network's own)."""
        res = self.frontend.process(image, camera)
        f = res.features
        return FrontendOutput(f.keypoints, f.descriptors, f.labels, f.scores, res.mask)


#: Keypoint noise (px) a mapper should assume for OpenCV keypoints: their detectors localise to
#: about 1 px, the network's keypoints (mapping_node's default, 2.5 px) to about 1.5-2 px with
#: tails (docs/RESULTS.md, Mapping).
OPENCV_BEARING_SIGMA_PX = 1.0


class OpenCVFrontend:
    """ORB or SIFT keypoints (at most ``max_features``) inside the image circle.

    ``border_px`` keeps keypoints this far from the image-circle edge (px); keypoints labelled
    with a class in ``drop_classes`` (the network front end's list: sky and dynamic classes) or
    outside the ground-truth mask (255) are removed, as the network front end removes them.
    """

    def __init__(self, kind: str, max_features: int = 1000, border_px: int = 8,
                 drop_classes: Sequence[str] = ('sky', 'car', 'pedestrian'),
                 label_set: LabelSet | None = None) -> None:
        if kind not in OPENCV_KINDS:
            raise OfflineConfigError(
                f'frontend: expected one of semfeat, {", ".join(OPENCV_KINDS)}, got {kind!r}')
        if max_features < 1:
            raise OfflineConfigError(f'max_features: expected >= 1, got {max_features}')
        self.name = kind
        self.kind = kind
        self.max_features = int(max_features)
        self.border_px = int(border_px)
        self.labels = label_set or load_labels()
        try:
            self.drop_ids = np.array(self.labels.ids_of(list(drop_classes)), dtype=np.int64)
        except KeyError as exc:
            raise OfflineConfigError(f'drop_classes: {exc.args[0]}') from None
        self.unlabeled_id = self.labels.id_of(UNLABELED_CLASS)
        self.descriptor_type = 'binary' if kind == 'orb' else 'float'
        self.needs_labels = True
        if kind == 'orb':
            self._det = cv2.ORB_create(nfeatures=self.max_features)
        else:
            self._det = cv2.SIFT_create(nfeatures=self.max_features)
        self._masks: dict[tuple, np.ndarray] = {}

    def describe(self) -> str:
        desc = ('32-byte binary descriptors, Hamming matching' if self.kind == 'orb'
                else '128-D L2-normalised float descriptors')
        return f'OpenCV {self.kind.upper()} (at most {self.max_features} keypoints, {desc})'

    def _mask(self, camera: CameraModel | None, width: int, height: int) -> np.ndarray:
        key = (camera, width, height)
        if key not in self._masks:
            if camera is None:
                valid = np.ones((height, width), np.uint8) * 255
            else:
                cam = camera if (camera.width, camera.height) == (width, height) \
                    else camera.scaled(width, height)
                valid = cam.valid_mask().astype(np.uint8) * 255
            if self.border_px > 0:
                valid[:self.border_px] = 0
                valid[-self.border_px:] = 0
                valid[:, :self.border_px] = 0
                valid[:, -self.border_px:] = 0
                k = 2 * self.border_px + 1
                valid = cv2.erode(valid, np.ones((k, k), np.uint8))
            self._masks = {key: valid}
        return self._masks[key]

    def process(self, image: np.ndarray, camera: CameraModel | None,
                labels: np.ndarray | None = None) -> FrontendOutput:
        """Features of an RGB / grey uint8 frame; ``labels`` an optional (H, W) class-id mask."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        gray = np.ascontiguousarray(gray)
        h, w = gray.shape
        kps, desc = self._det.detectAndCompute(gray, self._mask(camera, w, h))
        width = 32 if self.kind == 'orb' else 128
        if desc is None or not kps:
            dt = np.uint8 if self.kind == 'orb' else np.float32
            return FrontendOutput(np.zeros((0, 2), np.float32), np.zeros((0, width), dt),
                                  np.zeros(0, np.uint8), np.zeros(0, np.float32))
        pts = np.array([k.pt for k in kps], dtype=np.float32)
        resp = np.array([k.response for k in kps], dtype=np.float32)
        if len(kps) > self.max_features:  # SIFT may return a few more (ties)
            order = np.lexsort((pts[:, 1], pts[:, 0], -resp))[:self.max_features]
            pts, resp, desc = pts[order], resp[order], desc[order]
        if self.kind == 'sift':
            desc = desc.astype(np.float32)
            desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        if labels is None:
            lab = np.full(len(pts), self.unlabeled_id, np.uint8)
        else:
            lab_img = np.asarray(labels)
            if lab_img.shape[:2] != (h, w):
                lab_img = cv2.resize(lab_img, (w, h), interpolation=cv2.INTER_NEAREST)
            u = np.clip(np.rint(pts[:, 0]).astype(np.int64), 0, w - 1)
            v = np.clip(np.rint(pts[:, 1]).astype(np.int64), 0, h - 1)
            lab = lab_img[v, u].astype(np.uint8)
        keep = (lab != IGNORE_LABEL) & ~np.isin(lab, self.drop_ids)
        return FrontendOutput(pts[keep], desc[keep], lab[keep], resp[keep])


def make_frontend(kind: str, frontend_conf: FrontendConfig | None = None,
                  max_features: int = 1000) -> NetworkFrontend | OpenCVFrontend:
    """``'semfeat'`` (the network with ``frontend_conf``), ``'orb'`` or ``'sift'``.

    Raises:
        OfflineConfigError: unknown kind.
        semfeat_ros.model.errors.WeightsNotFoundError: no trained weights for ``'semfeat'``.
    """
    conf = frontend_conf or FrontendConfig()
    if kind == 'semfeat':
        return NetworkFrontend(conf)
    return OpenCVFrontend(kind, max_features=max_features, drop_classes=conf.drop_classes)
