"""Online odometry calibration (yaw-rate bias, yaw scale, distance scale) on synthetic pairs."""
from __future__ import annotations

import math

import numpy as np
import pytest

from semfeat_ros.mapping import OdometryDelta
from semfeat_ros.mapping.geometry import yaw_of
from semfeat_ros.mapping.odometry import OdometryCalibration

TRUE_S, TRUE_B, TRUE_K = 0.02, 0.003, -0.015  # yaw scale, yaw-rate bias (rad/s), distance


def calibration(min_pairs: int = 30) -> OdometryCalibration:
    return OdometryCalibration(sigma_rad=0.002, sigma_m=0.01, prior_bias=0.005,
                               prior_scale=0.05, min_pairs=min_pairs)


def feed(cal: OdometryCalibration, n: int, seed: int = 0) -> None:
    """``n`` keyframe pairs of a drive with turns and straights; the estimate is the truth
    plus noise, the odometry follows the error model of the module docstring."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        dt = rng.uniform(0.1, 0.5)
        d = 4.0 * dt
        dpsi = (0.2 * d if (i // 40) % 2 else 0.0) * rng.choice([-1.0, 1.0])
        odo_psi = (1 + TRUE_S) * dpsi + TRUE_B * dt + rng.normal(0.0, 0.001)
        cal.add(odo_psi, dpsi + rng.normal(0.0, 0.001), dt, (1 + TRUE_K) * d,
                d + rng.normal(0.0, 0.005))


def test_learns_bias_and_scales_from_anchored_pairs() -> None:
    cal = calibration()
    feed(cal, 29)
    assert not cal.ready and (cal.yaw_bias, cal.yaw_scale, cal.distance_scale) == (0, 0, 0)
    feed(cal, 300, seed=1)
    assert cal.ready and cal.n_pairs == 329
    assert cal.yaw_bias == pytest.approx(TRUE_B, abs=2e-4)
    assert cal.yaw_scale == pytest.approx(TRUE_S, abs=3e-3)
    assert cal.distance_scale == pytest.approx(TRUE_K, abs=1e-3)


def test_a_burst_of_bad_anchors_barely_moves_the_estimate() -> None:
    clean, bad = calibration(), calibration()
    feed(clean, 200)
    feed(bad, 200)
    for _ in range(10):  # a GNSS multipath jump: the anchored motion off by 3 deg and 0.5 m
        bad.add(0.0, math.radians(3.0), 0.4, 1.6, 2.1)
    assert bad.n_pairs == clean.n_pairs + 10
    assert bad.yaw_bias == pytest.approx(clean.yaw_bias, abs=3e-4)
    assert bad.distance_scale == pytest.approx(clean.distance_scale, abs=3e-3)


def test_correct_inverts_the_error_model() -> None:
    cal = calibration(min_pairs=1)
    feed(cal, 400)
    dt, dpsi, d = 0.1, 0.05, 0.4
    psi_m = (1 + TRUE_S) * dpsi + TRUE_B * dt  # the odometry integrates along its own heading
    measured = OdometryDelta.from_se2((1 + TRUE_K) * d * math.cos(psi_m / 2),
                                      (1 + TRUE_K) * d * math.sin(psi_m / 2), psi_m,
                                      np.eye(3) * 1e-4)
    fixed = cal.correct(measured, dt)
    assert yaw_of(fixed.T[:3, :3]) == pytest.approx(dpsi, abs=5e-5)
    assert np.linalg.norm(fixed.T[:3, 3]) == pytest.approx(d, rel=1e-3)
    # the translation points along the mid-interval heading, as it was integrated
    assert math.atan2(fixed.T[1, 3], fixed.T[0, 3]) == pytest.approx(dpsi / 2, abs=5e-5)
    assert np.array_equal(fixed.covariance, measured.covariance)
    # standing still (no time in motion): no bias is removed, only the scales
    still = cal.correct(OdometryDelta.from_se2(0.0, 0.0, 0.0, np.eye(3) * 1e-4), 0.0)
    assert yaw_of(still.T[:3, :3]) == pytest.approx(0.0, abs=1e-12)


def test_nothing_changes_before_enough_pairs_and_bad_pairs_are_ignored() -> None:
    cal = calibration()
    feed(cal, 10)
    delta = OdometryDelta.from_se2(0.4, 0.01, 0.02, np.eye(3) * 1e-4)
    assert cal.correct(delta, 0.1) is delta
    cal.add(math.nan, 0.0, 0.1, 0.4, 0.4)
    cal.add(0.0, 0.0, -1.0, 0.4, 0.4)
    cal.add(0.0, 0.0, 0.1, math.inf, 0.4)
    assert cal.n_pairs == 10


@pytest.mark.parametrize('kwargs', [{'sigma_rad': 0.0}, {'sigma_m': -1.0},
                                    {'prior_bias': 0.0}, {'min_pairs': 0}])
def test_invalid_settings_raise(kwargs: dict) -> None:
    args = {'sigma_rad': 0.002, 'sigma_m': 0.01, 'prior_bias': 0.005, 'prior_scale': 0.05,
            'min_pairs': 30, **kwargs}
    with pytest.raises(ValueError, match='OdometryCalibration'):
        OdometryCalibration(**args)
