"""Ground-truth correspondences between rendered frames from depth and camera poses.

Conventions (shared by the network, the matcher tests and the evaluation harness):

* ``depth`` images hold the **range along the pixel's ray** (m), not the z coordinate; sky and
  other escaping rays are ``+inf``, pixels outside the lens's image circle are ``NaN``.
* ``T_map_cam`` (4x4) maps points from the camera optical frame (z forward, x right, y down)
  into ``map``; see :mod:`semfeat_ros.sim.geometry` for ``T_map_cam = T_map_base @ T_base_cam``.
* Pixels ``(u, v)`` in px with the origin at the centre of the top-left pixel (OpenCV); the
  depth of a sub-pixel position is interpolated bilinearly on smooth surfaces and taken from the
  nearest pixel centre at depth edges (:func:`interpolate_depth`).

A pixel of frame ``a`` is warped into frame ``b`` by back-projecting it with its depth, moving
the 3-D point into ``b`` and projecting it. With ``depth_b`` the warp is occlusion-checked: the
predicted range must agree with ``depth_b`` at the landing position within
``occlusion_tol * range`` (interpolated on smooth surfaces, else the best of the 2x2
neighbourhood). Surfaces seen at grazing angles, where one pixel spans more than the tolerance,
may be rejected: the check is conservative. Dynamic objects move between frames: pass
``mask_a`` (e.g. ``~labels.dynamic[label_a]``) to keep them out.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.sim.errors import ShapeError
from semfeat_ros.sim.geometry import check_transform, invert_transform

DEFAULT_OCCLUSION_TOL = 0.02
"""Relative range tolerance of the occlusion check (fraction of the range)."""

SMOOTH_DEPTH_TOL = 0.25
"""Relative range spread below which four neighbouring pixels count as one surface."""

_ABS_TOL = 1e-3  # m, floor of the occlusion tolerance for very close points


@lru_cache(maxsize=16)
def _bearings_cached(camera: CameraModel) -> np.ndarray:
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64),
                       np.arange(camera.height, dtype=np.float64))
    rays = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1), check=False)
    rays = rays.reshape(camera.height, camera.width, 3)
    rays.setflags(write=False)
    return rays


def pixel_bearings(camera: CameraModel) -> np.ndarray:
    """Unit bearings (H, W, 3) of all pixel centres in the optical frame (NaN outside the circle).

    The array is cached per camera and read-only.
    """
    return _bearings_cached(camera)


def _check_depth(depth: np.ndarray, camera: CameraModel, name: str) -> np.ndarray:
    arr = np.asarray(depth)
    if arr.shape != (camera.height, camera.width):
        raise ShapeError(
            f'{name}: expected shape ({camera.height}, {camera.width}) of the camera, '
            f'got {arr.shape}')
    return arr


def _check_uv(uv: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(uv, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ShapeError(f'{name}: expected shape (N, 2), got {arr.shape}')
    return arr


def relative_pose(T_map_cam_a: np.ndarray, T_map_cam_b: np.ndarray) -> np.ndarray:
    """``T_b_a`` (4x4): maps points from camera ``a``'s optical frame into camera ``b``'s."""
    return invert_transform(T_map_cam_b) @ check_transform(T_map_cam_a, 'T_map_cam_a')


def sample_depth(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth (m) of the nearest pixel centre of each ``uv`` (N, 2); NaN outside the image."""
    h, w = depth.shape
    iu = np.rint(uv[:, 0])
    iv = np.rint(uv[:, 1])
    inside = (iu >= 0) & (iu <= w - 1) & (iv >= 0) & (iv <= h - 1)
    iu = np.where(inside, iu, 0).astype(np.intp)
    iv = np.where(inside, iv, 0).astype(np.intp)
    out = np.asarray(depth[iv, iu], dtype=np.float64)
    out[~inside] = np.nan
    return out


