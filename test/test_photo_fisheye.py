"""A real photo seen through the fisheye model (semfeat_ros.model.photo_fisheye)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from semfeat_ros.camera import load_camera_yaml
from semfeat_ros.model.photo_fisheye import (
    PhotoFisheyeError,
    PhotoPlacement,
    circle_coverage,
    fisheye_view,
    render_placement,
    sample_placement,
)


@pytest.fixture(scope='module')
def camera():
    """The shipped front camera (config/camera_front.yaml, ~190 deg) at the network's 640x512."""
    return load_camera_yaml()[0].scaled(640, 512)


def checkerboard(width: int, height: int, square: int) -> np.ndarray:
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    board = (((u // square) + (v // square)) % 2).astype(np.uint8) * 200 + 30
    return np.repeat(board[..., None], 3, axis=2)


def test_checkerboard_centre_lands_on_principal_point(camera) -> None:
    # 16 x 12 squares of 40 px: four squares meet at the photo's centre (319.5, 239.5) px.
    photo = checkerboard(640, 480, 40)
    placement = PhotoPlacement.facing(640, 480, np.array([0.0, 0.0, 1.0]), hfov_deg=90.0)
    image, mask = render_placement(photo, camera, placement)
    assert mask[round(camera.cy), round(camera.cx)]
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
    start = np.array([[[camera.cx + 1.5, camera.cy - 1.0]]], np.float32)  # off on purpose
    corner = cv2.cornerSubPix(gray, start, (4, 4), (-1, -1),
                              (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4))
    assert np.hypot(*(corner[0, 0] - [camera.cx, camera.cy])) < 0.15
    px, ok = placement.photo_to_fisheye(camera, np.array([placement.principal]))
    assert ok[0] and np.allclose(px[0], [camera.cx, camera.cy], atol=1e-9)


def line_centre_rows(image: np.ndarray, mask: np.ndarray, columns: np.ndarray,
                     guess: np.ndarray, half: int = 6) -> np.ndarray:
    """Sub-pixel row (px) of a dark line on white in each column, near ``guess``."""
    dark = 255.0 - image[..., 0].astype(np.float64)
    rows = np.full(len(columns), np.nan)
    for k, (u, g) in enumerate(zip(columns, guess)):
        v0 = int(round(g))
        lo, hi = v0 - half, v0 + half + 1
        if lo < 0 or hi > image.shape[0] or not mask[lo:hi, u].all():
            continue
        w = dark[lo:hi, u]
        rows[k] = float((w * np.arange(lo, hi)).sum() / w.sum())
    return rows


@pytest.mark.parametrize('direction, roll', [((0.0, 0.0, 1.0), 0.0), ((0.35, -0.2, 1.0), 12.0)])
def test_straight_photo_line_curves_like_the_fisheye_model(camera, direction, roll) -> None:
    # A horizontal line (Gaussian profile, sigma 3 px) 170 px above the centre of an 800x600 px
    # photo: a straight 3-D line on the photo's plane, which the fisheye bends.
    w, h, row = 800, 600, 129.5
    v = np.arange(h, dtype=np.float64)[:, None]
    line = 255.0 * (1.0 - np.exp(-((v - row) ** 2) / (2 * 3.0 ** 2)))
    photo = np.repeat(np.repeat(line, w, axis=1)[..., None], 3, axis=2).round().astype(np.uint8)
    placement = PhotoPlacement.facing(w, h, np.array(direction), hfov_deg=100.0, roll_deg=roll)
    image, mask = render_placement(photo, camera, placement)
    # Prediction: 3-D points of the line projected with the camera model.
    us = np.linspace(0.0, w - 1.0, 4001)
    pred, ok = placement.photo_to_fisheye(camera, np.stack([us, np.full_like(us, row)], axis=1))
    assert ok.all()
    pred = pred[np.argsort(pred[:, 0])]
    columns = np.arange(int(np.ceil(pred[0, 0])) + 10, int(pred[-1, 0]) - 10)
    guess = np.interp(columns, pred[:, 0], pred[:, 1])
    slope = np.abs(np.gradient(guess))
    columns, guess = columns[slope < 0.6], guess[slope < 0.6]
    measured = line_centre_rows(image, mask, columns, guess)
    good = np.isfinite(measured)
    assert good.sum() > 150
    err = np.abs(measured[good] - guess[good])
    assert err.max() < 0.5, f'line off the prediction by up to {err.max():.3f} px'
    # ... and the line really is curved: a straight line through the measurements misses them.
    fit = np.polyfit(columns[good], measured[good], 1)
    assert np.abs(np.polyval(fit, columns[good]) - measured[good]).max() > 4.0


def test_mask_is_exactly_where_the_photo_lands(camera) -> None:
    w, h = 640, 480
    placement = PhotoPlacement.facing(w, h, np.array([0.2, 0.1, 1.0]), hfov_deg=95.0,
                                      roll_deg=20.0, tilt_deg=25.0, tilt_axis_deg=40.0)
    colour = np.array([200, 100, 50], np.uint8)
    image, mask = render_placement(np.broadcast_to(colour, (h, w, 3)).copy(), camera, placement)
    # Every covered pixel shows the photo (no black bled in at its edges), nothing else does.
    assert (image[mask] == colour).all() and (image[~mask] == 0).all()
    # Definition: the ray meets the photo's rectangle (float64 recomputation, own unprojection).
    uu, vv = np.meshgrid(np.arange(camera.width, dtype=np.float64),
                         np.arange(camera.height, dtype=np.float64))
    rays = camera.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1), check=False)
    uv, hit = placement.bearings_to_photo(rays)
    inside = (hit & placement.inside(uv)).reshape(mask.shape)
    margin = np.minimum.reduce([uv[:, 0], w - 1 - uv[:, 0], uv[:, 1], h - 1 - uv[:, 1]])
    near_edge = (np.abs(np.nan_to_num(margin, nan=1e9)) < 1e-3).reshape(mask.shape)
    assert not (inside != mask)[~near_edge].any()
    # Geometry: the photo's border projected forward with the camera model encloses the mask.
    t = np.linspace(0.0, 1.0, 2000)
    border = np.concatenate([
        np.stack([t * (w - 1), np.zeros_like(t)], 1), np.stack([np.full_like(t, w - 1),
                                                                t * (h - 1)], 1),
        np.stack([(1 - t) * (w - 1), np.full_like(t, h - 1)], 1),
        np.stack([np.zeros_like(t), (1 - t) * (h - 1)], 1)])
    poly, ok = placement.photo_to_fisheye(camera, border)
    assert ok.all()
    filled = np.zeros(mask.shape, np.uint8)
    cv2.fillPoly(filled, [np.round(poly * 256).astype(np.int32)], 1, lineType=cv2.LINE_8,
                 shift=8)
    outline = np.zeros(mask.shape, np.uint8)
    cv2.polylines(outline, [np.round(poly * 256).astype(np.int32)], True, 1, thickness=3,
                  shift=8)
    differ = (filled.astype(bool) != mask)
    assert not (differ & ~outline.astype(bool)).any()
    assert mask.sum() > 30000 and differ.sum() < 0.01 * mask.sum()


def test_mask_stays_inside_the_image_circle(camera) -> None:
    # A wide photo 80 deg off-axis reaches past the lens's 95 deg: clipped at the circle.
    direction = np.array([np.sin(np.radians(80.0)), 0.0, np.cos(np.radians(80.0))])
    placement = PhotoPlacement.facing(800, 600, direction, hfov_deg=120.0)
    image, mask = render_placement(np.full((600, 800, 3), 255, np.uint8), camera, placement)
    valid = camera.valid_mask()
    assert mask.any() and not (mask & ~valid).any()
    assert mask[:, :camera.width // 2].sum() == 0  # all of it on the right-hand side
    assert mask[:, -3:].any()  # and up to the image border


def test_fisheye_view_is_deterministic_and_covers_the_circle(camera) -> None:
    rng = np.random.default_rng(1)
    photo = rng.integers(0, 256, (800, 1280, 3), dtype=np.uint8)
    a_img, a_mask = fisheye_view(photo, camera, np.random.default_rng(42))
    b_img, b_mask = fisheye_view(photo, camera, np.random.default_rng(42))
    c_img, c_mask = fisheye_view(photo, camera, np.random.default_rng(43))
    assert a_img.shape == (512, 640, 3) and a_img.dtype == np.uint8
    assert a_mask.shape == (512, 640) and a_mask.dtype == bool
    assert np.array_equal(a_img, b_img) and np.array_equal(a_mask, b_mask)
    assert not np.array_equal(a_mask, c_mask)
    cover = [circle_coverage(fisheye_view(photo, camera, np.random.default_rng(s))[1], camera)
             for s in range(24)]
    assert np.median(cover) >= 0.4, cover


def test_sampled_centres_spread_over_the_circle(camera) -> None:
    rng = np.random.default_rng(7)
    centres = []
    for _ in range(200):
        p = sample_placement((640, 480), camera, rng, max_offaxis_deg=50.0)
        px, ok = p.photo_to_fisheye(camera, np.array([p.principal]))
        assert ok[0]
        centres.append(px[0])
        off_axis = np.degrees(np.arccos(np.asarray(p.centre)[2] / np.linalg.norm(p.centre)))
        assert off_axis <= 50.0 + 1e-6 and 110.0 <= p.hfov_deg <= 150.0
    c = np.array(centres) - [camera.cx, camera.cy]
    # all four quadrants, and out to most of the 50-deg radius (~166 px)
    assert all(((np.sign(c[:, 0]) == sx) & (np.sign(c[:, 1]) == sy)).sum() > 20
               for sx in (-1, 1) for sy in (-1, 1))
    assert np.hypot(c[:, 0], c[:, 1]).max() > 140.0


def test_background_and_bad_inputs(camera) -> None:
    photo = np.full((300, 400, 3), 90, np.uint8)
    bg = np.full((512, 640, 3), 7, np.uint8)
    image, mask = fisheye_view(photo, camera, np.random.default_rng(0), background=bg)
    assert (image[~mask] == 7).all() and (image[mask] == 90).all()
    with pytest.raises(PhotoFisheyeError):
        fisheye_view(photo[..., 0], camera, np.random.default_rng(0))
    with pytest.raises(PhotoFisheyeError):
        fisheye_view(photo, camera, np.random.default_rng(0), hfov_deg=(10.0, 190.0))
    with pytest.raises(PhotoFisheyeError):
        fisheye_view(photo, camera, np.random.default_rng(0), background=bg[:10])
    placement = PhotoPlacement.facing(200, 100, np.array([0.0, 0.0, 1.0]), hfov_deg=60.0)
    with pytest.raises(PhotoFisheyeError):
        render_placement(photo, camera, placement)
