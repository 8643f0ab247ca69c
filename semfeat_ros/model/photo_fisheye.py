"""A real photograph as the project's fisheye camera would see it (numpy + cv2, no torch).

The photo is treated as a pinhole image with a horizontal field of view ``hfov`` (deg) and hung
on a virtual plane in front of the fisheye camera: its centre lies 1 m from the camera along a
viewing direction inside the lens's field of view, its pixels are squares of
``2 tan(hfov / 2) / width`` m, its rows run "upright" (perpendicular to the camera's y axis)
before a roll about the viewing direction, and the plane may be tilted away from facing the
camera. Every fisheye pixel's bearing (:meth:`CameraModel.unproject`) is intersected with that
plane, the intersection is expressed in photo pixels, and ``cv2.remap`` samples the photo there.
Straight lines of the photo therefore bend exactly as the fisheye model bends straight 3-D lines,
and a pixel is in the returned mask exactly when its ray meets the photo's rectangle.

With no tilt, the photo is the image of a pinhole camera sharing the fisheye's centre, so its
content keeps its own perspective: the fisheye shows what it would have seen of the photographed
scene within the photo's field of view. The plane's distance does not change the picture (only
the angle the photo subtends does), so it is fixed at 1 m.

Coverage: a photo subtending 50-100 deg covers a median of 16 % of the 190-deg image circle at
640x512 px (never 40 %); the defaults ``hfov_deg=(110, 150)`` with the photo's centre up to
``max_offaxis_deg=50`` off-axis cover a median of 47 % (16:10 photos) to 51 % (4:3), at least
40 % in 79-89 % of the views (``test/test_photo_fisheye.py`` checks the median).

Build the camera the way the rest of the project does::

    from semfeat_ros.camera import load_camera_yaml
    camera = load_camera_yaml()[0].scaled(640, 512)  # config/camera_front.yaml at 640x512 px
    image, mask = fisheye_view(rgb, camera, np.random.default_rng(seed))

Conventions follow :mod:`semfeat_ros.camera.models`: optical frame z forward, x right, y down;
pixels ``(u, v)`` in px with the origin at the centre of the top-left pixel.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from semfeat_ros.camera.models import CameraModel

#: Distance (m) of the photo's centre from the camera centre; the picture does not depend on it.
PLANE_DISTANCE_M = 1.0

_BEARING_CACHE: OrderedDict[tuple[CameraModel, str], np.ndarray] = OrderedDict()
_BEARING_CACHE_SIZE = 8


class PhotoFisheyeError(ValueError):
    """Invalid input of the photo-to-fisheye renderer (image layout, ranges, placement)."""


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _rotate(v: np.ndarray, axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues rotation of vector ``v`` about unit ``axis`` by ``angle_rad`` (rad)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return v * c + np.cross(axis, v) * s + axis * float(axis @ v) * (1.0 - c)


@dataclass(frozen=True)
class PhotoPlacement:
    """Where a ``width x height`` px photo hangs in the fisheye camera's optical frame.

    Attributes:
        width, height: photo size (px).
        centre: (3,) position (m) of the photo's centre pixel ``((w-1)/2, (h-1)/2)``.
        axis_u, axis_v: (3,) orthonormal directions of the photo's +u (columns) and +v (rows)
            on its plane.
        pixel_size: edge length (m) of one photo pixel on the plane.
        hfov_deg: horizontal field of view (deg) the photo would subtend untilted.
        roll_deg, tilt_deg: roll about the viewing direction and tilt of the plane (deg).
    """

    width: int
    height: int
    centre: tuple[float, float, float]
    axis_u: tuple[float, float, float]
    axis_v: tuple[float, float, float]
    pixel_size: float
    hfov_deg: float
    roll_deg: float = 0.0
    tilt_deg: float = 0.0

    @classmethod
    def facing(cls, width: int, height: int, direction: np.ndarray, hfov_deg: float,
               roll_deg: float = 0.0, tilt_deg: float = 0.0,
               tilt_axis_deg: float = 0.0) -> PhotoPlacement:
        """The photo centred on ``direction`` (unit or not), upright, then rolled and tilted.

        Args:
            width, height: photo size (px).
            direction: (3,) viewing direction of the photo's centre in the optical frame.
            hfov_deg: horizontal field of view (deg) of the photo as a pinhole image, in (0, 180).
            roll_deg: rotation (deg) of the photo about ``direction``.
            tilt_deg: rotation (deg) of the plane about an in-plane axis through its centre,
                in [0, 90).
            tilt_axis_deg: direction (deg) of that axis in the photo, from +u towards +v.
        """
        if width < 2 or height < 2:
            raise PhotoFisheyeError(f'photo must be at least 2x2 px, got {width}x{height}')
        if not 0.0 < hfov_deg < 180.0:
            raise PhotoFisheyeError(f'hfov_deg must be in (0, 180), got {hfov_deg}')
        if not 0.0 <= tilt_deg < 90.0:
            raise PhotoFisheyeError(f'tilt_deg must be in [0, 90), got {tilt_deg}')
        d = np.asarray(direction, dtype=np.float64).reshape(3)
        if not np.isfinite(d).all() or np.linalg.norm(d) < 1e-12:
            raise PhotoFisheyeError(f'direction must be a finite non-zero 3-vector, got {d}')
        d = _unit(d)
        down = np.array([0.0, 1.0, 0.0])
        if np.linalg.norm(np.cross(down, d)) < 1e-6:  # looking straight up or down
            down = np.array([0.0, 0.0, -1.0]) if d[1] > 0 else np.array([0.0, 0.0, 1.0])
        au = _unit(np.cross(down, d))
        av = np.cross(d, au)
        roll = np.radians(roll_deg)
        au, av = _rotate(au, d, roll), _rotate(av, d, roll)
        if tilt_deg > 0.0:
            phi = np.radians(tilt_axis_deg)
            axis = _unit(np.cos(phi) * au + np.sin(phi) * av)
            tilt = np.radians(tilt_deg)
            au, av = _rotate(au, axis, tilt), _rotate(av, axis, tilt)
        size = 2.0 * PLANE_DISTANCE_M * np.tan(np.radians(hfov_deg) / 2.0) / width
        return cls(width=int(width), height=int(height),
                   centre=tuple(float(x) for x in d * PLANE_DISTANCE_M),
                   axis_u=tuple(float(x) for x in au), axis_v=tuple(float(x) for x in av),
                   pixel_size=float(size), hfov_deg=float(hfov_deg), roll_deg=float(roll_deg),
                   tilt_deg=float(tilt_deg))

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal of the photo's plane, pointing away from the camera."""
        return np.cross(np.asarray(self.axis_u), np.asarray(self.axis_v))

    @property
    def principal(self) -> tuple[float, float]:
        """Photo pixel ``(u, v)`` (px) at the plane's centre: the middle of the image."""
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def photo_to_points(self, uv: np.ndarray) -> np.ndarray:
        """3-D points (N, 3) in m of photo pixels ``uv`` (N, 2) px on the plane."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        cu, cv = self.principal
        return (np.asarray(self.centre)[None]
                + ((uv[:, :1] - cu) * np.asarray(self.axis_u)[None]
                   + (uv[:, 1:] - cv) * np.asarray(self.axis_v)[None]) * self.pixel_size)

    def bearings_to_photo(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Photo pixels (N, 2) px where rays (N, 3) from the camera centre meet the plane.

        Returns ``(uv, hit)``: ``hit`` is False for NaN rays and rays that do not meet the
        plane in front of the camera (their ``uv`` is NaN). Computed in the dtype of ``rays``
        (float32 rays: about 1e-4 px rounding on a 1280 px photo).
        """
        rays = np.asarray(rays).reshape(-1, 3)
        if rays.dtype not in (np.float32, np.float64):
            rays = rays.astype(np.float64)
        au, av, n = np.asarray(self.axis_u), np.asarray(self.axis_v), self.normal
        c = np.asarray(self.centre)
        cn, cau, cav = float(c @ n), float(c @ au), float(c @ av)
        # ray b meets the plane at t b with t = (c.n) / (b.n); its photo offset from the centre
        # is (t b - c) . axis / pixel_size (per-column products: a BLAS call with an inner
        # dimension of 3 is slower)
        x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
        dt = rays.dtype.type
        denom = x * dt(n[0]) + y * dt(n[1]) + z * dt(n[2])
        with np.errstate(invalid='ignore', divide='ignore'):
            hit = denom > 1e-9
            t = dt(cn) / denom
        cu, cv = self.principal
        inv_s = dt(1.0 / self.pixel_size)
        uv = np.empty((rays.shape[0], 2), dtype=rays.dtype)
        uv[:, 0] = (t * (x * dt(au[0]) + y * dt(au[1]) + z * dt(au[2])) - dt(cau)) * inv_s + dt(cu)
        uv[:, 1] = (t * (x * dt(av[0]) + y * dt(av[1]) + z * dt(av[2])) - dt(cav)) * inv_s + dt(cv)
        uv[~hit] = np.nan
        return uv, hit

    def inside(self, uv: np.ndarray) -> np.ndarray:
        """(N,) bool: photo pixel lies within ``[0, w-1] x [0, h-1]`` (NaN: False)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        with np.errstate(invalid='ignore'):
            return ((uv[:, 0] >= 0.0) & (uv[:, 0] <= self.width - 1)
                    & (uv[:, 1] >= 0.0) & (uv[:, 1] <= self.height - 1))

    def photo_to_fisheye(self, camera: CameraModel, uv: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Fisheye pixels (N, 2) px of photo pixels ``uv`` (N, 2) px, and their validity."""
        return camera.project(self.photo_to_points(uv))


