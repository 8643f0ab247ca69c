"""Offline batch code without bags: metrics, floors, path confinement, config, front ends."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semfeat_ros.camera import load_camera_yaml
from semfeat_ros.labels import load_labels
from semfeat_ros.mapping import FloorLevels, SemanticCloud, Similarity
from semfeat_ros.offline.config import node_config, parse_overrides, read_node_params
from semfeat_ros.offline.errors import EvaluationError, OfflineConfigError, OutputPathError
from semfeat_ros.offline.frontends import OpenCVFrontend, matcher_frame
from semfeat_ros.offline.metrics import (
    DepthView,
    anchor_points,
    associate,
    evaluate_trajectory,
    floor_accuracy,
    pitch_of,
    point_errors,
    storey_of,
    surface_accuracy,
    surface_errors,
    timing_stats,
)
from semfeat_ros.offline.paths import confined, prepare_out_dir


def ramp_drive(n: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (ns) and base poses: 20 m level at z=3.6, a 12 % ramp down 30 m, 20 m at z=0."""
    s = np.linspace(0.0, 70.0, n)
    z = np.where(s < 20, 3.6, np.where(s < 50, 3.6 - 0.12 * (s - 20), 0.0))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3], poses[:, 2, 3] = s, z
    pitch = np.where((s >= 20) & (s < 50), -np.arctan(0.12), 0.0)
    c, si = np.cos(pitch), np.sin(pitch)
    poses[:, 0, 0], poses[:, 0, 2], poses[:, 2, 0], poses[:, 2, 2] = c, -si, si, c
    stamps = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000
    return stamps, poses


def test_evaluate_trajectory_recovers_similarity_and_ramp_error() -> None:
    stamps, gt = ramp_drive()
    rng = np.random.default_rng(0)
    yaw = 0.7
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    est = gt.copy()
    est[:, :3, 3] = 0.5 * gt[:, :3, 3] @ R.T + [3.0, -2.0, 1.0] + rng.normal(0, 0.01, (120, 3))
    ev = evaluate_trajectory(stamps, est, stamps, gt, metric=True)
    m = ev.metrics
    assert m['n_poses'] == 120
    assert m['scale_sim3'] == pytest.approx(2.0, rel=1e-2)
    assert m['ate_sim3_rmse_m'] < 0.05  # 2 x 1 cm noise per axis after the x2 scale
    assert m['ate_se3_rmse_m'] > 5.0  # half-size estimate: rigid alignment cannot fix it
    assert m['n_ramp_poses'] == int((np.abs(pitch_of(gt)) > 0.02).sum()) > 30
    assert m['ramp_altitude_rmse_sim3_m'] < 0.06
    assert m['gt_length_m'] == pytest.approx(70.0 + 30 * (np.hypot(1, 0.12) - 1), rel=1e-3)
    # a 0.5 m altitude bias on the ramp: the alignment absorbs part of it, the rest shows
    # mostly in the ramp metrics
    est2 = gt.copy()
    est2[ev.ramp, 2, 3] += 0.5
    m2 = evaluate_trajectory(stamps, est2, stamps, gt, metric=False).metrics
    assert m2['ramp_altitude_max_sim3_m'] > 0.2
    assert m2['ramp_altitude_rmse_sim3_m'] > m2['altitude_rmse_sim3_m']
    assert m2['ate_se3_rmse_m'] is None and m2['ramp_altitude_rmse_se3_m'] is None


def test_associate_interpolates_and_drops_outside() -> None:
    stamps, gt = ramp_drive(20)
    est_stamps = np.array([stamps[0] - 1, stamps[3], stamps[3] + 50_000_000, stamps[-1] + 1])
    idx, poses = associate(est_stamps, stamps, gt)
    assert idx.tolist() == [1, 2]
    np.testing.assert_allclose(poses[0], gt[3])
    np.testing.assert_allclose(poses[1][:3, 3], (gt[3][:3, 3] + gt[4][:3, 3]) / 2, atol=1e-9)
    with pytest.raises(EvaluationError, match='within the ground truth'):
        evaluate_trajectory(est_stamps, np.tile(np.eye(4), (4, 1, 1)), stamps, gt,
                            metric=False)


def test_storey_rule() -> None:
    levels = np.array([0.0, 3.6])
    z = np.array([-1.0, 0.0, 1.5, 3.25, 3.45, 3.6, 9.0])
    # the covered level's ceiling (3.25 m, under the 0.35 m deck slab) belongs to level 0;
    # a point 0.15 m below the deck surface still belongs to the deck
    assert storey_of(z, levels).tolist() == [0, 0, 0, 0, 1, 1, 1]
    assert storey_of(z, np.zeros(0)).tolist() == [0] * 7


