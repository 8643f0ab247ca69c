"""Mapping core without the smoother: geometry, floors, files, alignment, config, inputs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semfeat_ros.mapping import (
    AlignmentError,
    GnssFix,
    MapperConfigError,
    MapperInputError,
    OdometryDelta,
    PlyFormatError,
    SemanticCloud,
    Tracks,
    TumFormatError,
    align_umeyama,
    ate_rmse,
    default_conf,
    detect_floors,
    merge_conf,
    read_ply,
    read_tum,
    write_ply,
    write_tum,
)
from semfeat_ros.mapping import geometry as geo
from semfeat_ros.mapping.cloud import VoxelMap
from semfeat_ros.mapping.errors import MapWriteError
from semfeat_ros.mapping.factors import ground_error
from semfeat_ros.mapping.io import save_map
from semfeat_ros.rotations import (
    matrix_to_quaternion,
    quaternion_to_matrix,
    rpy_to_matrix,
    so3_exp,
    so3_log,
)


def random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return geo.se3_exp(rng.normal(size=6) * scale)


# ------------------------------------------------------------------------------------------------
# geometry
# ------------------------------------------------------------------------------------------------


def test_se3_exp_log_roundtrip_and_adjoint() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        xi = rng.normal(size=6)
        xi[:3] *= 0.9  # keep the rotation angle below pi
        T = geo.se3_exp(xi)
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.allclose(geo.se3_log(T), xi, atol=1e-9)
        # adjoint: T exp(xi) = exp(Ad xi) T
        d = rng.normal(size=6) * 1e-3
        assert np.allclose(T @ geo.se3_exp(d), geo.se3_exp(geo.adjoint(T) @ d) @ T, atol=1e-12)
    R = so3_exp(np.array([0.0, 0.0, np.pi - 1e-7]))
    assert np.allclose(so3_exp(so3_log(R)), R, atol=1e-6)


def test_quaternion_roundtrip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        R = so3_exp(rng.normal(size=3) * 2)
        q = matrix_to_quaternion(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        assert np.allclose(quaternion_to_matrix(q), R, atol=1e-12)


def test_triangulation_rays_from_behind_the_camera() -> None:
    rng = np.random.default_rng(2)
    P = rng.uniform(-8, 8, (40, 3))
    poses = [random_pose(rng, 0.5) for _ in range(3)]
    idx, centers, rays = [], [], []
    for T in poses:
        for j, p in enumerate(P):
            idx.append(j)
            centers.append(T[:3, 3])
            rays.append(geo.unit(p - T[:3, 3]))
    tri = geo.triangulate_bearings(np.array(idx), np.array(centers), np.array(rays), len(P))
    assert tri.ok.all()
    assert np.allclose(tri.points, P, atol=1e-9)
    assert (tri.depth > 0).all() and (tri.error < 1e-9).all()
    # with a single ray a point is not triangulated
    one = geo.triangulate_bearings(np.array([0]), np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), 1)
    assert not one.ok[0]


def test_pose_refinement_full_sphere_with_outliers() -> None:
    rng = np.random.default_rng(3)
    T_true = random_pose(rng, 0.3)
    P = rng.uniform(-10, 10, (150, 3))
    b = geo.unit((P - T_true[:3, 3]) @ T_true[:3, :3])
    assert (b[:, 2] < 0).sum() > 40  # many points behind the optical axis plane
    b = geo.unit(b + rng.normal(0, 1e-3, b.shape))
    b[:20] = geo.unit(rng.normal(size=(20, 3)))  # gross outliers
    est = geo.refine_pose_bearings(T_true @ geo.se3_exp(rng.normal(size=6) * 0.05), P, b,
                                 sigma=1e-3)
    err = geo.se3_log(geo.se3_inv(T_true) @ est.T_w_c)
    assert np.linalg.norm(err[:3]) < 1e-3 and np.linalg.norm(err[3:]) < 5e-3
    assert est.inliers[20:].mean() > 0.95 and est.inliers[:20].sum() <= 2
    assert est.covariance is not None and np.all(np.linalg.eigvalsh(est.covariance) > 0)


def test_two_view_points_for_a_known_motion_beyond_90_degrees() -> None:
    rng = np.random.default_rng(4)
    X = rng.uniform(-10, 10, (200, 3))  # all around the camera: half of it beyond 90 degrees
    R = so3_exp(np.array([0.02, 0.3, -0.05]))
    t = np.array([0.2, 0.05, 1.0])
    b1 = geo.unit(X)
    b2 = geo.unit(X @ R.T + t)
    b2[:20] = geo.unit(rng.normal(size=(20, 3)))
    rp = geo.relative_pose_known_motion(R, 3.0 * t, b1, b2, 2e-3)
    assert np.allclose(rp.t, t / np.linalg.norm(t))
    assert rp.inliers[20:].mean() > 0.95 and rp.inliers[:20].sum() <= 2
    # unit-baseline points: times the baseline they are the true points
    ok = rp.inliers
    np.testing.assert_allclose(rp.points[ok] * np.linalg.norm(t), X[ok], atol=1e-6)
    assert (X[ok][:, 2] < 0).any()  # points behind the image plane are kept
    with pytest.raises(ValueError):
        geo.relative_pose_known_motion(R, np.zeros(3), b1, b2, 2e-3)


def test_plane_fit_and_yaw_alignment() -> None:
    rng = np.random.default_rng(5)
    P = np.c_[rng.uniform(-5, 5, (100, 2)), np.full(100, -0.75)]
    P[:10, 2] += rng.uniform(0.3, 1.0, 10)
    n, d, inl = geo.fit_plane_ransac(P, 0.02, rng)
    assert abs(abs(n[2]) - 1) < 1e-9 and abs(abs(d) - 0.75) < 1e-9
    assert inl[10:].all() and not inl[:10].any()
    src = rng.normal(size=(30, 3)) * 10
    R = rpy_to_matrix(0.0, 0.0, 1.1)
    dst = 1.5 * src @ R.T + [3.0, -2.0, 1.0]
    s, Rz, t = geo.align_yaw(src, dst, True)
    assert abs(s - 1.5) < 1e-12 and np.allclose(Rz, R) and np.allclose(t, [3.0, -2.0, 1.0])


def test_ground_factor_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(6)
    T, p = random_pose(rng), rng.normal(size=3) * 3
    up = geo.unit(rng.normal(size=3))
    e0, H_pose, H_point = ground_error(T, p, up, 0.75)
    h = 1e-7
    num_pose = [(ground_error(T @ geo.se3_exp(np.eye(6)[i] * h), p, up, 0.75)[0] - e0) / h
                for i in range(6)]
    num_point = [(ground_error(T, p + np.eye(3)[i] * h, up, 0.75)[0] - e0) / h
                 for i in range(3)]
    assert np.allclose(H_pose[0], num_pose, atol=1e-5)
    assert np.allclose(H_point[0], num_point, atol=1e-5)


# ------------------------------------------------------------------------------------------------
# evaluation
# ------------------------------------------------------------------------------------------------


def test_umeyama_exact_on_synthetic_sim3() -> None:
    rng = np.random.default_rng(7)
    est = rng.normal(size=(50, 3)) * 5
    R = so3_exp(np.array([0.3, -1.2, 2.0]))
    gt = 2.5 * est @ R.T + np.array([10.0, -4.0, 3.0])
    sim = align_umeyama(est, gt, with_scale=True)
    assert abs(sim.s - 2.5) < 1e-12 and np.allclose(sim.R, R, atol=1e-12)
    assert np.allclose(sim.t, [10.0, -4.0, 3.0], atol=1e-10)
    assert ate_rmse(est, gt, with_scale=True) < 1e-10
    # SE(3) cannot absorb the scale; without alignment the error is the raw distance
    assert ate_rmse(est, gt, with_scale=False) > 1.0
    rigid = est @ R.T + 1.0  # a rigid motion is undone exactly by the SE(3) alignment
    assert ate_rmse(rigid, est, with_scale=False) < 1e-10
    assert align_umeyama(rigid, est, with_scale=False).s == 1.0
    assert ate_rmse(est, est + [0.0, 0.0, 0.3], align=False) == pytest.approx(0.3)
    poses = np.tile(np.eye(4), (50, 1, 1))
    poses[:, :3, 3] = est
    assert ate_rmse(poses, gt) < 1e-10
    with pytest.raises(AlignmentError, match='at least 3'):
        align_umeyama(est[:2], gt[:2])
    with pytest.raises(AlignmentError, match='identical'):
        align_umeyama(np.zeros((5, 3)), gt[:5])


# ------------------------------------------------------------------------------------------------
# floors
# ------------------------------------------------------------------------------------------------


def test_floor_detection_two_levels_and_revisit() -> None:
    s = np.arange(0, 120, 0.5)
    z = np.interp(s, [0, 30, 50, 80, 100, 120], [0, 0, 3, 3, 0, 0])
    P = np.c_[s, np.zeros_like(s), z]
    levels = detect_floors(P, min_plateau_m=8.0)
    assert np.allclose(levels.altitudes, [0.0, 3.0], atol=0.05)
    assert list(levels.assign(np.array([0.1, 2.8, 1.4, -0.5]))) == [0, 1, 0, 0]
    assert levels.flat[:50].all() and not levels.flat[(s > 33) & (s < 47)].any()
    single = detect_floors(np.c_[s, s * 0, s * 0.2])  # all ramp: one level
    assert len(single.altitudes) == 1
    assert len(detect_floors(np.zeros((0, 3))).altitudes) == 0


# ------------------------------------------------------------------------------------------------
# files
# ------------------------------------------------------------------------------------------------


def make_cloud(n: int = 25) -> SemanticCloud:
    rng = np.random.default_rng(8)
    colors = rng.integers(0, 255, (19, 3), dtype=np.uint8)
    return SemanticCloud.build(rng.normal(size=(n, 3)) * 10, rng.integers(0, 17, n),
                               rng.integers(0, 3, n), rng.integers(0, 2**32 - 1, n),
                               rng.integers(1, 70000, n), colors)


@pytest.mark.parametrize('binary', [True, False])
def test_ply_roundtrip(tmp_path, binary: bool) -> None:
    cloud = make_cloud()
    path = write_ply(tmp_path / 'map.ply', cloud, binary=binary)
    header = path.read_bytes()[:600].decode('ascii', errors='replace')
    for prop in ('x', 'y', 'z', 'red', 'green', 'blue', 'label', 'floor', 'landmark_id', 'n_obs'):
        assert f' {prop}\n' in header
    back = read_ply(path)
    assert np.allclose(back.xyz, cloud.xyz, atol=1e-5)
    for name in ('label', 'floor', 'landmark_id', 'n_obs', 'rgb'):
        assert np.array_equal(getattr(back, name), getattr(cloud, name)), name
    assert back.n_obs.max() == 65535  # clipped to uint16 on build
    empty = read_ply(write_ply(tmp_path / 'empty.ply', SemanticCloud.empty(), binary=binary))
    assert len(empty) == 0


def test_ply_errors(tmp_path) -> None:
    with pytest.raises(FileNotFoundError):
        read_ply(tmp_path / 'missing.ply')
    bad = tmp_path / 'bad.ply'
    bad.write_bytes(b'not a ply')
    with pytest.raises(PlyFormatError, match='not a PLY'):
        read_ply(bad)
    path = write_ply(tmp_path / 'map.ply', make_cloud())
    bad.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(PlyFormatError, match='truncated'):
        read_ply(bad)
    bad.write_bytes(b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n')
    with pytest.raises(PlyFormatError, match='missing vertex properties'):
        read_ply(bad)


def test_tum_roundtrip(tmp_path) -> None:
    rng = np.random.default_rng(9)
    poses = np.array([random_pose(rng, 2.0) for _ in range(10)])
    stamps = 1_700_000_000_123_456_789 + np.arange(10) * 33_333_333
    back_stamps, back = read_tum(write_tum(tmp_path / 'traj.txt', stamps, poses))
    assert np.array_equal(back_stamps, stamps)
    assert np.allclose(back, poses, atol=1e-9)
    with pytest.raises(TumFormatError, match='stamps but'):
        write_tum(tmp_path / 'x.txt', stamps[:3], poses)
    bad = tmp_path / 'bad.txt'
    bad.write_text('1.0 2 3\n')
    with pytest.raises(TumFormatError, match='8 columns'):
        read_tum(bad)
    bad.write_text('1.0 2 3 4 a 0 0 1\n')
    with pytest.raises(TumFormatError, match='non-numeric'):
        read_tum(bad)


def test_voxel_map_bounds_points_and_keeps_floors_apart() -> None:
    vm = VoxelMap(voxel_size=0.5, max_points=100)
    vm.insert(np.array([0.1, 0.1, 0.1]), 0, 1, 3, 0.0, 0)
    vm.insert(np.array([0.2, 0.2, 0.2]), 0, 2, 5, 0.0, 0)  # same voxel: more observations win
    vm.insert(np.array([0.2, 0.2, 0.2]), 0, 3, 2, 3.0, 1)  # another floor: kept apart
    xyz, label, lid, nobs, alt = vm.arrays()
    assert sorted(lid.tolist()) == [2, 3] and len(vm) == 2
    for i in range(300):
        vm.insert(np.array([i, 0.0, 0.0]), 1, 100 + i, 3, 0.0, 0)
    assert len(vm) == 100
    assert vm.arrays()[2].min() >= 300  # the oldest voxels went first


def test_voxel_map_keeps_each_points_anchor_observation() -> None:
    vm = VoxelMap(voxel_size=0.5, max_points=100)
    vm.insert(np.array([0.1, 0.1, 0.1]), 0, 1, 3, 0.0, 0, (1000, 10.0, 20.0))
    vm.insert(np.array([0.2, 0.2, 0.2]), 0, 2, 5, 0.0, 0, (2000, 30.0, 40.0))  # replaces it
    vm.insert(np.array([5.0, 0.0, 0.0]), 0, 3, 3, 0.0, 0)  # no anchor known
    for i in range(2000):  # grow the arrays past their first capacity
        vm.insert(np.array([10.0 + i, 0.0, 0.0]), 1, 100 + i, 3, 0.0, 0, (i, 1.0, 2.0))
    vm.transform(2.0, np.eye(3), np.zeros(3), lambda xyz, alt, label: 0)
    lid = vm.arrays()[2]
    stamps, px = vm.anchors()
    assert len(stamps) == len(lid) == len(px) == 100
    vm2 = VoxelMap(voxel_size=0.5, max_points=10)
    vm2.insert(np.array([0.1, 0.1, 0.1]), 0, 1, 3, 0.0, 0, (1000, 10.0, 20.0))
    vm2.insert(np.array([0.2, 0.2, 0.2]), 0, 2, 5, 0.0, 0, (2000, 30.0, 40.0))
    vm2.insert(np.array([5.0, 0.0, 0.0]), 0, 3, 3, 0.0, 0)
    vm2.transform(2.0, np.eye(3), np.zeros(3), lambda xyz, alt, label: 0)  # moves, keeps anchors
    by_lid = dict(zip(vm2.arrays()[2].tolist(), zip(*vm2.anchors())))
    assert by_lid[2][0] == 2000 and by_lid[2][1].tolist() == [30.0, 40.0]
    assert by_lid[3][0] == -1 and np.isnan(by_lid[3][1]).all()
    assert sorted(by_lid) == [2, 3]
    assert all(s == r - 100 for r, (s, _) in zip(lid.tolist(), zip(stamps, px)))


# ------------------------------------------------------------------------------------------------
# config and inputs
# ------------------------------------------------------------------------------------------------


def test_default_conf_is_valid_and_validated() -> None:
    conf = merge_conf()
    assert conf == default_conf and conf is not default_conf
    with pytest.raises(MapperConfigError, match='unknown mapping config key'):
        merge_conf({'no_such_key': 1})
    with pytest.raises(MapperConfigError, match='robust_kernel'):
        merge_conf({'robust_kernel': 'tukey'})
    with pytest.raises(MapperConfigError, match='window_keyframes'):
        merge_conf({'window_keyframes': 0})
    with pytest.raises(MapperConfigError, match='ground_labels'):
        merge_conf({'ground_labels': 'road'})
    with pytest.raises(MapperConfigError, match='ceiling_labels'):
        merge_conf({'ceiling_labels': [3]})
    with pytest.raises(MapperConfigError, match='lm_max_depth_m'):
        merge_conf({'lm_min_depth_m': 50.0})
    with pytest.raises(MapperConfigError, match='lm_lost_depth_m'):
        merge_conf({'lm_lost_depth_m': 30.0})
    for key, bad in (('kf_min_distance_m', True),
                     ('odom_calib_sigma_rad', 0.0), ('odom_calibration', 'yes'),
                     ('odom_calib_min_pairs', 0)):
        with pytest.raises(MapperConfigError, match=key):
            merge_conf({key: bad})


def test_tracks_validation() -> None:
    b = geo.unit(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, -0.2], [np.nan, 0.0, 1.0]]))
    tr = Tracks(5, np.array([3, 4, 5], np.uint32), b * 2.0, np.zeros((3, 2)),
                np.array([0, 6, 7], np.uint8))
    ok, dropped = tr.validated()
    assert dropped == 1 and len(ok) == 2
    assert np.allclose(np.linalg.norm(ok.bearing, axis=1), 1.0)
    with pytest.raises(MapperInputError, match='duplicate'):
        Tracks(5, np.array([1, 1]), b[:2], np.zeros((2, 2)), np.zeros(2)).validated()
    with pytest.raises(MapperInputError, match=r'bearing: expected shape \(2, 3\)'):
        Tracks(5, np.array([1, 2]), b[:2, :2], np.zeros((2, 2)), np.zeros(2)).validated()
    with pytest.raises(MapperInputError, match='stamp_ns'):
        Tracks(5.5, np.array([1]), b[:1], np.zeros((1, 2)), np.zeros(1)).validated()
    arr = np.zeros(2, dtype=[('u', 'f4'), ('v', 'f4'), ('bx', 'f4'), ('by', 'f4'), ('bz', 'f4'),
                             ('label', 'u1'), ('track_id', 'u4')])
    arr['bz'], arr['track_id'] = 1.0, [7, 8]
    assert Tracks.from_structured(arr, 9).validated()[0].track_id.tolist() == [7, 8]


def test_odometry_validation() -> None:
    d = OdometryDelta.from_se2(1.0, 0.1, 0.05, np.diag([1e-4, 1e-4, 1e-5]))
    assert np.allclose(d.T[:3, 3], [1.0, 0.1, 0.0]) and np.isclose(d.covariance[2, 2], 1e-5)
    assert np.isclose(d.covariance[3, 3], 1e-4) and d.covariance[5, 5] > 0
    with pytest.raises(MapperInputError, match='positive definite'):
        OdometryDelta.from_se2(1.0, 0.0, 0.0, np.zeros((3, 3)))
    with pytest.raises(MapperInputError, match='orthonormal'):
        OdometryDelta(np.diag([2.0, 1.0, 1.0, 1.0]), np.eye(6)).validated()
    assert GnssFix(1, np.zeros(3), None).covariance is None


def test_session_odometry_leaves_roll_and_pitch_to_the_ramp() -> None:
    from semfeat_ros.camera import Extrinsic, FisheyeCamera
    from semfeat_ros.mapping.session import MappingSession, SessionConfig

    cam = FisheyeCamera(640, 512, 186.7, 186.7, 320, 256, fov_deg=190)
    conf = SessionConfig(odom_sigma_rad_per_m=0.002, odom_sigma_tilt_rad_per_m=0.02)
    s = MappingSession(cam, Extrinsic((1.0, 0.0, 1.0), (0.0, 0.0, 0.0)).T_base_cam, None, conf)
    T = np.eye(4)
    T[0, 3] = 2.0  # 2 m straight ahead
    assert s._delta(np.eye(4)) is None
    d = s._delta(T)
    sig = np.sqrt(np.diag(d.covariance))  # (roll, pitch, yaw, x, y, z)
    np.testing.assert_allclose(sig[:3], [0.04, 0.04, 0.004])
    np.testing.assert_allclose(sig[3:], [0.04] * 3)


def test_vehicle_camera_translation_on_an_arc() -> None:
    # the base drives 2 m along a circle of radius 10 m (constant curvature), the camera sits
    # 3.7 m ahead of it and 0.75 m up: its translation comes from the arc and the lever arm
    from semfeat_ros.camera import Extrinsic

    T_bc = Extrinsic((3.7, 0.0, 0.75), (0.0, 0.12, 0.0)).T_base_cam
    radius, dist = 10.0, 2.0
    th = dist / radius
    T_wb_a = np.eye(4)
    T_wb_b = np.eye(4)
    T_wb_b[:3, :3] = rpy_to_matrix(0.0, 0.0, th)
    T_wb_b[:3, 3] = [radius * np.sin(th), radius * (1.0 - np.cos(th)), 0.0]
    T_wc_a, T_wc_b = T_wb_a @ T_bc, T_wb_b @ T_bc
    R = T_wc_b[:3, :3].T @ T_wc_a[:3, :3]  # x_b = R x_a + t
    t = T_wc_b[:3, :3].T @ (T_wc_a[:3, 3] - T_wc_b[:3, 3])
    chord = 2.0 * radius * np.sin(th / 2.0)
    assert np.allclose(geo.vehicle_camera_translation(R, T_bc, chord), t, atol=1e-9)
    # straight ahead, no rotation: the camera moves as the base, along the base's x axis
    t0 = geo.vehicle_camera_translation(np.eye(3), T_bc, 1.0)
    assert np.allclose(T_bc[:3, :3] @ -t0, [1.0, 0.0, 0.0])


class _RecordingMapper:
    """Stands in for the Mapper: records what the session hands it per frame."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, object, object]] = []

    def update(self, tracks, odometry=None, gnss=None):
        self.calls.append((tracks.stamp_ns, odometry, gnss))
        return tracks.stamp_ns