def pixel_bearings(camera: CameraModel, dtype: type = np.float64) -> np.ndarray:
    """(H, W, 3) unit bearings of every pixel of ``camera`` (NaN outside the image circle).

    Read-only and cached for the last few cameras and dtypes (unprojecting a 640x512 grid takes
    ~0.1 s).
    """
    key = (camera, np.dtype(dtype).str)
    rays = _BEARING_CACHE.get(key)
    if rays is None:
        if np.dtype(dtype) == np.float64:
            u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64),
                               np.arange(camera.height, dtype=np.float64))
            rays = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1), check=False)
            rays = rays.reshape(camera.height, camera.width, 3)
        else:
            rays = pixel_bearings(camera).astype(dtype)
        rays.setflags(write=False)
        _BEARING_CACHE[key] = rays
        while len(_BEARING_CACHE) > _BEARING_CACHE_SIZE:
            _BEARING_CACHE.popitem(last=False)
    else:
        _BEARING_CACHE.move_to_end(key)
    return rays


def sample_placement(photo_size: tuple[int, int], camera: CameraModel,
                     rng: np.random.Generator, *,
                     hfov_deg: tuple[float, float] = (110.0, 150.0),
                     max_offaxis_deg: float = 50.0, max_roll_deg: float = 30.0,
                     max_tilt_deg: float = 0.0) -> PhotoPlacement:
    """A random placement of a ``(width, height)`` px photo in front of ``camera``.

    Args:
        photo_size: ``(width, height)`` of the photo (px).
        camera: the fisheye (or pinhole) model the photo is seen with, at its image size.
        rng: source of randomness; the same generator state gives the same placement.
        hfov_deg: range (deg) of the photo's horizontal field of view, uniform.
        max_offaxis_deg: largest angle (deg) between the optical axis and the photo's centre.
            The centre's fisheye pixel is uniform over the part of the image within that angle,
            so the photo can appear anywhere in the image circle.
        max_roll_deg: roll (deg) about the viewing direction, uniform in +-max_roll_deg.
        max_tilt_deg: tilt (deg) of the plane away from facing the camera, uniform in
            [0, max_tilt_deg] about a random in-plane axis; 0 keeps the pure pinhole view.
    """
    lo, hi = (float(x) for x in hfov_deg)
    if not 0.0 < lo <= hi < 180.0:
        raise PhotoFisheyeError(f'hfov_deg range must satisfy 0 < lo <= hi < 180, got {hfov_deg}')
    if not 0.0 <= max_offaxis_deg <= 180.0:
        raise PhotoFisheyeError(f'max_offaxis_deg must be in [0, 180], got {max_offaxis_deg}')
    if not 0.0 <= max_tilt_deg < 90.0:
        raise PhotoFisheyeError(f'max_tilt_deg must be in [0, 90), got {max_tilt_deg}')
    width, height = (int(x) for x in photo_size)
    hfov = float(rng.uniform(lo, hi))
    cos_max = np.cos(np.radians(max_offaxis_deg))
    direction = None
    for _ in range(64):  # rejection sampling in batches of 64 pixels
        px = np.stack([rng.uniform(0.0, camera.width - 1.0, 64),
                       rng.uniform(0.0, camera.height - 1.0, 64)], axis=1)
        rays = camera.unproject(px, check=False)
        ok = np.flatnonzero(np.isfinite(rays[:, 2]) & (rays[:, 2] >= cos_max - 1e-12))
        if ok.size:
            direction = rays[ok[0]]
            break
    if direction is None:
        raise PhotoFisheyeError(f'no pixel of the {camera.width}x{camera.height} camera lies '
                                f'within {max_offaxis_deg} deg of its optical axis')
    roll = float(rng.uniform(-max_roll_deg, max_roll_deg))
    tilt = float(rng.uniform(0.0, max_tilt_deg)) if max_tilt_deg > 0.0 else 0.0
    tilt_axis = float(rng.uniform(0.0, 360.0))
    return PhotoPlacement.facing(width, height, direction, hfov, roll_deg=roll, tilt_deg=tilt,
                                 tilt_axis_deg=tilt_axis)


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    arr = np.asarray(rgb)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.dtype != np.uint8:
        raise PhotoFisheyeError(f'photo must be (H, W, 3) uint8, got {arr.shape} {arr.dtype}')
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise PhotoFisheyeError(f'photo must be at least 2x2 px, got {arr.shape[1]}x'
                                f'{arr.shape[0]}')
    return arr


