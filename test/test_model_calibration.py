"""Segmentation prior correction: tau fitted on training shards, folded into the head's bias."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_model_data import CAM, make_shard
import torch

from semfeat_ros.labels import load_labels
from semfeat_ros.model.calibration import CARD_BEGIN, main
from semfeat_ros.model.errors import DatasetError, WeightsFormatError
from semfeat_ros.model.semfeatnet import SemFeatNet
from semfeat_ros.model.weights_io import load_weights, save_weights
from semfeat_ros.tools.calibrate_seg import cli

TINY_NET = {'encoder_channels': [8, 16, 16, 24], 'decoder_channels': 16, 'descriptor_dim': 16,
            'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8}


@pytest.fixture(scope='module')
def setup(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp('calibration')
    for s in (11, 12):
        make_shard(d / 'train' / f's{s}.npz', n=3, seed=s)
    make_shard(d / 'val' / 's13.npz', n=2, seed=13)
    make_shard(d / 'test' / 's0.npz', n=2, seed=0)
    torch.manual_seed(0)
    model = SemFeatNet(TINY_NET).eval()
    names = load_labels().names
    weights = np.linspace(0.2, 5.0, len(names))  # rare classes weighted up, as in training
    save_weights(model, d / 'trained', {'class_names': names, 'input_size': [160, 128],
                                        'training': {'seg_class_weights': weights.tolist()}})
    (d / 'trained' / 'MODEL_CARD.md').write_text('# card\n\ntrained\n')
    return d


def _conf(d: Path, **over: object) -> dict:
    return {'train_shards': [str(d / 'train' / '*.npz')], 'val_shards': [str(d / 'val' / '*.npz')],
            'frames_per_shard': 2, 'val_frames_per_shard': 2, 'taus': [0.0, 0.5, 1.0, 1.5],
            **over}


def test_tau_is_folded_into_the_segmentation_bias_only(setup: Path, tmp_path: Path) -> None:
    cal = main(_conf(setup), setup / 'trained', tmp_path / 'cal', progress=False)
    assert cal.tau == max(cal.train, key=lambda t: (cal.train[t][0], -t))
    assert cal.frames == (4, 2) and cal.val_before is not None and cal.val_after is not None
    raw, _ = load_weights(setup / 'trained')
    new, config = load_weights(tmp_path / 'cal')
    w = np.asarray(config['training']['seg_class_weights'])
    bias = (new.seg_head.bias - raw.seg_head.bias).detach().numpy()
    assert np.allclose(bias, -cal.tau * np.log(w), atol=1e-5)
    assert config['seg_prior_correction']['tau'] == cal.tau
    x = torch.rand(1, 3, 128, 160)
    with torch.inference_mode():
        a, b = raw(x), new(x)
    for key in ('heatmap', 'descriptors'):  # the keypoint and descriptor heads are untouched
        assert torch.equal(a[key], b[key]), key
    shift = torch.as_tensor(bias, dtype=torch.float32)[None, :, None, None]
    assert torch.allclose(b['segmentation_logits'], a['segmentation_logits'] + shift, atol=1e-5)
    card = (tmp_path / 'cal' / 'MODEL_CARD.md').read_text()
    assert card.startswith('# card') and card.count(CARD_BEGIN) == 1
    assert f'tau = {cal.tau:g}' in card


def test_calibrating_twice_gives_the_same_weights(setup: Path, tmp_path: Path) -> None:
    conf = _conf(setup, taus=[1.0])  # a tau that moves the bias for sure
    main(conf, setup / 'trained', tmp_path / 'once', progress=False)
    again = main(conf, tmp_path / 'once', tmp_path / 'once', progress=False)  # in place
    once, _ = load_weights(setup / 'trained')
    twice, config = load_weights(tmp_path / 'once')
    w = np.asarray(config['training']['seg_class_weights'])
    assert again.tau == 1.0
    assert np.allclose((twice.seg_head.bias - once.seg_head.bias).detach().numpy(), -np.log(w),
                       atol=1e-5)
    card = (tmp_path / 'once' / 'MODEL_CARD.md').read_text()
    assert card.count(CARD_BEGIN) == 1  # the section is replaced, not appended again


def test_bad_inputs_are_refused(setup: Path, tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(DatasetError, match='excluded'):
        main(_conf(setup, train_shards=[str(setup / 'test' / '*.npz')]), setup / 'trained',
             tmp_path / 'x', progress=False)
    with pytest.raises(DatasetError, match='share worlds'):
        main(_conf(setup, val_shards=[str(setup / 'train' / '*.npz')]), setup / 'trained',
             tmp_path / 'x', progress=False)
    small = make_shard(tmp_path / 'small' / 's14.npz', n=2, seed=14, cam=CAM.scaled(80, 64))
    with pytest.raises(DatasetError, match=r'held-out shards rendered at 80x64 px, training '
                                           r'shards at 160x128 px'):
        main(_conf(setup, val_shards=[str(small)]), setup / 'trained', tmp_path / 'x',
             progress=False)
    assert not (tmp_path / 'x').exists()
    with pytest.raises(DatasetError, match='no training shards'):
        main(_conf(setup, train_shards=[str(tmp_path / 'none' / '*.npz')]), setup / 'trained',
             tmp_path / 'x', progress=False)
    plain = tmp_path / 'plain'
    raw, config = load_weights(setup / 'trained')
    save_weights(raw, plain, {'class_names': config['class_names'], 'input_size': [160, 128]})
    with pytest.raises(WeightsFormatError, match='seg_class_weights'):
        main(_conf(setup), plain, tmp_path / 'x', progress=False)
    assert cli(['--weights', str(tmp_path / 'missing.safetensors'), '--train-shards',
                str(setup / 'train' / '*.npz'), '--out', str(tmp_path / 'y')]) == 1
    err = capsys.readouterr().err
    assert err.startswith('semfeat-calibrate-seg: error: weights file not found')
    assert err.count('\n') == 1
    assert cli(['--weights', str(setup / 'trained'), '--train-shards',
                str(setup / 'train' / '*.npz'), '--frames-per-shard', '1', '--no-progress',
                '--out', str(tmp_path / 'z')]) == 0
    out = capsys.readouterr().out
    assert out.startswith('semfeat-calibrate-seg: tau ') and (tmp_path / 'z' / 'semfeat.json'
                                                              ).is_file()
    assert json.loads((tmp_path / 'z' / 'semfeat.json').read_text())['seg_prior_correction'][
        'val_before'] is None
