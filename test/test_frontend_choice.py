"""Selectable front ends (semfeat, xfeat, sift, orb) with the network's labels, the learned
matcher of the sequential matcher, and the node parameters that choose them.

The labelling test runs the shipped network on the first frame of the bundled bag (a mask with
many classes); it checks that every front end takes its labels from that mask, not the mask's
quality. The other tests use blurred noise (XFeat finds no keypoints on flat blocks).
"""
from __future__ import annotations

from conftest import REPO
import numpy as np
import pytest

from semfeat_ros.camera import load_camera_yaml
from semfeat_ros.frontend import FrontendConfig
from semfeat_ros.labels import load_labels
from semfeat_ros.matching.errors import FeatureInputError, MatchingConfigError
from semfeat_ros.matching.learned import LearnedMatcher
from semfeat_ros.matching.nn import bytes_from_floats
from semfeat_ros.matching.sequential import FrameFeatures, SequentialMatcher
from semfeat_ros.model.errors import WeightsNotFoundError
from semfeat_ros.model.glue import SHIPPED_GLUE
from semfeat_ros.offline.errors import OfflineConfigError
from semfeat_ros.offline.frontends import (
    FRONTEND_KINDS,
    NetworkLabeller,
    labels_at,
    make_frontend,
    matcher_frame,
)

W, H = 320, 256
DIMS = {'semfeat': (64, np.float32), 'xfeat': (64, np.float32), 'sift': (128, np.float32),
        'orb': (32, np.uint8)}


@pytest.fixture(scope='module')
def bag_frame():
    """The first camera frame of the bundled bag (640x512) and its camera model."""
    from msg_adapters import to_rgb_or_mono
    from semfeat_ros.offline.bag import BagSource
    from semfeat_ros.offline.mapping_run import read_cameras

    with BagSource(REPO / 'bags' / 'garage_ramp_seed0') as src:
        topic = src.image_topic(None, '/camera/front/image_raw')
        camera = read_cameras(src, '/camera/front/camera_info', 190.0).models[0]
        msg = next(iter(src.messages([topic]))).msg
        return to_rgb_or_mono(msg), camera


def conf_for(**kw) -> FrontendConfig:
    return FrontendConfig(num_threads=1, **kw)


def textured(seed: int = 0, shift: int = 0) -> np.ndarray:
    """Blurred colour noise (XFeat finds no keypoints on flat 8 px blocks); ``shift`` px moves
    the content to the left."""
    import cv2

    rng = np.random.default_rng(seed)
    wide = cv2.GaussianBlur((rng.random((H, W + 32, 3)) * 255).astype(np.uint8), (0, 0), 2)
    return np.ascontiguousarray(wide[:, 16 + shift:16 + shift + W])


@pytest.fixture(scope='module')
def camera():
    return load_camera_yaml()[0].scaled(W, H)


@pytest.mark.parametrize('kind', FRONTEND_KINDS)
def test_each_front_end_is_labelled_by_the_network(kind: str, bag_frame) -> None:
    image, camera = bag_frame
    h, w = image.shape[:2]
    mask, scale = NetworkLabeller(conf_for()).mask(image, camera)
    ids, counts = np.unique(mask[mask != 255], return_counts=True)
    assert len(ids) >= 4, ids
    # the most frequent class is dropped too, so the filter has work to do
    dropped = ('sky', 'car', 'pedestrian', load_labels().names[ids[np.argmax(counts)]])
    fe = make_frontend(kind, conf_for(drop_classes=dropped, max_keypoints=400), 400,
                       network_labels=True)
    out = fe.process(image, camera)
    dim, dtype = DIMS[kind]
    assert fe.name == kind and 50 < len(out) <= 400 and fe.last_count == len(out)
    assert out.descriptors.shape == (len(out), dim) and out.descriptors.dtype == dtype
    assert out.keypoints.dtype == np.float32 and out.scores.shape == (len(out),)
    assert fe.descriptor_type == ('binary' if kind == 'orb' else 'float')
    assert out.mask is not None
    np.testing.assert_array_equal(out.mask, mask)  # one pass of the same network
    drop_ids = [load_labels().id_of(n) for n in dropped]
    assert not np.isin(out.labels, [*drop_ids, 255]).any()
    if kind != 'semfeat':  # the others read the mask at the keypoint
        np.testing.assert_array_equal(out.labels, labels_at(mask, scale, out.keypoints))
    u, v = np.rint(out.keypoints).astype(int).T
    assert camera.valid_mask()[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)].all()
    frame = matcher_frame(5, out, camera, 'cam')
    assert frame.descriptors.dtype == dtype and frame.image_height == h


