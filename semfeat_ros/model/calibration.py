"""Segmentation prior correction of trained weights (an offline stage after ``semfeat-train``).

The segmentation loss weighs class ``c`` by ``w_c`` (config/train.yaml: ``(median frequency /
frequency) ** 0.5``, clipped). A weighted cross-entropy is minimised by scores proportional to
``w_c p(c | x)``: the rare classes (lines, curbs, poles, signs) win pixels that are more likely
road or wall, which lifts their recall and costs their precision. Logit adjustment (Menon et al.,
"Long-tail learning via logit adjustment", ICLR 2021) subtracts ``tau log w_c`` from the logits:
``tau = 1`` undoes the weighting (pixel accuracy), ``tau = 0`` is the network as trained.

``tau`` is chosen on rendered *training* worlds by the mean IoU over the static classes (the
target of the project) and folded into the segmentation head's bias, so the corrected network
costs nothing at run time and its keypoints and descriptors are bit for bit the same (the head
feeds nothing else). Held-out worlds are only evaluated, before and after, never fitted on.

The weights' JSON records the applied correction (``seg_prior_correction``); calibrating
corrected weights first removes it, so running the stage twice gives the same weights.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
import shutil
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 - the usual torch alias
from tqdm import tqdm

from semfeat_ros import conf as common_conf
from semfeat_ros.labels import load_labels
from semfeat_ros.model.errors import DatasetError, ModelConfigError, WeightsFormatError
from semfeat_ros.model.extractor import FeatureExtractor
from semfeat_ros.model.metrics import confusion_matrix, mean_iou, subset_iou
from semfeat_ros.model.semfeatnet import SemFeatNet
from semfeat_ros.model.training import check_render_sizes, check_seeds, expand_shards
from semfeat_ros.model.weights_io import load_weights, resolve_weights_path, save_weights

default_conf: dict[str, Any] = {
    'train_shards': ['out/sim_train/*.npz'],  # rendered training worlds: tau is fitted here
    'val_shards': [],  # held-out worlds: evaluated before / after only, never fitted on
    'exclude_seeds': list(range(10)),  # test worlds (the bags): refused in either set
    'frames_per_shard': 3,  # training frames per shard, evenly spaced (full frames)
    'val_frames_per_shard': 24,  # held-out frames per shard (the simulator's shards have 24)
    'taus': [round(0.125 * i, 3) for i in range(13)],  # candidate tau, 0 .. 1.5
    'num_threads': 2,  # torch intra-op threads
}

CARD_BEGIN = '<!-- seg_prior_correction: begin (written by semfeat-calibrate-seg) -->'
CARD_END = '<!-- seg_prior_correction: end -->'


@dataclass(frozen=True)
class Calibration:
    """Outcome of :func:`main`."""

    tau: float
    bias: np.ndarray  # (C,) added to the segmentation logits: -tau log w
    train: dict[float, tuple[float, float]]  # tau -> (static mIoU, mIoU) on training frames
    val_before: tuple[float, float] | None  # (static mIoU, mIoU) on held-out frames, tau = 0
    val_after: tuple[float, float] | None  # the same with the chosen tau
    frames: tuple[int, int]  # (training, held-out) frames evaluated

    def summary(self) -> dict[str, Any]:
        """JSON-ready record (stored in the weights' JSON)."""
        def pair(p: tuple[float, float] | None) -> dict[str, float] | None:
            return None if p is None else {'miou_static': round(p[0], 4), 'miou': round(p[1], 4)}
        return {'tau': self.tau, 'bias': [round(float(b), 6) for b in self.bias],
                'train_frames': self.frames[0], 'val_frames': self.frames[1],
                'train_miou_static_by_tau': {f'{t:g}': round(v[0], 4)
                                             for t, v in self.train.items()},
                'val_before': pair(self.val_before), 'val_after': pair(self.val_after)}


def merge_calibration_conf(conf: dict[str, Any] | None) -> dict[str, Any]:
    """``default_conf`` updated by ``conf`` (unknown keys and bad values raise)."""
    c = common_conf.merge_conf(default_conf, conf, ModelConfigError,
                               what='calibration config key')
    for key in ('frames_per_shard', 'val_frames_per_shard'):
        common_conf.check_int_min(c[key], key, ModelConfigError, 1)
    taus = c['taus']
    if not taus or not all(isinstance(t, int | float) and 0 <= t <= 5 for t in taus):
        raise ModelConfigError(f'taus must be numbers in [0, 5], got {taus!r}')
    return c


def class_weights_of(config: dict[str, Any]) -> np.ndarray:
    """The segmentation CE class weights the weights were trained with (their JSON)."""
    w = (config.get('training') or {}).get('seg_class_weights')
    n = len(config['class_names'])
    if w is None:
        raise WeightsFormatError('the weights JSON has no training.seg_class_weights: trained '
                                 'without class balancing, there is nothing to correct')
    w = np.asarray(w, dtype=np.float64)
    if w.shape != (n,) or not np.isfinite(w).all() or (w <= 0).any():
        raise WeightsFormatError(f'training.seg_class_weights must be {n} positive numbers')
    return w


def _frames(paths: Sequence[Path], per_shard: int):  # noqa: ANN202 - generator of arrays
    for p in paths:
        with np.load(p, allow_pickle=False) as npz:
            rgb, label = npz['rgb'], npz['label']
            for i in np.unique(np.linspace(0, len(rgb) - 1, per_shard).round().astype(int)):
                yield rgb[i], label[i]


def confusions(extractor: FeatureExtractor, paths: Sequence[Path], per_shard: int,
               offsets: dict[float, np.ndarray], progress: bool = False, desc: str = ''
               ) -> tuple[dict[float, np.ndarray], int]:
    """Confusion matrices (C, C) of full frames for every logit offset (C,); returns
    ``(matrices by key, frames)``. Logits are upsampled bilinearly to the label size."""
    n_cls = len(extractor.class_names)
    cms = {k: np.zeros((n_cls, n_cls), np.int64) for k in offsets}
    offs = {k: torch.as_tensor(v, dtype=torch.float32)[None, :, None, None]
            for k, v in offsets.items()}
    n = 0
    frames = _frames(paths, per_shard)
    for rgb, label in tqdm(frames, total=len(paths) * per_shard, disable=not progress,
                           desc=desc, unit='frame'):
        pred, _ = extractor.forward(rgb)
        with torch.inference_mode():
            up = F.interpolate(pred['segmentation_logits'].float(), size=label.shape,
                               mode='bilinear', align_corners=False)
            for k, o in offs.items():
                cms[k] += confusion_matrix((up + o).argmax(1)[0].numpy(), label, n_cls)
        n += 1
    return cms, n


def _scores(cm: np.ndarray, static: np.ndarray) -> tuple[float, float]:
    miou, iou = mean_iou(cm)
    return subset_iou(iou, static), miou


def main(conf: dict[str, Any] | None, weights: str | Path | None, out: Path,
         progress: bool = True) -> Calibration:
    """Fit tau on ``conf['train_shards']``, write the corrected weights into ``out``
    (``semfeat.safetensors`` + ``semfeat.json``; the model card section when a MODEL_CARD.md
    is there or beside the input weights). ``weights``: path or None (shipped)."""
    c = merge_calibration_conf(conf)
    src = resolve_weights_path(weights)
    model, config = load_weights(src)
    logw = np.log(class_weights_of(config))
    applied = (config.get('seg_prior_correction') or {}).get('bias')
    raw = model
    if applied is not None:  # start from the network as trained
        raw = _with_bias(model, -np.asarray(applied, dtype=np.float64))
    train = expand_shards(c['train_shards'])
    val = expand_shards(c['val_shards'])
    if not train:
        raise DatasetError(f'no training shards match {c["train_shards"]}')
    train_seeds = check_seeds(train, c['exclude_seeds'], 'training')
    val_seeds = check_seeds(val, c['exclude_seeds'], 'held-out')
    if set(train_seeds) & set(val_seeds):
        raise DatasetError(f'held-out shards share worlds with the training shards: '
                           f'{sorted(set(train_seeds) & set(val_seeds))}')
    check_render_sizes(train, val, 'held-out')
    torch.set_num_threads(int(c['num_threads']))
    ex = FeatureExtractor(raw, {'num_threads': int(c['num_threads'])},
                          class_names=config['class_names'])
    static = np.asarray(load_labels().static, bool)
    taus = [float(t) for t in c['taus']]
    cms, n_train = confusions(ex, train, c['frames_per_shard'],
                              {t: -t * logw for t in taus}, progress, 'fit tau')
    table = {t: _scores(cms[t], static) for t in taus}
    tau = max(taus, key=lambda t: (table[t][0], -t))  # best static mIoU, smaller tau on ties
    bias = -tau * logw
    before = after = None
    n_val = 0
    if val:
        vcm, n_val = confusions(ex, val, c['val_frames_per_shard'],
                                {0.0: np.zeros_like(logw), tau: bias}, progress, 'held-out')
        before, after = _scores(vcm[0.0], static), _scores(vcm[tau], static)
    cal = Calibration(tau, bias, table, before, after, (n_train, n_val))
    meta = {k: v for k, v in config.items() if k not in ('format', 'version', 'network')}
    meta['seg_prior_correction'] = cal.summary()
    out = Path(out)
    dst = save_weights(_with_bias(raw, bias), out, meta)
    _write_card(src.parent / 'MODEL_CARD.md', dst.parent / 'MODEL_CARD.md', cal)
    return cal


def _with_bias(model: SemFeatNet, bias: np.ndarray) -> SemFeatNet:
    """A copy of ``model`` whose segmentation logits are shifted by ``bias`` (C,)."""
    out = SemFeatNet(model.conf)
    out.load_state_dict(model.state_dict())
    with torch.no_grad():
        out.seg_head.bias += torch.as_tensor(bias, dtype=out.seg_head.bias.dtype)
    return out.eval()


def card_section(cal: Calibration) -> str:
    """The model card's markdown section of a calibration."""
    def fmt(p: tuple[float, float] | None) -> str:
        return 'n/a' if p is None else f'{p[0]:.3f} static / {p[1]:.3f} all classes'
    rows = '\n'.join(f'| {t:g} | {v[0]:.3f} | {v[1]:.3f} |' for t, v in cal.train.items())
    return f"""{CARD_BEGIN}
## Segmentation prior correction

The class-balanced segmentation loss favours rare classes; `tau log w_c` is subtracted from the
logits (logit adjustment) and folded into the segmentation head's bias: keypoints and
descriptors are unchanged. `tau` is chosen on {cal.frames[0]} full frames of the *training*
worlds by the static-class mIoU (`semfeat_ros/model/calibration.py`).

| tau | training frames: static mIoU | mIoU |
|---:|---:|---:|
{rows}

Chosen: **tau = {cal.tau:g}**. Held-out worlds ({cal.frames[1]} full frames), mIoU before ->
after: {fmt(cal.val_before)} -> {fmt(cal.val_after)}.

Rebuild (after `semfeat-train`): `semfeat-calibrate-seg --weights semfeat_ros/weights
--train-shards 'out/sim_train/*.npz' --val-shards 'out/sim_val/*.npz' --out semfeat_ros/weights`.
{CARD_END}
"""


def _write_card(src: Path, dst: Path, cal: Calibration) -> None:
    """Replace (or append) the calibration section of ``dst`` (copied from ``src`` first when
    ``dst`` does not exist); nothing when neither card exists."""
    if not dst.is_file():
        if not src.is_file():
            return
        shutil.copyfile(src, dst)
    text = dst.read_text(encoding='utf-8')
    if CARD_BEGIN in text and CARD_END in text:
        head, rest = text.split(CARD_BEGIN, 1)
        text = head + rest.split(CARD_END, 1)[1].lstrip('\n')
    dst.write_text(text.rstrip('\n') + '\n\n' + card_section(cal), encoding='utf-8')