def _session():
    from semfeat_ros.camera import Extrinsic, FisheyeCamera
    from semfeat_ros.mapping.session import MappingSession

    cam = FisheyeCamera(640, 512, 186.7, 186.7, 320, 256, fov_deg=190)
    s = MappingSession(cam, Extrinsic((1.0, 0.0, 1.0), (0.0, 0.0, 0.0)).T_base_cam)
    s.mapper = _RecordingMapper()
    return s


def _frame(stamp_ns: int) -> Tracks:
    return Tracks(stamp_ns, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 2)),
                  np.zeros(0, np.uint8))


MS = 1_000_000  # ns


def test_session_attaches_gnss_by_stamp_even_when_fixes_arrive_first() -> None:
    # live, frames reach the mapper 0.1-0.5 s late: fixes stamped after a frame are already in
    # (the demo bag: fixes at 5 Hz on every other 10 Hz frame)
    s = _session()
    for k in range(6):  # fixes at 0, 200, ..., 1000 ms, all before any frame is processed
        s.add_gnss(k * 200 * MS, (48.0 + 1e-5 * k, 11.0, 500.0), np.eye(3) * 1e-4)
    for t in (0, 100, 200, 300, 500, 700):  # frames 400 and 600 were dropped upstream
        s.process(_frame(t * MS))
    got = {stamp // MS: None if fix is None else fix.stamp_ns // MS
           for stamp, _, fix in s.mapper.calls}
    # each frame gets the newest fix at or before it (at most gnss_max_dt_s = 150 ms older),
    # never a newer one: 300 gets none (200 went to frame 200), 500 takes 400's fix
    assert got == {0: 0, 100: None, 200: 200, 300: None, 500: 400, 700: 600}
    s.add_gnss(600 * MS, (48.0, 11.0, 500.0), None)  # a repeated stamp is ignored
    s.add_gnss(100 * MS, (48.0, 11.0, 500.0), None)  # time went backwards: buffer restarts
    s.process(_frame(1100 * MS))
    assert s.mapper.calls[-1][2] is None  # 1000 was dropped with the restart; 100 is too old


