"""The drive (path, speed, ramp profile), the world layout and the GNSS / odometry models."""
from __future__ import annotations

import numpy as np
import pytest

from semfeat_ros.rotations import matrix_to_rpy
from semfeat_ros.sim.config import GarageConfig, load_config, random_config
from semfeat_ros.sim.errors import SimConfigError
from semfeat_ros.sim.geometry import camera_pose
from semfeat_ros.sim.sensors import (
    STATUS_FIX,
    STATUS_GBAS_FIX,
    STATUS_NO_FIX,
    GnssModel,
    WheelOdometry,
    enu_to_geodetic,
    geodetic_to_enu,
)
from semfeat_ros.sim.trajectory import Trajectory
from semfeat_ros.sim.world import build_world


@pytest.fixture(scope='module')
def world():
    return build_world(0)


@pytest.fixture(scope='module')
def drive(world):
    tr = Trajectory(world.layout)
    times = np.arange(0.0, tr.duration, 0.1)
    samples = [tr.sample(t) for t in times]
    return tr, times, samples


def test_drive_is_long_and_car_like(drive) -> None:
    tr, times, samples = drive
    assert tr.length >= 300.0
    v = np.array([s.speed for s in samples])
    assert v.max() <= 8.0 and v.min() >= 0.0
    moving = v > 0.05
    assert np.mean(v[moving] < 2.0) < 0.2  # below 2 m/s only while starting / stopping
    assert np.median(v[moving]) > 3.0
    stops = np.flatnonzero(~moving[1:-1]) + 1
    assert len(stops) >= 10  # it stops (1.5 s dwell before the ramp, at an intersection)
    yaw = np.unwrap([matrix_to_rpy(s.T_map_base[:3, :3])[2] for s in samples])
    w = np.diff(yaw) / 0.1
    assert np.abs(w).max() < 1.2  # rad/s
    assert np.abs(np.diff(w)).max() < 0.35  # smooth: no yaw-rate jumps at 10 Hz
    xy = np.array([s.T_map_base[:2, 3] for s in samples])
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert step.max() <= 8.0 * 0.1 + 1e-6


def test_ramp_profile_and_levels(world, drive) -> None:
    tr, times, samples = drive
    lay = world.layout
    cfg = world.config
    z = np.array([s.T_map_base[2, 3] for s in samples])
    x = np.array([s.T_map_base[0, 3] for s in samples])
    assert z[0] == pytest.approx(lay.deck_z) and z[-1] == pytest.approx(0.0)
    assert lay.deck_z - 0.0 >= 3.0  # at least 3 m of rise
    on_ramp = (x > lay.ramp_x0) & (x < lay.ramp_x1) & (z < lay.deck_z - 1e-6) & (z > 1e-6)
    assert on_ramp.sum() > 20
    np.testing.assert_allclose(z[on_ramp], lay.ramp_profile(x[on_ramp]), atol=1e-3)
    # grade of the main section from the ground-truth poses
    grade = -np.diff(z) / np.maximum(np.abs(np.diff(x)), 1e-9)
    main = on_ramp[1:] & on_ramp[:-1] & (np.abs(np.diff(x)) > 0.05)
    assert 0.10 <= np.max(grade[main]) <= 0.15
    assert np.max(grade[main]) == pytest.approx(cfg.ramp_grade, abs=1e-6)
    # the car pitches nose-down on the way down (positive pitch)
    pitch = np.array([matrix_to_rpy(s.T_map_base[:3, :3])[1] for s in samples])
    assert pitch[on_ramp].max() > 0.8 * np.arctan(cfg.ramp_grade)
    # deck first, covered level after the ramp
    level = np.array([s.level for s in samples])
    assert level[0] == 1 and level[-1] == 0 and np.all(np.diff(level) <= 0)


def test_camera_pose_convention(world, drive) -> None:
    from semfeat_ros.camera import load_camera_yaml

    _, ext = load_camera_yaml()
    T_base = drive[2][0].T_map_base
    T_cam = camera_pose(T_base, ext.T_base_cam)
    # optical z axis points forward and a little down; camera about 0.75 m above the road
    fwd = T_base[:3, 0]
    assert T_cam[:3, 2] @ fwd > 0.95 and T_cam[2, 2] < 0
    assert T_cam[2, 3] - T_base[2, 3] == pytest.approx(0.75, abs=0.05)


def test_gnss_quality_follows_the_sky(world, drive) -> None:
    tr = drive[0]
    gnss = GnssModel(world, tr, seed=0, rate_hz=5.0)
    fixes = [gnss.fix(t) for t in np.arange(0.0, tr.duration, 0.2)]
    status = np.array([f.status for f in fixes])
    assert status[0] == STATUS_GBAS_FIX and status[-1] == STATUS_NO_FIX
    first_none = np.flatnonzero(status == STATUS_NO_FIX)[0]
    assert np.all(status[first_none:] == STATUS_NO_FIX), 'no fix under the slab'
    assert (status == STATUS_FIX).sum() >= 3, 'degraded fixes in the ramp trench'
    for st in (STATUS_GBAS_FIX, STATUS_FIX):
        sel = [f for f in fixes if f.status == st]
        z2 = np.concatenate([f.error_enu ** 2 / f.covariance_enu for f in sel])
        assert 0.3 < z2.mean() < 3.0, 'reported covariances describe the actual errors'
    rtk = [f for f in fixes if f.status == STATUS_GBAS_FIX]
    assert max(np.abs(f.error_enu[:2]).max() for f in rtk) < 0.1  # centimetre level
    geo = np.array([f.lat_lon_alt for f in rtk[:5]])
    enu = geodetic_to_enu(geo, world.config.geo_origin)
    np.testing.assert_allclose(enu_to_geodetic(enu, world.config.geo_origin), geo, atol=1e-9)


def test_wheel_odometry_drifts_realistically(drive) -> None:
    tr = drive[0]
    odo = WheelOdometry(tr, seed=0, rate_hz=50.0)
    ts = np.arange(0.0, tr.duration, 0.02)
    out = [odo.step(t) for t in ts]
    T0, T1 = tr.sample(0.0).T_map_base, tr.sample(ts[-1]).T_map_base
    rel = np.linalg.inv(T0) @ T1
    end = np.array([out[-1].x, out[-1].y])
    err = np.linalg.norm(end - rel[:2, 3])
    assert 0.2 < err < 0.1 * tr.length  # drift, but odometry-like (not garbage)
    assert abs(odo.scale_error) < 0.05
    assert out[-1].pose_var[0] > out[10].pose_var[0] > 0  # covariance grows


def test_config_validation_and_random_worlds(tmp_path) -> None:
    with pytest.raises(SimConfigError, match='ramp_grade'):
        GarageConfig(ramp_grade=0.3)
    p = tmp_path / 'g.yaml'
    p.write_text('ramp_grade: 0.14\nn_bays: 20\n')
    cfg = load_config(p)
    assert cfg.ramp_grade == 0.14 and cfg.n_bays == 20
    p.write_text('bogus: 1\n')
    with pytest.raises(SimConfigError, match='unknown fields'):
        load_config(p)
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / 'missing.yaml')
    cfg = random_config(np.random.default_rng(5))
    w = build_world(5, cfg)
    tr = Trajectory(w.layout)
    assert tr.length > 250 and w.layout.deck_z == cfg.level_height
