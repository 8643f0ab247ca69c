"""Saving and loading SemFeatNet weights: safetensors tensors + a JSON config next to them.

A weights file ``NAME.safetensors`` always has a sibling ``NAME.json`` with::

    {"format": "semfeat_ros.semfeatnet", "version": 1,
     "network": {...SemFeatNet conf...},
     "class_names": [...19 names...],
     "input_size": [W, H]   # network resolution (px) of full frames during training
     ...free-form training metadata...}

Loading never executes code: ``safetensors.torch.load_file`` + ``json.load``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from safetensors.torch import load_file, save_file
import torch

from semfeat_ros.model.errors import WeightsFormatError, WeightsNotFoundError
from semfeat_ros.model.semfeatnet import SemFeatNet

WEIGHTS_FORMAT = 'semfeat_ros.semfeatnet'
WEIGHTS_VERSION = 1
WEIGHTS_NAME = 'semfeat'
"""Stem of the weights files written by training and shipped in ``semfeat_ros/weights``."""

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / 'weights'
SHIPPED_WEIGHTS = WEIGHTS_DIR / f'{WEIGHTS_NAME}.safetensors'
"""The weights shipped with the package (produced by ``semfeat-train --export``)."""

TRAIN_COMMAND = ('semfeat-train --config config/train.yaml --out out/train_v3, then '
                 'semfeat-train --config config/finetune_seg.yaml --out out/train_v5, then '
                 'semfeat-train --config config/finetune_seg_ctx_light.yaml --out out/train_v8, '
                 'then semfeat-train --config config/finetune_kp.yaml --out out/train_v9 '
                 '--export semfeat_ros/weights')
"""The command that (re)creates :data:`SHIPPED_WEIGHTS` (see MODEL_CARD.md)."""


LEGACY_NETWORK_CONF: dict[str, Any] = {'kp_pixel_channels': 0, 'kp_head_layers': 1}
"""Network keys a weights JSON may lack, at the values that reproduce the layout it was trained
with: a JSON without them describes a network without those layers."""


def resolve_weights_path(path: str | Path | None) -> Path:
    """The ``.safetensors`` file for ``path`` (a file, a directory holding ``semfeat.*``, or None
    for the shipped weights). Raises :class:`WeightsNotFoundError` if it does not exist."""
    if path is None:
        p = SHIPPED_WEIGHTS
        if not p.is_file():
            raise WeightsNotFoundError(
                f'no trained weights shipped at {p}. The network must be trained first: '
                f'run `{TRAIN_COMMAND}` (about 3 h 45 min on 2 AVX-512 CPU cores, 5 h on '
                f'AVX2 ones), '
                f'or pass weights=PATH to a trained .safetensors file')
        return p
    p = Path(path)
    if p.is_dir():
        p = p / f'{WEIGHTS_NAME}.safetensors'
    if not p.is_file():
        raise WeightsNotFoundError(f'weights file not found: {p}')
    return p


def save_weights(model: SemFeatNet, path: str | Path, meta: dict[str, Any]) -> Path:
    """Write ``path`` (.safetensors) and its JSON sibling; returns the .safetensors path.

    ``meta`` must hold ``class_names`` and ``input_size`` and may hold any JSON-serialisable
    training metadata.
    """
    p = Path(path)
    if p.suffix != '.safetensors':
        p = p / f'{WEIGHTS_NAME}.safetensors' if p.suffix == '' else p.with_suffix('.safetensors')
    for key in ('class_names', 'input_size'):
        if key not in meta:
            raise WeightsFormatError(f'save_weights: meta is missing {key!r}')
    if len(meta['class_names']) != model.conf['num_classes']:
        raise WeightsFormatError(f'save_weights: {len(meta["class_names"])} class names for a '
                                 f'{model.conf["num_classes"]}-class network')
    p.parent.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(tensors, str(p), metadata={'format': WEIGHTS_FORMAT})
    config = {'format': WEIGHTS_FORMAT, 'version': WEIGHTS_VERSION, 'network': model.conf,
              **meta}
    p.with_suffix('.json').write_text(json.dumps(config, indent=1, sort_keys=True) + '\n')
    return p


def load_weights(path: str | Path | None) -> tuple[SemFeatNet, dict[str, Any]]:
    """Build a SemFeatNet from a weights file (None = shipped); returns ``(model.eval(), config)``.

    Raises :class:`WeightsNotFoundError` or :class:`WeightsFormatError`.
    """
    p = resolve_weights_path(path)
    jpath = p.with_suffix('.json')
    if not jpath.is_file():
        raise WeightsFormatError(f'{p}: missing JSON config {jpath}')
    try:
        config = json.loads(jpath.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise WeightsFormatError(f'{jpath}: unreadable JSON ({exc})') from exc
    if not isinstance(config, dict):
        raise WeightsFormatError(f'{jpath}: expected a JSON object, got {type(config).__name__}')
    if config.get('format') != WEIGHTS_FORMAT:
        raise WeightsFormatError(
            f'{jpath}: format must be {WEIGHTS_FORMAT!r}, got {config.get("format")!r}')
    if config.get('version') != WEIGHTS_VERSION:
        raise WeightsFormatError(
            f'{jpath}: version must be {WEIGHTS_VERSION}, got {config.get("version")!r}')
    for key in ('network', 'class_names', 'input_size'):
        if key not in config:
            raise WeightsFormatError(f'{jpath}: missing key {key!r}')
    try:
        model = SemFeatNet({**LEGACY_NETWORK_CONF, **config['network']})
    except ValueError as exc:
        raise WeightsFormatError(f'{jpath}: bad network config ({exc})') from exc
    try:
        state = load_file(str(p))
    except Exception as exc:  # safetensors raises its own SafetensorError / OSError types
        raise WeightsFormatError(f'{p}: unreadable safetensors file ({exc})') from exc
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise WeightsFormatError(f'{p}: tensors do not match the network config: {exc}') from exc
    model.eval()
    return model, config


def state_dict_allclose(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """True when two modules hold identical parameters and buffers (used by tests/resume)."""
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