def test_frame_feeder_waits_for_the_odometry_after_a_frame() -> None:
    from semfeat_ros.mapping.session import FrameFeeder

    s = _session()
    feeder = FrameFeeder(s, wait_s=0.5)
    feeder.push(_frame(0), 'a')  # no odometry seen yet: frames pass at once
    assert [f.tag for f in feeder.release(0)] == ['a']
    move = np.eye(4)
    for t in (0, 20, 40, 60, 80, 100):
        move[0, 3] = t * 1e-3
        feeder.add_odometry(t * MS, move.copy())
    feeder.push(_frame(100 * MS), 'b')
    feeder.push(_frame(200 * MS), 'c')  # its odometry is late
    fed = feeder.release(200 * MS)
    assert [f.tag for f in fed] == ['b'] and len(feeder.pending) == 1
    for t in (120, 140, 160, 180, 200):
        move[0, 3] = t * 1e-3
        feeder.add_odometry(t * MS, move.copy())
    fed = feeder.release(200 * MS)
    assert [f.tag for f in fed] == ['c']
    odom = s.mapper.calls[-1][1]
    np.testing.assert_allclose(odom.T[0, 3], 0.1)  # 100 -> 200 ms of motion, none missing
    assert s.odometry_missing == {'ahead': 0, 'gap': 0, 'behind': 0}
    # odometry stalls: a frame waits at most wait_s of stream time, then goes without it
    feeder.push(_frame(300 * MS), 'd')
    assert feeder.release(700 * MS) == []
    assert [f.tag for f in feeder.release(800 * MS)] == ['d']
    assert s.odometry_missing['ahead'] == 1 and s.mapper.calls[-1][1] is None
    feeder.push(_frame(900 * MS), 'e')
    assert [f.tag for f in feeder.release(None)] == ['e']  # flush (end of bag, save_map)
    for k in range(4):
        feeder.push(_frame((1000 + k) * MS), k)
    assert feeder.trim(2) == 2 and [tag for _, tag in feeder.pending] == [2, 3]  # oldest go
    feeder.reset()
    assert feeder.release(None) == []
    # the odometry restarts earlier (a bag loops): frames wait for the new stream again
    feeder.add_odometry(5000 * MS, move.copy())
    feeder.add_odometry(100 * MS, move.copy())
    feeder.push(_frame(300 * MS), 'f')
    assert feeder.release(300 * MS) == [] and len(feeder.pending) == 1


