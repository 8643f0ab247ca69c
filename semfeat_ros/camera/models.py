"""Camera models: Kannala-Brandt / OpenCV-fisheye (equidistant) and pinhole with radtan distortion.

Conventions
-----------
* Camera optical frame: z forward, x right, y down (REP-103 ``*_optical``).
* Pixels are ``(u, v)`` in px, origin at the centre of the top-left pixel (OpenCV convention).
* Bearings are unit vectors in the optical frame. The fisheye model is valid beyond 180 degrees:
  bearings with ``z < 0`` are legal as long as the angle to the optical axis is within
  ``fov / 2``.

All functions are vectorised over ``(N, 2)`` / ``(N, 3)`` float arrays and never import rclpy.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np

from semfeat_ros.camera.errors import CameraModelError, OutsideImageCircleError

_NEWTON_ITERS = 20


def _as_points(points: np.ndarray, dim: int, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f'{name}: expected shape (N, {dim}), got {arr.shape}')
    return arr


def _finite_rows(arr: np.ndarray, fill: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, finite)``: ``arr`` with its non-finite rows replaced by ``fill`` (a harmless
    value the caller computes with and then marks invalid) and the (N,) mask of finite rows."""
    finite = np.isfinite(arr).all(axis=1)
    if finite.all():
        return arr, finite
    return np.where(finite[:, None], arr, np.asarray(fill, dtype=np.float64)), finite


# Huge finite inputs overflow to inf / NaN inside the models; those rows come out invalid (NaN
# bearings, valid=False) and no RuntimeWarning reaches the caller's log.
_QUIET = dict(over='ignore', invalid='ignore', divide='ignore', under='ignore')