def render_placement(rgb: np.ndarray, camera: CameraModel, placement: PhotoPlacement, *,
                     background: np.ndarray | None = None, antialias: bool = True
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Render ``rgb`` hung at ``placement`` as ``camera`` sees it.

    Args:
        rgb: (h, w, 3) uint8 photo; its size must match ``placement``.
        camera: camera model at the output size (e.g. ``load_camera_yaml()[0].scaled(640, 512)``).
        placement: where the photo hangs (:func:`sample_placement`, :meth:`PhotoPlacement.facing`).
        background: optional (H, W, 3) uint8 image shown where the photo is not; default black.
        antialias: when the fisheye samples the photo more coarsely than 1.25 photo px per
            fisheye px (median over the covered pixels), sample an area-downscaled copy instead.

    Returns:
        ``(image, mask)``: (H, W, 3) uint8 and (H, W) bool, True exactly where the pixel's ray
        meets the photo's rectangle ``[0, w-1] x [0, h-1]`` inside the image circle.
    """
    photo = _check_rgb(rgb)
    h, w = photo.shape[:2]
    if (w, h) != (placement.width, placement.height):
        raise PhotoFisheyeError(f'photo is {w}x{h} px but the placement is for '
                                f'{placement.width}x{placement.height} px')
    H, W = camera.height, camera.width
    if background is not None:
        background = np.asarray(background)
        if background.shape != (H, W, 3) or background.dtype != np.uint8:
            raise PhotoFisheyeError(f'background must be ({H}, {W}, 3) uint8, got '
                                    f'{background.shape} {background.dtype}')
    uv, hit = placement.bearings_to_photo(pixel_bearings(camera, np.float32).reshape(-1, 3))
    mask = (hit & placement.inside(uv)).reshape(H, W)
    map_u = np.where(mask, uv[:, 0].reshape(H, W), np.float32(0.0))
    map_v = np.where(mask, uv[:, 1].reshape(H, W), np.float32(0.0))
    src = photo
    if antialias:
        # photo px per fisheye px: sqrt |det J| of the map, on a 4-px grid of covered pixels
        # whose right and lower neighbours on that grid are covered too
        su, sv, sm = map_u[::4, ::4], map_v[::4, ::4], mask[::4, ::4]
        ok = sm[:-1, :-1] & sm[1:, :-1] & sm[:-1, 1:]
        if ok.any():
            du_x, dv_x = su[:-1, 1:] - su[:-1, :-1], sv[:-1, 1:] - sv[:-1, :-1]
            du_y, dv_y = su[1:, :-1] - su[:-1, :-1], sv[1:, :-1] - sv[:-1, :-1]
            step = float(np.median(np.sqrt(np.abs(du_x * dv_y - du_y * dv_x))[ok])) / 4.0
            if step > 1.25:
                sw, sh = max(2, round(w / step)), max(2, round(h / step))
                src = cv2.resize(photo, (sw, sh), interpolation=cv2.INTER_AREA)
                map_u = (map_u + 0.5) * np.float32(sw / w) - 0.5
                map_v = (map_v + 0.5) * np.float32(sh / h) - 0.5
    out = cv2.remap(src, map_u.astype(np.float32, copy=False),
                    map_v.astype(np.float32, copy=False), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    if background is None:
        out[~mask] = 0
    else:
        out[~mask] = background[~mask]
    return out, mask


def fisheye_view(rgb: np.ndarray, camera: CameraModel, rng: np.random.Generator, *,
                 hfov_deg: tuple[float, float] = (110.0, 150.0), max_offaxis_deg: float = 50.0,
                 max_roll_deg: float = 30.0, max_tilt_deg: float = 0.0,
                 background: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A real photograph as seen by the fisheye ``camera`` from a random placement.

    Args:
        rgb: (h, w, 3) uint8 photo.
        camera: camera model at the output size, e.g.
            ``load_camera_yaml()[0].scaled(640, 512)`` (``config/camera_front.yaml``).
        rng: random generator; the same seed gives the same view.
        hfov_deg, max_offaxis_deg, max_roll_deg, max_tilt_deg: see :func:`sample_placement`
            (deg).
        background: optional (H, W, 3) uint8 image where the photo is not; default black.

    Returns:
        ``(image, mask)``: (H, W, 3) uint8 fisheye image at the camera's size and (H, W) bool
        mask of the pixels covered by the photo.
    """
    photo = _check_rgb(rgb)
    placement = sample_placement((photo.shape[1], photo.shape[0]), camera, rng,
                                 hfov_deg=hfov_deg, max_offaxis_deg=max_offaxis_deg,
                                 max_roll_deg=max_roll_deg, max_tilt_deg=max_tilt_deg)
    return render_placement(photo, camera, placement, background=background)


def circle_coverage(mask: np.ndarray, camera: CameraModel) -> float:
    """Fraction of ``camera``'s valid pixels (the image circle within the image) in ``mask``."""
    valid = np.isfinite(pixel_bearings(camera, np.float32)[..., 2])
    return float((mask & valid).sum() / max(1, int(valid.sum())))
