"""Ground-truth warps on analytic scenes (independent of the renderer)."""
from __future__ import annotations

import numpy as np
import pytest

from semfeat_ros.camera import load_camera_yaml
from semfeat_ros.rotations import rpy_to_matrix
from semfeat_ros.sim.errors import ShapeError
from semfeat_ros.sim.geometry import make_transform
from semfeat_ros.sim.groundtruth import (
    backproject,
    pixel_bearings,
    relative_pose,
    sample_correspondences,
    warp_dense,
    warp_pixels,
)

W, H = 320, 256


@pytest.fixture(scope='module')
def camera():
    return load_camera_yaml()[0].scaled(W, H)


def plane_depth(camera, T_map_cam: np.ndarray, z0: float = 0.0,
                box: tuple[float, float, float, float, float] | None = None) -> np.ndarray:
    """Range image of the ground plane z = z0 (m), optionally with an occluding slab
    ``box = (x0, x1, y0, y1, z_top)`` (its top face only, which is enough from above)."""
    rays = pixel_bearings(camera).reshape(-1, 3)
    d = rays @ T_map_cam[:3, :3].T
    o = T_map_cam[:3, 3]
    with np.errstate(invalid='ignore', divide='ignore'):
        t = (z0 - o[2]) / d[:, 2]
    t[~(t > 0)] = np.inf
    if box is not None:
        x0, x1, y0, y1, zt = box
        with np.errstate(invalid='ignore', divide='ignore'):
            tb = (zt - o[2]) / d[:, 2]
        p = o + tb[:, None] * d
        hit = (tb > 0) & (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
        t = np.where(hit & (tb < t), tb, t)
    t[~np.isfinite(rays[:, 0])] = np.nan
    return t.reshape(camera.height, camera.width).astype(np.float32)


def cam_pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    # Optical frame looking along +x of map, tilted down by 0.3 rad, then yawed.
    R_body = rpy_to_matrix(0.0, 0.3, yaw)
    R_bo = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return make_transform(R_body @ R_bo, [x, y, z])


def test_identity_warp_returns_same_pixels(camera) -> None:
    T = cam_pose(0, 0, 1.5, 0.0)
    depth = plane_depth(camera, T)
    uv_b, valid = warp_dense(depth, T, T, camera, depth)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    assert valid.sum() > 0.3 * W * H
    np.testing.assert_allclose(uv_b[valid][:, 0], u[valid], atol=1e-6)
    np.testing.assert_allclose(uv_b[valid][:, 1], v[valid], atol=1e-6)


def _world_error(camera, uv_a, uv_b, da, Ta, Tb) -> np.ndarray:
    """Distance (m) between a's back-projected point and b's ray at uv_b hitting z = 0."""
    pa, _ = backproject(uv_a, da, camera)
    wa = pa @ Ta[:3, :3].T + Ta[:3, 3]
    rays_b = camera.unproject(uv_b) @ Tb[:3, :3].T
    t = -Tb[2, 3] / rays_b[:, 2]
    wb = Tb[:3, 3] + t[:, None] * rays_b
    return np.linalg.norm(wa - wb, axis=1) / np.linalg.norm(wa - Ta[:3, 3], axis=1)


def test_warp_lands_on_same_world_point(camera) -> None:
    Ta = cam_pose(0, 0, 1.5, 0.0)
    Tb = cam_pose(1.2, 0.3, 1.5, 0.15)
    da, db = plane_depth(camera, Ta), plane_depth(camera, Tb)
    rng = np.random.default_rng(0)
    # Pixel centres: exact.
    uv_a = rng.integers([0, 0], [W, H], size=(400, 2)).astype(float)
    uv_b, valid = warp_pixels(uv_a, da, Ta, Tb, camera, db)
    assert valid.sum() > 50
    assert _world_error(camera, uv_a[valid], uv_b[valid], da, Ta, Tb).max() < 1e-6
    # Sub-pixel positions: interpolated range, small relative error.
    uv_a = rng.uniform([0, 0], [W - 1, H - 1], size=(400, 2))
    uv_b, valid = warp_pixels(uv_a, da, Ta, Tb, camera, db)
    assert valid.sum() > 50
    assert np.median(_world_error(camera, uv_a[valid], uv_b[valid], da, Ta, Tb)) < 2e-3


def test_occlusion_rejects_hidden_points(camera) -> None:
    Ta = cam_pose(0, 0, 1.5, 0.0)
    Tb = cam_pose(3.0, 0.0, 1.5, 0.0)
    box = (2.0, 6.0, -3.0, 3.0, 1.0)  # a 1 m high slab in front of b's position
    da = plane_depth(camera, Ta)  # a sees only the ground (slab absent in a)
    db = plane_depth(camera, Tb, box=box)
    _, valid_free = warp_dense(da, Ta, Tb, camera)
    _, valid_occ = warp_dense(da, Ta, Tb, camera, db)
    assert valid_occ.sum() < valid_free.sum()
    # Rejected pixels within 8 m are hidden behind the slab: b sees something closer there.
    uv_b, _ = warp_dense(da, Ta, Tb, camera)
    rejected = valid_free & ~valid_occ
    pts, _ = backproject(np.stack(np.nonzero(rejected)[::-1], 1).astype(float), da, camera)
    rel = relative_pose(Ta, Tb)
    rng_b = np.linalg.norm(pts @ rel[:3, :3].T + rel[:3, 3], axis=1)
    near = rng_b < 8.0
    assert near.sum() > 10
    iu = np.rint(uv_b[rejected][near, 0]).astype(int)
    iv = np.rint(uv_b[rejected][near, 1]).astype(int)
    seen = db[iv, iu]
    border = np.isnan(seen)  # landing on the rim of b's image circle
    assert border.mean() < 0.01
    assert np.all(seen[~border] < 0.98 * rng_b[near][~border])


def test_mask_and_sky_are_invalid(camera) -> None:
    T = cam_pose(0, 0, 1.5, 0.0)
    depth = plane_depth(camera, T)
    assert np.isinf(depth).any() and np.isnan(depth).any()
    mask = np.ones((H, W), bool)
    mask[:, : W // 2] = False
    uv_b, valid = warp_dense(depth, T, T, camera, depth, mask_a=mask)
    assert not valid[:, : W // 2].any()
    assert not valid[~np.isfinite(depth)].any()
    assert np.isnan(uv_b[~valid]).all()


def test_sample_correspondences_and_errors(camera) -> None:
    Ta = cam_pose(0, 0, 1.5, 0.0)
    Tb = cam_pose(0.5, 0, 1.5, 0.05)
    da, db = plane_depth(camera, Ta), plane_depth(camera, Tb)
    uv_a, uv_b, overlap = sample_correspondences(da, db, Ta, Tb, camera, 100,
                                                 np.random.default_rng(1))
    assert uv_a.shape == uv_b.shape == (100, 2) and 0.5 < overlap <= 1.0
    ref, ok = warp_pixels(uv_a, da, Ta, Tb, camera, db)
    assert ok.all()
    np.testing.assert_allclose(ref, uv_b, atol=1e-3)
    with pytest.raises(ShapeError, match='depth'):
        warp_pixels(uv_a, da[:-1], Ta, Tb, camera)
    with pytest.raises(ShapeError, match='4x4'):
        warp_pixels(uv_a, da, Ta[:3], Tb, camera)
    with pytest.raises(ShapeError, match=r'\(N, 2\)'):
        warp_pixels(uv_a[:, :1], da, Ta, Tb, camera)
