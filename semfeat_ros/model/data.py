"""Training data of SemFeatNet: rendered shards and real photos -> augmented view pairs + targets.

Sources
-------
* **Rendered frames** from simulator shards (``semfeat_ros.sim.dataset``: rgb, label, range
  depth, instance ids, poses, camera JSON). Frames are resized once so that their longer side is
  ``frame_long_side`` px, the resolution the :class:`FeatureExtractor` runs the network at, so
  training and inference see objects at the same scale.
* **Real photographs** that ship inside installed packages (``photos`` in the config; defaults:
  the five Balbianello photos in gtsam's data directory and matplotlib's ``grace_hopper.jpg``).
  They have no labels (segmentation loss ignores them) and train only the keypoint and
  descriptor heads, self-supervised SuperPoint-style (homographic pairs; the keypoint candidates
  are homographically adapted, see :func:`adapted_corner_score`). The evaluation images of
  ``real_fisheye_calib`` are never used.

Pair kinds (mixed by ``pair_mix``)
----------------------------------
``synthetic``  one rendered frame and a warped copy: random rotation (+-``rotation_deg``),
               translation (+-``translation_px``), scale (``scale_range``) and, with probability
               ``homography_prob``, a projective warp (corners moved by up to
               ``homography_shift`` x crop size). The image-space mapping is exact for every
               pixel, but a projective warp only simulates a viewpoint change of *planar*
               surfaces, so for projective pairs correspondences are kept only on classes flagged
               ``planar`` in ``labels.yaml`` (non-planar objects such as cars, pillars or poles
               are excluded from homography-derived correspondences and keypoint targets).
``drive``      two frames of the same drive (the shard's ``pairs``): real viewpoint change, with
               ground-truth correspondences from range depth and poses
               (:func:`semfeat_ros.sim.groundtruth.warp_pixels`, occlusion-checked, moving
               agents excluded; parked cars keep their correspondences). The second view gets
               an extra small similarity warp with probability ``drive_warp_prob``.
``photo``      a real photograph and a projective warp of it (all pixels valid).

Every view is a ``crop_size`` window (a homography ``H`` from source px to view px renders it
with ``cv2.warpPerspective``); photometric augmentation (gain, contrast, gamma, colour balance,
blur, noise, JPEG) is applied to each view independently *after* the targets are computed on the
clean views.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
import glob
import hashlib
import importlib.util
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from semfeat_ros import conf as common_conf
from semfeat_ros.labels import IGNORE_LABEL, LabelSet, load_labels
from semfeat_ros.model.errors import DatasetError, ModelConfigError

default_data_conf: dict[str, Any] = {
    'frame_long_side': 640,  # px, frames are resized to this longer side (= extractor resize_max)
    'crop_size': [256, 256],  # [w, h] px of each training view
    'pair_mix': {'synthetic': 0.5, 'drive': 0.4, 'photo': 0.1},  # sampling probabilities
    'rotation_deg': 30.0,  # synthetic pairs: rotation uniform in +-this (deg)
    'translation_px': 15.0,  # synthetic pairs: translation uniform in +-this (px)
    'scale_range': [0.8, 1.2],  # synthetic pairs: scale uniform in this range
    'homography_prob': 0.5,  # synthetic pairs: probability of an added projective warp
    'homography_shift': 0.15,  # projective warp: max corner shift as a fraction of the crop
    'drive_warp_prob': 0.3,  # drive pairs: probability of a mild extra similarity on view b
    'drive_min_overlap': 0.25,  # drive pairs: minimum shard pair_overlap to use a pair
    'min_valid_fraction': 0.5,  # crops must have at least this fraction of labelled pixels
    'dense_flow': False,  # also give each view-a pixel's position in view b (flow_a, for
    #                       loss.kp_repeat_weight and loss.kp_reproj_weight)
    'num_points': 256,  # descriptor correspondences per pair (padded with invalid rows)
    'random_point_fraction': 0.25,  # share of those drawn at random valid pixels (not keypoints)
    'kp_max': 2000,  # max keypoint candidates per source frame
    'kp_nms_radius': 2,  # px, NMS radius of the candidate score
    'kp_tolerance': 2.0,  # px, repeatability tolerance of keypoint targets across the pair
    'kp_border': 4,  # px, no targets this close to the view border or the image circle
    'kp_image_threshold': 0.03,  # image-corner threshold (1 = ideal unit-contrast corner)
    'kp_geometry_threshold': 0.3,  # label/instance/depth-edge corner threshold (1 = L corner)
    'depth_edge_ratio': 0.05,  # relative range jump (5%) that makes a depth discontinuity
    'photos': ['module:gtsam/Data/Balbianello/*.jpg',
               'module:matplotlib/mpl-data/sample_data/grace_hopper.jpg'],  # real photos
    'photo_adaptation': 16,  # homographies of the homographic adaptation of photo keypoints
    'photo_score': 'corners',  # photos' keypoint-candidate score: 'corners' (homographically
    #                            adapted Shi-Tomasi) or 'aliked' (ALIKED's score map, a real-image
    #                            teacher; candidates where it exceeds ALIKED's threshold 0.2)
    'photo_score_cache': None,  # directory of cached 'aliked' score maps (relative to the cwd;
    #                             None: computed at every start, ~0.7 s a photo)
    'photo_fisheye_views': 0,  # per photo, this many more frames showing it through the front
    #                            fisheye camera (semfeat_ros.model.photo_fisheye) at the rendered
    #                            frames' size (frame_long_side, the camera's aspect)
    'photometric': {
        'gain': [0.6, 1.4],  # multiplicative brightness
        'contrast': [0.7, 1.3],  # contrast around the mean
        'gamma': [0.7, 1.5],  # gamma exponent
        'color': 0.1,  # per-channel gain jitter (+-)
        'blur_prob': 0.3,  # probability of a Gaussian blur ...
        'blur_sigma': [0.3, 1.2],  # ... with this sigma (px)
        'noise_sigma': [0.0, 6.0],  # Gaussian noise sigma (grey levels)
        'jpeg_prob': 0.3,  # probability of JPEG re-encoding ...
        'jpeg_quality': [40, 95],  # ... at this quality
    },
}

PAIR_KINDS = ('synthetic', 'drive', 'photo')

# Responses of ideal structures under :func:`_min_eig` (calibration of the thresholds): a unit
# step corner for image corners and an L junction of two 1-px lines for edge-map corners.
_SIGMA_IMG = 1.0
_SIGMA_EDGE = 1.5


def _min_eig(img: np.ndarray, sigma: float) -> np.ndarray:
    """Smaller eigenvalue of the 5x5 structure tensor after a Gaussian blur (Shi-Tomasi)."""
    blurred = cv2.GaussianBlur(img.astype(np.float32), (0, 0), sigma)
    return cv2.cornerMinEigenVal(blurred, 5, 3)


def _calibrate() -> tuple[float, float]:
    step = np.zeros((64, 64), np.float32)
    step[32:, 32:] = 1.0
    lines = np.zeros((64, 64), np.float32)
    lines[32, 32:] = 1.0
    lines[32:, 32] = 1.0
    return float(_min_eig(step, _SIGMA_IMG).max()), float(_min_eig(lines, _SIGMA_EDGE).max())


_UNIT_IMG, _UNIT_EDGE = _calibrate()


def merge_conf(default: dict[str, Any], conf: dict[str, Any] | None, name: str) -> dict[str, Any]:
    """Deep copy of ``default`` updated with ``conf``, nested sections merged, unknown keys
    raising :class:`ModelConfigError` (named ``name.key``); ``pair_mix`` (keys are pair kinds,
    not options) is replaced whole."""
    return common_conf.merge_conf(default, conf, ModelConfigError, name=name,
                                  opaque=('pair_mix',))


# ---------------------------------------------------------------------------- frames


@dataclass
class Frame:
    """One source image at training scale. Rendered frames have everything; photos only rgb.

    Attributes:
        rgb: (H, W, 3) uint8.
        label: (H, W) uint8 class ids, 255 = no label (outside the circle; all of a photo).
        depth: (H, W) float16 range along the ray (m), inf sky, NaN outside; None for photos.
        instance: (H, W) uint16 instance ids; None for photos.
        T_map_cam: (4, 4) camera pose; None for photos.
        camera: camera model scaled to the frame size; None for photos.
        static: (H, W) bool pixels whose correspondences are valid across frames (labelled and
            not a moving agent of the shard's ``moving_instances``); None for photos.
        score: optional (H, W) float32 precomputed corner score (photos: adapted).
        mask: photos only: optional (H, W) bool pixels that show the photograph (a fisheye
            view of a photo covers part of the frame); None: every pixel.
        candidates: cache of :func:`frame_candidates` (K, 2) float px.
        name: source description (shard path + index, or photo path).
    """

    rgb: np.ndarray
    label: np.ndarray
    depth: np.ndarray | None = None
    instance: np.ndarray | None = None
    T_map_cam: np.ndarray | None = None
    camera: Any = None
    static: np.ndarray | None = None
    score: np.ndarray | None = None
    candidates: np.ndarray | None = None
    mask: np.ndarray | None = None
    name: str = ''

    @property
    def is_photo(self) -> bool:
        return self.depth is None

    @property
    def size(self) -> tuple[int, int]:
        """(W, H) px."""
        return self.rgb.shape[1], self.rgb.shape[0]


def _target_size(w: int, h: int, long_side: int) -> tuple[int, int]:
    s = long_side / max(w, h)
    return max(1, int(round(w * s))), max(1, int(round(h * s)))


def load_shard_frames(path: str | Path, long_side: int
                      ) -> tuple[list[Frame], list[tuple[int, int, float]]]:
    """Frames of one simulator shard resized to ``long_side`` and its pairs (a, b, overlap).

    Raises :class:`DatasetError` if the shard cannot be read.
    """
    from semfeat_ros.sim.dataset import load_shard
    from semfeat_ros.sim.errors import ShardError
    try:
        data = load_shard(path)
    except (FileNotFoundError, ShardError) as exc:
        raise DatasetError(f'training shard {path}: {exc}') from exc
    cam = data['camera_model']
    n, h, w = data['label'].shape
    tw, th = _target_size(w, h, long_side)
    cam_s = cam.scaled(tw, th) if (tw, th) != (w, h) else cam
    moving = np.asarray(data['moving_instances'], np.int64)
    frames = []
    for i in range(n):
        rgb, label = data['rgb'][i], data['label'][i]
        depth = data['depth'][i].astype(np.float32)
        inst = data['instance'][i].astype(np.uint16)
        if (tw, th) != (w, h):
            interp = cv2.INTER_AREA if tw < w else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, (tw, th), interpolation=interp)
            label = cv2.resize(label, (tw, th), interpolation=cv2.INTER_NEAREST)
            depth = cv2.resize(depth, (tw, th), interpolation=cv2.INTER_NEAREST)
            inst = cv2.resize(inst, (tw, th), interpolation=cv2.INTER_NEAREST)
        static = (label != IGNORE_LABEL) & ~np.isin(inst, moving)
        frames.append(Frame(rgb=rgb, label=label, depth=depth.astype(np.float16), instance=inst,
                            T_map_cam=data['T_map_cam'][i].astype(np.float64), camera=cam_s,
                            static=static, name=f'{path}#{i}'))
    pairs = [(int(a), int(b), float(o)) for (a, b), o in zip(data['pairs'], data['pair_overlap'])]
    return frames, pairs


def resolve_photo_paths(patterns: Sequence[str], strict: bool = False) -> list[Path]:
    """Expand photo patterns: plain globs or ``module:PKG/rel/glob`` inside an installed package.

    The package is located with ``importlib.util.find_spec`` (not imported). Missing packages or
    patterns matching nothing are skipped, or with ``strict`` refused (a missing photo would
    silently change the training data); the result is sorted and deduplicated.
    """
    out: set[Path] = set()
    for pat in patterns:
        matches: list[str] = []
        if pat.startswith('module:'):
            mod, _, rel = pat[len('module:'):].partition('/')
            try:
                spec = importlib.util.find_spec(mod)
            except (ImportError, ValueError):
                spec = None
            if spec is not None and spec.submodule_search_locations:
                base = Path(list(spec.submodule_search_locations)[0])
                matches = glob.glob(str(base / rel))
        else:
            matches = glob.glob(pat)
        if strict and not matches:
            raise DatasetError(f'photos: {pat!r} matches no file (is its package installed? '
                               f'see requirements.txt)')
        out.update(Path(p) for p in matches)
    if any('real_fisheye_calib' in str(p) for p in out):
        raise DatasetError('photos: real_fisheye_calib is reserved for evaluation and must never '
                           'be used for training')
    return sorted(out)


class _AlikedScores:
    """ALIKED score maps (:class:`semfeat_ros.model.teachers.AlikedScoreTeacher`) scaled to the
    corner-score units (``>= kp_image_threshold`` where ALIKED detects), cached by image hash."""

    def __init__(self, image_threshold: float, cache: Path | None) -> None:
        self.scale = image_threshold
        self.cache = cache
        self.teacher: Any = None

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        from semfeat_ros.model.teachers import AlikedScoreTeacher
        key = hashlib.sha1(rgb.tobytes() + repr(rgb.shape).encode()).hexdigest()
        path = None if self.cache is None else self.cache / f'aliked_{key}.npy'
        if path is not None and path.is_file():
            score = np.load(path, allow_pickle=False)
        else:
            if self.teacher is None:
                self.teacher = AlikedScoreTeacher()
            # float16 as cached, so a cold and a warm cache give the same training data
            score = self.teacher(rgb).astype(np.float16)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix('.tmp.npy')
                np.save(tmp, score, allow_pickle=False)
                tmp.replace(path)
        return score.astype(np.float32) * np.float32(self.scale / AlikedScoreTeacher.threshold)


def load_photo_frames(paths: Sequence[Path], long_side: int, adaptation: int,
                      seed: int, conf: dict[str, Any] | None = None,
                      progress: bool = False) -> list[Frame]:
    """Real photographs as label-free frames with keypoint-candidate scores.

    Each photo gives a frame at ``long_side`` px and ``photo_fisheye_views`` frames of it seen
    through the front fisheye camera (masked to where the photo lands). Scores: ``photo_score``
    of ``conf`` (keys of :data:`default_data_conf`; default: adapted corners).
    """
    c = merge_conf(default_data_conf, conf, 'data')
    scorer = None
    if c['photo_score'] == 'aliked':
        cache = c['photo_score_cache']
        scorer = _AlikedScores(float(c['kp_image_threshold']),
                               None if cache is None else Path(cache))
    elif c['photo_score'] != 'corners':
        raise ModelConfigError(f"data.photo_score must be 'corners' or 'aliked', got "
                               f"{c['photo_score']!r}")
    views = int(c['photo_fisheye_views'])
    camera = None
    if views > 0:
        from semfeat_ros.camera import load_camera_yaml
        from semfeat_ros.model.photo_fisheye import fisheye_view
        cam = load_camera_yaml()[0]
        camera = cam.scaled(*_target_size(cam.width, cam.height, long_side))
    frames = []
    for k, p in enumerate(tqdm(paths, desc='photos', disable=not progress, leave=False)):
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            raise DatasetError(f'photo {p}: unreadable image')
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        h, w = rgb.shape[:2]
        tw, th = _target_size(w, h, long_side)
        if (tw, th) != (w, h):
            rgb = cv2.resize(rgb, (tw, th), interpolation=cv2.INTER_AREA if tw < w
                             else cv2.INTER_LINEAR)
        shown: list[tuple[np.ndarray, np.ndarray | None, str]] = [(rgb, None, str(p))]
        for j in range(views):
            img, mask = fisheye_view(rgb, camera, np.random.default_rng([seed, 6151, k, j]))
            shown.append((img, mask, f'{p}#fisheye{j}'))
        for i, (img, mask, name) in enumerate(shown):
            label = np.full(img.shape[:2], IGNORE_LABEL, np.uint8)
            if scorer is not None:
                score = scorer(img)
            else:
                rng = np.random.default_rng([seed, 7919, k] + ([i] if i else []))
                score = adapted_corner_score(img, adaptation, rng)
            if mask is not None:
                score = np.where(mask, score, 0.0).astype(np.float32)
            frames.append(Frame(rgb=img, label=label, score=score, mask=mask, name=name))
    return frames


# ---------------------------------------------------------------------------- geometry


def apply_h(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to (N, 2) px (pixel centres at integers)."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    hom = pts @ H[:, :2].T + H[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        return hom[:, :2] / hom[:, 2:3]


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def random_similarity(rng: np.random.Generator, center: np.ndarray, rotation_deg: float,
                      translation_px: float, scale_range: Sequence[float]) -> np.ndarray:
    """Rotation (+-deg) and scale about ``center`` followed by a translation (+-px); 3x3."""
    a = np.radians(rng.uniform(-rotation_deg, rotation_deg))
    s = rng.uniform(scale_range[0], scale_range[1])
    t = rng.uniform(-translation_px, translation_px, size=2)
    R = np.array([[s * np.cos(a), -s * np.sin(a), 0.0], [s * np.sin(a), s * np.cos(a), 0.0],
                  [0.0, 0.0, 1.0]])
    return _translation(center[0] + t[0], center[1] + t[1]) @ R @ _translation(-center[0],
                                                                              -center[1])


def random_projective(rng: np.random.Generator, size: tuple[int, int], shift: float
                      ) -> np.ndarray:
    """Homography moving the corners of a ``size`` (w, h) window by up to ``shift`` x size."""
    w, h = size
    src = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float32)
    d = rng.uniform(-shift, shift, size=(4, 2)) * np.array([w, h])
    return cv2.getPerspectiveTransform(src, (src + d).astype(np.float32)).astype(np.float64)


def render_view(frame: Frame, H: np.ndarray, size: tuple[int, int]) -> dict[str, np.ndarray]:
    """Warp a frame into a view (``H``: source px -> view px); outside = black / 255 / NaN."""
    w, h = size
    out = {
        'rgb': cv2.warpPerspective(frame.rgb, H, (w, h), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0),
        'label': cv2.warpPerspective(frame.label, H, (w, h), flags=cv2.INTER_NEAREST,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=IGNORE_LABEL),
    }
    if frame.depth is not None:
        out['depth'] = cv2.warpPerspective(frame.depth.astype(np.float32), H, (w, h),
                                           flags=cv2.INTER_NEAREST,
                                           borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
        out['instance'] = cv2.warpPerspective(frame.instance.astype(np.float32), H, (w, h),
                                              flags=cv2.INTER_NEAREST,
                                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    shown = np.ones(frame.label.shape, np.uint8) if frame.mask is None else \
        frame.mask.astype(np.uint8)
    out['coverage'] = cv2.warpPerspective(shown, H, (w, h), flags=cv2.INTER_NEAREST,
                                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if frame.score is not None:
        out['score'] = cv2.warpPerspective(frame.score, H, (w, h), flags=cv2.INTER_LINEAR,
                                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out


def _nearest(img: np.ndarray, pts: np.ndarray, fill: float) -> np.ndarray:
    h, w = img.shape[:2]
    iu = np.rint(np.nan_to_num(pts[:, 0], nan=-1.0))
    iv = np.rint(np.nan_to_num(pts[:, 1], nan=-1.0))
    inside = (iu >= 0) & (iu <= w - 1) & (iv >= 0) & (iv <= h - 1)
    out = np.full(len(pts), fill, dtype=np.float64)
    out[inside] = img[iv[inside].astype(np.intp), iu[inside].astype(np.intp)]
    return out


@dataclass
class PairSample:
    """Two views of one or two source frames and their exact correspondence.

    ``H_a``/``H_b`` map source px to view px. ``projective`` marks synthetic pairs whose relative
    warp has a projective part (correspondences restricted to planar classes).
    """

    kind: str
    frame_a: Frame
    frame_b: Frame
    H_a: np.ndarray
    H_b: np.ndarray
    size: tuple[int, int]
    projective: bool
    labels: LabelSet
    view_a: dict[str, np.ndarray] = field(default_factory=dict)
    view_b: dict[str, np.ndarray] = field(default_factory=dict)

    def render(self) -> None:
        self.view_a = render_view(self.frame_a, self.H_a, self.size)
        self.view_b = render_view(self.frame_b, self.H_b, self.size)

    def correspond(self, pts: np.ndarray, reverse: bool = False
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Map view-a px (N, 2) to view-b px (or b -> a with ``reverse``); ``(pts, valid)``."""
        fa, fb, Ha, Hb, vb = self.frame_a, self.frame_b, self.H_a, self.H_b, self.view_b
        if reverse:
            fa, fb, Ha, Hb, vb = fb, fa, Hb, Ha, self.view_a
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        src_a = apply_h(np.linalg.inv(Ha), pts)
        finite = np.isfinite(src_a).all(axis=1)
        src_a = np.where(finite[:, None], src_a, -1.0)
        if fa.is_photo:
            wa, ha = fa.size
            valid = finite & (src_a[:, 0] >= 0) & (src_a[:, 0] <= wa - 1) & \
                (src_a[:, 1] >= 0) & (src_a[:, 1] <= ha - 1)
            if fa.mask is not None:
                valid &= _nearest(fa.mask, src_a, 0) > 0
        else:
            lab = _nearest(fa.label, src_a, IGNORE_LABEL).astype(np.int64)
            valid = finite & (lab != IGNORE_LABEL)
        if fa is fb:
            src_b = src_a
            if self.projective and not fa.is_photo:
                planar = np.append(self.labels.planar, False)
                valid &= planar[np.where(lab == IGNORE_LABEL, len(self.labels), lab)]
        else:
            from semfeat_ros.sim.groundtruth import warp_pixels
            src_b, ok = warp_pixels(src_a, fa.depth.astype(np.float32), fa.T_map_cam,
                                    fb.T_map_cam, fa.camera, fb.depth.astype(np.float32),
                                    camera_b=fb.camera, mask_a=fa.static)
            valid &= ok
            src_b = np.where(valid[:, None], src_b, -1.0)
        out = apply_h(Hb, src_b)
        w, h = self.size
        valid &= np.isfinite(out).all(axis=1)
        out = np.where(valid[:, None], out, -1.0)
        valid &= (out[:, 0] >= 0) & (out[:, 0] <= w - 1) & (out[:, 1] >= 0) & (out[:, 1] <= h - 1)
        if not fb.is_photo and vb:
            valid &= _nearest(vb['label'], out, IGNORE_LABEL) != IGNORE_LABEL
        return out, valid

    def valid_grid(self, stride: int = 4, reverse: bool = False) -> np.ndarray:
        """(h, w) bool: pixels of view a (b with ``reverse``) with a valid correspondence,
        evaluated on a ``stride`` grid and expanded (nearest)."""
        w, h = self.size
        gu, gv = np.meshgrid(np.arange(stride // 2, w, stride), np.arange(stride // 2, h, stride))
        pts = np.stack([gu.ravel(), gv.ravel()], axis=1).astype(np.float64)
        _, ok = self.correspond(pts, reverse)
        grid = ok.reshape(gu.shape).astype(np.uint8)
        return cv2.resize(grid, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)


# ---------------------------------------------------------------------------- keypoint targets


def image_corner_score(rgb: np.ndarray) -> np.ndarray:
    """(H, W) Shi-Tomasi score of the grey image, 1 = ideal unit-contrast (black/white) corner."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    return _min_eig(grey, _SIGMA_IMG) / _UNIT_IMG


def edge_map(label: np.ndarray, instance: np.ndarray | None, depth: np.ndarray | None,
             depth_ratio: float) -> np.ndarray:
    """(H, W) float32 1-px edge map of label, instance and depth discontinuities.

    A pixel is an edge when its right or lower neighbour has another label or instance id, or a
    range differing by more than ``depth_ratio`` (relative; sky counts as 1e4 m). Edges against
    unlabelled pixels (255, the image-circle border) are not edges.
    """
    lab = label.astype(np.int32)
    known = lab != IGNORE_LABEL
    edges = np.zeros(label.shape, bool)
    maps = [lab]
    if instance is not None:
        maps.append(instance.astype(np.int64))
    for m in maps:
        edges[:, :-1] |= m[:, :-1] != m[:, 1:]
        edges[:-1, :] |= m[:-1, :] != m[1:, :]
    if depth is not None:
        d = np.asarray(depth, dtype=np.float32)
        d = np.where(np.isinf(d), 1e4, d)
        logd = np.log(np.clip(np.nan_to_num(d, nan=1.0), 1e-3, None))
        thr = np.log1p(depth_ratio)
        edges[:, :-1] |= np.abs(logd[:, :-1] - logd[:, 1:]) > thr
        edges[:-1, :] |= np.abs(logd[:-1, :] - logd[1:, :]) > thr
    both = known.copy()
    both[:, :-1] &= known[:, 1:]
    both[:-1, :] &= known[1:, :]
    return (edges & both).astype(np.float32)


def geometry_corner_score(label: np.ndarray, instance: np.ndarray | None,
                          depth: np.ndarray | None, depth_ratio: float) -> np.ndarray:
    """(H, W) corner score of the edge map (1 = an L junction of two edges); straight edges 0."""
    return _min_eig(edge_map(label, instance, depth, depth_ratio), _SIGMA_EDGE) / _UNIT_EDGE


def adapted_corner_score(rgb: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Homographic adaptation (SuperPoint) of :func:`image_corner_score` for a real photo.

    The score is averaged over the identity and ``n`` random homographies (each warps the
    photo, scores it, and warps the score back); a pixel's average uses only the warps that
    covered it.
    """
    h, w = rgb.shape[:2]
    acc = image_corner_score(rgb)
    cnt = np.ones((h, w), np.float32)
    center = np.array([(w - 1) / 2, (h - 1) / 2])
    for _ in range(n):
        H = random_projective(rng, (w, h), 0.15) @ random_similarity(rng, center, 20.0, 0.0,
                                                                     (0.8, 1.2))
        warped = cv2.warpPerspective(rgb, H, (w, h), flags=cv2.INTER_LINEAR)
        cover = cv2.warpPerspective(np.ones((h, w), np.float32), H, (w, h),
                                    flags=cv2.INTER_NEAREST)
        back = cv2.warpPerspective(image_corner_score(warped) * cover, np.linalg.inv(H), (w, h),
                                   flags=cv2.INTER_LINEAR)
        cov = cv2.warpPerspective(cover, np.linalg.inv(H), (w, h), flags=cv2.INTER_NEAREST)
        acc += back * cov
        cnt += cov
    return (acc / cnt).astype(np.float32)


def _nms_points(score: np.ndarray, radius: int, min_score: float, max_points: int
                ) -> np.ndarray:
    """Integer (K, 2) (u, v) of local maxima >= min_score, best first, at most max_points."""
    k = 2 * radius + 1
    dil = cv2.dilate(score, np.ones((k, k), np.uint8))
    peaks = (score >= dil) & (score >= min_score)
    vv, uu = np.nonzero(peaks)
    order = np.argsort(-score[vv, uu], kind='stable')[:max_points]
    return np.stack([uu[order], vv[order]], axis=1).astype(np.int64)


def keypoint_candidates(view: dict[str, np.ndarray], conf: dict[str, Any]) -> np.ndarray:
    """Candidate keypoints (K, 2) int px of one clean view (before photometric augmentation).

    Score ``S = max(S_img / kp_image_threshold, S_geo / kp_geometry_threshold)`` where

    * ``S_img``: Shi-Tomasi corner score of the grey image (blur sigma 1 px, 5x5 window),
      normalised so an ideal black/white corner scores 1 (a corner of contrast c scores ~c^2);
      photos use the homographically adapted score instead;
    * ``S_geo``: Shi-Tomasi score of the edge map of label / instance / range discontinuities
      (:func:`edge_map`, blur sigma 1.5 px), normalised so an L junction scores 1: corners of
      painted markings, junctions of regions, ends and corners of pillar/wall edges; straight
      edges score ~0.

    Candidates are local maxima of ``S`` in a (2 ``kp_nms_radius`` + 1)^2 window with
    ``S >= 1``, at least ``kp_border`` px from the view border and from unlabelled pixels (image
    circle), at most ``kp_max`` (highest first). Training computes them once per *source frame*
    (:func:`frame_candidates`) and carries them into the views by their homographies.
    """
    if 'score' in view:
        s = view['score'] / conf['kp_image_threshold']
    else:
        s = image_corner_score(view['rgb']) / conf['kp_image_threshold']
    if 'depth' in view:
        geo = geometry_corner_score(view['label'], view.get('instance'), view['depth'],
                                    conf['depth_edge_ratio'])
        s = np.maximum(s, geo / conf['kp_geometry_threshold'])
    b = int(conf['kp_border'])
    usable = view['coverage'].copy()
    if 'depth' in view:  # rendered frames: only labelled pixels (inside the image circle)
        usable &= (view['label'] != IGNORE_LABEL).astype(np.uint8)
    if b > 0:
        usable = cv2.erode(usable, np.ones((2 * b + 1, 2 * b + 1), np.uint8), borderValue=0)
    s = np.where(usable > 0, s, 0.0).astype(np.float32)
    return _nms_points(s, int(conf['kp_nms_radius']), 1.0, int(conf['kp_max']))


def frame_candidates(frame: Frame, conf: dict[str, Any]) -> np.ndarray:
    """Candidates (K, 2) float px of a whole source frame (computed once, then cached).

    The cache assumes one candidate configuration per frame (one PairGenerator).
    """
    if frame.candidates is None:
        view = render_view(frame, np.eye(3), frame.size)
        frame.candidates = keypoint_candidates(view, conf).astype(np.float64)
    return frame.candidates


def view_candidates(frame: Frame, H: np.ndarray, view: dict[str, np.ndarray],
                    conf: dict[str, Any]) -> np.ndarray:
    """Source-frame candidates carried into a view (``H``: source px -> view px), rounded to
    pixels, kept when at least ``kp_border`` px inside the view's usable area; (K, 2) int."""
    pts = np.rint(apply_h(H, frame_candidates(frame, conf)))
    pts = pts[np.isfinite(pts).all(axis=1)]
    usable = view['coverage'].copy()
    if 'depth' in view:
        usable &= (view['label'] != IGNORE_LABEL).astype(np.uint8)
    b = int(conf['kp_border'])
    if b > 0:
        usable = cv2.erode(usable, np.ones((2 * b + 1, 2 * b + 1), np.uint8), borderValue=0)
    h, w = usable.shape
    inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
    pts = pts[inside].astype(np.int64)
    pts = pts[usable[pts[:, 1], pts[:, 0]] > 0]
    if len(pts):
        _, first = np.unique(pts, axis=0, return_index=True)
        pts = pts[np.sort(first)]
    return pts


def keypoint_targets(pair: PairSample, conf: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth keypoints of both views of a pair: the exact rule.

    1. Candidates of each source frame by :func:`keypoint_candidates` (edge-detection and
       region-based corners of the rendered geometry plus image corners), carried into each
       view by its homography (:func:`view_candidates`; computing them on the warped views
       instead would add staircase corners of the nearest-neighbour-resampled label maps).
    2. A candidate of view a is kept iff its correspondence in view b is valid
       (:meth:`PairSample.correspond`: visible, not occluded, not a moving agent, planar for
       projective pairs) and some *kept* candidate of view b lies within ``kp_tolerance`` px of it;
       symmetrically for view b (iterated to the fixed point, so the two sets are mutually
       consistent). Non-repeatable candidates become negatives of the heatmap loss; pixels
       without a valid correspondence are ignored by it.

    Returns:
        ``(kp_a (Ka, 2), kp_b (Kb, 2))`` int px of the kept keypoints.
    """
    tol2 = float(conf['kp_tolerance']) ** 2
    cand = [view_candidates(pair.frame_a, pair.H_a, pair.view_a, conf),
            view_candidates(pair.frame_b, pair.H_b, pair.view_b, conf)]
    mapped = []
    for i, reverse in ((0, False), (1, True)):
        if len(cand[i]) == 0:
            mapped.append((np.zeros((0, 2)), np.zeros(0, bool)))
        else:
            mapped.append(pair.correspond(cand[i].astype(np.float64), reverse=reverse))
    keep = [m[1].copy() for m in mapped]
    # iterate to the fixed point, so that every kept keypoint has a kept partner and vice versa
    for _ in range(10):
        changed = False
        for i in (0, 1):
            other = cand[1 - i][keep[1 - i]].astype(np.float64)
            if len(other) == 0 or not keep[i].any():
                new = np.zeros_like(keep[i])
            else:
                d2 = ((mapped[i][0][:, None, :] - other[None, :, :]) ** 2).sum(-1)
                new = keep[i] & (d2.min(axis=1) <= tol2)
            changed |= bool((new != keep[i]).any())
            keep[i] = new
        if not changed:
            break
    return cand[0][keep[0]], cand[1][keep[1]]


# ---------------------------------------------------------------------------- photometric


def photometric_augment(rgb: np.ndarray, rng: np.random.Generator, conf: dict[str, Any]
                        ) -> np.ndarray:
    """Random gain, contrast, gamma, colour balance, blur, noise and JPEG of a uint8 RGB view.

    Black pixels (outside the image circle / the warped area) stay black.
    """
    c = conf
    outside = (rgb.max(axis=2) == 0)
    x = rgb.astype(np.float32) / 255.0
    x = x * rng.uniform(*c['gain'])
    mean = x.mean()
    x = (x - mean) * rng.uniform(*c['contrast']) + mean
    x = x * (1.0 + rng.uniform(-c['color'], c['color'], size=3)).astype(np.float32)
    x = np.clip(x, 0.0, 1.0) ** rng.uniform(*c['gamma'])
    if rng.random() < c['blur_prob']:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(*c['blur_sigma']))
    sigma = rng.uniform(*c['noise_sigma']) / 255.0
    if sigma > 0:
        x = x + rng.normal(0.0, sigma, size=x.shape).astype(np.float32)
    out = np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if rng.random() < c['jpeg_prob']:
        q = int(rng.integers(c['jpeg_quality'][0], c['jpeg_quality'][1] + 1))
        ok, buf = cv2.imencode('.jpg', cv2.cvtColor(out, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, q])
        if ok:
            out = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    out[outside] = 0
    return out


# ---------------------------------------------------------------------------- dataset


class PairGenerator:
    """Deterministic pair samples: ``sample(seed_key)`` depends only on its key (and the data).

    Args:
        shards: simulator shard paths (may be empty if only photos are used).
        conf: data config (keys of :data:`default_data_conf`).
        seed: base seed of all randomness.
        use_photos: load the real photos of ``conf['photos']``.
        labels: class table (default: the shipped labels.yaml).
        progress: show a progress bar while the photos load (teacher scores take time).
    """

    def __init__(self, shards: Sequence[str | Path], conf: dict[str, Any] | None = None,
                 seed: int = 0, use_photos: bool = True, labels: LabelSet | None = None,
                 progress: bool = False) -> None:
        self.conf = c = merge_conf(default_data_conf, conf, 'data')
        self.seed = int(seed)
        self.labels = labels or load_labels()
        self.size = (int(c['crop_size'][0]), int(c['crop_size'][1]))
        if min(self.size) < 32 or self.size[0] % 16 or self.size[1] % 16:
            raise ModelConfigError(f'data.crop_size must be multiples of 16 px >= 32, got '
                                   f'{c["crop_size"]}')
        self.frames: list[Frame] = []
        self.sim_frames: list[int] = []
        self.drive_pairs: list[tuple[int, int]] = []
        for path in shards:
            frames, pairs = load_shard_frames(path, int(c['frame_long_side']))
            base = len(self.frames)
            self.frames += frames
            self.sim_frames += list(range(base, base + len(frames)))
            self.drive_pairs += [(base + a, base + b) for a, b, o in pairs
                                 if o >= c['drive_min_overlap'] and a != b]
        self.photo_frames: list[int] = []
        if use_photos:
            paths = resolve_photo_paths(c['photos'], strict=True)
            base = len(self.frames)
            self.frames += load_photo_frames(paths, int(c['frame_long_side']),
                                             int(c['photo_adaptation']), self.seed, c,
                                             progress=progress)
            self.photo_frames = list(range(base, len(self.frames)))
        mix = {k: float(v) for k, v in c['pair_mix'].items()}
        if set(mix) - set(PAIR_KINDS) or any(v < 0 for v in mix.values()):
            raise ModelConfigError(f'data.pair_mix: keys must be in {PAIR_KINDS} with weights '
                                   f'>= 0, got {c["pair_mix"]}')
        avail = {'synthetic': bool(self.sim_frames), 'drive': bool(self.drive_pairs),
                 'photo': bool(self.photo_frames)}
        self.kinds = [k for k in PAIR_KINDS if mix.get(k, 0.0) > 0 and avail[k]]
        if not self.kinds:
            raise DatasetError(f'no training data: pair_mix {mix} but available sources {avail} '
                               f'({len(self.sim_frames)} rendered frames, '
                               f'{len(self.drive_pairs)} drive pairs, '
                               f'{len(self.photo_frames)} photos)')
        p = np.array([mix[k] for k in self.kinds])
        self.kind_p = p / p.sum()

    def class_counts(self, num_classes: int) -> np.ndarray:
        """(num_classes,) int64 labelled pixel counts over the rendered frames (255 ignored)."""
        counts = np.zeros(num_classes, np.int64)
        for i in self.sim_frames:
            lab = self.frames[i].label
            counts += np.bincount(lab[lab < num_classes].ravel(), minlength=num_classes)
        return counts

    # -- pair construction

    def _crop_origin(self, frame: Frame, rng: np.random.Generator) -> np.ndarray:
        """Top-left (x, y) of a crop with enough labelled pixels (photos: enough of the photo;
        anywhere when it fills the frame)."""
        W, H = frame.size
        w, h = self.size
        best, best_frac = np.array([max(0, (W - w) // 2), max(0, (H - h) // 2)], float), -1.0
        for _ in range(8):
            o = np.array([rng.uniform(0, max(W - w, 0)), rng.uniform(0, max(H - h, 0))])
            if frame.is_photo and frame.mask is None:
                return np.floor(o)
            ox, oy = int(o[0]), int(o[1])
            shown = frame.mask if frame.is_photo else frame.label != IGNORE_LABEL
            frac = float(shown[oy:oy + h, ox:ox + w].mean())
            if frac >= self.conf['min_valid_fraction']:
                return np.floor(o)
            if frac > best_frac:
                best, best_frac = np.floor(o), frac
        return best

    def _synthetic(self, fi: int, rng: np.random.Generator, kind: str) -> PairSample:
        c = self.conf
        frame = self.frames[fi]
        o = self._crop_origin(frame, rng)
        H_a = _translation(-o[0], -o[1])
        center = np.array([(self.size[0] - 1) / 2, (self.size[1] - 1) / 2])
        warp = random_similarity(rng, center, c['rotation_deg'], c['translation_px'],
                                 c['scale_range'])
        projective = kind == 'photo' or rng.random() < c['homography_prob']
        if projective:
            warp = random_projective(rng, self.size, c['homography_shift']) @ warp
        return PairSample(kind, frame, frame, H_a, warp @ H_a, self.size, projective,
                          self.labels)

    def _drive(self, rng: np.random.Generator) -> PairSample | None:
        c = self.conf
        ia, ib = self.drive_pairs[int(rng.integers(len(self.drive_pairs)))]
        if rng.random() < 0.5:
            ia, ib = ib, ia
        fa, fb = self.frames[ia], self.frames[ib]
        o = self._crop_origin(fa, rng)
        H_a = _translation(-o[0], -o[1])
        w, h = self.size
        probe = PairSample('drive', fa, fb, H_a, np.eye(3), fb.size, False, self.labels)
        gu, gv = np.meshgrid(np.arange(8, w, 16), np.arange(8, h, 16))
        grid = np.stack([gu.ravel(), gv.ravel()], axis=1).astype(np.float64)
        mapped, ok = probe.correspond(grid)
        if ok.mean() < 0.1:
            return None
        centre_b = np.median(mapped[ok], axis=0)
        H_b = _translation(-(centre_b[0] - (w - 1) / 2), -(centre_b[1] - (h - 1) / 2))
        if rng.random() < c['drive_warp_prob']:
            center = np.array([(w - 1) / 2, (h - 1) / 2])
            H_b = random_similarity(rng, center, c['rotation_deg'] / 3, c['translation_px'],
                                    (0.9, 1.1)) @ H_b
        return PairSample('drive', fa, fb, H_a, H_b, self.size, False, self.labels)

    def make_pair(self, rng: np.random.Generator) -> PairSample:
        """A random rendered pair (views not yet rendered)."""
        kind = self.kinds[int(rng.choice(len(self.kinds), p=self.kind_p))]
        if kind == 'drive':
            pair = self._drive(rng)
            if pair is not None:
                return pair
            kind = 'synthetic' if self.sim_frames else 'photo'
        pool = self.sim_frames if kind == 'synthetic' else self.photo_frames
        return self._synthetic(pool[int(rng.integers(len(pool)))], rng, kind)

    # -- targets

    def build(self, pair: PairSample, rng: np.random.Generator,
              augment: bool = True) -> dict[str, np.ndarray]:
        """Render a pair and compute every training target (numpy, one pair).

        Returns a dict: ``image_a``/``image_b`` (h, w, 3) uint8 (augmented), ``kp_a``/``kp_b``
        (h, w) float32 heatmap targets, ``kpv_a``/``kpv_b`` (h, w) bool loss masks,
        ``label_a``/``label_b`` (h, w) uint8 (255 ignore), ``cov_a``/``cov_b`` (h, w) bool
        pixels showing the source image (inside the warp and, for rendered frames, the image
        circle), ``points_a``/``points_b`` (M, 2)
        float32 px, ``corr_valid`` (M,) bool, ``kind`` int (index in :data:`PAIR_KINDS`); with
        ``dense_flow``, ``flow_a`` (h, w, 2) float32 px (each view-a pixel in view b) and
        ``flowv_a`` (h, w) bool (where that correspondence exists).
        """
        c = self.conf
        pair.render()
        w, h = self.size
        kp_a, kp_b = keypoint_targets(pair, c)
        out: dict[str, np.ndarray] = {}
        for name, view, kps, rev in (('a', pair.view_a, kp_a, False),
                                     ('b', pair.view_b, kp_b, True)):
            target = np.zeros((h, w), np.float32)
            target[kps[:, 1], kps[:, 0]] = 1.0
            out[f'kp_{name}'] = target
            # verified keypoints always take part, even where the coarse grid says invalid
            out[f'kpv_{name}'] = pair.valid_grid(4, reverse=rev) | (target > 0)
            out[f'label_{name}'] = view['label'].copy()
            cov = view['coverage'] > 0
            out[f'cov_{name}'] = cov if 'depth' not in view else cov & (view['label'] !=
                                                                         IGNORE_LABEL)
            img = view['rgb']
            out[f'image_{name}'] = photometric_augment(img, rng, c['photometric']) if augment \
                else img.copy()
        # descriptor correspondences: kept keypoints of a + random valid pixels of a
        m = int(c['num_points'])
        n_rand = int(round(m * c['random_point_fraction']))
        pts = kp_a.astype(np.float64)
        if len(pts) > m - n_rand:
            pts = pts[rng.choice(len(pts), m - n_rand, replace=False)]
        rand = np.stack([rng.uniform(0, w - 1, 4 * m), rng.uniform(0, h - 1, 4 * m)], axis=1)
        mapped_r, ok_r = pair.correspond(rand)
        rand = rand[ok_r][: m - len(pts)]
        pts = np.concatenate([pts, rand], axis=0)
        mapped, ok = pair.correspond(pts)
        points_a = np.zeros((m, 2), np.float32)
        points_b = np.zeros((m, 2), np.float32)
        valid = np.zeros(m, bool)
        k = len(pts)
        points_a[:k] = pts
        points_b[:k] = np.where(ok[:, None], mapped, 0.0)
        valid[:k] = ok
        out.update(points_a=points_a, points_b=points_b, corr_valid=valid,
                   kind=np.array(PAIR_KINDS.index(pair.kind)))
        if c['dense_flow']:
            gu, gv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            flow, ok = pair.correspond(np.stack([gu.ravel(), gv.ravel()], axis=1))
            out['flow_a'] = flow.reshape(h, w, 2).astype(np.float32)
            out['flowv_a'] = ok.reshape(h, w)
        return out

    def sample(self, key: int | Sequence[int], augment: bool = True) -> dict[str, np.ndarray]:
        """The training sample of integer ``key`` (deterministic for a given seed and data)."""
        keys = [key] if isinstance(key, int) else list(key)
        rng = np.random.default_rng([self.seed, *keys])
        return self.build(self.make_pair(rng), rng, augment)


def collate(samples: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Stack samples into a pair batch (numpy): views a first, then views b (2B images)."""
    out = {
        'image': np.stack([s['image_a'] for s in samples] + [s['image_b'] for s in samples]),
        'kp_target': np.stack([s['kp_a'] for s in samples] + [s['kp_b'] for s in samples]),
        'kp_valid': np.stack([s['kpv_a'] for s in samples] + [s['kpv_b'] for s in samples]),
        'label': np.stack([s['label_a'] for s in samples] + [s['label_b'] for s in samples]),
        'coverage': np.stack([s['cov_a'] for s in samples] + [s['cov_b'] for s in samples]),
        'points_a': np.stack([s['points_a'] for s in samples]),
        'points_b': np.stack([s['points_b'] for s in samples]),
        'corr_valid': np.stack([s['corr_valid'] for s in samples]),
        'kind': np.stack([s['kind'] for s in samples]),
    }
    if all('flow_a' in s for s in samples):
        out['flow'] = np.stack([s['flow_a'] for s in samples])
        out['flow_valid'] = np.stack([s['flowv_a'] for s in samples])
    return out