def test_floor_accuracy_maps_estimated_levels() -> None:
    labels = load_labels()
    # estimate in a frame shifted by -3.6 m (started on the deck): levels -3.6 and 0
    kf = np.array([[x, 0.0, -3.6 if x < 10 else 0.0] for x in range(20)], dtype=float)
    est_levels = FloorLevels(np.array([-3.6, 0.0]), np.ones(20, bool))
    xyz = np.array([[1, 2, -3.0], [2, 2, -0.5], [3, 2, 1.0], [4, 2, 0.2]], dtype=float)
    floor = np.array([0, 0, 1, 0])  # the last one is wrong (it is on the deck)
    cloud = SemanticCloud.build(xyz, np.full(4, 6), floor, np.arange(4), np.full(4, 3),
                                labels.colors)
    shift = Similarity(1.0, np.eye(3), np.array([0.0, 0.0, 3.6]))
    out = floor_accuracy(cloud, shift, est_levels, kf, np.array([0.0, 3.6]))
    assert out['est_to_gt'] == [0, 1]
    assert out['accuracy'] == pytest.approx(0.75)
    assert out['confusion'] == [[2, 0], [1, 1]]
    empty = floor_accuracy(SemanticCloud.empty(), shift, est_levels, kf, np.array([0.0, 3.6]))
    assert empty['accuracy'] is None


def test_timing_stats() -> None:
    assert timing_stats([])['median'] is None
    s = timing_stats([1.0, 2.0, 3.0, 100.0])
    assert s['n'] == 4 and s['median'] == 2.5 and s['max'] == 100.0


def test_confined_paths(tmp_path: Path) -> None:
    out = prepare_out_dir(tmp_path / 'out')
    assert confined(out, 'cloud.ply') == out / 'cloud.ply'
    assert confined(out, 'images/1.jpg') == out / 'images' / '1.jpg'
    for bad in ('../x', '/etc/passwd', 'a/../../x', ''):
        with pytest.raises(OutputPathError):
            confined(out, bad)
    outside = tmp_path / 'outside.txt'
    outside.write_text('keep')
    (out / 'link.ply').symlink_to(outside)
    with pytest.raises(OutputPathError, match='outside the output directory'):
        confined(out, 'link.ply')
    (tmp_path / 'file').write_text('x')
    with pytest.raises(OutputPathError, match='not a directory'):
        prepare_out_dir(tmp_path / 'file')


def test_node_config_checks(tmp_path: Path) -> None:
    from semfeat_ros.nodes.feature_node import FeatureNodeConfig

    def write(params: str) -> Path:
        p = tmp_path / 'f.yaml'
        p.write_text(f'feature_node:\n  ros__parameters:\n{params}')
        return p

    c = node_config(FeatureNodeConfig, read_node_params(write('    max_keypoints: 500\n'),
                                                        'feature_node'), 'f.yaml')
    assert c.max_keypoints == 500 and c.resize_max == 640
    for params, match in (('    nope: 1\n', 'unknown parameter'),
                          ('    max_keypoints: many\n', 'must be of type int'),
                          ('    max_keypoints: 1\n', r'must be in \[16'),
                          ('    mask_resolution: huge\n', 'must be one of')):
        with pytest.raises(OfflineConfigError, match=match):
            node_config(FeatureNodeConfig, read_node_params(write(params), 'feature_node'),
                        'f.yaml')
    with pytest.raises(OfflineConfigError, match='no "matcher_node'):
        read_node_params(write('    max_keypoints: 500\n'), 'matcher_node')
    with pytest.raises(OfflineConfigError, match='does not exist'):
        read_node_params(tmp_path / 'missing.yaml', 'feature_node')
    assert parse_overrides(['a=[1, 2]', 'b=true', 'c=0.5']) == {'a': [1, 2], 'b': True,
                                                                'c': 0.5}
    with pytest.raises(OfflineConfigError, match='KEY=VALUE'):
        parse_overrides(['novalue'])


