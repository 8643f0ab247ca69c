"""Metrics of the evaluation harness on hand-built cases with exactly known answers."""
from __future__ import annotations

import math

import numpy as np
import pytest

from semfeat_ros.evaluation.groundtruth import HomographyGroundTruth, sample_mask
from semfeat_ros.evaluation.methods import (
    compatibility_matrix,
    fill_mutual_nn,
    mutual_nn_opencv,
    mutual_nn_similarity,
)
from semfeat_ros.evaluation.metrics import (
    estimate_homography,
    gt_keypoint_recall,
    homography_corner_error,
    inlier_ratio,
    keypoint_recall,
    match_errors,
    matchable_keypoints,
    mean_matching_accuracy,
    nearest_distance,
    pair_metrics,
    repeatability,
    summarize,
)
from semfeat_ros.evaluation.segmentation import (
    confusion_matrix,
    iou_from_confusion,
    mean_iou,
    segmentation_summary,
)
from semfeat_ros.evaluation.transforms import apply_homography

# A 100x100 image pair related by a 10 px shift to the right.
H_SHIFT = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
FULL = np.ones((100, 100), bool)
KPTS_A = np.array([[10, 10], [20, 20], [30, 30], [40, 40], [50, 50], [60, 60], [70, 70],
                   [95, 50]], dtype=float)  # a7 maps to (105, 50): outside B
KPTS_B = np.array([[20, 10], [30, 20], [41.5, 30], [50, 40], [60, 50], [70, 60], [90, 90],
                   [5, 5]], dtype=float)  # b0..b5 = H a0..a5 (b2 off by 1.5 px); b7 -> A (-5, 5)
# (0,0) (1,1) exact, (2,2) 1.5 px, (3,4) wrong, (4,6) wrong, (7,7) a7 not visible, (6,5) wrong
MATCHES = np.array([[0, 0], [1, 1], [2, 2], [3, 4], [4, 6], [7, 7], [6, 5]])


def _gt() -> HomographyGroundTruth:
    return HomographyGroundTruth(H_SHIFT, FULL, FULL)


def test_match_errors_and_correctness() -> None:
    proj, vis = _gt().a_to_b(KPTS_A)
    assert vis.tolist() == [True] * 7 + [False]
    err = match_errors(proj, vis, KPTS_B, MATCHES)
    expected = [0.0, 0.0, 1.5, math.hypot(10, 10), math.hypot(30, 40), math.inf,
                math.hypot(10, 10)]
    np.testing.assert_allclose(err, expected)
    assert inlier_ratio(err <= 3.0) == pytest.approx(3 / 7)


def test_matchable_and_recall() -> None:
    proj, vis = _gt().a_to_b(KPTS_A)
    matchable = matchable_keypoints(proj, vis, KPTS_B, 3.0)
    # a0..a5 have a B keypoint within 3 px of their GT location; a6 (-> (80,70)) and a7 not.
    assert matchable.tolist() == [True] * 6 + [False, False]
    correct = match_errors(proj, vis, KPTS_B, MATCHES) <= 3.0
    assert keypoint_recall(MATCHES, correct, matchable) == pytest.approx(3 / 6)
    # eps 1 px: b2 is 1.5 px off, so a2 is neither matchable nor correctly matched.
    m1 = matchable_keypoints(proj, vis, KPTS_B, 1.0)
    c1 = match_errors(proj, vis, KPTS_B, MATCHES) <= 1.0
    assert m1.sum() == 5
    assert keypoint_recall(MATCHES, c1, m1) == pytest.approx(2 / 5)


def test_recall_counts_each_keypoint_once() -> None:
    # Two correct matches of the same A keypoint (a one-to-many matcher) count once.
    kb = np.array([[20.0, 10.0], [21.0, 10.0]])
    matches = np.array([[0, 0], [0, 1]])
    proj, vis = _gt().a_to_b(KPTS_A[:1])
    correct = match_errors(proj, vis, kb, matches) <= 3.0
    assert correct.tolist() == [True, True]
    assert keypoint_recall(matches, correct, matchable_keypoints(proj, vis, kb, 3.0)) == 1.0


def test_mma_thresholds() -> None:
    proj, vis = _gt().a_to_b(KPTS_A)
    err = match_errors(proj, vis, KPTS_B, MATCHES)
    mma = mean_matching_accuracy(err)
    assert len(mma) == 10
    assert mma[0] == pytest.approx(2 / 7)  # 1 px: the two exact matches
    np.testing.assert_allclose(mma[1:], 3 / 7)  # 2..10 px: + the 1.5 px one (others >= 14 px)
    assert np.isnan(mean_matching_accuracy(np.zeros(0))).all()


def test_repeatability_symmetric() -> None:
    # A visible in B: a0..a6 (7), repeated a0..a5 (6). B visible in A: b0..b6 (7; b7 -> (-5, 5)
    # is outside A), repeated b0..b5 (6; b6 -> (80, 90) has no A keypoint within 3 px).
    assert repeatability(KPTS_A, KPTS_B, _gt(), 3.0) == pytest.approx(12 / 14)
    assert np.isnan(repeatability(np.zeros((0, 2)), np.zeros((0, 2)), _gt(), 3.0))