def interpolate_depth(depth: np.ndarray, uv: np.ndarray,
                      smooth_tol: float = SMOOTH_DEPTH_TOL) -> np.ndarray:
    """Range (m) at sub-pixel positions ``uv`` (N, 2).

    Bilinear between the four surrounding pixel centres where they lie on one surface (their
    ranges agree within ``smooth_tol`` relative), else the nearest pixel's range (no blending
    across depth edges). NaN outside the image.
    """
    h, w = depth.shape
    near = sample_depth(depth, uv)
    u0 = np.floor(uv[:, 0])
    v0 = np.floor(uv[:, 1])
    ok = (u0 >= 0) & (u0 + 1 <= w - 1) & (v0 >= 0) & (v0 + 1 <= h - 1)
    iu = np.where(ok, u0, 0).astype(np.intp)
    iv = np.where(ok, v0, 0).astype(np.intp)
    d00 = np.asarray(depth[iv, iu], dtype=np.float64)
    d01 = np.asarray(depth[iv, iu + 1], dtype=np.float64)
    d10 = np.asarray(depth[iv + 1, iu], dtype=np.float64)
    d11 = np.asarray(depth[iv + 1, iu + 1], dtype=np.float64)
    quad = np.stack([d00, d01, d10, d11], axis=1)
    with np.errstate(invalid='ignore'):
        lo, hi = quad.min(axis=1), quad.max(axis=1)
        smooth = ok & np.isfinite(lo) & np.isfinite(hi) & (hi <= lo * (1.0 + smooth_tol))
    fu = np.where(ok, uv[:, 0] - u0, 0.0)
    fv = np.where(ok, uv[:, 1] - v0, 0.0)
    with np.errstate(invalid='ignore'):
        bil = (d00 * (1 - fu) * (1 - fv) + d01 * fu * (1 - fv) + d10 * (1 - fu) * fv
               + d11 * fu * fv)
    return np.where(smooth, bil, near)


def backproject(uv: np.ndarray, depth: np.ndarray, camera: CameraModel) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    """3-D points (N, 3) in the optical frame (m) of pixels ``uv`` (N, 2) px with a depth image.

    The range of a sub-pixel position is interpolated with :func:`interpolate_depth`.
    Returns ``(points, valid)``; ``valid`` is False where the pixel is outside the image or the
    image circle or its depth is not a finite positive range (sky, ignore).
    """
    uv = _check_uv(uv, 'uv')
    depth = _check_depth(depth, camera, 'depth')
    rng = interpolate_depth(depth, uv)
    rays = camera.unproject(uv, check=False)
    valid = np.isfinite(rng) & (rng > 0) & np.isfinite(rays).all(axis=1)
    pts = rays * np.where(valid, rng, np.nan)[:, None]
    return pts, valid


def _occlusion_ok(depth_b: np.ndarray, uv_b: np.ndarray, rng_b: np.ndarray,
                  tol: float) -> np.ndarray:
    """True where ``depth_b`` at ``uv_b`` agrees with the predicted range ``rng_b``.

    Agreement within ``tol * rng_b`` of either the interpolated range (:func:`interpolate_depth`)
    or of one of the four surrounding pixel centres.
    """
    h, w = depth_b.shape
    with np.errstate(invalid='ignore'):
        best = np.abs(interpolate_depth(depth_b, uv_b) - rng_b)
    best = np.where(np.isfinite(best), best, np.inf)
    u0 = np.nan_to_num(np.floor(uv_b[:, 0]), nan=0.0)
    v0 = np.nan_to_num(np.floor(uv_b[:, 1]), nan=0.0)
    for du in (0, 1):
        for dv in (0, 1):
            iu = np.clip(u0 + du, 0, w - 1).astype(np.intp)
            iv = np.clip(v0 + dv, 0, h - 1).astype(np.intp)
            with np.errstate(invalid='ignore'):
                err = np.abs(np.asarray(depth_b[iv, iu], dtype=np.float64) - rng_b)
            best = np.fmin(best, np.where(np.isfinite(err), err, np.inf))
    return best <= tol * rng_b + _ABS_TOL