def textured(h: int = 256, w: int = 320, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = (rng.random((h // 8, w // 8)) * 255).astype(np.uint8)
    return np.kron(img, np.ones((8, 8), np.uint8))


@pytest.mark.parametrize('kind', ['orb', 'sift'])
def test_opencv_frontend(kind: str) -> None:
    camera = load_camera_yaml()[0].scaled(320, 256)
    image = textured()
    labels = np.full(image.shape, 6, np.uint8)
    labels[:, :100] = 17  # car: dropped
    labels[:, 100:140] = 255  # no class: dropped
    fe = OpenCVFrontend(kind, max_features=300)
    out = fe.process(np.repeat(image[:, :, None], 3, axis=2), camera, labels)
    assert 20 < len(out) <= 300
    assert (out.keypoints[:, 0] >= 139.5).all() and (out.labels == 6).all()
    valid = camera.valid_mask()
    u, v = np.rint(out.keypoints).astype(int).T
    assert valid[v, u].all()  # inside the image circle
    if kind == 'orb':
        assert out.descriptors.dtype == np.uint8 and out.descriptors.shape[1] == 32
    else:
        assert out.descriptors.dtype == np.float32 and out.descriptors.shape[1] == 128
        np.testing.assert_allclose(np.linalg.norm(out.descriptors, axis=1), 1.0, atol=1e-5)
    unlabeled = fe.process(image, camera, None)
    assert (unlabeled.labels == load_labels().id_of('wall')).all()
    frame = matcher_frame(123, out, camera, 'cam')
    assert frame.descriptors.dtype == out.descriptors.dtype
    assert frame.keypoints.dtype == np.float32 and frame.bearings.shape == (len(out), 3)
    with pytest.raises(OfflineConfigError, match='frontend'):
        OpenCVFrontend('surf')


def test_surface_errors_against_a_rendered_wall() -> None:
    from semfeat_ros.camera import FisheyeCamera

    cam = FisheyeCamera(64, 48, 20.0, 20.0, 31.5, 23.5, fov_deg=190)
    vv, uu = np.mgrid[0:48, 0:64]
    rays = cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1).astype(float), check=False)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    with np.errstate(divide='ignore', invalid='ignore'):
        rng = np.where(rays[:, 2] > 0.05, 5.0 / rays[:, 2], np.inf)  # wall at z = 5 m
    T = np.eye(4)
    T[:3, 3] = [10.0, 0.0, 0.0]  # the camera stands at x = 10 m in the map
    view = DepthView(rng.reshape(48, 64).astype(np.float32), T, cam)
    on_wall = np.array([[10.0, 0.0, 5.0], [11.0, 0.5, 5.0]])
    behind = np.array([[10.0, 0.0, 6.0]])  # 1 m behind the wall, straight ahead
    unseen = np.array([[10.0, 0.0, -5.0]])  # behind the camera: no range there
    err = surface_errors(np.vstack([on_wall, behind, unseen]), [view])
    assert err[0] < 0.05 and err[1] < 0.3 and abs(err[2] - 1.0) < 0.05 and np.isnan(err[3])
    # the best of several views counts; no view: NaN
    assert np.isnan(surface_errors(on_wall, [])).all()
    cloud = SemanticCloud.build(np.vstack([on_wall, behind, unseen]), np.zeros(4, np.uint8),
                                np.zeros(4, np.uint8), np.arange(4, dtype=np.uint32),
                                np.full(4, 3), load_labels().colors)
    acc = surface_accuracy(cloud, Similarity(1.0, np.eye(3), np.zeros(3)), [view, view])
    assert acc['n_seen'] == 3 and acc['on_surface'] == pytest.approx(2 / 3)


def _wall_view(cam, x_cam: float, stamp: int, z_wall: float = 5.0) -> DepthView:
    """Range image of a wall at z = ``z_wall`` m seen by a camera at (x_cam, 0, 0) looking +z;
    left of x = 10.5 m a post stands 2 m in front of the wall (an occluding edge)."""
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    rays = cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1).astype(float), check=False)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    with np.errstate(divide='ignore', invalid='ignore'):
        t_wall = np.where(rays[:, 2] > 0.05, z_wall / rays[:, 2], np.inf)
        t_post = np.where(rays[:, 2] > 0.05, (z_wall - 2.0) / rays[:, 2], np.inf)
    post = (x_cam + t_post * rays[:, 0]) < 10.5
    rng = np.where(post, t_post, t_wall)
    T = np.eye(4)
    T[:3, 3] = [x_cam, 0.0, 0.0]
    return DepthView(rng.reshape(cam.height, cam.width).astype(np.float32), T, cam, stamp)


