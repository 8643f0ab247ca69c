"""The paper's transform sampler, image warping and the valid-region (image circle) masks."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semfeat_ros.evaluation.errors import ConfigError
from semfeat_ros.evaluation.masks import MaskSource, camera_valid_mask, estimate_valid_mask
from semfeat_ros.evaluation.run_transforms import make_transform_pair
from semfeat_ros.evaluation.transforms import (
    TransformConf,
    apply_homography,
    compose_homography,
    erode_mask,
    sample_transform,
    warp_image,
)

# Real fisheye frames of shared/ (next to the repository, as on the developers' machines and CI).
REAL = next((p for p in (Path(__file__).resolve().parents[2] / 'shared/data/real_fisheye_calib',
                         Path('/work/shared/data/real_fisheye_calib')) if p.is_dir()),
            Path('/work/shared/data/real_fisheye_calib'))
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f'real fisheye frames not at {REAL}')


def _jacobian(H: np.ndarray, p: np.ndarray, h: float = 1e-4) -> np.ndarray:
    J = np.zeros((2, 2))
    for k in range(2):
        d = np.zeros(2)
        d[k] = h
        J[:, k] = (apply_homography(H, [p + d])[0] - apply_homography(H, [p - d])[0]) / (2 * h)
    return J


def test_sampler_ranges_and_decomposition() -> None:
    rng = np.random.default_rng(0)
    w, h = 640, 480
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    angles, scales, persp = [], [], []
    for _ in range(300):
        t = sample_transform(rng, w, h)
        assert -30.0 <= t.angle_deg <= 30.0
        assert 0.8 <= t.scale <= 1.2
        assert abs(t.tx) <= 15.0 and abs(t.ty) <= 15.0
        assert all(abs(p) <= 0.1 for p in t.perspective)
        # The centre maps exactly to centre + t, the Jacobian there is s R(angle).
        np.testing.assert_allclose(apply_homography(t.H, [c])[0], c + [t.tx, t.ty], atol=1e-9)
        J = _jacobian(t.H, c)
        s = np.sqrt(abs(np.linalg.det(J)))
        ang = np.degrees(np.arctan2(J[1, 0], J[0, 0]))
        assert s == pytest.approx(t.scale, rel=1e-6)
        assert ang == pytest.approx(t.angle_deg, abs=1e-5)
        angles.append(t.angle_deg)
        scales.append(t.scale)
        persp.extend(t.perspective)
    # The draws cover the ranges (uniform sampling, 300 draws).
    assert min(angles) < -25 and max(angles) > 25
    assert min(scales) < 0.85 and max(scales) > 1.15
    assert min(persp) < -0.08 and max(persp) > 0.08


def test_sampler_is_deterministic_and_configurable() -> None:
    a = sample_transform(np.random.default_rng(7), 100, 80)
    b = sample_transform(np.random.default_rng(7), 100, 80)
    np.testing.assert_array_equal(a.H, b.H)
    conf = TransformConf(max_rotation_deg=0, max_translation_px=0, min_scale=1, max_scale=1,
                         max_perspective=0)
    t = sample_transform(np.random.default_rng(1), 100, 80, conf)
    np.testing.assert_allclose(t.H, np.eye(3), atol=1e-12)
    with pytest.raises(ConfigError, match='scale'):
        TransformConf(min_scale=1.3, max_scale=1.2)
    with pytest.raises(ConfigError, match='max_perspective'):
        TransformConf(max_perspective=0.7)


def test_warp_image_agrees_with_apply_homography() -> None:
    img = np.zeros((120, 160), np.uint8)
    img[40, 50] = 255
    H = compose_homography(160, 120, 12.0, 1.1, 4.0, -3.0, (0.05, -0.03))
    warped = warp_image(img.astype(np.float32), H)
    v, u = np.unravel_index(np.argmax(warped), warped.shape)
    expected = apply_homography(H, [[50.0, 40.0]])[0]
    assert np.hypot(u - expected[0], v - expected[1]) <= 1.0


def test_erode_mask_includes_frame() -> None:
    m = erode_mask(np.ones((10, 12), bool), 2)
    assert m.sum() == (10 - 4) * (12 - 4)
    assert erode_mask(np.ones((3, 3), bool), 0).all()


def _disk_image(h: int = 200, w: int = 260, r: float = 110.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:h, 0:w]
    disk = (xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2 <= r * r
    img = rng.integers(40, 255, size=(h, w, 3)).astype(np.uint8)
    img[~disk] = rng.integers(0, 6, size=(int((~disk).sum()), 3))  # noisy black border
    return img, disk


def test_estimate_valid_mask_finds_image_circle() -> None:
    img, disk = _disk_image()
    est = estimate_valid_mask(img)
    iou = (est & disk).sum() / (est | disk).sum()
    assert iou > 0.98
    # A pinhole image without a border is valid everywhere; the margin erodes it.
    plain = np.full((50, 60, 3), 128, np.uint8)
    assert estimate_valid_mask(plain).all()
    assert estimate_valid_mask(plain, margin_px=5).sum() == 40 * 50


@needs_real
def test_real_fisheye_mask_auto_and_camera() -> None:
    import cv2

    img = cv2.imread(str(REAL / 'left-0003.png'), cv2.IMREAD_GRAYSCALE)
    auto = estimate_valid_mask(img)
    assert 0.95 < auto.mean() < 1.0  # only the black corners are outside
    assert not auto[0, 0] and not auto[-1, -1] and auto[250, 400]
    cam = camera_valid_mask(REAL / 'ost.yaml', 800, 503, distortion_model='equidistant')
    assert cam.shape == (503, 800) and not cam[0, 0] and cam[250, 400]
    half = camera_valid_mask(REAL / 'ost.yaml', 400, 251, distortion_model='equidistant')
    assert half.shape == (251, 400)
    with pytest.raises(ConfigError, match='aspect ratio'):
        camera_valid_mask(REAL / 'ost.yaml', 400, 400, distortion_model='equidistant')
    src = MaskSource('camera', camera_yaml=REAL / 'ost.yaml', distortion_model='equidistant')
    assert src(img[:, :, None].repeat(3, axis=2)).shape == (503, 800)
    with pytest.raises(ConfigError, match='--camera'):
        MaskSource('camera')


def test_transform_pair_ground_truth_is_exact() -> None:
    img, disk = _disk_image()
    pair = make_transform_pair('p', img, np.random.default_rng(5), MaskSource('auto',
                                                                             margin_px=4))
    # Pixels of A map to the same colour in B (inside both masks), through the exact H.
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(0, 259, 400), rng.uniform(0, 199, 400)], axis=1).round()
    uv_b, vis = pair.gt.a_to_b(uv)
    assert vis.sum() > 100
    assert not vis[~disk[uv[:, 1].astype(int), uv[:, 0].astype(int)]].any()
    back, vis_back = pair.gt.b_to_a(uv_b[vis])
    np.testing.assert_allclose(back, uv[vis], atol=1e-6)
    assert vis_back.all()
    # B's mask holds only pixels that come from A's valid region.
    ys, xs = np.nonzero(pair.mask_b)
    src = apply_homography(np.linalg.inv(pair.H), np.stack([xs, ys], axis=1))
    iu, iv = np.rint(src[:, 0]).astype(int), np.rint(src[:, 1]).astype(int)
    assert disk[iv, iu].all()