def test_ground_truth_labels_and_missing_weights(camera) -> None:
    gt = np.full((H, W), 6, np.uint8)
    gt[:, : W // 2] = 17  # car: dropped
    fe = make_frontend('xfeat', conf_for(), 300, network_labels=False)
    out = fe.process(textured(), camera, gt)
    assert len(out) > 10 and (out.labels == 6).all() and (out.keypoints[:, 0] >= W / 2 - 1).all()
    assert out.mask is None
    missing = conf_for(weights='/nonexistent/w.safetensors')
    with pytest.raises(WeightsNotFoundError):
        make_frontend('orb', missing, 100, network_labels=True)
    quiet = make_frontend('orb', missing, 100, network_labels=None)  # when found: not found
    assert quiet.labeller is None
    assert (quiet.process(textured(), camera).labels == load_labels().id_of('wall')).all()
    with pytest.raises(OfflineConfigError, match='frontend: expected one of semfeat, xfeat'):
        make_frontend('surf', missing)


def xfeat_frames(camera, shift: int = 6) -> tuple[FrameFeatures, FrameFeatures, int]:
    fe = make_frontend('xfeat', FrontendConfig(num_threads=1), 500, network_labels=False)
    a = matcher_frame(1_000_000_000, fe.process(textured(3), camera), camera, 'cam')
    b = matcher_frame(1_100_000_000, fe.process(textured(3, shift), camera), camera, 'cam')
    return a, b, shift


def test_learned_matching_on_two_frames(camera) -> None:
    a, b, shift = xfeat_frames(camera)
    conf = {'matching': {'method': 'learned', 'features': 'xfeat'},
            'verification': {'min_inliers': 8}}
    learned = SequentialMatcher(conf)
    learned.process(a)
    r = learned.process(b)
    assert r.n_matches > 50 and r.verified and r.n_tracks == r.n_inliers
    d = b.keypoints[r.inlier_matches[:, 1]] - a.keypoints[r.inlier_matches[:, 0]]
    assert np.median(d[:, 0]) == pytest.approx(-shift, abs=1.0)  # the image moved left
    assert ((r.scores >= 0.1) & (r.scores <= 1.0)).all()  # LighterGlue's confidences
    # semantic consistency still applies: the right half relabelled (wall -> road) in frame b
    labels = b.labels.copy()
    labels[b.keypoints[:, 0] > W / 2] = 0
    a6 = FrameFeatures(**{**a.__dict__, 'labels': np.full_like(a.labels, 6)})
    b6 = FrameFeatures(**{**b.__dict__, 'labels': np.where(labels == 0, 0, 6).astype(np.uint8)})
    m = SequentialMatcher(conf)
    m.process(a6)
    r2 = m.process(b6)
    assert r2.n_matches > 20
    assert (b6.labels[r2.matches[:, 1]] == 6).all()
    # without the image size the learned matcher refuses
    nosize = SequentialMatcher(conf)
    nosize.process(FrameFeatures(**{**a.__dict__, 'image_width': 0, 'image_height': 0}))
    with pytest.raises(FeatureInputError, match='image size'):
        nosize.process(FrameFeatures(**{**b.__dict__, 'image_width': 0, 'image_height': 0}))


@pytest.mark.parametrize('features', ['sift', 'orb', ''])
def test_learned_is_refused_for_other_descriptors(features: str) -> None:
    with pytest.raises(MatchingConfigError, match='semfeat, xfeat') as err:
        SequentialMatcher({'matching': {'method': 'learned', 'features': features}})
    assert "method 'mnn'" in str(err.value)  # names the way out
    with pytest.raises(MatchingConfigError, match='matching.method'):
        SequentialMatcher({'matching': {'method': 'lightglue'}})


@pytest.mark.skipif(not SHIPPED_GLUE.is_file(), reason='no shipped SemfeatGlue weights')
def test_learned_matching_of_the_network_features(camera) -> None:
    fe = make_frontend('semfeat', FrontendConfig(num_threads=1), 500, network_labels=True)
    a = matcher_frame(1_000_000_000, fe.process(textured(3), camera), camera, 'cam')
    b = matcher_frame(1_100_000_000, fe.process(textured(3, 6), camera), camera, 'cam')
    conf = {'matching': {'method': 'learned', 'features': 'semfeat'},
            'verification': {'min_inliers': 8}}
    assert LearnedMatcher('semfeat').describe() == 'SemfeatGlue on semfeat descriptors'
    learned = SequentialMatcher(conf)
    learned.process(a)
    r = learned.process(b)
    assert r.n_matches > 30 and r.verified
    d = b.keypoints[r.inlier_matches[:, 1]] - a.keypoints[r.inlier_matches[:, 0]]
    assert np.median(d[:, 0]) == pytest.approx(-6, abs=1.0)  # the image moved left
    assert ((r.scores >= 0.1) & (r.scores <= 1.0)).all()  # the matcher's confidences
    assert LearnedMatcher('semfeat').net.conf['depth_confidence'] > 0  # early exit by default
    full = SequentialMatcher({**conf, 'matching': {**conf['matching'],
                                                   'learned_early_exit': False}})
    assert LearnedMatcher('semfeat', early_exit=False).net.conf['depth_confidence'] == -1
    full.process(a)
    assert full.process(b).verified
    with pytest.raises(MatchingConfigError, match='learned_early_exit'):
        SequentialMatcher({'matching': {'learned_early_exit': 'yes'}})


@pytest.mark.skipif(not SHIPPED_GLUE.is_file(), reason='no shipped SemfeatGlue weights')
def test_learned_matching_filled_by_nearest_neighbours(camera) -> None:
    fe = make_frontend('semfeat', FrontendConfig(num_threads=1), 500, network_labels=True)
    a = matcher_frame(1_000_000_000, fe.process(textured(5), camera), camera, 'cam')
    b = matcher_frame(1_100_000_000, fe.process(textured(5, 9), camera), camera, 'cam')
    conf = {'matching': {'method': 'learned', 'features': 'semfeat', 'learned_min_score': 0.9},
            'verification': {'min_inliers': 8}}

    def matches(**kw) -> np.ndarray:
        m = SequentialMatcher({**conf, 'matching': {**conf['matching'], **kw}})
        m.process(a)
        return m.process(b).matches

    learned, filled = matches(), matches(learned_fill_nn=True)
    pairs = {tuple(p) for p in filled.tolist()}
    assert {tuple(p) for p in learned.tolist()} <= pairs  # the learned matches stay
    added = np.array(sorted(pairs - {tuple(p) for p in learned.tolist()}))
    assert len(added) > 10
    # each added pair is unmatched by the learned matcher on both sides ...
    assert not np.isin(added[:, 0], learned[:, 0]).any()
    assert not np.isin(added[:, 1], learned[:, 1]).any()
    # ... and passes the fill's rule: similarity >= learned_fill_min_similarity (0.7)
    sim = np.sum(a.descriptors[added[:, 0]] * b.descriptors[added[:, 1]], axis=1)
    assert (sim >= 0.7 - 1e-6).all()
    assert len(matches(learned_fill_nn=True, learned_fill_min_similarity=1.0)) == len(learned)
    # the fill has its own thresholds: mutual NN's min_similarity does not change it, and the
    # looser rule of mutual NN (0.9, 0.5) adds at least as many
    assert matches(learned_fill_nn=True, min_similarity=1.0).tolist() == filled.tolist()
    loose = matches(learned_fill_nn=True, learned_fill_ratio=0.9,
                    learned_fill_min_similarity=0.5)
    assert len(loose) >= len(filled)
    with pytest.raises(MatchingConfigError, match='learned_fill_nn'):
        SequentialMatcher({'matching': {'learned_fill_nn': 1}})
    with pytest.raises(MatchingConfigError, match='learned_fill_ratio'):
        SequentialMatcher({'matching': {'learned_fill_ratio': 0.0}})
    with pytest.raises(MatchingConfigError, match='learned_fill_min_similarity'):
        SequentialMatcher({'matching': {'learned_fill_min_similarity': 1.5}})


def test_node_parameters() -> None:
    from semfeat_ros.nodes.feature_node import FeatureNodeConfig
    from semfeat_ros.nodes.matcher_node import (
        MatcherNodeConfig,
        matcher_conf,
        message_descriptors,
    )
    from semfeat_ros.nodes.params import check_value, describe

    finfo = {i.name: i for i in describe(FeatureNodeConfig)}['frontend']
    assert finfo.read_only and finfo.default == 'semfeat'
    assert all(check_value(finfo, k) is None for k in FRONTEND_KINDS)
    assert 'not one of' in check_value(finfo, 'surf')
    minfo = {i.name: i for i in describe(MatcherNodeConfig)}
    assert check_value(minfo['matcher'], 'learned') is None
    assert 'not one of' in check_value(minfo['matcher'], 'superglue')

    orb = matcher_conf(MatcherNodeConfig(frontend='orb'))
    assert orb['matching']['descriptor_type'] == 'binary'
    SequentialMatcher(orb)
    for kind in ('sift', 'orb'):
        with pytest.raises(MatchingConfigError, match='a shipped matcher was trained on'):
            SequentialMatcher(matcher_conf(MatcherNodeConfig(frontend=kind, matcher='learned')))
    for kind in ('semfeat', 'xfeat'):
        lg = matcher_conf(MatcherNodeConfig(frontend=kind, matcher='learned'))
        assert lg['matching']['method'] == 'learned' and lg['matching']['features'] == kind
        assert lg['matching']['learned_early_exit']
    assert not matcher_conf(MatcherNodeConfig(learned_early_exit=False))['matching'][
        'learned_early_exit']
    # the offline tools override frontend and matcher
    over = matcher_conf(MatcherNodeConfig(), 'xfeat', 'learned')
    assert over['matching']['method'] == 'learned' and over['matching']['features'] == 'xfeat'

    raw = np.random.default_rng(0).integers(0, 256, (5, 32)).astype(np.uint8)
    np.testing.assert_array_equal(message_descriptors('orb', raw.astype(np.float32)), raw)
    with pytest.raises(FeatureInputError, match='D=64 but frontend orb gives 32'):
        message_descriptors('orb', np.zeros((5, 64), np.float32))
    with pytest.raises(FeatureInputError, match='frontend xfeat gives 64'):
        message_descriptors('xfeat', np.zeros((5, 128), np.float32))
    unit = np.full((2, 16), 0.25, np.float32)
    assert message_descriptors('semfeat', unit) is unit  # semfeat: any D
    with pytest.raises(FeatureInputError, match='byte values'):
        bytes_from_floats(np.full((2, 32), 0.5, np.float32))


def test_match_pairs_tool_on_three_frames() -> None:
    from semfeat_ros.tools import match_pairs

    r = match_pairs.run(REPO / 'bags' / 'garage_ramp_seed0', frames=3)
    assert r['frames'] == 3
    assert match_pairs.methods('semfeat') == ('mnn', 'learned', 'learned_all')
    assert 'xfeat_learned_all' not in r  # LighterGlue has no trained early exit
    for kind in match_pairs.FRONTENDS:
        for m in match_pairs.methods(kind):
            s = r[f'{kind}_{m}']
            assert s['pairs'] == 2 and s['matcher_ms_median'] > 0
            assert 0 < s['verified_median'] <= s['matches_median']
        assert r[f'{kind}_learned']['ms_ratio_to_mnn'] > 0
        assert r[f'{kind}_learned']['frame_ms_ratio_to_mnn'] > 0
        assert r[f'{kind}_frontend_ms_median'] > 0
    assert r['xfeat_learned']['verified_frames'] == 1.0
    table = match_pairs.format_table(r)
    assert table.count('\n') == 6 and '| xfeat + learned |' in table
    assert '| semfeat + learned_all |' in table
