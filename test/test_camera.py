"""Camera models: agreement with OpenCV, round trips over the full 190-degree circle, errors."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from semfeat_ros.camera import (
    CameraModelError,
    FisheyeCamera,
    OutsideImageCircleError,
    PinholeCamera,
    load_camera_yaml,
)

REAL_CALIB = Path(__file__).resolve().parents[2] / 'shared/data/real_fisheye_calib/ost.yaml'


@pytest.fixture(scope='module')
def front() -> FisheyeCamera:
    cam, _ = load_camera_yaml()
    assert isinstance(cam, FisheyeCamera)
    return cam


def _sphere_points(n: int, theta_max: float, rng: np.random.Generator) -> np.ndarray:
    theta = np.arccos(1 - rng.random(n) * (1 - np.cos(theta_max)))
    phi = rng.random(n) * 2 * np.pi
    dirs = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    return dirs * rng.uniform(0.5, 30.0, (n, 1))


def test_fisheye_matches_cv2_project(front: FisheyeCamera) -> None:
    rng = np.random.default_rng(0)
    pts = _sphere_points(2000, np.radians(85), rng)
    ours, valid = front.project(pts)
    ref, _ = cv2.fisheye.projectPoints(pts[:, None], np.zeros(3), np.zeros(3), front.K, front.D)
    assert valid.all()
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-6)


def test_fisheye_matches_cv2_undistort(front: FisheyeCamera) -> None:
    rng = np.random.default_rng(1)
    pts = _sphere_points(2000, np.radians(80), rng)
    px, _ = front.project(pts)
    ref = cv2.fisheye.undistortPoints(px[:, None], front.K, front.D,
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                50, 1e-12))[:, 0]
    rays = front.unproject(px)
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], ref, atol=1e-6)


def test_fisheye_round_trip_whole_circle(front: FisheyeCamera) -> None:
    """pixel -> bearing -> pixel below 1e-3 px over the whole 190-degree image circle."""
    rng = np.random.default_rng(2)
    dirs = _sphere_points(20000, front.theta_max, rng)
    dirs = np.concatenate([dirs, [[1.0, 0.0, -np.tan(np.radians(4.9))]]])  # beyond 90 degrees
    px, valid = front.project(dirs)
    assert valid.all()
    assert (dirs[:, 2] < 0).any()
    bearings = front.unproject(px)
    np.testing.assert_allclose(np.linalg.norm(bearings, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(bearings, dirs / np.linalg.norm(dirs, axis=1, keepdims=True),
                               atol=1e-9)
    back, ok = front.project(bearings)
    assert ok.all()
    assert np.abs(back - px).max() < 1e-3


def test_fisheye_grid_round_trip(front: FisheyeCamera) -> None:
    small = front.scaled(320, 256)
    mask = small.valid_mask()
    v, u = np.nonzero(mask)
    px = np.stack([u, v], 1).astype(np.float64)
    back, ok = small.project(small.unproject(px))
    assert ok.all() and np.abs(back - px).max() < 1e-3
    # The 190-degree circle covers most of the sensor; only the corners fall outside.
    assert 0.8 < mask.mean() < 1.0
    assert not mask[0, 0] and not mask[-1, -1] and mask[128, 160] and mask[128, 1]


def test_outside_image_circle_raises() -> None:
    cam = FisheyeCamera(640, 512, 150.0, 150.0, 320.0, 256.0, k=(0.0, 0.0, 0.0, 0.0), fov_deg=180)
    with pytest.raises(OutsideImageCircleError, match='outside the image circle'):
        cam.unproject(np.array([[0.0, 0.0]]))
    rays = cam.unproject(np.array([[0.0, 0.0], [320.0, 256.0]]), check=False)
    assert np.isnan(rays[0]).all() and np.allclose(rays[1], [0, 0, 1])
    _, valid = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert valid.tolist() == [False, True]


def test_scaling_keeps_bearings(front: FisheyeCamera) -> None:
    small = front.scaled(640, 512)
    ray = np.array([[0.3, -0.2, 0.9]])
    big_px, _ = front.project(ray)
    small_px, _ = small.project(ray)
    np.testing.assert_allclose((small_px + 0.5) * 3.0 - 0.5, big_px, atol=1e-9)


def test_real_calibration_agrees_with_cv2() -> None:
    cam, _ = load_camera_yaml(REAL_CALIB, distortion_model='equidistant', fov_deg=180)
    rng = np.random.default_rng(3)
    pts = _sphere_points(500, np.radians(80), rng)
    ours, _ = cam.project(pts)
    ref, _ = cv2.fisheye.projectPoints(pts[:, None], np.zeros(3), np.zeros(3), cam.K, cam.D)
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-6)


@pytest.mark.parametrize('model,d', [('plumb_bob', (-0.28, 0.07, 1e-3, -5e-4, 0.0)),
                                     ('rational_polynomial', (0.5, -0.1, 1e-3, 1e-3, 0.01,
                                                              0.8, -0.05, 0.02))])
def test_pinhole_matches_cv2(model: str, d: tuple[float, ...]) -> None:
    cam = PinholeCamera(800, 600, 450.0, 452.0, 401.0, 299.0, d=d, model=model)
    rng = np.random.default_rng(4)
    pts = _sphere_points(1000, np.radians(40), rng)
    ours, valid = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.D)
    assert valid.all()
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-6)
    rays = cam.unproject(ours)
    np.testing.assert_allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-8)


@pytest.mark.parametrize('kwargs,match', [
    (dict(width=0, height=10, fx=1, fy=1, cx=0, cy=0), 'positive'),
    (dict(width=10, height=10, fx=-1, fy=1, cx=5, cy=5), 'focal'),
    (dict(width=10, height=10, fx=1, fy=1, cx=50, cy=5), 'outside'),
    (dict(width=10, height=10, fx=float('nan'), fy=1, cx=5, cy=5), 'NaN'),
])
def test_bad_intrinsics(kwargs: dict, match: str) -> None:
    with pytest.raises(CameraModelError, match=match):
        FisheyeCamera(**kwargs)


def test_non_monotonic_distortion_rejected() -> None:
    with pytest.raises(CameraModelError, match='monotonic'):
        FisheyeCamera(640, 512, 150.0, 150.0, 320.0, 256.0, k=(0.0, -0.5, 0.0, 0.0))


def test_extrinsic_points_camera_forward_and_down() -> None:
    _, ext = load_camera_yaml()
    T = ext.T_base_cam
    optical_axis_in_base = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert optical_axis_in_base[0] > 0.9 and optical_axis_in_base[2] < 0  # forward, pitched down
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert 0.6 <= ext.height <= 0.9


@pytest.mark.parametrize('cam', [
    FisheyeCamera(640, 512, 186.7, 186.7, 320.0, 256.0, k=(0.02, -0.004, 0.0005, -0.0001),
                  fov_deg=190),
    PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, d=(-0.2, 0.05, 0.001, 0.001, 0.0)),
    PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0,
                  d=(-0.2, 0.05, 0.001, 0.001, 0.0, 0.1, 0.0, 0.0),
                  model='rational_polynomial')])
def test_non_finite_and_huge_inputs_are_invalid_without_warnings(cam) -> None:  # noqa: ANN001
    import warnings

    inf, nan = float('inf'), float('nan')
    pixels = np.array([[300.0, 200.0], [inf, 1.0], [nan, 5.0], [1e308, 1e308], [-inf, -inf]])
    points = np.array([[0.1, 0.2, 1.0], [inf, 0.0, 1.0], [nan, 0.0, 1.0],
                       [1e308, 1e308, 1e-308], [0.0, 0.0, -inf]])
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # a RuntimeWarning would go raw into a node's log
        rays = cam.unproject(pixels, check=False)
        px, valid = cam.project(points)
    assert np.isfinite(rays[0]).all() and np.isnan(rays[1:]).all()
    np.testing.assert_allclose(rays[0], cam.unproject(pixels[:1])[0])
    assert valid.tolist() == [True, False, False, False, False]
    np.testing.assert_allclose(px[0], cam.project(points[:1])[0][0])
    with pytest.raises(OutsideImageCircleError):
        cam.unproject(pixels)  # checked: non-finite pixels have no bearing


def test_frame_features_drops_non_finite_rows_without_warnings() -> None:
    import warnings

    from semfeat_ros.pipeline import frame_features

    cam = FisheyeCamera(640, 512, 186.7, 186.7, 320.0, 256.0, fov_deg=190)
    kp = np.array([[300.0, 200.0], [float('inf'), 1.0], [310.0, 210.0], [320.0, 220.0]])
    desc = np.ones((4, 8), np.float32)
    desc[2, 3] = float('nan')
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        f = frame_features(1, kp, desc, np.zeros(4, np.uint8), np.ones(4), cam)
    np.testing.assert_array_equal(f.keypoints, kp[[0, 3]].astype(np.float32))
    assert np.isfinite(f.descriptors).all() and np.isfinite(f.bearings).all()
