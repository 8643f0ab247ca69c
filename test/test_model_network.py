"""SemFeatNet, the Cross-Task Mixer Module and the losses."""
from __future__ import annotations

import math
from pathlib import Path
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F  # noqa: N812

from semfeat_ros.model.errors import ModelConfigError, ModelInputError
from semfeat_ros.model.losses import (
    MultiTaskLoss,
    descriptor_loss,
    dual_softmax_loss,
    keypoint_cell_loss,
    keypoint_loss,
    keypoint_peaky_loss,
    keypoint_repeat_loss,
    keypoint_reprojection_loss,
    lovasz_softmax_loss,
    sample_descriptors,
    segmentation_loss,
)
from semfeat_ros.model.semfeatnet import (
    CrossTaskMixer,
    SemFeatNet,
    count_parameters,
    fuse_batchnorm,
    normalize_image,
)

sys.path.insert(0, str(Path(__file__).parent / 'helpers'))
from nets import perturb_batchnorm  # noqa: E402


def _reference_ctmm(z: np.ndarray, tasks: np.ndarray, wq: np.ndarray, wk: np.ndarray,
                    wv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Equations (2)-(5) written literally, one location at a time (float64)."""
    _, _, h, w = z.shape
    d = wq.shape[0]
    K = wk @ tasks.T  # (d, 3): column t = W_k z_t
    V = wv @ tasks.T  # (d, 3)
    out = np.zeros((1, d, h, w))
    alphas = np.zeros((1, 3, h, w))
    for u in range(h):
        for v in range(w):
            q = wq @ z[0, :, u, v]  # (d,)
            s = q @ K / math.sqrt(d)  # (3,)
            a = np.exp(s - s.max())
            a /= a.sum()
            alphas[0, :, u, v] = a
            out[0, :, u, v] = sum(a[t] * V[:, t] for t in range(3))
    return out, alphas


def test_ctmm_matches_handwritten_reference() -> None:
    torch.manual_seed(0)
    d_enc, d_task, d = 5, 4, 6
    mixer = CrossTaskMixer(d_enc, d_task, d).double()
    z = torch.randn(1, d_enc, 3, 4, dtype=torch.float64)
    tasks = torch.randn(3, d_task, dtype=torch.float64) * 2.0
    z_tilde, alpha = mixer.mix(z, tasks)
    wq = mixer.w_q.weight.detach().numpy()[:, :, 0, 0]  # (d, d_enc)
    wk = mixer.w_k.weight.detach().numpy()  # (d, d_task)
    wv = mixer.w_v.weight.detach().numpy()
    ref, ref_alpha = _reference_ctmm(z.numpy(), tasks.numpy(), wq, wk, wv)
    np.testing.assert_allclose(z_tilde.detach().numpy(), ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(alpha.detach().numpy(), ref_alpha, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(alpha.sum(dim=1).detach().numpy(), 1.0, atol=1e-12)
    # the attention really varies per location (not a constant mixture)
    assert alpha.detach().std(dim=(2, 3)).max() > 1e-3


def test_ctmm_fusion_modes() -> None:
    torch.manual_seed(1)
    z = torch.randn(2, 8, 5, 6)
    tasks = torch.randn(3, 4)
    add = CrossTaskMixer(8, 4, 6, fusion='add').eval()
    z_tilde, _ = add.mix(z, tasks)
    expected = z + F.conv2d(z_tilde, add.fuse.weight)
    torch.testing.assert_close(add(z, tasks), expected)
    cat = CrossTaskMixer(8, 4, 6, fusion='concat').eval()
    out = cat(z, tasks)
    assert out.shape == z.shape and (out >= 0).all()  # ReLU after the 1x1 conv
    with pytest.raises(ModelConfigError, match='mixer_fusion'):
        CrossTaskMixer(8, 4, 6, fusion='sum')


@pytest.mark.parametrize('enc', [[8, 16, 24], [8, 16, 24, 32], [8, 8, 16, 16, 24]])
def test_forward_shapes_and_ranges(enc: list[int]) -> None:
    torch.manual_seed(0)
    net = SemFeatNet({'encoder_channels': enc, 'decoder_channels': 16, 'descriptor_dim': 24,
                      'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8}).eval()
    stride = 2 ** len(enc)
    h, w = 2 * stride, 3 * stride
    with torch.inference_mode():
        out = net(torch.randn(2, 3, h, w))
    assert out['keypoint_logits'].shape == (2, 1, h, w)
    assert out['heatmap'].shape == (2, h, w)
    assert ((out['heatmap'] >= 0) & (out['heatmap'] <= 1)).all()
    assert out['descriptors'].shape == (2, 24, h // 8, w // 8)
    torch.testing.assert_close(out['descriptors'].norm(dim=1), torch.ones(2, h // 8, w // 8))
    assert out['segmentation_logits'].shape == (2, 19, h // 4, w // 4)
    assert out['mixer_attention'].shape == (2, 3, 3, h // 8, w // 8)
    torch.testing.assert_close(out['mixer_attention'].sum(dim=2),
                               torch.ones(2, 3, h // 8, w // 8))


def test_heatmap_is_depth_to_space_of_cell_logits() -> None:
    torch.manual_seed(0)
    net = SemFeatNet({'encoder_channels': [8, 8, 8], 'decoder_channels': 8}).eval()
    cells = {}
    net.kp_head.register_forward_hook(lambda m, i, o: cells.setdefault('x', o))
    with torch.inference_mode():
        out = net(torch.randn(1, 3, 16, 24))
    c = cells['x']  # (1, 64, 2, 3)
    logits = out['keypoint_logits']
    for i, j, di, dj in [(0, 0, 0, 0), (1, 2, 7, 3), (0, 1, 5, 6)]:
        assert logits[0, 0, 8 * i + di, 8 * j + dj] == c[0, 8 * di + dj, i, j]
    torch.testing.assert_close(out['heatmap'], torch.sigmoid(logits[:, 0]))


def test_default_model_size_and_bn_fusion() -> None:
    torch.manual_seed(0)
    net = SemFeatNet()
    n = count_parameters(net)
    assert 200_000 < n < 2_000_000  # a few MB of fp32 weights
    perturb_batchnorm(net)  # non-trivial BN statistics, so folding is really exercised
    net.eval()
    x = torch.randn(1, 3, 64, 96)
    with torch.inference_mode():
        ref = net(x)
        fused = fuse_batchnorm(net)
        got = fused(x)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    for k in ('heatmap', 'descriptors', 'segmentation_logits'):
        torch.testing.assert_close(got[k], ref[k], atol=1e-4, rtol=1e-4)
    with pytest.raises(ModelConfigError, match='eval mode'):
        fuse_batchnorm(SemFeatNet().train())


def test_seg_layers_deepen_the_stride4_decoder_and_keep_old_keys() -> None:
    small = {'encoder_channels': [8, 16, 24], 'decoder_channels': 16, 'descriptor_dim': 16,
             'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8}
    one = SemFeatNet(small).state_dict()
    # checkpoints without seg_refine keys load unchanged
    assert not any(k.startswith('seg_refine') for k in one)
    torch.manual_seed(0)
    deep = SemFeatNet({**small, 'seg_layers': 3}).eval()
    extra = {k for k in deep.state_dict() if k not in one}
    assert extra and all(k.startswith('seg_refine.') for k in extra)
    assert len(deep.seg_refine) == 2
    x = torch.randn(1, 3, 32, 64)
    with torch.inference_mode():
        ref = deep(x)['segmentation_logits']
        assert ref.shape == (1, 19, 8, 16)
        torch.testing.assert_close(fuse_batchnorm(deep)(x)['segmentation_logits'], ref,
                                   atol=1e-4, rtol=1e-4)
    with pytest.raises(ModelConfigError, match='seg_layers'):
        SemFeatNet({**small, 'seg_layers': 0})


def test_seg_context_blocks_start_as_the_identity_and_fold() -> None:
    small = {'encoder_channels': [8, 16, 24], 'decoder_channels': 16, 'descriptor_dim': 16,
             'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8, 'seg_stride': 2}
    torch.manual_seed(0)
    plain = SemFeatNet(small).eval()
    assert not any(k.startswith(('seg_context', 'seg_blocks')) for k in plain.state_dict())
    ctx = SemFeatNet({**small, 'seg_context_blocks': 5, 'seg_blocks': 2,
                      'seg_block_expansion': 2}).eval()
    extra = set(ctx.state_dict()) - set(plain.state_dict())
    assert extra and all(k.startswith(('seg_context.', 'seg_blocks.')) for k in extra)
    dilations = [b.body[3].dilation[0] for b in ctx.seg_context]
    assert dilations == [1, 2, 4, 8, 1]
    assert ctx.seg_context[0].body[0].out_channels == 32  # 16 x expansion 2
    ctx.load_state_dict(plain.state_dict(), strict=False)
    x = torch.randn(1, 3, 32, 64)
    with torch.inference_mode():
        ref = plain(x)
        out = ctx(x)
        for k in ('heatmap', 'descriptors', 'segmentation_logits'):  # new blocks: identity
            torch.testing.assert_close(out[k], ref[k])
        perturb_batchnorm(ctx, ('seg_context', 'seg_blocks'))  # trained blocks: exact folding
        moved = ctx(x)['segmentation_logits']
        assert not torch.allclose(moved, ref['segmentation_logits'])
        torch.testing.assert_close(ctx(x)['heatmap'], ref['heatmap'])  # only the seg branch
        torch.testing.assert_close(fuse_batchnorm(ctx)(x)['segmentation_logits'], moved,
                                   atol=1e-4, rtol=1e-4)
    for key, bad in (('seg_context_blocks', -1), ('seg_blocks', -2), ('seg_block_expansion', 0)):
        with pytest.raises(ModelConfigError, match=key):
            SemFeatNet({**small, key: bad})


def test_seg_stride_2_refines_residually_from_the_stride4_logits() -> None:
    small = {'encoder_channels': [8, 16, 24], 'decoder_channels': 16, 'descriptor_dim': 16,
             'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8}
    torch.manual_seed(0)
    coarse = SemFeatNet(small).eval()
    fine = SemFeatNet({**small, 'seg_stride': 2}).eval()
    extra = set(fine.state_dict()) - set(coarse.state_dict())
    assert extra and all(k.startswith(('seg_fine.', 'seg_fine_head.')) for k in extra)
    fine.load_state_dict(coarse.state_dict(), strict=False)
    x = torch.randn(1, 3, 32, 64)
    with torch.inference_mode():
        ref = coarse(x)['segmentation_logits']
        out = fine(x)['segmentation_logits']
        assert out.shape == (1, 19, 16, 32)
        # the zero-initialised correction: exactly the upsampled stride-4 logits
        up = torch.nn.functional.interpolate(ref, size=(16, 32), mode='bilinear',
                                             align_corners=False)
        torch.testing.assert_close(out, up)
        torch.nn.init.normal_(fine.seg_fine_head.weight)
        moved = fine(x)['segmentation_logits']
        assert not torch.allclose(moved, up)
        torch.testing.assert_close(fuse_batchnorm(fine)(x)['segmentation_logits'], moved,
                                   atol=1e-4, rtol=1e-4)
    with pytest.raises(ModelConfigError, match='seg_stride'):
        SemFeatNet({**small, 'seg_stride': 8})


def test_config_and_input_validation() -> None:
    with pytest.raises(ModelConfigError, match='encoder_channels'):
        SemFeatNet({'encoder_channels': [8, 16]})
    with pytest.raises(ModelConfigError, match='unknown network config'):
        SemFeatNet({'widht': 3})
    with pytest.raises(ModelConfigError, match='descriptor_dim'):
        SemFeatNet({'descriptor_dim': 0})
    net = SemFeatNet().eval()
    with pytest.raises(ModelInputError, match='multiples of 32'):
        net(torch.randn(1, 3, 48, 64))
    with pytest.raises(ModelInputError, match=r'\(B, 3, H, W\)'):
        net(torch.randn(1, 1, 32, 32))


def test_normalize_image() -> None:
    u8 = torch.full((1, 3, 2, 2), 255, dtype=torch.uint8)
    torch.testing.assert_close(normalize_image(u8), normalize_image(u8.float() / 255.0))
    assert normalize_image(u8)[0, 0, 0, 0].item() == pytest.approx((1.0 - 0.45) / 0.25)


def test_gradients_reach_every_parameter() -> None:
    torch.manual_seed(0)
    net = SemFeatNet({'encoder_channels': [8, 8, 16], 'decoder_channels': 16}).train()
    out = net(torch.randn(2, 3, 32, 32))
    loss = (out['keypoint_logits'].mean() + out['descriptors'][:, 0].mean()
            + out['segmentation_logits'].mean())
    loss.backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum()]
    assert not missing, missing


# ---------------------------------------------------------------- losses


def test_keypoint_loss_is_weighted_bce_over_valid_pixels() -> None:
    logits = torch.tensor([[[2.0, -1.0], [0.5, -3.0]]])
    target = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])
    valid = torch.tensor([[[True, True], [False, True]]])
    p = torch.sigmoid(logits)
    w = 5.0
    terms = -(w * target * torch.log(p) + (1 - target) * torch.log(1 - p))
    expected = terms[valid].mean()
    got = keypoint_loss(logits[:, None], target, valid, pos_weight=w)
    torch.testing.assert_close(got, expected)
    torch.testing.assert_close(keypoint_loss(logits, target, None, 1.0),
                               F.binary_cross_entropy_with_logits(logits, target))
    with pytest.raises(ModelInputError):
        keypoint_loss(logits, target[:, :1])


def test_keypoint_cell_loss_is_a_softmax_over_each_keypoint_cell() -> None:
    torch.manual_seed(0)
    logits = torch.randn(1, 8, 16)  # two 8x8 cells side by side
    target = torch.zeros(1, 8, 16)
    target[0, 2, 3] = 1.0  # cell 0: one keypoint
    valid = torch.ones(1, 8, 16, dtype=torch.bool)
    valid[0, 0, 0] = False  # an invalid pixel leaves cell 0's softmax
    # cell 1 has no keypoint: it takes no part
    cell0 = logits[0, :, :8].reshape(-1)
    keep = valid[0, :, :8].reshape(-1)
    expected = -(cell0[2 * 8 + 3] - torch.logsumexp(cell0[keep], dim=0))
    torch.testing.assert_close(keypoint_cell_loss(logits[:, None], target, valid), expected)
    # two keypoints in one cell share the target evenly
    target[0, 5, 6] = 1.0
    two = 0.5 * (2 * torch.logsumexp(cell0[keep], 0) - cell0[2 * 8 + 3] - cell0[5 * 8 + 6])
    torch.testing.assert_close(keypoint_cell_loss(logits, target, valid), two)
    # the right peak costs less than a peak one pixel off
    sharp = torch.full((1, 8, 8), -5.0)
    off = sharp.clone()
    sharp[0, 2, 3] = 5.0
    off[0, 2, 4] = 5.0
    t = torch.zeros(1, 8, 8)
    t[0, 2, 3] = 1.0
    assert keypoint_cell_loss(sharp, t) < 0.01 < keypoint_cell_loss(off, t)
    assert keypoint_cell_loss(logits, torch.zeros(1, 8, 16)) == 0.0
    with pytest.raises(ModelInputError):
        keypoint_cell_loss(logits, target[:, :1])


def test_kp_cell_weight_adds_the_cell_term_to_the_keypoint_loss() -> None:
    torch.manual_seed(0)
    pred = {'keypoint_logits': torch.randn(2, 1, 8, 8),
            'descriptors': F.normalize(torch.randn(2, 4, 1, 1), dim=1),
            'segmentation_logits': torch.randn(2, 19, 2, 2)}
    target = torch.zeros(2, 8, 8)
    target[0, 3, 4] = 1.0
    batch = {'kp_target': target, 'kp_valid': torch.ones(2, 8, 8, dtype=torch.bool),
             'label': torch.full((2, 8, 8), 255), 'points_a': torch.zeros(1, 1, 2),
             'points_b': torch.zeros(1, 1, 2), 'corr_valid': torch.zeros(1, 1, dtype=torch.bool)}
    _, base = MultiTaskLoss({'w_desc': 0.0, 'w_seg': 0.0})(pred, batch)
    _, logs = MultiTaskLoss({'w_desc': 0.0, 'w_seg': 0.0, 'kp_cell_weight': 0.5})(pred, batch)
    cell = float(keypoint_cell_loss(pred['keypoint_logits'], target, batch['kp_valid']))
    assert logs['kp_cell'] == pytest.approx(cell)
    assert logs['kp'] == pytest.approx(base['kp'] + 0.5 * cell)
    assert 'kp_cell' not in base


def test_pixel_branch_feeds_the_keypoint_head() -> None:
    torch.manual_seed(0)
    conf = {'encoder_channels': [8, 8, 16], 'decoder_channels': 16, 'kp_pixel_channels': 8,
            'kp_head_layers': 2}
    net = SemFeatNet(conf).train()
    x = torch.randn(2, 3, 32, 32, requires_grad=True)
    out = net(x)
    out['keypoint_logits'].mean().backward()
    assert net.kp_pixels is not None
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.kp_pixels.parameters())
    assert len(net.kp_head) == 3  # two hidden layers + the 64-logit conv
    assert SemFeatNet({'encoder_channels': [8, 8, 16], 'kp_pixel_channels': 0}).kp_pixels is None
    net.eval()
    with torch.inference_mode():
        ref = net(x.detach())['heatmap']
        got = fuse_batchnorm(net)(x.detach())['heatmap']
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-4)
    with pytest.raises(ModelConfigError, match='kp_pixel_channels'):
        SemFeatNet({'kp_pixel_channels': -1})
    with pytest.raises(ModelConfigError, match='kp_head_layers'):
        SemFeatNet({'kp_head_layers': 0})


def test_kp_refine_starts_as_the_identity_and_corrects_single_pixels() -> None:
    small = {'encoder_channels': [8, 16, 24], 'decoder_channels': 16, 'descriptor_dim': 16,
             'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8}
    torch.manual_seed(0)
    plain = SemFeatNet(small).eval()
    assert plain.kp_refine is None
    ref = SemFeatNet({**small, 'kp_refine_channels': 4}).eval()
    extra = set(ref.state_dict()) - set(plain.state_dict())
    assert extra and all(k.startswith('kp_refine.') for k in extra)
    ref.load_state_dict(plain.state_dict(), strict=False)
    x = torch.randn(1, 3, 32, 64)
    with torch.inference_mode():
        base = plain(x)
        out = ref(x)
        for k in ('keypoint_logits', 'heatmap', 'descriptors', 'segmentation_logits'):
            torch.testing.assert_close(out[k], base[k])  # inserted: the same network
        torch.nn.init.normal_(ref.kp_refine[-1].weight, std=0.5)  # trained: per-pixel changes
        moved = ref(x)
        delta = moved['keypoint_logits'] - base['keypoint_logits']
        cells = F.pixel_unshuffle(delta, 8)  # (1, 64, h, w): not constant within an 8x8 cell
        assert (cells.std(dim=1) > 1e-3).all()
        torch.testing.assert_close(moved['descriptors'], base['descriptors'])
        torch.testing.assert_close(moved['segmentation_logits'], base['segmentation_logits'])
    with pytest.raises(ModelConfigError, match='kp_refine_channels'):
        SemFeatNet({**small, 'kp_refine_channels': -1})


def test_sample_descriptors_cell_centres() -> None:
    desc = F.normalize(torch.randn(1, 4, 2, 3), dim=1)
    # cell (i, j) is centred at input px (8j + 3.5, 8i + 3.5)
    pts = torch.tensor([[[3.5, 3.5], [8 * 2 + 3.5, 8 + 3.5]]])
    got = sample_descriptors(desc, pts)
    torch.testing.assert_close(got[0, 0], desc[0, :, 0, 0])
    torch.testing.assert_close(got[0, 1], desc[0, :, 1, 2])


def _three_cell_maps() -> tuple[torch.Tensor, ...]:
    """Descriptor maps of one row of three cells with points on the cell centres (1x1-cell
    maps are constant): sim[i, j] = <a_i, b_j> = [[0.6, 0, -1], [0.8, 1, 0], [0.6, 0, -1]]."""
    da = torch.zeros(1, 2, 1, 3)
    db = torch.zeros(1, 2, 1, 3)
    da[0, :, 0, 0] = torch.tensor([1.0, 0.0])
    da[0, :, 0, 1] = torch.tensor([0.0, 1.0])
    da[0, :, 0, 2] = torch.tensor([1.0, 0.0])
    db[0, :, 0, 0] = torch.tensor([0.6, 0.8])
    db[0, :, 0, 1] = torch.tensor([0.0, 1.0])
    db[0, :, 0, 2] = torch.tensor([-1.0, 0.0])
    pts = torch.tensor([[[3.5, 3.5], [11.5, 3.5], [19.5, 3.5]]])
    valid = torch.tensor([[True, True, True]])
    return da, db, pts, valid


def test_descriptor_loss_hand_computed() -> None:
    da, db, pts, valid = _three_cell_maps()
    loss, stats = descriptor_loss(da, db, pts, pts, valid, pos_margin=1.0, neg_margin=0.2,
                                  neg_radius=4.0)
    # sim[i, j] = <a_i, b_j>
    sim = np.array([[0.6, 0.0, -1.0], [0.8, 1.0, 0.0], [0.6, 0.0, -1.0]])
    pos = np.diag(sim)
    pos_term = np.mean(np.maximum(0, 1.0 - pos))
    off = sim + np.diag([np.nan] * 3)
    hard_ab = np.nanmax(off, axis=1)
    hard_ba = np.nanmax(off, axis=0)
    neg_term = np.mean(np.maximum(0, np.concatenate([hard_ab, hard_ba]) - 0.2))
    assert loss.item() == pytest.approx(pos_term + neg_term, abs=1e-6)
    assert stats['pos_sim'].item() == pytest.approx(pos.mean(), abs=1e-6)
    # a radius covering every point leaves only the positive term
    loss_far, _ = descriptor_loss(da, db, pts, pts, valid, 1.0, 0.2, neg_radius=100.0)
    assert loss_far.item() == pytest.approx(pos_term, abs=1e-6)
    # invalid rows are ignored entirely; no valid row -> 0
    loss_none, _ = descriptor_loss(da, db, pts, pts, torch.zeros_like(valid))
    assert loss_none.item() == 0.0


def test_dual_softmax_loss_hand_computed() -> None:
    da, db, pts, valid = _three_cell_maps()
    t = 0.5
    loss = dual_softmax_loss(da, db, pts, pts, valid, temperature=t, neg_radius=4.0)
    sim = np.array([[0.6, 0.0, -1.0], [0.8, 1.0, 0.0], [0.6, 0.0, -1.0]]) / t
    row = np.log(np.exp(sim).sum(axis=1)) - np.diag(sim)  # a_i against every b_j
    col = np.log(np.exp(sim).sum(axis=0)) - np.diag(sim)  # b_i against every a_j
    assert loss.item() == pytest.approx(0.5 * (row.mean() + col.mean()), abs=1e-5)
    # a radius covering every point leaves each point alone with its partner: NLL 0
    alone = dual_softmax_loss(da, db, pts, pts, valid, temperature=t, neg_radius=100.0)
    assert alone.item() == pytest.approx(0.0, abs=1e-6)
    # an invalid point is neither scored nor a negative of the others
    part = torch.tensor([[True, True, False]])
    keep = [0, 1]
    s2 = sim[np.ix_(keep, keep)]
    row2 = np.log(np.exp(s2).sum(axis=1)) - np.diag(s2)
    col2 = np.log(np.exp(s2).sum(axis=0)) - np.diag(s2)
    assert dual_softmax_loss(da, db, pts, pts, part, t, 4.0).item() == pytest.approx(
        0.5 * (row2.mean() + col2.mean()), abs=1e-5)
    assert dual_softmax_loss(da, db, pts, pts, torch.zeros_like(valid)).item() == 0.0
    # swapping the partners of two points raises the loss
    swapped = dual_softmax_loss(da, db, pts, pts[:, [1, 0, 2]], valid, t, 4.0)
    assert swapped.item() > loss.item()
    with pytest.raises(ModelConfigError, match='temperature'):
        dual_softmax_loss(da, db, pts, pts, valid, temperature=0.0)
    with pytest.raises(ModelConfigError, match='desc_dsm_temperature'):
        MultiTaskLoss({'desc_dsm_temperature': 0.0})


def test_dsm_neg_radius_is_its_own_or_the_contrastive_one() -> None:
    # points 8 and 16 px apart: a 20 px radius leaves each alone with its partner, 4 px keeps all
    da, db, pts, valid = _three_cell_maps()
    pred = {'keypoint_logits': torch.zeros(2, 1, 8, 24),
            'descriptors': torch.cat([da, db]),
            'segmentation_logits': torch.zeros(2, 19, 2, 6)}
    batch = {'kp_target': torch.zeros(2, 8, 24),
             'kp_valid': torch.ones(2, 8, 24, dtype=torch.bool),
             'label': torch.full((2, 8, 24), 255), 'points_a': pts, 'points_b': pts,
             'corr_valid': valid}
    conf = {'desc_dsm_weight': 1.0, 'desc_dsm_temperature': 0.5, 'desc_neg_radius': 20.0}
    _, same = MultiTaskLoss(conf)(pred, batch)
    _, own = MultiTaskLoss({**conf, 'desc_dsm_neg_radius': 4.0})(pred, batch)
    assert same['dsm'] == pytest.approx(0.0, abs=1e-6)
    assert own['dsm'] == pytest.approx(
        float(dual_softmax_loss(da, db, pts, pts, valid, 0.5, 4.0)), abs=1e-6)
    assert own['dsm'] > 0.1
    with pytest.raises(ModelConfigError, match='desc_dsm_neg_radius'):
        MultiTaskLoss({'desc_dsm_neg_radius': -1.0})


def _identity_flow(b: int, h: int, w: int) -> torch.Tensor:
    gu, gv = torch.meshgrid(torch.arange(w, dtype=torch.float32),
                            torch.arange(h, dtype=torch.float32), indexing='xy')
    return torch.stack([gu, gv], dim=-1)[None].repeat(b, 1, 1, 1)


def test_keypoint_repeat_loss_rewards_heatmaps_that_follow_the_flow() -> None:
    torch.manual_seed(0)
    b, h, w = 2, 32, 48
    heat_a = torch.randn(b, 1, h, w) * 3
    shifted = torch.roll(heat_a, shifts=3, dims=-1)  # view b: view a moved 3 px right
    logits = torch.cat([heat_a, shifted])
    flow = _identity_flow(b, h, w)
    flow[..., 0] += 3
    valid = torch.ones(b, h, w, dtype=torch.bool)
    valid[:, :, w - 3:] = False  # their partners fall outside view b
    follows = keypoint_repeat_loss(logits, flow, valid, patch=8)
    assert follows.item() == pytest.approx(0.0, abs=1e-5)
    # the same heatmaps read through the identity flow disagree
    ignores = keypoint_repeat_loss(logits, _identity_flow(b, h, w), valid, patch=8)
    assert ignores.item() > 0.2
    # hand check of one window: cosine of the two 8x8 heat patches
    one = keypoint_repeat_loss(logits[[0, 2]][:, :, :8, :8], _identity_flow(1, 8, 8),
                               torch.ones(1, 8, 8, dtype=torch.bool), patch=8)
    pa, pb = torch.sigmoid(logits[0, 0, :8, :8]), torch.sigmoid(logits[2, 0, :8, :8])
    cos = (pa * pb).sum() / (pa.norm() * pb.norm())
    assert one.item() == pytest.approx(1.0 - cos.item(), abs=1e-5)
    # no window with enough corresponding pixels: 0, and finite gradients where masked
    x = logits.clone().requires_grad_()
    none = keypoint_repeat_loss(x, flow, torch.zeros_like(valid), patch=8)
    assert none.item() == 0.0
    part = valid.clone()
    part[:, :, : w // 2] = False
    keypoint_repeat_loss(x, flow, part, patch=8).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    with pytest.raises(ModelInputError, match='flow'):
        keypoint_repeat_loss(logits, flow[:, :-1], valid)
    with pytest.raises(ModelConfigError, match='kp_repeat_patch'):
        MultiTaskLoss({'kp_repeat_patch': 7})
    with pytest.raises(ModelInputError, match='dense_flow'):
        MultiTaskLoss({'kp_repeat_weight': 1.0})(
            {'keypoint_logits': logits}, {'kp_target': torch.zeros(2 * b, h, w),
                                          'kp_valid': torch.ones(2 * b, h, w, dtype=torch.bool)})


def test_keypoint_peaky_loss_rewards_one_clear_peak_a_window() -> None:
    n, h, w = 2, 16, 24
    valid = torch.ones(n, h, w, dtype=torch.bool)
    flat = torch.zeros(n, 1, h, w)  # sigmoid 0.5 everywhere: max - mean = 0
    assert keypoint_peaky_loss(flat, valid, patch=8).item() == pytest.approx(1.0, abs=1e-6)
    peaked = torch.full((n, 1, h, w), -20.0)
    peaked[:, :, 2::4, 2::4] = 20.0  # a peak in every 8 px window (stride 4)
    loss = keypoint_peaky_loss(peaked, valid, patch=8)
    assert loss.item() == pytest.approx(1.0 - (1.0 - 4 / 64), abs=1e-4)
    # hand check of one window, half of it valid: max and mean over the valid pixels only
    x = torch.randn(1, 1, 8, 8) * 2
    half = torch.zeros(1, 8, 8, dtype=torch.bool)
    half[:, :, :4] = True
    p = torch.sigmoid(x[0, 0, :, :4])
    assert keypoint_peaky_loss(x, half, patch=8).item() == pytest.approx(
        1.0 - (p.max() - p.mean()).item(), abs=1e-5)
    # too few valid pixels: 0 with a graph; masked pixels get no gradient
    few = torch.zeros(1, 8, 8, dtype=torch.bool)
    few[:, 0, 0] = True
    assert keypoint_peaky_loss(x, few, patch=8).item() == 0.0
    g = x.clone().requires_grad_()
    keypoint_peaky_loss(g, half, patch=8).backward()
    assert torch.isfinite(g.grad).all() and g.grad[0, 0, :, :4].abs().sum() > 0
    assert (g.grad[0, 0, :, 4:] == 0).all()
    with pytest.raises(ModelInputError, match='valid'):
        keypoint_peaky_loss(x, valid, patch=8)
    # in the total loss: logged, and added with its weight
    torch.manual_seed(0)
    pred = {'keypoint_logits': torch.randn(2, 1, 8, 8),
            'descriptors': F.normalize(torch.randn(2, 4, 1, 1), dim=1),
            'segmentation_logits': torch.randn(2, 19, 2, 2)}
    batch = {'kp_target': torch.zeros(2, 8, 8), 'kp_valid': torch.ones(2, 8, 8, dtype=torch.bool),
             'label': torch.full((2, 8, 8), 255), 'points_a': torch.zeros(1, 1, 2),
             'points_b': torch.zeros(1, 1, 2), 'corr_valid': torch.zeros(1, 1, dtype=torch.bool)}
    base_total, base = MultiTaskLoss({'kp_repeat_patch': 4})(pred, batch)
    total, logs = MultiTaskLoss({'kp_peaky_weight': 2.0, 'kp_repeat_patch': 4})(pred, batch)
    peaky = float(keypoint_peaky_loss(pred['keypoint_logits'], batch['kp_valid'], patch=4))
    assert logs['peaky'] == pytest.approx(peaky) and 'peaky' not in base
    assert float(total) == pytest.approx(float(base_total) + 2.0 * peaky, abs=1e-5)
    with pytest.raises(ModelConfigError, match='kp_peaky_weight'):
        MultiTaskLoss({'kp_peaky_weight': -1.0})


def _blob_logits(points: list[tuple[float, float]], h: int, w: int) -> torch.Tensor:
    """(h, w) logits of Gaussian heat blobs (sigma 1 px) centred at sub-pixel (u, v)."""
    vv, uu = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing='ij')
    heat = torch.zeros(h, w)
    for u, v in points:
        heat = torch.maximum(heat, torch.exp(-((uu - u) ** 2 + (vv - v) ** 2) / 2))
    return torch.logit(heat.clamp(1e-4, 1 - 1e-4))


def test_keypoint_reprojection_loss_is_the_refined_peaks_offset_in_px() -> None:
    h, w, shift = 32, 40, (2.3, -1.4)  # view b: view a moved by a sub-pixel shift
    pts = [(8.2, 9.7), (20.4, 12.1), (14.6, 22.3), (30.5, 18.8)]
    flow = _identity_flow(1, h, w)
    flow[..., 0] += shift[0]
    flow[..., 1] += shift[1]
    valid = torch.ones(1, h, w, dtype=torch.bool)
    moved = [(u + shift[0], v + shift[1]) for u, v in pts]
    follows = torch.stack([_blob_logits(pts, h, w), _blob_logits(moved, h, w)])[:, None]
    # the centroid of a window truncated at 3 px is within a few hundredths of the blob centre
    assert keypoint_reprojection_loss(follows, flow, valid).item() < 0.08
    # view b's blobs 1 px right of where the flow puts them: the loss reads ~1 px
    off = [(u + 1.0, v) for u, v in moved]
    x = torch.stack([_blob_logits(pts, h, w), _blob_logits(off, h, w)])[:, None]
    x.requires_grad_()
    loss = keypoint_reprojection_loss(x, flow, valid)
    assert loss.item() == pytest.approx(1.0, abs=0.1)
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad[1].abs().sum() > 0
    # top_k 1 reads one peak only; peaks without a valid correspondence are not used
    assert keypoint_reprojection_loss(x, flow, valid, top_k=1).item() == pytest.approx(
        1.0, abs=0.1)
    none = keypoint_reprojection_loss(x, flow, torch.zeros_like(valid))
    assert none.item() == 0.0 and none.requires_grad
    # peaks moved outside view b count for nothing
    far = flow.clone()
    far[..., 0] += 100.0
    assert keypoint_reprojection_loss(x, far, valid).item() == 0.0
    with pytest.raises(ModelInputError, match='flow'):
        keypoint_reprojection_loss(x, flow[:, :-1], valid)
    with pytest.raises(ModelConfigError, match='kp_reproj_top_k'):
        MultiTaskLoss({'kp_reproj_top_k': 0})
    with pytest.raises(ModelConfigError, match='kp_reproj_radius'):
        MultiTaskLoss({'kp_reproj_radius': 2.5})
    with pytest.raises(ModelInputError, match='kp_reproj_weight'):
        MultiTaskLoss({'kp_reproj_weight': 1.0})(
            {'keypoint_logits': x}, {'kp_target': torch.zeros(2, h, w),
                                     'kp_valid': torch.ones(2, h, w, dtype=torch.bool)})
    # in the total loss: logged, and added with its weight
    torch.manual_seed(0)
    pred = {'keypoint_logits': x.detach(),
            'descriptors': F.normalize(torch.randn(2, 4, h // 8, w // 8), dim=1),
            'segmentation_logits': torch.randn(2, 19, h // 4, w // 4)}
    batch = {'kp_target': torch.zeros(2, h, w), 'kp_valid': torch.ones(2, h, w, dtype=torch.bool),
             'label': torch.full((2, h, w), 255), 'points_a': torch.zeros(1, 1, 2),
             'points_b': torch.zeros(1, 1, 2), 'corr_valid': torch.zeros(1, 1, dtype=torch.bool),
             'flow': flow, 'flow_valid': valid}
    base_total, base = MultiTaskLoss()(pred, batch)
    total, logs = MultiTaskLoss({'kp_reproj_weight': 0.5})(pred, batch)
    assert logs['reproj'] == pytest.approx(loss.item(), abs=1e-5) and 'reproj' not in base
    assert float(total) == pytest.approx(float(base_total) + 0.5 * loss.item(), abs=1e-4)


def test_segmentation_loss_ignores_255() -> None:
    torch.manual_seed(0)
    logits = torch.randn(1, 19, 2, 2)
    labels = torch.tensor([[[0, 255, 3, 4], [255, 255, 18, 1],
                            [2, 2, 255, 255], [5, 6, 7, 255]]])
    up = F.interpolate(logits, size=(4, 4), mode='bilinear', align_corners=False)
    keep = labels != 255
    expected = F.cross_entropy(up.permute(0, 2, 3, 1)[keep], labels[keep])
    torch.testing.assert_close(segmentation_loss(logits, labels), expected)
    assert segmentation_loss(logits, torch.full((1, 4, 4), 255)).item() == 0.0
    # at the logit resolution: labels sampled at the cell centres (stride 2 -> pixel 2i + 1)
    sub = labels[:, 1::2, 1::2]
    keep = sub != 255
    expected = F.cross_entropy(logits.permute(0, 2, 3, 1)[keep], sub[keep])
    torch.testing.assert_close(segmentation_loss(logits, labels, stride=2), expected)
    with pytest.raises(ModelInputError, match='multiple of the loss stride'):
        segmentation_loss(logits, labels[:, :3, :4], stride=2)


def test_segmentation_loss_between_logit_and_label_resolution() -> None:
    torch.manual_seed(1)
    logits = torch.randn(2, 19, 2, 3)  # stride 4 for 8 x 12 labels
    labels = torch.randint(0, 19, (2, 8, 12))
    labels[0, :, 5] = 255
    # stride 2: logits upsampled to the 4 x 6 grid, labels at pixels 2i + 1
    up = F.interpolate(logits, size=(4, 6), mode='bilinear', align_corners=False)
    sub = labels[:, 1::2, 1::2]
    keep = sub != 255
    expected = F.cross_entropy(up.permute(0, 2, 3, 1)[keep], sub[keep])
    torch.testing.assert_close(segmentation_loss(logits, labels, stride=2), expected)
    assert not torch.allclose(segmentation_loss(logits, labels, stride=4), expected)
    with pytest.raises(ModelInputError, match='finer than the loss stride'):
        segmentation_loss(torch.randn(2, 19, 8, 12), labels, stride=2)


def test_lovasz_softmax_is_one_minus_the_miou_of_hard_predictions() -> None:
    torch.manual_seed(2)
    labels = torch.randint(0, 4, (2, 8, 8))
    pred = torch.randint(0, 4, (2, 8, 8))
    labels[0, 0, :3] = 255
    logits = F.one_hot(pred, 5).permute(0, 3, 1, 2).float() * 100.0  # class 4: never present
    keep = labels != 255
    ious = [((labels == c) & (pred == c) & keep).sum()
            / (((labels == c) | (pred == c)) & keep).sum()
            for c in torch.unique(labels[keep]).tolist()]
    expected = 1.0 - torch.stack(ious).float().mean()
    torch.testing.assert_close(lovasz_softmax_loss(logits, labels), expected)
    assert lovasz_softmax_loss(F.one_hot(labels.clamp(max=4), 5).permute(0, 3, 1, 2).float()
                               * 100.0, labels).item() == pytest.approx(0.0, abs=1e-6)
    soft = torch.randn(2, 5, 4, 4, requires_grad=True)  # stride 2: on the 4 x 4 grid
    loss = lovasz_softmax_loss(soft, labels, stride=2)
    loss.backward()
    assert 0.0 < loss.item() < 1.0 and soft.grad.abs().sum() > 0
    assert lovasz_softmax_loss(soft, torch.full((2, 8, 8), 255)).item() == 0.0
    # in the multi-task loss: added to L_seg with its weight, and logged
    net = SemFeatNet({'encoder_channels': [8, 8, 16], 'decoder_channels': 16}).eval()
    out = net(torch.randn(2, 3, 32, 32))
    batch = {'kp_target': torch.zeros(2, 32, 32), 'kp_valid': torch.ones(2, 32, 32, dtype=bool),
             'label': torch.randint(0, 19, (2, 32, 32)), 'points_a': torch.rand(1, 4, 2) * 31,
             'points_b': torch.rand(1, 4, 2) * 31, 'corr_valid': torch.ones(1, 4, dtype=bool)}
    _, plain = MultiTaskLoss({})(out, batch)
    _, both = MultiTaskLoss({'seg_lovasz_weight': 0.5})(out, batch)
    assert 'seg_lovasz' not in plain
    assert both['seg'] == pytest.approx(plain['seg'] + 0.5 * both['seg_lovasz'], rel=1e-5)


def test_multitask_loss_weights() -> None:
    torch.manual_seed(0)
    net = SemFeatNet({'encoder_channels': [8, 8, 16], 'decoder_channels': 16}).train()
    pred = net(torch.randn(4, 3, 32, 32))
    batch = {
        'kp_target': (torch.rand(4, 32, 32) > 0.95).float(),
        'kp_valid': torch.ones(4, 32, 32, dtype=torch.bool),
        'label': torch.randint(0, 19, (4, 32, 32)),
        'points_a': torch.rand(2, 10, 2) * 31, 'points_b': torch.rand(2, 10, 2) * 31,
        'corr_valid': torch.ones(2, 10, dtype=torch.bool),
    }
    total, logs = MultiTaskLoss({'w_kp': 2.0, 'w_desc': 0.5, 'w_seg': 3.0})(pred, batch)
    assert total.item() == pytest.approx(2.0 * logs['kp'] + 0.5 * logs['desc'] + 3.0 * logs['seg'],
                                         rel=1e-5)
    with pytest.raises(ModelConfigError, match='unknown loss'):
        MultiTaskLoss({'w_foo': 1.0})
    with pytest.raises(ModelConfigError, match='w_kp'):
        MultiTaskLoss({'w_kp': -1.0})


def test_descriptor_loss_all_negatives_penalises_collapse() -> None:
    """With 'all' negatives a collapsed descriptor map costs (1 - alpha) on the negatives, and
    spread-out descriptors cost less: the dense term pushes every pair apart."""
    from semfeat_ros.model.losses import descriptor_loss

    torch.manual_seed(0)
    pts = torch.rand(1, 32, 2) * 120 + 4
    valid = torch.ones(1, 32, dtype=torch.bool)
    collapsed = F.normalize(torch.ones(1, 8, 16, 16), dim=1)
    loss_c, st = descriptor_loss(collapsed, collapsed, pts, pts, valid, 1.0, 0.2, 24.0, 'all')
    assert abs(float(loss_c) - 0.8) < 1e-5 and abs(float(st['pos_sim']) - 1.0) < 1e-5
    spread = F.normalize(torch.randn(1, 8, 16, 16), dim=1)
    loss_s, _ = descriptor_loss(spread, spread, pts, pts, valid, 1.0, 0.2, 24.0, 'all')
    loss_h, _ = descriptor_loss(spread, spread, pts, pts, valid, 1.0, 0.2, 24.0, 'hardest')
    assert float(loss_s) < float(loss_c)
    assert float(loss_s) < float(loss_h)  # the mean over all negatives is below the hardest
    with pytest.raises(ModelConfigError):
        descriptor_loss(spread, spread, pts, pts, valid, 1.0, 0.2, 24.0, 'some')


def test_descriptor_loss_sum_is_the_papers_sum_over_positives() -> None:
    """'sum': eq. 7 with both sums divided by |P| (hand computation on the 3-point example)."""
    da, db, pts, valid = _three_cell_maps()
    loss, _ = descriptor_loss(da, db, pts, pts, valid, 1.0, 0.2, 4.0, 'sum')
    sim = np.array([[0.6, 0.0, -1.0], [0.8, 1.0, 0.0], [0.6, 0.0, -1.0]])
    pos_term = np.maximum(0, 1.0 - np.diag(sim)).sum() / 3
    off = np.where(np.eye(3, dtype=bool), -np.inf, sim)
    neg_term = np.maximum(0, off - 0.2).sum() / 3  # 0.6, 0.8, 0.6 above alpha
    assert loss.item() == pytest.approx(pos_term + neg_term, abs=1e-6)
    # the violators weigh the same however many satisfied negatives there are ('all' dilutes)
    loss_all, _ = descriptor_loss(da, db, pts, pts, valid, 1.0, 0.2, 4.0, 'all')
    assert loss_all.item() == pytest.approx(pos_term + np.maximum(0, off - 0.2).sum() / 6,
                                            abs=1e-6)


def test_class_balance_weights() -> None:
    from semfeat_ros.model.losses import class_balance_weights

    counts = np.array([1000, 100, 10, 0])
    np.testing.assert_allclose(class_balance_weights(counts, 0.0, 10.0), np.ones(4))
    w = class_balance_weights(counts, 0.5, 10.0)
    # median frequency of the present classes is that of the 100-pixel class
    np.testing.assert_allclose(w, [np.sqrt(0.1), 1.0, np.sqrt(10.0), 10.0], rtol=1e-6)
    w = class_balance_weights(counts, 1.0, 5.0)
    np.testing.assert_allclose(w, [0.2, 1.0, 5.0, 5.0], rtol=1e-6)
    with pytest.raises(ModelConfigError):
        class_balance_weights(np.array([-1, 2]), 0.5, 10.0)
    with pytest.raises(ModelConfigError, match='seg_max_class_weight'):
        MultiTaskLoss({'seg_max_class_weight': 0.5})
    # the weights reach the cross-entropy
    torch.manual_seed(0)
    net = SemFeatNet({'encoder_channels': [8, 8, 16], 'decoder_channels': 16}).eval()
    pred = net(torch.randn(2, 3, 32, 32))
    batch = {'kp_target': torch.zeros(2, 32, 32), 'kp_valid': torch.ones(2, 32, 32, dtype=bool),
             'label': torch.randint(0, 19, (2, 32, 32)), 'points_a': torch.rand(1, 4, 2) * 31,
             'points_b': torch.rand(1, 4, 2) * 31, 'corr_valid': torch.ones(1, 4, dtype=bool)}
    weights = np.linspace(0.5, 3.0, 19).astype(np.float32)
    _, logs = MultiTaskLoss({}, weights)(pred, batch)
    expected = segmentation_loss(pred['segmentation_logits'], batch['label'],
                                 torch.from_numpy(weights), stride=4)
    assert logs['seg'] == pytest.approx(float(expected.detach()), rel=1e-5)