def test_gt_keypoint_recall() -> None:
    gt_kpts = np.array([[10, 10], [31, 31], [60, 60], [70, 70], [95, 95]], dtype=float)
    proj, vis = _gt().a_to_b(KPTS_A)
    correct = match_errors(proj, vis, KPTS_B, MATCHES) <= 3.0
    rec, det, n_vis = gt_keypoint_recall(gt_kpts, _gt(), KPTS_A, MATCHES, correct, 3.0)
    # (95, 95) -> (105, 95) is not visible in B: 4 visible GT keypoints. Recalled: (10,10) by
    # the exact match of a0, (31,31) by the correct match of a2 (1.41 px away). (60,60) = a5 is
    # detected but a5 has no match; (70,70) = a6 is matched, wrongly.
    assert n_vis == 4
    assert rec == pytest.approx(2 / 4)
    assert det == pytest.approx(4 / 4)


def test_pair_metrics_exact_numbers() -> None:
    verified = np.array([True, True, True, False, False, False, True])
    gt_kpts = np.array([[10, 10], [31, 31], [60, 60], [70, 70]], dtype=float)
    H_est = H_SHIFT.copy()
    H_est[0, 2] += 2.0  # every corner off by exactly 2 px
    m = pair_metrics(KPTS_A, KPTS_B, MATCHES, _gt(), eps=3.0, verified=verified,
                     gt_keypoints_a=gt_kpts, H_gt=H_SHIFT, H_est=H_est, image_size=(100, 100))
    assert m['n_matches'] == 7
    assert m['n_correct'] == 3
    assert m['n_matchable'] == 6
    assert m['keypoint_recall'] == pytest.approx(0.5)
    assert m['inlier_ratio'] == pytest.approx(3 / 7)
    assert m['n_verified'] == 4
    assert m['inlier_ratio_verified'] == pytest.approx(3 / 4)
    assert m['keypoint_recall_verified'] == pytest.approx(3 / 6)
    assert m['gt_keypoint_recall'] == pytest.approx(0.5)
    assert m['repeatability'] == pytest.approx(12 / 14)
    assert m['homography_error'] == pytest.approx(2.0)


def test_pair_metrics_without_matches_and_bad_input() -> None:
    m = pair_metrics(KPTS_A, KPTS_B, np.zeros((0, 2), int), _gt())
    assert m['keypoint_recall'] == 0.0
    assert math.isnan(m['inlier_ratio'])
    with pytest.raises(ValueError, match='indices out of range'):
        pair_metrics(KPTS_A, KPTS_B, np.array([[0, 99]]), _gt())
    with pytest.raises(ValueError, match='eps'):
        pair_metrics(KPTS_A, KPTS_B, MATCHES, _gt(), eps=0.0)


def test_summarize_skips_undefined_and_counts_homography_failures() -> None:
    pairs = [
        {'keypoint_recall': 0.5, 'inlier_ratio': 0.25, 'n_matches': 4, 'homography_error': 0.5,
         'mma': [0.1] * 10},
        {'keypoint_recall': 1.0, 'inlier_ratio': float('nan'), 'n_matches': 0,
         'homography_error': float('inf'), 'mma': [float('nan')] * 10},
        {'keypoint_recall': 0.0, 'inlier_ratio': 0.75, 'n_matches': 8, 'homography_error': 4.0,
         'mma': [0.3] * 10},
    ]
    s = summarize(pairs)
    assert s['keypoint_recall'] == pytest.approx(0.5)
    assert s['inlier_ratio'] == pytest.approx(0.5)  # the pair without matches is skipped
    assert s['n_inlier_ratio'] == 2
    assert s['pairs_without_matches'] == 1
    assert s['homography_accuracy'] == {'1': pytest.approx(1 / 3), '3': pytest.approx(1 / 3),
                                        '5': pytest.approx(2 / 3)}
    np.testing.assert_allclose(s['mma'], 0.2)


def test_homography_ransac_and_corner_error() -> None:
    rng = np.random.default_rng(3)
    H = np.array([[0.9, -0.2, 12.0], [0.15, 1.05, -7.0], [1e-4, -2e-4, 1.0]])
    pa = rng.uniform(0, 300, size=(60, 2))
    pb = apply_homography(H, pa)
    pb[:12] += rng.uniform(20, 60, size=(12, 2))  # planted outliers
    H_est, inl = estimate_homography(pa, pb, 1.0)
    assert inl[:12].sum() == 0 and inl[12:].all()
    assert homography_corner_error(H_est, H, 320, 240) < 1e-3
    assert homography_corner_error(None, H, 320, 240) == math.inf
    none, inl3 = estimate_homography(pa[:3], pb[:3])
    assert none is None and not inl3.any()