def test_map_writers_refuse_symlinks(tmp_path) -> None:
    out, outside = tmp_path / 'out', tmp_path / 'outside'
    out.mkdir()
    outside.mkdir()
    victim = outside / 'victim.txt'
    victim.write_text('keep me')
    (out / 'cloud.ply').symlink_to(victim)
    (out / 'trajectory.tum').symlink_to(outside / 'created.tum')  # dangling
    with pytest.raises(MapWriteError, match='symlink'):
        write_ply(out / 'cloud.ply', make_cloud())
    with pytest.raises(MapWriteError, match='symlink'):
        write_tum(out / 'trajectory.tum', np.zeros(1, np.int64), np.eye(4)[None])
    with pytest.raises(MapWriteError, match='symlink'):
        save_map(out, make_cloud(), np.zeros(1, np.int64), np.eye(4)[None])
    assert victim.read_text() == 'keep me'
    assert sorted(p.name for p in outside.iterdir()) == ['victim.txt']
    assert sorted(p.name for p in out.iterdir()) == ['cloud.ply', 'trajectory.tum']  # no temps
    # a symlinked sub-directory is refused too
    (out / 'cloud.ply').unlink()
    (out / 'trajectory.tum').unlink()
    (out / 'before_reset').symlink_to(outside, target_is_directory=True)
    with pytest.raises(MapWriteError, match='before_reset'):
        save_map(out, make_cloud(), np.zeros(1, np.int64), np.eye(4)[None],
                 subdir='before_reset')
    assert sorted(p.name for p in outside.iterdir()) == ['victim.txt']
    with pytest.raises(MapWriteError, match='plain file name'):
        save_map(out, make_cloud(), np.zeros(1, np.int64), np.eye(4)[None], subdir='../x')


