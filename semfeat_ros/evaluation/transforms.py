"""The paper's synthetic transforms: random rotation, translation, scale and perspective.

A sampled transform is one 3x3 homography ``H`` (px -> px, OpenCV pixel-centre convention) built
about the image centre ``c``::

    H = T(c + t) . [s R(angle)] . P(p) . T(-c)

``P(p) = [[1, 0, 0], [0, 1, 0], [p1, p2, 1]]`` is the perspective part with ``p1 = a / (W / 2)``,
``p2 = b / (H / 2)`` (px^-1), so the projective denominator at the image corners lies in
``1 +- (|a| + |b|)``. Because ``P`` is the identity to first order at the centre, the centre maps
exactly to ``c + t`` and the Jacobian there is exactly ``s R(angle)``: the sampled parameters are
the rotation (deg), scale and translation (px) that the paper quotes.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from semfeat_ros.evaluation.errors import ConfigError


@dataclass(frozen=True)
class TransformConf:
    """Ranges of the random transform (paper, Results: rotation +-30 deg, translation up to
    +-15 px, scale 0.8-1.2, plus a homography for perspective)."""

    max_rotation_deg: float = 30.0
    max_translation_px: float = 15.0
    min_scale: float = 0.8
    max_scale: float = 1.2
    max_perspective: float = 0.1
    """Bound of ``a`` and ``b`` (unitless): the denominator at the corners is within +-2x this."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_rotation_deg <= 180.0:
            raise ConfigError(f'max_rotation_deg must be in [0, 180], got {self.max_rotation_deg}')
        if self.max_translation_px < 0.0:
            raise ConfigError(
                f'max_translation_px must be >= 0, got {self.max_translation_px}')
        if not 0.0 < self.min_scale <= self.max_scale:
            raise ConfigError(
                f'scale range must satisfy 0 < min <= max, got [{self.min_scale}, '
                f'{self.max_scale}]')
        if not 0.0 <= self.max_perspective < 0.5:
            raise ConfigError(f'max_perspective must be in [0, 0.5), got {self.max_perspective}')


@dataclass(frozen=True)
class SampledTransform:
    """One draw: the parameters and the resulting homography (image A px -> image B px)."""

    angle_deg: float
    scale: float
    tx: float
    ty: float
    perspective: tuple[float, float]
    H: np.ndarray  # (3, 3) float64

    def as_dict(self) -> dict[str, object]:
        return {'angle_deg': self.angle_deg, 'scale': self.scale, 'tx_px': self.tx,
                'ty_px': self.ty, 'perspective': list(self.perspective),
                'H': self.H.tolist()}


def compose_homography(width: int, height: int, angle_deg: float, scale: float, tx: float,
                       ty: float, perspective: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The homography of the module docstring for a ``width x height`` px image."""
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    a, b = perspective
    to_centre = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    persp = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                      [a / (width / 2.0), b / (height / 2.0), 1.0]])
    th = np.radians(angle_deg)
    rot = np.array([[scale * np.cos(th), -scale * np.sin(th), 0.0],
                    [scale * np.sin(th), scale * np.cos(th), 0.0], [0.0, 0.0, 1.0]])
    back = np.array([[1.0, 0.0, cx + tx], [0.0, 1.0, cy + ty], [0.0, 0.0, 1.0]])
    H = back @ rot @ persp @ to_centre
    return H / H[2, 2]


def sample_transform(rng: np.random.Generator, width: int, height: int,
                     conf: TransformConf | None = None) -> SampledTransform:
    """Draw one transform uniformly within ``conf``'s ranges (translation: uniform in the square
    ``[-max, max]^2`` px; rotation uniform in deg; scale uniform)."""
    conf = conf or TransformConf()
    angle = float(rng.uniform(-conf.max_rotation_deg, conf.max_rotation_deg))
    scale = float(rng.uniform(conf.min_scale, conf.max_scale))
    tx, ty = (float(x) for x in rng.uniform(-conf.max_translation_px,
                                             conf.max_translation_px, size=2))
    a, b = (float(x) for x in rng.uniform(-conf.max_perspective, conf.max_perspective, size=2))
    H = compose_homography(width, height, angle, scale, tx, ty, (a, b))
    return SampledTransform(angle, scale, tx, ty, (a, b), H)


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 2) px points through a 3x3 homography; points at infinity become NaN."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    hom = np.concatenate([pts, np.ones((len(pts), 1))], axis=1) @ np.asarray(H, np.float64).T
    w = hom[:, 2:3]
    with np.errstate(divide='ignore', invalid='ignore'):
        out = hom[:, :2] / w
    out[np.abs(w[:, 0]) < 1e-12] = np.nan
    return out


def warp_image(image: np.ndarray, H: np.ndarray, size: tuple[int, int] | None = None,
               *, nearest: bool = False, border_value: int = 0) -> np.ndarray:
    """Warp ``image`` by ``H`` into a ``size = (width, height)`` px canvas (default: same size).

    Pixels without a source are ``border_value``. ``nearest`` for label maps and masks.
    """
    h, w = image.shape[:2]
    width, height = size or (w, h)
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.warpPerspective(image, np.asarray(H, np.float64), (int(width), int(height)),
                               flags=flags, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=border_value)


def erode_mask(mask: np.ndarray, margin_px: int) -> np.ndarray:
    """Shrink a bool mask by ``margin_px`` px (the image frame counts as invalid outside)."""
    if margin_px <= 0:
        return mask.astype(bool)
    m = np.pad(mask.astype(np.uint8), 1, constant_values=0)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
    return cv2.erode(m, k, borderType=cv2.BORDER_CONSTANT, borderValue=0)[1:-1, 1:-1] > 0
