"""Training loop (smoke test: the loss goes down), resume, CLI, schedule, metrics, configs."""
from __future__ import annotations

import csv
import json
from pathlib import Path

from conftest import REPO
import numpy as np
import pytest
from test_model_data import CAM, make_shard
import torch
import yaml

from semfeat_ros.model import load_model_yaml
from semfeat_ros.model.errors import DatasetError, ModelConfigError
from semfeat_ros.model.extractor import FeatureExtractor
from semfeat_ros.model.metrics import (
    confusion_matrix,
    matching_precision,
    mean_iou,
    mutual_nn,
    repeatability,
    subset_iou,
)
from semfeat_ros.model.semfeatnet import SemFeatNet
from semfeat_ros.model.training import (
    init_from,
    load_train_conf,
    lr_factor,
    main,
    set_frozen,
    set_train_only,
)
from semfeat_ros.model.weights_io import load_weights, state_dict_allclose
from semfeat_ros.tools.train import cli, read_config

TINY = {
    'steps': 20, 'batch_size': 2, 'val_every': 10, 'val_pairs': 2, 'num_workers': 0,
    'lr': 3e-3, 'lr_ramp_steps': 2,
    'network': {'encoder_channels': [8, 16, 16, 24], 'decoder_channels': 16,
                'descriptor_dim': 16, 'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8},
    'data': {'frame_long_side': 160, 'crop_size': [96, 96], 'num_points': 64,
             'photo_adaptation': 2},
}


@pytest.fixture(scope='module')
def shards(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp('train_shards')
    for s in (1, 2):
        make_shard(d / 'train' / f's{s}.npz', n=4, seed=s)
    make_shard(d / 'val' / 's3.npz', n=3, seed=3)
    return d


def tiny_conf(shards: Path, **over: object) -> dict:
    return {**TINY, 'train_shards': [str(shards / 'train' / '*.npz')],
            'val_shards': [str(shards / 'val' / '*.npz')], **over}


def _losses(out: Path) -> np.ndarray:
    with open(out / 'train_log.csv', newline='') as f:
        return np.array([float(r['loss']) for r in csv.DictReader(f)])


def test_training_smoke_loss_goes_down_and_outputs_work(shards: Path, tmp_path: Path) -> None:
    out = tmp_path / 'run'
    summary = main(tiny_conf(shards), out, export=tmp_path / 'export', progress=False)
    loss = _losses(out)
    assert len(loss) == 20
    assert loss[-5:].mean() < 0.9 * loss[:5].mean(), loss
    for name in ('semfeat.safetensors', 'semfeat.json', 'val_log.csv', 'config.json',
                 'summary.json', 'plots/losses.png', 'plots/metrics.png',
                 'checkpoints/last.pt'):
        assert (out / name).is_file(), name
    for name in ('semfeat.safetensors', 'semfeat.json', 'MODEL_CARD.md', 'training_losses.png'):
        assert (tmp_path / 'export' / name).is_file(), name
    card = (tmp_path / 'export' / 'MODEL_CARD.md').read_text()
    assert 'world seeds [1, 2]' in card and 'real_fisheye_calib' in card
    assert 0.0 <= summary['val_repeatability'] <= 1.0 and np.isfinite(summary['val_miou'])
    model, config = load_weights(out)
    assert config['input_size'] == [160, 128] and config['training']['train_seeds'] == [1, 2]
    feats = FeatureExtractor(out / 'semfeat.safetensors',
                             {'detection_threshold': 0.0}).extract(
        np.random.default_rng(0).integers(0, 255, (256, 320, 3), dtype=np.uint8))
    assert len(feats) > 0 and feats.descriptors.shape[1] == 16


def test_resume_reproduces_an_uninterrupted_run(shards: Path, tmp_path: Path) -> None:
    conf = tiny_conf(shards, steps=6, val_every=6)
    main(conf, tmp_path / 'full', progress=False)
    paused = main(conf, tmp_path / 'chunked', progress=False, stop_after=3)
    assert paused['stopped'] and paused['steps'] == 3
    assert not (tmp_path / 'chunked' / 'semfeat.safetensors').exists()
    main(conf, tmp_path / 'chunked', progress=False, resume=True)
    a, _ = load_weights(tmp_path / 'full')
    b, _ = load_weights(tmp_path / 'chunked')
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert ka == kb
        torch.testing.assert_close(va, vb, atol=1e-5, rtol=1e-4)
    np.testing.assert_allclose(_losses(tmp_path / 'full'), _losses(tmp_path / 'chunked'),
                               rtol=1e-4)


def test_fine_tune_trains_only_the_named_parameters(shards: Path, tmp_path: Path) -> None:
    main(tiny_conf(shards, steps=4, val_every=4), tmp_path / 'base', progress=False)
    net = {**TINY['network'], 'seg_stride': 2, 'seg_context_blocks': 1}
    conf = tiny_conf(shards, steps=6, val_every=6, network=net, warmup_fraction=0.0,
                     init_weights=str(tmp_path / 'base' / 'semfeat.safetensors'),
                     train_only=['decoder1.seg', 'mixer.seg', 'seg_'],
                     loss={'seg_loss_stride': 2})
    main(conf, tmp_path / 'fine', export=tmp_path / 'export', progress=False)
    base, _ = load_weights(tmp_path / 'base')
    tuned, meta = load_weights(tmp_path / 'fine')
    assert meta['training']['initialised_tensors'] and \
        all(k.startswith(('seg_fine', 'seg_context.0.'))
            for k in meta['training']['initialised_tensors'])
    old, new = base.state_dict(), tuned.state_dict()
    changed = {k for k in old if not torch.equal(old[k], new[k])}
    assert changed and all(k.startswith(('decoder1.seg.', 'mixer.seg.', 'seg_')) for k in changed)
    assert new['seg_fine_head.weight'].abs().sum() > 0  # the zero-initialised head learned
    x = torch.randn(1, 3, 64, 96)
    with torch.inference_mode():  # keypoints and descriptors exactly as before
        a, b = base.eval()(x), tuned.eval()(x)
    for k in ('heatmap', 'descriptors'):
        torch.testing.assert_close(a[k], b[k], atol=0, rtol=0)
    assert b['segmentation_logits'].shape[-2:] == (32, 48)
    card = (tmp_path / 'export' / 'MODEL_CARD.md').read_text()
    assert 'Fine-tuned from' in card and 'stride 2 logits' in card
    assert '1 dilated inverted-residual block(s) at stride 8' in card
    assert 'inverted-residual block(s) at stride 4' not in card
    with pytest.raises(ModelConfigError, match='match no parameter'):
        main(tiny_conf(shards, train_only=['seg_nope']), tmp_path / 'o', progress=False)
    with pytest.raises(ModelConfigError, match='other shapes'):
        init_from(SemFeatNet({**TINY['network'], 'seg_channels': 4}),
                  tmp_path / 'base' / 'semfeat.safetensors')


def test_keypoint_fine_tune_inserts_the_refinement_and_keeps_the_rest(shards: Path,
                                                                     tmp_path: Path) -> None:
    main(tiny_conf(shards, steps=4, val_every=4), tmp_path / 'base', progress=False)
    net = {**TINY['network'], 'kp_refine_channels': 2}
    conf = tiny_conf(shards, steps=6, val_every=6, network=net, warmup_fraction=0.0, lr=1e-2,
                     init_weights=str(tmp_path / 'base' / 'semfeat.safetensors'),
                     train_only=['decoder1.kp', 'mixer.kp', 'kp_'],
                     loss={'w_desc': 0.0, 'w_seg': 0.0, 'kp_cell_weight': 1.0})
    main(conf, tmp_path / 'fine', export=tmp_path / 'export', progress=False)
    base, _ = load_weights(tmp_path / 'base')
    tuned, meta = load_weights(tmp_path / 'fine')
    assert meta['training']['initialised_tensors'] and \
        all(k.startswith('kp_refine.') for k in meta['training']['initialised_tensors'])
    assert tuned.kp_refine[-1].weight.abs().sum() > 0  # the zero-initialised layer learned
    x = torch.randn(1, 3, 64, 96)
    with torch.inference_mode():
        a, b = base.eval()(x), tuned.eval()(x)
    for k in ('descriptors', 'segmentation_logits'):  # exactly as before
        torch.testing.assert_close(a[k], b[k], atol=0, rtol=0)
    assert not torch.equal(a['heatmap'], b['heatmap'])
    card = (tmp_path / 'export' / 'MODEL_CARD.md').read_text()
    assert 'full-resolution correction (3 x 3x3 conv, 2 channels' in card


def test_config_base_and_network_overrides(tmp_path: Path) -> None:
    (tmp_path / 'model.yaml').write_text(yaml.safe_dump(
        {'network': {'seg_channels': 8, 'seg_stride': 2}}))
    (tmp_path / 'a.yaml').write_text(yaml.safe_dump(
        {'steps': 10, 'lr': 0.1, 'network': 'model.yaml', 'network_overrides': {'seg_stride': 4},
         'loss': {'w_kp': 2.0, 'w_seg': 3.0}}))
    (tmp_path / 'b.yaml').write_text(yaml.safe_dump(
        {'base': 'a.yaml', 'steps': 5, 'network_overrides': {'seg_stride': 2},
         'loss': {'w_seg': 0.5}}))
    a, b = read_config(tmp_path / 'a.yaml'), read_config(tmp_path / 'b.yaml')
    assert a['network'] == {'seg_channels': 8, 'seg_stride': 4} and a['steps'] == 10
    assert b['network'] == {'seg_channels': 8, 'seg_stride': 2}
    assert b['steps'] == 5 and b['lr'] == 0.1 and b['loss'] == {'w_kp': 2.0, 'w_seg': 0.5}
    assert 'base' not in b and 'network_overrides' not in b
    (tmp_path / 'c.yaml').write_text(yaml.safe_dump({'base': 'd.yaml'}))
    (tmp_path / 'd.yaml').write_text(yaml.safe_dump({'base': 'c.yaml'}))
    with pytest.raises(ValueError, match='cycle'):
        read_config(tmp_path / 'c.yaml')
    (tmp_path / 'e.yaml').write_text(yaml.safe_dump({'base': 'missing.yaml'}))
    with pytest.raises(FileNotFoundError, match='missing.yaml'):
        read_config(tmp_path / 'e.yaml')


def test_set_train_only_keeps_frozen_batchnorm_statistics() -> None:
    net = SemFeatNet({'encoder_channels': [8, 8, 16], 'decoder_channels': 8}).train()
    set_train_only(net, ['seg_'])
    enc_bn, seg_bn = net.encoder.blocks[0][0][1], net.seg_reduce[1]
    assert not enc_bn.training and seg_bn.training
    before = enc_bn.running_mean.clone()
    net(torch.randn(2, 3, 32, 32) * 3 + 1)['segmentation_logits'].mean().backward()
    torch.testing.assert_close(enc_bn.running_mean, before)
    assert all((p.grad is not None) == n.startswith('seg_') for n, p in net.named_parameters())


def test_cli(shards: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / 'train.yaml'
    cfg.write_text(yaml.safe_dump(tiny_conf(shards, steps=2, val_every=2)))
    assert cli(['--config', str(cfg), '--out', str(tmp_path / 'o'), '--no-progress']) == 0
    assert 'wrote' in capsys.readouterr().out
    assert cli(['--config', str(tmp_path / 'nope.yaml'), '--out', str(tmp_path / 'o')]) == 1
    err = capsys.readouterr().err
    assert err.startswith('semfeat-train: error: config file not found') and err.count('\n') == 1
    cfg.write_text(yaml.safe_dump({**tiny_conf(shards),
                                   'train_shards': [str(tmp_path / 'x/*.npz')],
                                   'data': {**TINY['data'], 'pair_mix': {'synthetic': 1.0}}}))
    assert cli(['--config', str(cfg), '--out', str(tmp_path / 'o')]) == 1
    assert 'no training shards' in capsys.readouterr().err
    cfg.write_text(yaml.safe_dump({**tiny_conf(shards), 'bogus': 1}))
    assert cli(['--config', str(cfg), '--out', str(tmp_path / 'o')]) == 1
    assert 'unknown training config key bogus' in capsys.readouterr().err
    cfg.write_text(': not yaml [')
    assert cli(['--config', str(cfg), '--out', str(tmp_path / 'o')]) == 1
    with pytest.raises(SystemExit) as exc:
        cli(['--out', str(tmp_path)])
    assert exc.value.code == 2


def test_test_seeds_and_overlap_are_refused(shards: Path, tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r'excluded \(test\) seeds \[2\]'):
        main(tiny_conf(shards, exclude_seeds=[2]), tmp_path / 'o', progress=False)
    with pytest.raises(DatasetError, match='overlap'):
        main(tiny_conf(shards, val_shards=[str(shards / 'train' / 's1.npz')]), tmp_path / 'o',
             progress=False)


def test_held_out_shards_rendered_at_another_size_are_refused(shards: Path,
                                                              tmp_path: Path) -> None:
    small = make_shard(tmp_path / 'val' / 's7.npz', n=3, seed=7, cam=CAM.scaled(80, 64))
    with pytest.raises(DatasetError, match=r'validation shards rendered at 80x64 px, training '
                                           r'shards at 160x128 px'):
        main(tiny_conf(shards, val_shards=[str(small)]), tmp_path / 'o', progress=False)
    assert not (tmp_path / 'o' / 'train_log.csv').exists()


def test_lr_schedule_and_freezing() -> None:
    c = load_train_conf({'steps': 100, 'lr_ramp_steps': 10, 'warmup_fraction': 0.2,
                         'min_lr_ratio': 0.1})
    assert lr_factor(0, c) == pytest.approx(0.1)
    assert lr_factor(9, c) == pytest.approx(1.0)
    assert lr_factor(15, c) == 1.0 and lr_factor(20, c) == pytest.approx(1.0)
    assert lr_factor(60, c) == pytest.approx(0.55)
    assert lr_factor(100, c) == pytest.approx(0.1)
    net = SemFeatNet({'encoder_channels': [8, 8, 16], 'decoder_channels': 8}).train()
    set_frozen(net, 1, True)
    bn = net.encoder.blocks[0][0][1]
    before = bn.running_mean.clone()
    out = net(torch.randn(2, 3, 32, 32) * 3 + 1)
    out['heatmap'].mean().backward()
    assert all(p.grad is None for p in net.encoder.blocks[0].parameters())
    assert any(p.grad is not None for p in net.encoder.blocks[1].parameters())
    torch.testing.assert_close(bn.running_mean, before)  # frozen BN statistics
    set_frozen(net, 1, False)
    assert all(p.requires_grad for p in net.parameters()) and bn.training


def test_metrics_hand_examples() -> None:
    gt = np.array([[0, 0, 1, 255]])
    pred = np.array([[0, 1, 1, 0]])
    cm = confusion_matrix(pred, gt, 3)
    assert cm.sum() == 3
    miou, iou = mean_iou(cm)
    assert iou[0] == pytest.approx(0.5) and iou[1] == pytest.approx(0.5) and np.isnan(iou[2])
    assert miou == pytest.approx(0.5)
    assert subset_iou(np.array([0.2, 0.6, np.nan]), np.array([True, True])) == pytest.approx(0.4)
    assert np.isnan(subset_iou(iou, np.array([False, False, True])))  # only absent classes

    def shift(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return p + [10.0, 0.0], p[:, 0] < 50

    def unshift(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return p - [10.0, 0.0], p[:, 0] < 60

    kp_a = np.array([[0.0, 0.0], [20.0, 5.0], [100.0, 0.0]])  # last one has no GT in b
    kp_b = np.array([[11.0, 0.0], [40.0, 40.0]])
    rep, checked = repeatability(kp_a, kp_b, shift, unshift, tol=2.0)
    # a->b: 2 checked, 1 repeated; b->a: 2 checked ((11,0)->(1,0) repeated, (40,40) not)
    assert checked == 4 and rep == pytest.approx(0.5)
    da = np.eye(3)[[0, 1, 2]].astype(np.float32)
    db = np.eye(3)[[0, 2]].astype(np.float32)
    assert mutual_nn(da, db).tolist() == [[0, 0], [2, 1]]
    prec, correct, scored = matching_precision(kp_a, kp_b, da, db, shift, tol=2.0)
    assert (correct, scored) == (1, 1) and prec == 1.0  # (100,0) has no GT -> not scored


def test_shipped_config_files_match_the_code() -> None:
    cfg = load_model_yaml()
    shipped, meta = load_weights(None)
    assert cfg['network'] == shipped.conf  # the architecture of the shipped weights
    raw = yaml.safe_load((REPO / 'config' / 'model.yaml').read_text())
    assert set(raw['extractor']) == set(FeatureExtractor.default_conf)  # every key documented
    assert set(raw['network']) == set(SemFeatNet.default_conf)
    conf = load_train_conf(read_config(REPO / 'config' / 'train.yaml'))
    net3 = {**shipped.conf, 'kp_refine_channels': 0}  # the network of stage 3
    net2 = {**net3, 'seg_context_blocks': 0}  # of stage 2
    assert conf['network'] == {**net2, 'seg_stride': 4}  # stage 1
    stage2 = load_train_conf(read_config(REPO / 'config' / 'finetune_seg.yaml'))
    assert stage2['network'] == net2 and net2['seg_stride'] == 2
    assert stage2['init_weights'] and stage2['train_only'] and stage2['data'] == conf['data']
    stage3 = load_train_conf(read_config(REPO / 'config' / 'finetune_seg_ctx_light.yaml'))
    assert stage3['network'] == net3
    assert shipped.conf['seg_context_blocks'] == 2 and shipped.conf['seg_blocks'] == 0
    assert stage2['train_only'] == stage3['train_only']
    stage4 = load_train_conf(read_config(REPO / 'config' / 'finetune_kp.yaml'))
    assert stage4['network'] == shipped.conf  # stage 4: the keypoint refinement
    assert shipped.conf['kp_refine_channels'] == 8
    assert stage4['init_weights'] == stage3['init_weights'].replace('train_v5', 'train_v8')
    assert stage4['data'] == conf['data']  # stage 1's views and photos
    stage5 = load_train_conf(read_config(REPO / 'config' / 'distill.yaml'))
    assert stage5['network'] == shipped.conf and stage5['teacher'] == 'xfeat'
    stage6 = load_train_conf(read_config(REPO / 'config' / 'distill_long.yaml'))
    stage7 = load_train_conf(read_config(REPO / 'config' / 'distill_stage7.yaml'))
    stage8 = load_train_conf(read_config(REPO / 'config' / 'distill_stage8.yaml'))
    assert stage6['init_weights'] == stage5['init_weights'].replace('train_v9', 'train_v10')
    assert stage7['init_weights'] == stage6['init_weights'].replace('train_v10', 'train_v11')
    assert stage8['init_weights'] == stage7['init_weights'].replace('train_v11', 'train_v12')
    for stage in (stage6, stage7, stage8):  # stage 5's recipe with more photos and distillation
        assert stage['network'] == shipped.conf and stage['teacher'] == 'xfeat'
        assert stage['loss']['distill_desc_weight'] > stage5['loss']['distill_desc_weight']
        assert stage['data']['pair_mix']['photo'] > stage5['data']['pair_mix']['photo']
    for stage in (stage7, stage8):  # stage 6's recipe, continued from the previous weights
        assert {k: v for k, v in stage6.items() if k not in ('init_weights', 'steps')} == \
            {k: v for k, v in stage.items() if k not in ('init_weights', 'steps')}
    stage9 = load_train_conf(read_config(REPO / 'config' / 'distill_stage9.yaml'))
    assert stage9['init_weights'] == stage8['init_weights'].replace('train_v12', 'train_v13')
    assert stage9['loss']['desc_dsm_weight'] > 0 == stage8['loss']['desc_dsm_weight']
    dsm = ('desc_dsm_weight', 'desc_dsm_temperature')
    assert {k: v for k, v in stage8['loss'].items() if k not in dsm} == \
        {k: v for k, v in stage9['loss'].items() if k not in dsm}  # stage 8's + the dual softmax
    assert {k: v for k, v in stage8.items() if k not in ('init_weights', 'steps', 'loss')} == \
        {k: v for k, v in stage9.items() if k not in ('init_weights', 'steps', 'loss')}
    stage10 = load_train_conf(read_config(REPO / 'config' / 'distill_stage10.yaml'))
    assert stage10['init_weights'] == stage9['init_weights'].replace('train_v13', 'train_v14')
    assert stage10['loss']['desc_dsm_weight'] > stage9['loss']['desc_dsm_weight']
    assert {k: v for k, v in stage9['loss'].items() if k != 'desc_dsm_weight'} == \
        {k: v for k, v in stage10['loss'].items() if k != 'desc_dsm_weight'}
    assert {k: v for k, v in stage9.items() if k not in ('init_weights', 'steps', 'loss')} == \
        {k: v for k, v in stage10.items() if k not in ('init_weights', 'steps', 'loss')}
    stage11 = load_train_conf(read_config(REPO / 'config' / 'distill_stage11.yaml'))
    assert stage11['init_weights'] == stage10['init_weights'].replace('train_v14', 'train_v15')
    assert stage11['loss']['kp_repeat_weight'] > 0 == stage10['loss']['kp_repeat_weight']
    assert stage11['data']['dense_flow'] and not stage10['data']['dense_flow']
    rep = ('kp_repeat_weight', 'kp_repeat_patch')
    assert {k: v for k, v in stage10['loss'].items() if k not in rep} == \
        {k: v for k, v in stage11['loss'].items() if k not in rep}  # stage 10's + consistency
    assert {k: v for k, v in stage10['data'].items() if k != 'dense_flow'} == \
        {k: v for k, v in stage11['data'].items() if k != 'dense_flow'}
    assert {k: v for k, v in stage10.items() if k not in ('init_weights', 'steps', 'loss',
                                                          'data')} == \
        {k: v for k, v in stage11.items() if k not in ('init_weights', 'steps', 'loss', 'data')}
    stage12 = load_train_conf(read_config(REPO / 'config' / 'distill_stage12.yaml'))
    assert stage12['init_weights'] == stage11['init_weights'].replace('train_v15', 'train_v16')
    assert stage12['loss']['desc_dsm_neg_radius'] < stage11['loss']['desc_neg_radius']
    assert stage11['loss']['desc_dsm_neg_radius'] is None  # stage 11: the contrastive radius
    assert {k: v for k, v in stage11['loss'].items() if k != 'desc_dsm_neg_radius'} == \
        {k: v for k, v in stage12['loss'].items() if k != 'desc_dsm_neg_radius'}
    assert {k: v for k, v in stage11.items() if k not in ('init_weights', 'steps', 'loss')} == \
        {k: v for k, v in stage12.items() if k not in ('init_weights', 'steps', 'loss')}
    kept = json.loads((REPO / 'stages' / 'stage12' / 'semfeat.json').read_text())
    assert kept['training']['init_weights'] == stage12['init_weights']  # committed weights
    # three quarters of each batch on the photographs, then once more: the shipped weights
    photo = load_train_conf(read_config(REPO / 'config' / 'distill_photo075.yaml'))
    photo2 = load_train_conf(read_config(REPO / 'config' / 'distill_photo075_2.yaml'))
    assert photo['data']['pair_mix']['photo'] == 0.75 > stage12['data']['pair_mix']['photo']
    assert {k: v for k, v in stage12['data'].items() if k != 'pair_mix'} == \
        {k: v for k, v in photo['data'].items() if k != 'pair_mix'}
    assert {k: v for k, v in stage12.items() if k not in ('init_weights', 'data')} == \
        {k: v for k, v in photo.items() if k not in ('init_weights', 'data')}
    assert {k: v for k, v in photo.items() if k != 'init_weights'} == \
        {k: v for k, v in photo2.items() if k != 'init_weights'}
    staged = json.loads((REPO / 'stages' / 'photo075' / 'semfeat.json').read_text())
    assert staged['training']['init_weights'] == photo['init_weights']
    assert photo2['init_weights'] == 'stages/photo075/semfeat.safetensors'
    assert meta['training']['init_weights'] == photo2['init_weights']
    assert meta['training']['train_only'] == photo2['train_only'] == stage12['train_only']
    assert meta['training']['teacher'] == 'xfeat'
    assert stage5['train_only'] == [] and stage5['warmup_fraction'] == 0.0  # the whole network
    assert stage5['init_weights'] == stage4['init_weights'].replace('train_v8', 'train_v9')
    assert stage5['loss']['distill_desc_weight'] > 0 and stage5['data']['photo_score'] == 'aliked'
    assert stage5['loss']['seg_lovasz_weight'] == stage2['loss']['seg_lovasz_weight']
    probe = load_train_conf(read_config(REPO / 'config' / 'finetune_joint.yaml'))
    assert probe['network'] == net2 and probe['train_only'] == []  # a probe over stage 2
    assert probe['loss'] == stage2['loss'] and probe['init_weights'] != stage2['init_weights']
    ctx = load_train_conf(read_config(REPO / 'config' / 'finetune_seg_ctx.yaml'))  # a probe
    assert ctx['network'] == {**net2, 'seg_context_blocks': 4, 'seg_blocks': 2}
    assert ctx['train_only'] == stage2['train_only'] and ctx['loss'] == stage2['loss']
    assert ctx['init_weights'] == probe['init_weights'] == stage3['init_weights']  # stage 2's
    assert ctx['data']['pair_mix']['photo'] == 0.0 and ctx['data']['crop_size'] == [512, 384]
    assert {k: v for k, v in stage3.items() if k != 'network'} == \
        {k: v for k, v in ctx.items() if k != 'network'}  # only the blocks differ
    # paper: AdamW 2e-4 over 100 epochs; the shipped recipe raises it for its CPU step budget
    assert conf['lr'] == 5e-4 and conf['warmup_fraction'] == 0.2
    assert conf['data']['rotation_deg'] == 30.0 and conf['data']['scale_range'] == [0.8, 1.2]
    with pytest.raises(ModelConfigError, match='unknown training config'):
        load_train_conf({'stepz': 3})
    with pytest.raises(ModelConfigError, match='freeze_levels'):
        load_train_conf({'freeze_levels': 9})
    with pytest.raises(ModelConfigError, match='dense_flow'):
        load_train_conf({'loss': {'kp_repeat_weight': 1.0}})
    with pytest.raises(ModelConfigError, match='kp_reproj_weight > 0 needs data.dense_flow'):
        load_train_conf({'loss': {'kp_reproj_weight': 1.0}})
    # the reprojection probe: the shipped recipe from the shipped weights plus that one term
    reproj = load_train_conf(read_config(REPO / 'config' / 'distill_reproj.yaml'))
    assert reproj['loss']['kp_reproj_weight'] > 0 == photo2['loss']['kp_reproj_weight']
    assert {k: v for k, v in reproj['loss'].items() if k != 'kp_reproj_weight'} == \
        {k: v for k, v in photo2['loss'].items() if k != 'kp_reproj_weight'}
    assert {k: v for k, v in reproj.items() if k not in ('init_weights', 'steps', 'loss')} == \
        {k: v for k, v in photo2.items() if k not in ('init_weights', 'steps', 'loss')}
    with pytest.raises(ModelConfigError, match='multiples of the network stride, 8 px'):
        load_train_conf({'network': {'encoder_channels': [8, 8, 8]},
                         'data': {'crop_size': [96, 100]}})


def test_state_dict_allclose() -> None:
    a = SemFeatNet({'encoder_channels': [8, 8, 8]})
    b = SemFeatNet({'encoder_channels': [8, 8, 8]})
    assert not state_dict_allclose(a, b)
    b.load_state_dict(a.state_dict())
    assert state_dict_allclose(a, b)