@dataclass(frozen=True)
class CameraModel(ABC):
    """Common interface of all camera models (image size in px, intrinsics in px)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    distortion_model: ClassVar[str] = ''

    def __post_init__(self) -> None:
        for name in ('fx', 'fy', 'cx', 'cy'):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, 'width', int(self.width))
        object.__setattr__(self, 'height', int(self.height))
        if self.width <= 0 or self.height <= 0:
            raise CameraModelError(f'image size must be positive, got {self.width}x{self.height}')
        if not (np.isfinite([self.fx, self.fy, self.cx, self.cy]).all()):
            raise CameraModelError('intrinsics contain NaN or inf')
        if self.fx <= 0 or self.fy <= 0:
            raise CameraModelError(
                f'focal lengths must be positive, got fx={self.fx} fy={self.fy}')
        if not (0 <= self.cx < self.width and 0 <= self.cy < self.height):
            raise CameraModelError(
                f'principal point ({self.cx}, {self.cy}) lies outside the '
                f'{self.width}x{self.height} image')

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name of the intrinsic matrix
        """3x3 intrinsic matrix (px)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    @abstractmethod
    def D(self) -> np.ndarray:  # noqa: N802 - CameraInfo's name
        """Distortion coefficients in CameraInfo order."""

    @abstractmethod
    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project points (N, 3) in the optical frame (m) to pixels (N, 2) px.

        Returns ``(pixels, valid)``; ``valid`` is False for points outside the field of view
        (their pixel is still finite but meaningless) or at the camera centre.
        """

    @abstractmethod
    def unproject(self, pixels: np.ndarray, *, check: bool = True) -> np.ndarray:
        """Unit bearings (N, 3) in the optical frame for pixels (N, 2) px.

        With ``check`` a pixel outside the valid image region raises
        :class:`OutsideImageCircleError`; without it, such rows are NaN.
        """

    def scaled(self, width: int, height: int) -> CameraModel:
        """The same lens on an image resized to ``width x height`` px (pixel-centre aware)."""
        sx = width / self.width
        sy = height / self.height
        return replace(
            self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    def valid_mask(self) -> np.ndarray:
        """(height, width) bool mask of pixels that have a valid bearing (the image circle)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64),
                           np.arange(self.height, dtype=np.float64))
        px = np.stack([u.ravel(), v.ravel()], axis=1)
        rays = self.unproject(px, check=False)
        return np.isfinite(rays[:, 0]).reshape(self.height, self.width)

    def in_image(self, pixels: np.ndarray, border: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel lies inside the image rectangle shrunk by ``border`` px."""
        px = _as_points(pixels, 2, 'pixels')
        return ((px[:, 0] >= border) & (px[:, 0] <= self.width - 1 - border)
                & (px[:, 1] >= border) & (px[:, 1] <= self.height - 1 - border))


@dataclass(frozen=True)
class FisheyeCamera(CameraModel):
    """Kannala-Brandt / OpenCV ``cv2.fisheye`` equidistant model.

    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` with ``theta`` the
    angle (rad) between the ray and the optical axis; ``r = theta_d`` in normalised coordinates.
    ``fov_deg`` is the full cone angle of the lens (deg); rays beyond ``fov_deg / 2`` are invalid.
    """

    k: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    fov_deg: float = 190.0
    _theta_max: float = field(init=False, repr=False, compare=False, default=0.0)

    distortion_model: ClassVar[str] = 'equidistant'

    def __post_init__(self) -> None:
        super().__post_init__()
        k = tuple(float(x) for x in self.k)
        if len(k) != 4 or not np.isfinite(k).all():
            raise CameraModelError(f'equidistant model needs 4 finite coefficients, got {self.k}')
        object.__setattr__(self, 'k', k)
        if not 0.0 < self.fov_deg < 360.0:
            raise CameraModelError(f'fov_deg must be in (0, 360), got {self.fov_deg}')
        theta_max = np.radians(self.fov_deg) / 2.0
        # theta_d must be strictly increasing up to theta_max, or unprojection is ambiguous.
        t = np.linspace(0.0, theta_max, 512)
        if not np.all(np.diff(self._theta_d(t)) > 0):
            raise CameraModelError(
                f'distortion {k} is not monotonic up to {self.fov_deg / 2:.1f} deg off-axis')
        object.__setattr__(self, '_theta_max', float(theta_max))

    @property
    def D(self) -> np.ndarray:  # noqa: N802
        return np.array(self.k, dtype=np.float64)

    @property
    def theta_max(self) -> float:
        """Largest valid angle from the optical axis (rad)."""
        return self._theta_max

    def _theta_d(self, theta: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = self.k
        t2 = theta * theta
        return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def _dtheta_d(self, theta: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = self.k
        t2 = theta * theta
        return 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, finite = _finite_rows(_as_points(points, 3, 'points'), (0.0, 0.0, 1.0))
        with np.errstate(**_QUIET):
            rxy = np.hypot(p[:, 0], p[:, 1])
            theta = np.arctan2(rxy, p[:, 2])
            theta_d = self._theta_d(theta)
            scale = np.where(rxy > 1e-12, theta_d / np.maximum(rxy, 1e-300), 0.0)
            u = self.fx * p[:, 0] * scale + self.cx
            v = self.fy * p[:, 1] * scale + self.cy
            norm = np.linalg.norm(p, axis=1)
        uv = np.stack([u, v], axis=1)
        valid = ((theta <= self._theta_max + 1e-12) & (norm > 1e-12) & np.isfinite(norm)
                 & finite & np.isfinite(uv).all(axis=1))
        return uv, valid

    def unproject(self, pixels: np.ndarray, *, check: bool = True) -> np.ndarray:
        raw = _as_points(pixels, 2, 'pixels')
        px, finite = _finite_rows(raw, (self.cx, self.cy))
        with np.errstate(**_QUIET):
            mx = (px[:, 0] - self.cx) / self.fx
            my = (px[:, 1] - self.cy) / self.fy
            theta_d = np.hypot(mx, my)
        theta_d_max = float(self._theta_d(np.array(self._theta_max)))
        outside = ~(theta_d <= theta_d_max * (1.0 + 1e-9)) | ~finite
        if check and outside.any():
            bad = raw[np.argmax(outside)]
            raise OutsideImageCircleError(
                f'{int(outside.sum())} pixel(s) outside the image circle of the '
                f'{self.fov_deg:.0f} deg lens, e.g. ({bad[0]:.1f}, {bad[1]:.1f}) px; '
                f'radius there {theta_d[np.argmax(outside)] * self.fx:.1f} px > '
                f'{theta_d_max * self.fx:.1f} px')
        td = np.where(outside, 0.0, np.minimum(theta_d, theta_d_max))
        theta = td.copy()
        for _ in range(_NEWTON_ITERS):
            step = (self._theta_d(theta) - td) / self._dtheta_d(theta)
            theta -= step
            if np.max(np.abs(step), initial=0.0) < 1e-14:
                break
        np.clip(theta, 0.0, self._theta_max, out=theta)
        with np.errstate(**_QUIET):
            s = np.where(theta_d > 1e-15, np.sin(theta) / np.maximum(theta_d, 1e-300), 1.0)
            rays = np.stack([mx * s, my * s, np.cos(theta)], axis=1)
        rays[outside] = np.nan
        return rays


@dataclass(frozen=True)
class PinholeCamera(CameraModel):
    """Pinhole with OpenCV radial-tangential distortion (``plumb_bob`` or ``rational_polynomial``).

    ``d`` is CameraInfo's D: ``k1 k2 p1 p2 k3`` (plumb_bob, 5 values; fewer are zero-padded) or
    ``k1 k2 p1 p2 k3 k4 k5 k6`` (rational_polynomial, 8 values). Valid only for ``z > 0``.
    """

    d: tuple[float, ...] = ()
    model: str = 'plumb_bob'

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.model not in ('plumb_bob', 'rational_polynomial'):
            raise CameraModelError(f'unknown pinhole distortion model {self.model!r}')
        n = 5 if self.model == 'plumb_bob' else 8
        d = tuple(float(x) for x in self.d)
        if len(d) > n and any(x != 0.0 for x in d[n:]):
            raise CameraModelError(f'{self.model} takes at most {n} coefficients, got {len(d)}')
        d = (d + (0.0,) * n)[:n]
        if not np.isfinite(d).all():
            raise CameraModelError('distortion coefficients contain NaN or inf')
        object.__setattr__(self, 'd', d)

    @property
    def distortion_model(self) -> str:  # type: ignore[override]
        return self.model

    @property
    def D(self) -> np.ndarray:  # noqa: N802
        return np.array(self.d, dtype=np.float64)

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self.d
        k1, k2, p1, p2, k3 = d[:5]
        k4, k5, k6 = d[5:8] if len(d) == 8 else (0.0, 0.0, 0.0)
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, finite = _finite_rows(_as_points(points, 3, 'points'), (0.0, 0.0, 1.0))
        z = p[:, 2]
        valid = (z > 1e-9) & finite
        zs = np.where(valid, z, 1.0)
        with np.errstate(**_QUIET):
            xd, yd = self._distort(p[:, 0] / zs, p[:, 1] / zs)
            px = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        return px, valid & np.isfinite(px).all(axis=1)

    def unproject(self, pixels: np.ndarray, *, check: bool = True) -> np.ndarray:
        raw = _as_points(pixels, 2, 'pixels')
        px, finite = _finite_rows(raw, (self.cx, self.cy))
        with np.errstate(**_QUIET):
            x, y, xd, yd = self._undistort(px)
        with np.errstate(**_QUIET):
            fx_, fy_ = self._distort(x, y)
            bad = ~((np.hypot(fx_ - xd, fy_ - yd) < 1e-6) & np.isfinite(x) & np.isfinite(y)
                    & finite)
        if check and bad.any():
            b = raw[np.argmax(bad)]
            raise OutsideImageCircleError(
                f'{int(bad.sum())} pixel(s) cannot be undistorted (outside the valid region '
                f'of the {self.model} model), e.g. ({b[0]:.1f}, {b[1]:.1f}) px')
        x, y = np.where(bad, 0.0, x), np.where(bad, 0.0, y)
        rays = np.stack([x, y, np.ones_like(x)], axis=1)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        rays[bad] = np.nan
        return rays

    def _undistort(self, px: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(x, y, xd, yd)``: undistorted and distorted normalised coordinates of pixels."""
        xd = (px[:, 0] - self.cx) / self.fx
        yd = (px[:, 1] - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        # Newton on the 2-D distortion map with a numerical Jacobian: robust for strong k.
        h = 1e-7
        for _ in range(_NEWTON_ITERS):
            fx_, fy_ = self._distort(x, y)
            rx, ry = fx_ - xd, fy_ - yd
            ax, ay = self._distort(x + h, y)
            bx, by = self._distort(x, y + h)
            j11, j21 = (ax - fx_) / h, (ay - fy_) / h
            j12, j22 = (bx - fx_) / h, (by - fy_) / h
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (j22 * rx - j12 * ry) / det
            dy = (-j21 * rx + j11 * ry) / det
            x -= dx
            y -= dy
            if max(np.max(np.abs(dx), initial=0.0), np.max(np.abs(dy), initial=0.0)) < 1e-13:
                break
        return x, y, xd, yd