def test_anchor_points_march_the_pixel_ray_through_the_nearest_range_image() -> None:
    from semfeat_ros.camera import FisheyeCamera

    cam = FisheyeCamera(64, 48, 20.0, 20.0, 31.5, 23.5, fov_deg=190)
    t0 = 1_700_000_000_000_000_000
    stamps_gt = t0 + np.arange(3, dtype=np.int64) * 100_000_000
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [11.0, 11.5, 12.0]  # base = camera frame here; moving along +x
    views = [_wall_view(cam, 11.0, int(stamps_gt[0])), _wall_view(cam, 12.0, int(stamps_gt[2]))]
    wall_pts = np.array([[11.0, 0.0, 5.0], [12.5, 1.0, 5.0], [13.0, -1.0, 5.0]])

    def pixels(x_cam: float, pts: np.ndarray) -> np.ndarray:
        return cam.project(pts - [x_cam, 0.0, 0.0])[0]

    # the frame of the anchor has a range image: the rendered range at the pixel
    got = anchor_points(np.full(3, stamps_gt[0]), pixels(11.0, wall_pts), cam,
                        (stamps_gt, poses), np.eye(4), views)
    assert np.allclose(got, wall_pts, atol=0.15)
    # a frame without one: its ray is marched through the nearest range image
    got = anchor_points(np.full(3, stamps_gt[1]), pixels(11.5, wall_pts), cam,
                        (stamps_gt, poses), np.eye(4), views)
    assert np.allclose(got, wall_pts, atol=0.15)
    # seen from x = 12 m, hidden behind the post from x = 11 m: with only that range image the
    # ray passes behind the post at its edge (a range jump), and no surface is invented
    hidden = np.array([[10.0, 0.0, 5.0]])
    got = anchor_points(np.array([stamps_gt[2]]), pixels(12.0, hidden), cam,
                        (stamps_gt, poses), np.eye(4), views[:1])
    assert np.isnan(got).all()
    got = anchor_points(np.array([stamps_gt[2]]), pixels(12.0, hidden), cam,
                        (stamps_gt, poses), np.eye(4), views)
    assert np.allclose(got, hidden, atol=0.15)
    # no ground-truth pose, no range image in time, sky, unknown anchor: NaN
    far = stamps_gt[-1] + 10 * 10**9
    sky = cam.project(np.array([[0.0, -1.0, -0.02]]))[0]  # 91 deg off-axis: nothing there
    got = anchor_points(np.array([far, stamps_gt[0], -1]),
                        np.vstack([pixels(11.0, wall_pts[:1]), sky, [np.nan, np.nan]]), cam,
                        (stamps_gt, poses), np.eye(4), views)
    assert np.isnan(got).all()
    assert np.isnan(anchor_points(np.full(3, stamps_gt[0]), pixels(11.0, wall_pts), cam,
                                  (stamps_gt, poses), np.eye(4), [])).all()


def test_floor_accuracy_and_point_errors_against_true_positions() -> None:
    labels = load_labels()
    kf = np.array([[x, 0.0, -3.6 if x < 10 else 0.0] for x in range(20)], dtype=float)
    est_levels = FloorLevels(np.array([-3.6, 0.0]), np.ones(20, bool))
    shift = Similarity(1.0, np.eye(3), np.array([0.0, 0.0, 3.6]))
    # a ceiling point of the lower storey (3.3 m), estimated 0.2 m too high: the aligned
    # estimate puts it on the deck, its true position under the slab
    xyz = np.array([[1, 2, -0.1], [2, 2, -0.1], [3, 2, 1.0]], dtype=float)
    truth = np.array([[1, 2, 3.3], [2, 2, 3.6], [np.nan] * 3])
    cloud = SemanticCloud.build(xyz, np.full(3, 8), np.array([0, 1, 1]), np.arange(3),
                                np.full(3, 3), labels.colors)
    aligned = floor_accuracy(cloud, shift, est_levels, kf, np.array([0.0, 3.6]))
    true = floor_accuracy(cloud, shift, est_levels, kf, np.array([0.0, 3.6]), truth_xyz=truth)
    assert aligned['accuracy'] == pytest.approx(2 / 3) and aligned['n_scored'] == 3
    assert true['accuracy'] == 1.0 and true['n_scored'] == 2  # the NaN row is not scored
    assert true['confusion'] == [[1, 0], [0, 1]]
    err = point_errors(cloud, shift, truth)
    assert err['n_scored'] == 2 and err['median_m'] == pytest.approx(0.15)
    assert err['within_tolerance'] == 1.0
    none = point_errors(cloud, shift, np.full((3, 3), np.nan))
    assert none['n_scored'] == 0 and none['median_m'] is None


def test_map_tool_keypoint_noise_per_front_end() -> None:
    from semfeat_ros.nodes.mapping_node import MappingNodeConfig
    from semfeat_ros.tools.map import OPENCV_BEARING_SIGMA_PX, MapToolConfig, build_map_config

    net, _ = build_map_config(MapToolConfig(frontend='semfeat'))
    assert net.mapper_conf['bearing_sigma_px'] == MappingNodeConfig().bearing_sigma_px
    orb, notes = build_map_config(MapToolConfig(frontend='orb'))
    assert orb.mapper_conf['bearing_sigma_px'] == OPENCV_BEARING_SIGMA_PX
    assert any('bearing_sigma_px' in n for n in notes)
    mine, _ = build_map_config(MapToolConfig(frontend='sift',
                                             overrides={'bearing_sigma_px': 1.7}))
    assert mine.mapper_conf['bearing_sigma_px'] == 1.7