def test_nearest_distance_and_mask_sampling() -> None:
    d = nearest_distance(np.array([[0.0, 0.0], [np.nan, 1.0]]), np.array([[3.0, 4.0]]))
    assert d[0] == pytest.approx(5.0) and d[1] == math.inf
    assert nearest_distance(np.zeros((2, 2)), np.zeros((0, 2))).tolist() == [math.inf] * 2
    mask = np.zeros((4, 5), bool)
    mask[1, 2] = True
    uv = np.array([[2.2, 0.9], [2.0, 2.0], [-1.0, 1.0], [4.6, 1.0], [np.nan, 0.0]])
    assert sample_mask(mask, uv).tolist() == [True, False, False, False, False]


def test_mutual_nn() -> None:
    sim = np.array([[0.9, 0.1, 0.0], [0.8, 0.2, 0.1], [0.0, 0.1, 0.95]])
    # row 1's best is column 0, but column 0 prefers row 0: not mutual.
    assert mutual_nn_similarity(sim).tolist() == [[0, 0], [2, 2]]
    sim[2, 2] = -np.inf  # forbidden entries are never matched
    assert mutual_nn_similarity(sim).tolist() == [[0, 0]]
    a = np.array([[0b11110000], [0b00001111]], dtype=np.uint8)
    b = np.array([[0b00001110], [0b11110001], [0b10101010]], dtype=np.uint8)
    import cv2

    assert mutual_nn_opencv(a, b, cv2.NORM_HAMMING).tolist() == [[0, 1], [1, 0]]
    assert mutual_nn_opencv(a[:0], b, cv2.NORM_HAMMING).shape == (0, 2)


def test_fill_mutual_nn_matches_only_the_unmatched() -> None:
    d = np.eye(4, dtype=np.float32)  # four unit descriptors, each its own nearest neighbour
    # 0 and 1 are matched (0 -> 1 crosswise): the fill pairs 2 and 3 with themselves
    assert fill_mutual_nn(d, d, np.array([[0, 1]])).tolist() == [[2, 2], [3, 3]]
    # 2 is as close to both rows of b (a ratio-test tie), 0 and 1 below the minimum
    # similarity: nothing; with one row of b, 2 pairs with it
    b = np.array([[0, 0, 0.8, 0.6], [0, 0, 0.8, -0.6]], np.float32)
    assert fill_mutual_nn(d[:3], b, np.zeros((0, 2), np.int64)).tolist() == []
    assert fill_mutual_nn(d[:3], b[:1], np.zeros((0, 2), np.int64)).tolist() == [[2, 0]]
    assert fill_mutual_nn(d, d, np.array([[i, i] for i in range(4)])).shape == (0, 2)
    # the fill's minimum similarity is matcher_node's learned_fill_min_similarity (0.7), above
    # mutual NN's 0.5: a pair at 0.6 stays unmatched, one at 0.8 is added
    c = np.array([[0, 0, 0.6, 0.8]], np.float32)
    assert fill_mutual_nn(d[:3], c, np.zeros((0, 2), np.int64)).tolist() == []
    assert fill_mutual_nn(d[[0, 1, 3]], c, np.zeros((0, 2), np.int64)).tolist() == [[2, 0]]
    assert fill_mutual_nn(d[:3], c, np.zeros((0, 2), np.int64), min_similarity=0.5).tolist() \
        == [[2, 0]]


def test_compatibility_matrix() -> None:
    names = ('road', 'line', 'marking', 'car')
    comp = compatibility_matrix(names, np.array([False, False, False, True]),
                                [('line', 'marking')])
    assert comp[0, 0] and comp[1, 2] and comp[2, 1] and not comp[0, 1]
    assert not comp[3, 3]  # dynamic classes never match
    assert not comp[255, 255]
    with pytest.raises(ValueError, match='unknown class'):
        compatibility_matrix(names, np.zeros(4, bool), [('road', 'tree')])


def test_segmentation_iou() -> None:
    gt = np.array([[0, 0, 1], [1, 2, 255]], dtype=np.uint8)
    pred = np.array([[0, 1, 1], [1, 255, 0]], dtype=np.uint8)
    cm = confusion_matrix(pred, gt, 3)
    # rows: GT 0 -> pred {0, 1}; GT 1 -> {1, 1}; GT 2 -> "none"; the GT-255 pixel is ignored.
    assert cm.tolist() == [[1, 1, 0, 0], [0, 2, 0, 0], [0, 0, 0, 1]]
    iou = iou_from_confusion(cm)
    np.testing.assert_allclose(iou, [1 / 2, 2 / 3, 0.0])
    assert mean_iou(cm) == pytest.approx((1 / 2 + 2 / 3 + 0) / 3)
    summ = segmentation_summary(cm, ['a', 'b', 'c'])
    assert summ['pixel_accuracy'] == pytest.approx(3 / 5)
    assert summ['iou']['b'] == pytest.approx(2 / 3)
    valid = np.array([[True, False, True], [True, True, True]])
    assert confusion_matrix(pred, gt, 3, valid=valid).sum() == 4
    with pytest.raises(ValueError, match='shape'):
        confusion_matrix(pred[:, :2], gt, 3)
