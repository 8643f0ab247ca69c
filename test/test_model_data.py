"""Training data pipeline: shards -> pairs, correspondences, keypoint targets, augmentation.

``make_shard`` renders a tiny analytic garage (road plane with parking lines, two walls, a
ceiling, an end wall) through a fisheye camera, so depth, poses and correspondences are exact
and independent of the simulator's renderer.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semfeat_ros.camera.models import FisheyeCamera
from semfeat_ros.labels import load_labels
from semfeat_ros.model.data import (
    PairGenerator,
    apply_h,
    collate,
    default_data_conf,
    edge_map,
    geometry_corner_score,
    image_corner_score,
    keypoint_candidates,
    keypoint_targets,
    photometric_augment,
    resolve_photo_paths,
)
from semfeat_ros.model.errors import DatasetError, ModelConfigError
from semfeat_ros.sim.dataset import camera_to_json, save_shard

W, H = 160, 128
CAM = FisheyeCamera(W, H, 560.0 / 12, 560.0 / 12, 79.5, 63.5,
                    k=(0.02, -0.004, 0.0005, -0.0001), fov_deg=190.0)
# optical frame (z fwd, x right, y down) -> base (x fwd, y left, z up), pitched down 0.12 rad
_R_BASE_OPT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _pitch(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def camera_pose(x: float, yaw: float = 0.0) -> np.ndarray:
    """T_map_cam of the camera 0.75 m above the road at map x (m), heading yaw (rad)."""
    cz, sz = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = Rz @ _pitch(0.12) @ _R_BASE_OPT
    T[:3, 3] = [x, 0.0, 0.75]
    return T


def render(T_map_cam: np.ndarray, cam: FisheyeCamera = CAM) -> tuple[np.ndarray, ...]:
    """rgb, label, depth (range, m), instance of the analytic garage."""
    W, H = cam.width, cam.height
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = cam.unproject(np.stack([u.ravel(), v.ravel()], 1), check=False)
    inside = np.isfinite(rays[:, 0])
    rays = np.nan_to_num(rays)
    d = rays @ T_map_cam[:3, :3].T
    o = T_map_cam[:3, 3]
    # planes: (axis, value, label, instance)
    planes = [(2, 0.0, 0, 1), (2, 2.6, 8, 2), (1, 4.0, 6, 3), (1, -4.0, 6, 4), (0, 40.0, 6, 5)]
    best = np.full(len(d), np.inf)
    lab = np.full(len(d), 16, np.uint8)  # sky where nothing is hit
    inst = np.zeros(len(d), np.uint16)
    hit = np.zeros((len(d), 3))
    for axis, val, cls, iid in planes:
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (val - o[axis]) / d[:, axis]
        t = np.nan_to_num(t, nan=-1.0, posinf=-1.0, neginf=-1.0)
        ok = (t > 1e-6) & (t < best)
        best = np.where(ok, t, best)
        lab = np.where(ok, cls, lab)
        inst = np.where(ok, iid, inst)
        hit = np.where(ok[:, None], o + t[:, None] * d, hit)
    x, y, z = hit[:, 0], hit[:, 1], hit[:, 2]
    shade = 0.5 + 0.25 * np.sin(1.7 * x) * np.cos(2.3 * y) + 0.15 * np.sign(np.sin(3.1 * x + z))
    rgb = np.stack([shade * 0.9, shade, shade * 1.1], 1)
    # parking lines: 0.15 m wide stripes every 2.5 m on the road between |y| 1.5 .. 3.8 m
    stripe = (lab == 0) & (np.abs(y) > 1.5) & (np.abs(y) < 3.8) & (np.mod(x, 2.5) < 0.15)
    lab = np.where(stripe, 2, lab)
    rgb[stripe] = 0.95
    # a pillar-coloured panel on the walls (non-planar class, to test the planar rule)
    panel = (lab == 6) & (np.mod(x, 6.0) < 0.6)
    lab = np.where(panel, 7, lab)
    rgb[panel] = [0.8, 0.6, 0.6]
    rgb[lab == 16] = [0.4, 0.6, 0.9]
    rgb = np.clip(rgb * 255, 0, 255).astype(np.uint8)
    depth = best.astype(np.float32)
    depth[lab == 16] = np.inf
    lab[~inside] = 255
    depth[~inside] = np.nan
    inst[~inside] = 0
    rgb[~inside] = 0
    return (rgb.reshape(H, W, 3), lab.reshape(H, W), depth.reshape(H, W),
            inst.reshape(H, W))


def make_shard(path: Path, n: int = 4, seed: int = 0, step: float = 0.5,
               cam: FisheyeCamera = CAM) -> Path:
    """A valid simulator shard of ``n`` frames driving forward ``step`` m per frame."""
    rgbs, labs, deps, insts, poses = [], [], [], [], []
    for i in range(n):
        T = camera_pose(0.3 * seed + step * i, yaw=0.02 * i)
        rgb, lab, dep, inst = render(T, cam)
        rgbs.append(rgb)
        labs.append(lab)
        deps.append(dep)
        insts.append(inst)
        poses.append(T)
    pairs = np.array([[i, i + 1] for i in range(n - 1)], np.int32).reshape(-1, 2)
    arrays = {
        'rgb': np.stack(rgbs), 'label': np.stack(labs),
        'depth': np.stack(deps).astype(np.float16), 'instance': np.stack(insts),
        'T_map_cam': np.stack(poses), 'T_map_base': np.stack(poses),
        'time_s': np.arange(n, dtype=np.float64) * 0.1,
        'frame_index': np.arange(n, dtype=np.int32), 'seed': np.array(seed, np.int64),
        'camera': np.array(camera_to_json(cam)), 'pairs': pairs,
        'corr_uv_a': np.zeros((len(pairs), 1, 2), np.float32),
        'corr_uv_b': np.zeros((len(pairs), 1, 2), np.float32),
        'corr_count': np.zeros(len(pairs), np.int32),
        'pair_overlap': np.full(len(pairs), 0.8, np.float32),
        'moving_instances': np.array([4], np.int64),  # the left wall 'moves' (excluded)
    }
    return save_shard(path, arrays)


SMALL_DATA = {'frame_long_side': 160, 'crop_size': [96, 96], 'num_points': 64,
              'photo_adaptation': 2, 'kp_max': 100}


@pytest.fixture(scope='module')
def shard(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_shard(tmp_path_factory.mktemp('shards') / 'seed0.npz', n=4)


def test_rendered_shard_is_consistent_with_ground_truth_warp(shard: Path) -> None:
    gen = PairGenerator([shard], {**SMALL_DATA, 'pair_mix': {'drive': 1.0}}, seed=0,
                        use_photos=False)
    assert len(gen.frames) == 4 and gen.drive_pairs == [(0, 1), (1, 2), (2, 3)]
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(6):
        pair = gen._drive(rng)
        assert pair is not None
        pair.render()
        grid = np.meshgrid(np.arange(4, 92, 6.0), np.arange(4, 92, 6.0))
        pts = np.stack(grid, -1).reshape(-1, 2)
        mapped, ok = pair.correspond(pts)
        assert ok.mean() > 0.2
        # re-render the 3-D point seen at view-a pixel and check that view b's range agrees
        fa, fb = pair.frame_a, pair.frame_b
        src_a = apply_h(np.linalg.inv(pair.H_a), pts[ok])
        src_b = apply_h(np.linalg.inv(pair.H_b), mapped[ok])
        rays_a = CAM.unproject(src_a, check=False)
        rays_b = CAM.unproject(src_b, check=False)
        da = fa.depth[np.rint(src_a[:, 1]).astype(int), np.rint(src_a[:, 0]).astype(int)]
        db = fb.depth[np.rint(src_b[:, 1]).astype(int), np.rint(src_b[:, 0]).astype(int)]
        pa = rays_a * da[:, None].astype(np.float64) @ fa.T_map_cam[:3, :3].T + fa.T_map_cam[:3, 3]
        pb = rays_b * db[:, None].astype(np.float64) @ fb.T_map_cam[:3, :3].T + fb.T_map_cam[:3, 3]
        err = np.linalg.norm(pa - pb, axis=1) / np.maximum(da, 1.0)
        assert np.median(err) < 0.05
        checked += int(ok.sum())
    assert checked > 100


def test_synthetic_pairs_map_exactly_and_respect_planar_rule(shard: Path) -> None:
    labels = load_labels()
    gen = PairGenerator([shard], {**SMALL_DATA, 'pair_mix': {'synthetic': 1.0},
                                  'homography_prob': 1.0}, seed=1, use_photos=False)
    rng = np.random.default_rng(3)
    pair = gen.make_pair(rng)
    assert pair.projective and pair.frame_a is pair.frame_b
    pair.render()
    pts = np.stack(np.meshgrid(np.arange(0, 96, 3.0), np.arange(0, 96, 3.0)), -1).reshape(-1, 2)
    mapped, ok = pair.correspond(pts)
    rel = pair.H_b @ np.linalg.inv(pair.H_a)
    np.testing.assert_allclose(mapped[ok], apply_h(rel, pts[ok]), atol=1e-9)
    lab = pair.view_a['label'][pts[ok][:, 1].astype(int), pts[ok][:, 0].astype(int)]
    assert labels.planar[lab].all()  # projective pairs: only planar classes correspond
    # the back mapping inverts the forward one
    back, ok_back = pair.correspond(mapped[ok], reverse=True)
    np.testing.assert_allclose(back[ok_back], pts[ok][ok_back], atol=1e-6)
    # similarity-only pairs keep non-planar classes too
    gen2 = PairGenerator([shard], {**SMALL_DATA, 'pair_mix': {'synthetic': 1.0},
                                   'homography_prob': 0.0}, seed=1, use_photos=False)
    found_nonplanar = False
    for k in range(10):
        p2 = gen2.make_pair(np.random.default_rng(k))
        p2.render()
        m2, ok2 = p2.correspond(pts)
        lab2 = p2.view_a['label'][pts[ok2][:, 1].astype(int), pts[ok2][:, 0].astype(int)]
        found_nonplanar |= bool((~labels.planar[lab2]).any())
    assert found_nonplanar


def test_corner_scores_and_candidates() -> None:
    img = np.zeros((64, 64, 3), np.uint8)
    img[20:44, 20:44] = 255
    s = image_corner_score(img)
    assert 0.8 < s.max() < 1.2  # calibrated: an ideal corner scores ~1
    lab = np.zeros((64, 64), np.uint8)
    lab[20:44, 20:44] = 2
    e = edge_map(lab, None, None, 0.05)
    assert e.sum() > 0 and e[30, 30] == 0
    g = geometry_corner_score(lab, None, None, 0.05)
    assert g[20:24, 20:24].max() > 0.3 and g[30:34, 5:15].max() < 0.05  # corner vs straight edge
    # depth discontinuity edges
    depth = np.full((64, 64), 5.0, np.float32)
    depth[:, 32:] = 10.0
    assert edge_map(np.zeros((64, 64), np.uint8), None, depth, 0.05)[:, 31].all()
    view = {'rgb': img, 'label': lab, 'depth': depth * 0 + 5.0, 'instance': None,
            'coverage': np.ones((64, 64), np.uint8)}
    conf = {'kp_image_threshold': 0.03, 'kp_geometry_threshold': 0.3, 'kp_nms_radius': 2,
            'kp_border': 4, 'kp_max': 50, 'depth_edge_ratio': 0.05}
    cand = keypoint_candidates(view, conf)
    corners = np.array([[20, 20], [43, 20], [20, 43], [43, 43]])
    d = np.linalg.norm(cand[:, None] - corners[None], axis=-1)
    assert (d.min(axis=0) <= 2).all()  # every square corner is found
    assert (d.min(axis=1) <= 3).all()  # and nothing else
    view['label'] = np.full((64, 64), 255, np.uint8)
    assert len(keypoint_candidates(view, conf)) == 0  # nothing outside the image circle


def test_keypoint_targets_are_repeatable(shard: Path) -> None:
    gen = PairGenerator([shard], {**SMALL_DATA, 'pair_mix': {'synthetic': 1.0, 'drive': 1.0}},
                        seed=2, use_photos=False)
    total = 0
    for k in range(6):
        rng = np.random.default_rng(k)
        pair = gen.make_pair(rng)
        pair.render()
        kp_a, kp_b = keypoint_targets(pair, gen.conf)
        total += len(kp_a)
        if len(kp_a) == 0:
            continue
        mapped, ok = pair.correspond(kp_a.astype(float))
        assert ok.all()
        d = np.linalg.norm(mapped[:, None] - kp_b[None].astype(float), axis=-1)
        assert (d.min(axis=1) <= gen.conf['kp_tolerance'] + 1e-9).all()
    assert total > 20


def test_samples_are_deterministic_and_well_formed(shard: Path) -> None:
    gen = PairGenerator([shard], SMALL_DATA, seed=5, use_photos=True)
    assert gen.photo_frames, 'real photos shipped in gtsam/matplotlib are found'
    a = gen.sample(11)
    b = gen.sample(11)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.array_equal(gen.sample(12)['image_a'], a['image_a'])
    for key in range(8):
        s = gen.sample(key)
        assert s['image_a'].shape == (96, 96, 3) and s['image_a'].dtype == np.uint8
        assert s['kp_a'].shape == (96, 96) and set(np.unique(s['kp_a'])) <= {0.0, 1.0}
        assert s['kpv_a'].dtype == bool and s['label_a'].dtype == np.uint8
        assert s['points_a'].shape == (64, 2) and s['corr_valid'].shape == (64,)
        assert (s['kp_a'][~s['kpv_a']] == 0).all()  # no target where nothing is verifiable
        v = s['corr_valid']
        assert (s['points_a'][v] >= 0).all() and (s['points_a'][v] <= 95).all()
        assert (s['points_b'][v] >= 0).all() and (s['points_b'][v] <= 95).all()
    batch = collate([gen.sample(0), gen.sample(1)])
    assert batch['image'].shape == (4, 96, 96, 3) and batch['points_a'].shape == (2, 64, 2)


def test_dense_flow_is_each_pixel_s_correspondence(shard: Path) -> None:
    gen = PairGenerator([shard], {**SMALL_DATA, 'dense_flow': True}, seed=5, use_photos=True)
    kinds = set()
    for key in range(6):
        rng = np.random.default_rng([5, key])
        pair = gen.make_pair(rng)
        s = gen.build(pair, rng)
        kinds.add(pair.kind)
        assert s['flow_a'].shape == (96, 96, 2) and s['flow_a'].dtype == np.float32
        assert s['flowv_a'].shape == (96, 96) and s['flowv_a'].dtype == bool
        assert s['flowv_a'].any()
        vv, uu = np.nonzero(s['flowv_a'])
        pick = np.linspace(0, len(uu) - 1, 20).astype(int)
        pts = np.stack([uu[pick], vv[pick]], axis=1).astype(np.float64)
        mapped, ok = pair.correspond(pts)
        assert ok.all()
        np.testing.assert_allclose(s['flow_a'][vv[pick], uu[pick]], mapped, atol=1e-3)
    assert len(kinds) > 1
    batch = collate([gen.sample(0), gen.sample(1)])
    assert batch['flow'].shape == (2, 96, 96, 2) and batch['flow_valid'].shape == (2, 96, 96)
    assert 'flow' not in collate([PairGenerator([shard], SMALL_DATA, seed=5,
                                                use_photos=False).sample(0)])


def test_photo_pairs_have_no_labels_and_full_correspondence(shard: Path) -> None:
    gen = PairGenerator([], {**SMALL_DATA, 'pair_mix': {'photo': 1.0}}, seed=0)
    s = gen.sample(0)
    assert (s['label_a'] == 255).all() and s['kind'] == 2
    assert s['corr_valid'].sum() > 32


def test_photometric_augmentation(shard: Path) -> None:
    rng = np.random.default_rng(0)
    img = np.full((32, 32, 3), 128, np.uint8)
    img[:4] = 0
    out = photometric_augment(img, rng, default_data_conf['photometric'])
    assert out.shape == img.shape and out.dtype == np.uint8
    assert (out[:4] == 0).all()
    assert not np.array_equal(out, img)


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match='training shard'):
        PairGenerator([tmp_path / 'missing.npz'], SMALL_DATA, use_photos=False)
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'not a zip')
    with pytest.raises(DatasetError, match='training shard'):
        PairGenerator([bad], SMALL_DATA, use_photos=False)
    with pytest.raises(DatasetError, match='no training data'):
        PairGenerator([], SMALL_DATA, use_photos=False)
    with pytest.raises(ModelConfigError, match='data.crop_size'):
        PairGenerator([], {**SMALL_DATA, 'crop_size': [100, 96]}, use_photos=False)
    with pytest.raises(ModelConfigError, match='unknown config key data.photometric.hue'):
        PairGenerator([], {**SMALL_DATA, 'photometric': {'hue': 1}}, use_photos=False)
    with pytest.raises(DatasetError, match="'module:no_such_package/x.png' matches no file"):
        PairGenerator([], {**SMALL_DATA, 'photos': ['module:no_such_package/x.png']})
    with pytest.raises(DatasetError, match='reserved for evaluation'):
        resolve_photo_paths([str(Path(__file__).resolve().parents[2] / 'shared' / 'data'
                                 / 'real_fisheye_calib' / '*')])