def test_save_map_writes_the_pair_as_a_unit(tmp_path) -> None:
    import hashlib
    import json

    out = tmp_path / 'map'
    rng = np.random.default_rng(3)
    poses = np.array([random_pose(rng, 2.0) for _ in range(4)])
    stamps = 10**9 + np.arange(4) * 10**8
    saved = save_map(out, make_cloud(), stamps, poses, stamp_ns=int(stamps[-1]))
    assert (saved.n_points, saved.n_poses) == (25, 4)
    manifest = json.loads((out / 'map.json').read_text())
    for name in ('cloud.ply', 'trajectory.tum'):
        assert manifest['files'][name]['sha256'] == hashlib.sha256(
            (out / name).read_bytes()).hexdigest()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # a failure half-way (the trajectory cannot be written) leaves the previous pair as it was
    with pytest.raises(TumFormatError):
        save_map(out, make_cloud(5), stamps[:2], poses)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    with pytest.raises(MapWriteError, match='absolute'):
        save_map(Path('relative'), make_cloud(), stamps, poses)
    assert len(read_ply(saved.cloud)) == 25 and len(read_tum(saved.trajectory)[0]) == 4


@pytest.fixture
def readonly_dir(tmp_path):
    """A directory nobody can write into: a read-only tmpfs when running as root (root ignores
    the mode bits), else mode 0555."""
    import os
    import subprocess

    d = tmp_path / 'ro'
    d.mkdir()
    if os.geteuid() != 0:
        d.chmod(0o555)
        yield d
        d.chmod(0o755)
        return
    if subprocess.run(['mount', '-t', 'tmpfs', '-o', 'ro,size=1m', 'tmpfs', str(d)],
                      capture_output=True).returncode != 0:
        pytest.skip('cannot make a read-only directory here (root without mount)')
    try:
        yield d
    finally:
        subprocess.run(['umount', str(d)], check=True)


def test_save_map_into_a_readonly_directory(readonly_dir) -> None:
    with pytest.raises(MapWriteError, match='cannot create a file for cloud.ply'):
        save_map(readonly_dir, make_cloud(), np.zeros(1, np.int64), np.eye(4)[None])
    with pytest.raises(MapWriteError):
        write_ply(readonly_dir / 'cloud.ply', make_cloud())
    assert list(readonly_dir.iterdir()) == []
