"""Methods of the evaluation harness: OpenCV extractors, semantic NN, the sequential-matcher
adapter, the registry and the skip of unavailable methods."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from semfeat_ros.evaluation.errors import ConfigError, MethodUnavailableError
from semfeat_ros.evaluation.masks import MaskSource
from semfeat_ros.evaluation.methods import (
    Features,
    MethodConf,
    OpenCVExtractor,
    SemanticNNMethod,
    SequentialMatcherMethod,
    build_method,
    compatibility_matrix,
    method_names,
    pseudo_pinhole_bearings,
)
from semfeat_ros.evaluation.metrics import match_errors
from semfeat_ros.evaluation.pipeline import EvalConf, build_methods
from semfeat_ros.evaluation.run_transforms import make_transform_pair


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((h, w, 3), 60, np.uint8)
    for _ in range(60):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.rectangle(img, (x, y), (x + int(rng.integers(5, 30)), y + int(rng.integers(5, 30))),
                      color, -1)
    return img


@pytest.mark.parametrize('kind', ['sift', 'orb', 'akaze', 'brisk'])
def test_opencv_extractor_cap_mask_and_determinism(kind: str) -> None:
    img = _texture(200, 260, 0)
    mask = np.zeros((200, 260), bool)
    mask[:, :130] = True
    ex = OpenCVExtractor(kind, max_features=50)
    f = ex.extract(img, mask)
    assert 0 < len(f) <= 50
    assert (f.keypoints[:, 0] <= 130.5).all()  # only inside the mask
    assert f.descriptors.dtype == (np.float32 if kind == 'sift' else np.uint8)
    g = OpenCVExtractor(kind, max_features=50).extract(img, mask)
    np.testing.assert_array_equal(f.keypoints, g.keypoints)
    empty = ex.extract(np.zeros((60, 60, 3), np.uint8), np.ones((60, 60), bool))
    assert len(empty) == 0 and empty.descriptors.shape[0] == 0
    with pytest.raises(ConfigError):
        OpenCVExtractor('surf')


def test_semantic_nn_only_compatible_classes_and_no_dynamic() -> None:
    names = ('road', 'wall', 'car')
    comp = compatibility_matrix(names, np.array([False, False, True]))
    m = SemanticNNMethod('s', 'S', None, comp)  # type: ignore[arg-type]
    d = np.eye(4, dtype=np.float32)
    fa = Features(np.zeros((4, 2)), d, labels=np.array([0, 1, 2, 0], np.uint8))
    # B: the same descriptors, but keypoint 1 is labelled "road" (incompatible with "wall").
    fb = Features(np.zeros((4, 2)), d, labels=np.array([0, 0, 2, 0], np.uint8))
    got = m.match(fa, fb, None).matches.tolist()  # type: ignore[arg-type]
    # 0-0 and 3-3 match; 1 (wall vs road) is forbidden; 2 (car) is dynamic.
    assert got == [[0, 0], [3, 3]]
    with pytest.raises(MethodUnavailableError):
        m.match(Features(np.zeros((1, 2)), d[:1]), fb, None)  # type: ignore[arg-type]


def test_registry_and_unavailable_semfeat(tmp_path: Path) -> None:
    names = method_names()
    for n in ('sift_nn', 'orb_nn', 'akaze_nn', 'brisk_nn', 'semfeat_nn', 'semfeat_semantic',
              'semfeat_seq'):
        assert n in names
    with pytest.raises(ConfigError, match='unknown method'):
        build_method('superglue')
    missing = MethodConf(weights=tmp_path / 'none.safetensors')
    with pytest.raises(MethodUnavailableError, match='weights'):
        build_method('semfeat_nn', missing)
    runnable, skipped = build_methods(EvalConf(methods=('orb_nn', 'semfeat_nn', 'semfeat_seq'),
                                               weights=str(tmp_path / 'none.safetensors')))
    assert [m.name for m in runnable] == ['orb_nn']
    assert set(skipped) == {'semfeat_nn', 'semfeat_seq'}


def test_pseudo_pinhole_bearings() -> None:
    b = pseudo_pinhole_bearings(np.array([[49.5, 29.5], [149.5, 29.5]]), 100, 60)
    np.testing.assert_allclose(b[0], [0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0)
    assert b[1, 0] / b[1, 2] == pytest.approx(1.0)


def test_sequential_matcher_adapter_on_a_transform_pair() -> None:
    pair = make_transform_pair('p', _texture(240, 320, 4), np.random.default_rng(2),
                               MaskSource('none', margin_px=4))
    method = SequentialMatcherMethod('seq', 'Seq', OpenCVExtractor('sift', 500), 3.0)
    fa = method.extractor.extract(pair.image_a, pair.mask_a)
    fb = method.extractor.extract(pair.image_b, pair.mask_b)
    res = method.match(fa, fb, pair)
    assert len(res.matches) > 20 and res.verified is not None
    assert 'pseudo-bearings' in res.verification
    proj, vis = pair.gt.a_to_b(fa.keypoints)
    correct = match_errors(proj, vis, fb.keypoints, res.matches) <= 3.0
    # Verification keeps mostly correct matches and most of the correct ones.
    assert correct[res.verified].mean() > 0.9
    assert res.verified[correct].mean() > 0.7
