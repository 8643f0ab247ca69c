"""Descriptor matching: mutual NN, ratio test, thresholds, semantic filter (matching.nn)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from semfeat_ros.labels import load_labels
from semfeat_ros.matching.errors import FeatureInputError, MatchingConfigError
from semfeat_ros.matching.nn import (
    compatibility_from_labels,
    hamming_distances,
    match_binary,
    match_float,
    semantic_compatibility,
)

LABELS = load_labels()
ROAD, PARKING_LINE, LANE_DIVIDER, WALL, CAR = (
    LABELS.id_of(n) for n in ('road', 'parking_line', 'lane_divider', 'wall', 'car'))


def unit2(angle_deg: float) -> np.ndarray:
    """Unit vector in the x-y plane of a 4-D descriptor space at the given angle (deg)."""
    a = np.radians(angle_deg)
    return np.array([np.cos(a), np.sin(a), 0.0, 0.0], dtype=np.float32)


def pairs(m) -> set[tuple[int, int]]:
    return {tuple(int(x) for x in row) for row in m.indices}


def test_mutual_check_hand_built() -> None:
    # d1[0] is the nearest neighbour of both d0[0] and d0[1]; only d0[0] is mutual.
    d0 = np.stack([unit2(0), unit2(20), unit2(90)])
    d1 = np.stack([unit2(5), unit2(60), unit2(92)])
    m = match_float(d0, d1, ratio=None, min_similarity=-1.0)
    assert pairs(m) == {(0, 0), (2, 2)}
    m = match_float(d0, d1, ratio=None, min_similarity=-1.0, mutual=False)
    assert pairs(m) == {(0, 0), (1, 0), (2, 2)}
    assert m.scores.dtype == np.float32
    assert m.scores[m.indices[:, 0] == 2][0] == pytest.approx(np.cos(np.radians(2)), abs=1e-6)


def test_ratio_test_exact_boundary() -> None:
    # Best at 30 deg, second at 40 deg: L2 distances 2 sin(15), 2 sin(20); ratio 0.7569.
    d0 = np.stack([unit2(0)])
    d1 = np.stack([unit2(30), unit2(-40)])
    r = np.sin(np.radians(15)) / np.sin(np.radians(20))
    assert len(match_float(d0, d1, ratio=r + 1e-4, min_similarity=0.0)) == 1
    assert len(match_float(d0, d1, ratio=r - 1e-4, min_similarity=0.0)) == 0
    assert len(match_float(d0, d1, ratio=None, min_similarity=0.0)) == 1
    assert len(match_float(d0, d1, ratio=1.0, min_similarity=0.0)) == 1  # >= 1 disables
    # A single candidate always passes the ratio test.
    assert len(match_float(d0, d1[:1], ratio=0.1, min_similarity=0.0)) == 1


def test_min_similarity_threshold() -> None:
    d0 = np.stack([unit2(0)])
    d1 = np.stack([unit2(60)])  # cosine 0.5
    assert len(match_float(d0, d1, ratio=None, min_similarity=0.49)) == 1
    assert len(match_float(d0, d1, ratio=None, min_similarity=0.51)) == 0
    m = match_float(d0, d1, ratio=None, min_similarity=0.49)
    assert m.distances[0] == pytest.approx(1.0, abs=1e-6)  # sqrt(2 - 2 * 0.5)


def test_descriptors_are_normalised_and_ties_pick_lowest_index() -> None:
    d0 = np.stack([unit2(0) * 7.0, unit2(0) * 0.1])  # identical directions, different norms
    d1 = np.stack([unit2(1) * 3.0])
    m = match_float(d0, d1, ratio=None, min_similarity=0.0)
    assert pairs(m) == {(0, 0)}
    zero = np.zeros((1, 4), np.float32)
    assert len(match_float(zero, d1, ratio=None, min_similarity=-1.0)) == 0  # zero rows: never


def test_noisy_descriptors_with_planted_mismatches() -> None:
    rng = np.random.default_rng(0)
    n, dim = 600, 64
    base = rng.normal(size=(n, dim)).astype(np.float32)
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    perm = rng.permutation(n)
    obs = base[perm] + rng.normal(0, 0.03, (n, dim)).astype(np.float32)
    planted = rng.choice(n, n // 5, replace=False)  # 20 % have no true partner
    obs[planted] = rng.normal(size=(planted.size, dim))
    m = match_float(base, obs, ratio=0.9, min_similarity=0.5)
    truth = {(int(perm[j]), j) for j in range(n) if j not in set(planted.tolist())}
    found = pairs(m)
    assert found <= truth  # no wrong match survives mutual NN + ratio + similarity
    assert len(found) >= 0.97 * len(truth)


def test_semantic_filter_and_groups() -> None:
    compat = compatibility_from_labels(LABELS)
    assert compat.shape == (len(LABELS) + 1, len(LABELS) + 1)
    assert compat[PARKING_LINE, LANE_DIVIDER] and compat[LANE_DIVIDER, PARKING_LINE]
    assert not compat[ROAD, WALL] and not compat[CAR, CAR]
    d0 = np.stack([unit2(0), unit2(90)])
    d1 = np.stack([unit2(1), unit2(-1.2), unit2(91)])
    # d0[0] is a wall; its nearest d1[0] is road -> matched to the wall d1[1] instead.
    l0 = np.array([WALL, PARKING_LINE], np.uint8)
    l1 = np.array([ROAD, WALL, LANE_DIVIDER], np.uint8)
    m = match_float(d0, d1, labels0=l0, labels1=l1, compatibility=compat, ratio=0.8,
                    min_similarity=0.5)
    # The ratio test runs among compatible candidates only: d1[0] does not make d0[0] ambiguous.
    assert pairs(m) == {(0, 1), (1, 2)}  # parking_line ~ lane_divider is allowed
    no_sem = match_float(d0, d1, ratio=0.8, min_similarity=0.5)
    assert pairs(no_sem) == {(1, 2)}  # without labels d0[0] is ambiguous (1 vs 1.2 deg)


def test_dynamic_and_unknown_labels() -> None:
    compat = compatibility_from_labels(LABELS)
    d = np.stack([unit2(0), unit2(90), unit2(180)])
    l0 = np.array([CAR, 255, ROAD], np.uint8)
    l1 = np.array([CAR, 255, 200], np.uint8)
    m = match_float(d, d, labels0=l0, labels1=l1, compatibility=compat, ratio=None,
                    min_similarity=0.0)
    assert pairs(m) == {(1, 1)}  # cars never; unknown only with unknown; road != unknown
    with_dyn = compatibility_from_labels(LABELS, match_dynamic=True)
    m = match_float(d, d, labels0=l0, labels1=l1, compatibility=with_dyn, ratio=None,
                    min_similarity=0.0)
    assert pairs(m) == {(0, 0), (1, 1)}


def test_semantic_compatibility_validation() -> None:
    c = semantic_compatibility(3, dynamic=[False, False, True], groups=[[0, 1]])
    assert c.tolist() == [[True, True, False, False], [True, True, False, False],
                          [False, False, False, False], [False, False, False, True]]
    with pytest.raises(MatchingConfigError, match='class ids'):
        semantic_compatibility(3, groups=[[0, 5]])
    with pytest.raises(MatchingConfigError, match='unknown class'):
        compatibility_from_labels(LABELS, groups=[['road', 'tarmac']])
    with pytest.raises(MatchingConfigError, match='dynamic'):
        semantic_compatibility(3, dynamic=[True])


def test_float_input_errors() -> None:
    d = np.stack([unit2(0), unit2(10)])
    with pytest.raises(FeatureInputError, match='descriptor sizes differ'):
        match_float(d, d[:, :3])
    bad = d.copy()
    bad[0, 0] = np.nan
    with pytest.raises(FeatureInputError, match='desc1.*NaN'):
        match_float(d, bad)
    with pytest.raises(FeatureInputError, match='labels0'):
        match_float(d, d, compatibility=compatibility_from_labels(LABELS))
    with pytest.raises(FeatureInputError, match='float'):
        match_float(d.astype(np.uint8), d.astype(np.uint8))
    with pytest.raises(MatchingConfigError, match='ratio'):
        match_float(d, d, ratio=-0.5)
    assert len(match_float(d[:0], d)) == 0 and len(match_float(d, d[:0])) == 0


def test_hamming_distances_and_opencv_agreement() -> None:
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    ref = np.array([[cv2.norm(x, y, cv2.NORM_HAMMING) for y in b] for x in a])
    assert np.array_equal(hamming_distances(a, b), ref)
    # Mutual NN without ratio equals OpenCV's brute-force matcher with cross-check.
    b[:30] = a[:30] ^ (rng.random((30, 32)) < 0.05).astype(np.uint8)  # noisy copies
    ours = match_binary(a, b, ratio=None, max_distance=256)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a, b)
    assert pairs(ours) == {(x.queryIdx, x.trainIdx) for x in bf}


def test_binary_ratio_threshold_and_labels() -> None:
    z = np.zeros(4, np.uint8)
    d0 = np.stack([z])
    d1 = np.stack([np.array([0b111, 0, 0, 0], np.uint8),  # 3 bits
                   np.array([0b11111, 0, 0, 0], np.uint8)])  # 5 bits
    assert len(match_binary(d0, d1, ratio=0.61, max_distance=3)) == 1  # 3 <= 0.61 * 5
    assert len(match_binary(d0, d1, ratio=0.59, max_distance=3)) == 0
    assert len(match_binary(d0, d1, ratio=None, max_distance=2)) == 0
    m = match_binary(d0, d1, ratio=None, max_distance=3)
    assert m.distances[0] == 3 and m.scores[0] == pytest.approx(1 - 3 / 32)
    compat = compatibility_from_labels(LABELS)
    m = match_binary(d0, d1, labels0=np.array([WALL]), labels1=np.array([ROAD, WALL]),
                     compatibility=compat, ratio=0.5, max_distance=10)
    assert pairs(m) == {(0, 1)}
    with pytest.raises(FeatureInputError, match='uint8'):
        match_binary(d0.astype(np.float32), d1)


@pytest.mark.parametrize('kind', ['float', 'binary'])
def test_spatial_gate_restricts_candidates(kind: str) -> None:
    rng = np.random.default_rng(3)
    if kind == 'float':
        d0 = rng.normal(size=(3, 16)).astype(np.float32)
        d1 = np.stack([d0[0], d0[1] + 0.3 * rng.normal(size=16), d0[2]]).astype(np.float32)
        match = match_float
    else:
        d0 = rng.integers(0, 256, (3, 32), dtype=np.uint8)
        d1 = d0.copy()
        d1[1, :4] ^= 0xFF  # 32 bits off: still the best candidate of row 1
        match = match_binary
    p0 = np.array([[10.0, 10.0], [100.0, 100.0], [300.0, 50.0]])
    # feature 0 moved 200 px (beyond the gate), 1 moved 5 px, 2 moved 40 px
    p1 = np.array([[210.0, 10.0], [105.0, 100.0], [340.0, 50.0]])
    free = match(d0, d1, ratio=None)
    assert sorted(free.indices[:, 0].tolist()) == [0, 1, 2]
    gated = match(d0, d1, ratio=None, positions0=p0, positions1=p1, max_distance_px=50.0)
    assert sorted(map(tuple, gated.indices.tolist())) == [(1, 1), (2, 2)]
    none = match(d0, d1, ratio=None, positions0=p0, positions1=p1, max_distance_px=1.0)
    assert len(none) == 0
    with pytest.raises(FeatureInputError, match='positions1'):
        match(d0, d1, positions0=p0, positions1=p1[:2], max_distance_px=50.0)
    with pytest.raises(MatchingConfigError, match='max_distance_px'):
        match(d0, d1, positions0=p0, positions1=p1, max_distance_px=0.0)