def warp_pixels(uv_a: np.ndarray, depth_a: np.ndarray, T_map_cam_a: np.ndarray,
                T_map_cam_b: np.ndarray, camera: CameraModel, depth_b: np.ndarray | None = None,
                occlusion_tol: float = DEFAULT_OCCLUSION_TOL, *,
                camera_b: CameraModel | None = None,
                mask_a: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Warp pixels ``uv_a`` (N, 2) px of frame ``a`` into frame ``b``.

    Args:
        uv_a: pixel positions in image ``a`` (px).
        depth_a: range image of ``a`` (H, W) in m (``inf`` sky, ``NaN`` ignore).
        T_map_cam_a, T_map_cam_b: camera poses (4x4, optical frame -> map).
        camera: camera model of image ``a`` (and of ``b`` unless ``camera_b`` is given).
        depth_b: range image of ``b``; enables the occlusion check.
        occlusion_tol: allowed relative range disagreement in the occlusion check.
        camera_b: camera model of image ``b`` if it differs.
        mask_a: optional (H, W) bool image of ``a``; pixels where it is False are invalid
            (e.g. dynamic objects, which move between frames).

    Returns:
        ``(uv_b (N, 2) px, valid (N,))``. ``valid`` requires a finite depth in ``a``, a
        projection inside ``b``'s field of view and image and, with ``depth_b``, visibility.
        ``uv_b`` rows that are not valid may hold NaN.
    """
    cam_b = camera if camera_b is None else camera_b
    if occlusion_tol < 0:
        raise ShapeError(f'occlusion_tol must be >= 0, got {occlusion_tol}')
    uv_a = _check_uv(uv_a, 'uv_a')
    pts_a, valid = backproject(uv_a, depth_a, camera)
    if mask_a is not None:
        mask = _check_depth(mask_a, camera, 'mask_a').astype(np.float32)
        valid &= np.nan_to_num(sample_depth(mask, uv_a)) > 0.5
    T_ba = relative_pose(T_map_cam_a, T_map_cam_b)
    pts_b = np.where(valid[:, None], pts_a, 1.0) @ T_ba[:3, :3].T + T_ba[:3, 3]
    uv_b, in_fov = cam_b.project(pts_b)
    valid &= in_fov & cam_b.in_image(np.nan_to_num(uv_b, nan=-1e9))
    if depth_b is not None:
        depth_b = _check_depth(depth_b, cam_b, 'depth_b')
        rng_b = np.linalg.norm(pts_b, axis=1)
        valid &= _occlusion_ok(depth_b, np.where(valid[:, None], uv_b, 0.0), rng_b,
                               occlusion_tol)
    uv_b = np.where(valid[:, None], uv_b, np.nan)
    return uv_b, valid


def warp_dense(depth_a: np.ndarray, T_map_cam_a: np.ndarray, T_map_cam_b: np.ndarray,
               camera: CameraModel, depth_b: np.ndarray | None = None,
               occlusion_tol: float = DEFAULT_OCCLUSION_TOL, *,
               camera_b: CameraModel | None = None,
               mask_a: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Dense version of :func:`warp_pixels` for every pixel centre of image ``a``.

    Returns ``(uv_b (H, W, 2) px, valid (H, W))``; invalid entries of ``uv_b`` are NaN.
    """
    depth_a = _check_depth(depth_a, camera, 'depth_a')
    cam_b = camera if camera_b is None else camera_b
    if occlusion_tol < 0:
        raise ShapeError(f'occlusion_tol must be >= 0, got {occlusion_tol}')
    h, w = depth_a.shape
    rays = pixel_bearings(camera).reshape(-1, 3)
    rng = np.asarray(depth_a, dtype=np.float64).ravel()
    valid = np.isfinite(rng) & (rng > 0) & np.isfinite(rays[:, 0])
    if mask_a is not None:
        valid &= _check_depth(mask_a, camera, 'mask_a').astype(bool).ravel()
    pts_a = np.where(valid[:, None], rays * np.where(valid, rng, 1.0)[:, None], 1.0)
    T_ba = relative_pose(T_map_cam_a, T_map_cam_b)
    pts_b = pts_a @ T_ba[:3, :3].T + T_ba[:3, 3]
    uv_b, in_fov = cam_b.project(pts_b)
    valid &= in_fov & cam_b.in_image(uv_b)
    if depth_b is not None:
        depth_b = _check_depth(depth_b, cam_b, 'depth_b')
        rng_b = np.linalg.norm(pts_b, axis=1)
        valid &= _occlusion_ok(depth_b, np.where(valid[:, None], uv_b, 0.0), rng_b,
                               occlusion_tol)
    uv_b[~valid] = np.nan
    return uv_b.reshape(h, w, 2), valid.reshape(h, w)


def sample_correspondences(depth_a: np.ndarray, depth_b: np.ndarray, T_map_cam_a: np.ndarray,
                           T_map_cam_b: np.ndarray, camera: CameraModel, n: int,
                           rng: np.random.Generator, *, mask_a: np.ndarray | None = None,
                           occlusion_tol: float = DEFAULT_OCCLUSION_TOL,
                           ) -> tuple[np.ndarray, np.ndarray, float]:
    """Up to ``n`` random occlusion-checked correspondences between two frames.

    Returns ``(uv_a (M, 2), uv_b (M, 2), overlap)`` with ``M <= n`` (pixel centres of ``a``,
    float32 px) and ``overlap`` the fraction of ``a``'s pixels with a finite depth (inside
    ``mask_a``) that are visible in ``b``.
    """
    if n < 0:
        raise ShapeError(f'n must be >= 0, got {n}')
    uv_b, valid = warp_dense(depth_a, T_map_cam_a, T_map_cam_b, camera, depth_b, occlusion_tol,
                             mask_a=mask_a)
    usable = np.isfinite(np.asarray(depth_a, dtype=np.float64))
    if mask_a is not None:
        usable &= np.asarray(mask_a, dtype=bool)
    n_usable = int(usable.sum())
    overlap = float(valid.sum()) / n_usable if n_usable else 0.0
    idx = np.flatnonzero(valid.ravel())
    if len(idx) > n:
        idx = np.sort(rng.choice(idx, size=n, replace=False))
    w = depth_a.shape[1]
    uv_a = np.stack([idx % w, idx // w], axis=1).astype(np.float32)
    return uv_a, uv_b.reshape(-1, 2)[idx].astype(np.float32), overlap
