"""SemFeatNet: the multi-task network of the paper (keypoints, descriptors, 19-class segmentation).

Architecture (paper, Methodology; sizes for the default configuration)::

    image (B,3,H,W)
      └─ shared U-Net-style encoder: N blocks, block n at stride 2**n  ->  F1 .. FN
           (block 1: stride-2 conv + conv; blocks 2..N: 2x2 max-pool + two 3x3 convs; BN + ReLU)
      └─ per task t in (kp, desc, seg):
           Decoder 1   : U-Net up-path from FN to stride 8 with skips F(N-1) .. F3
           CTMM        : cross-task mixer, equations (1)-(5), on the stride-8 map
           Decoder 2   : task-specific refinement with a skip from F1 (kp) or F2 (seg)
           head        : kp  -> 64 cell logits at stride 8 -> depth-to-space -> (B,1,H,W) logits
                                -> sigmoid heatmap H_kp in [0, 1] at full input resolution
                         desc-> D channels at stride 8, L2-normalised per location
                         seg -> C class logits at stride 4 (softmax = class probabilities);
                                with seg_stride 2, plus a residual stride-2 refinement (F1 skip)

Design decisions the paper leaves open (documented here and in MODEL_CARD.md):

* Resolution. The paper upsamples every decoder to H x W. Full-resolution decoders dominate the
  cost on a CPU, so the mixers and decoders run at stride 8 (seg: stride 4) and the keypoint
  heatmap is produced by depth-to-space (pixel shuffle) of 64 cell logits, as SuperPoint and
  XFeat do: a 1x1 convolution at stride 8 producing 8x8 = 64 logits per cell is exactly a 1x1
  convolution applied to the depth-to-space upsampled feature map, followed by the sigmoid. There
  is no dustbin channel: each pixel is an independent Bernoulli (the paper's per-pixel BCE).
  To localise keypoints inside the 8x8 cell the keypoint decoder also sees the stride-2 feature
  map F1 folded to stride 8 (space-to-depth + 1x1 conv, XFeat-style, implemented as one 4x4
  stride-4 convolution, which is the same linear map) and, with ``kp_pixel_channels`` > 0, the
  grey input itself folded to stride 8 (each cell's 64 pixels as channels, two 1x1 layers), as
  XFeat's keypoint head does: trained without it, the network placed its peaks a median 1.8 px
  from the repeated ones, against 1.0 px for ORB on the same rendered pairs.
* CTMM output. The mixer output ``z~`` lies in the span of the three value vectors, so it cannot
  replace the decoder features. It is combined with them by ``fusion``: ``'concat'`` (default):
  ``ReLU(BN(Conv1x1([z, z~])))`` back to the decoder width; ``'add'``: ``z + Conv1x1(z~)``.
* Task embeddings. One set ``T = [z_kp; z_desc; z_seg]`` (3 x d_task) is shared by the three
  decoders; every decoder has its own projections ``W_q``, ``W_k``, ``W_v``.
* Segmentation at stride 2 (``seg_stride: 2``). Labels averaged over 4x4 cells and upsampled
  cap the static-class mIoU at 0.818 (stride 2: 0.925): a 2 px parking line or a pole cannot be
  drawn at stride 4. The stride-2 option upsamples the stride-4 decoder features, joins them with
  F1 (stride 2) through one separable layer and adds a 1x1 correction to the bilinearly upsampled
  stride-4 logits. The correction starts at zero, so a network fine-tuned from stride-4 weights
  starts from their exact output.
* Segmentation context (``seg_context_blocks``, ``seg_blocks``; 0 by default). MobileNetV2
  inverted-residual blocks on the segmentation branch only: dilated ones (1, 2, 4, 8 in turn)
  on its stride-8 features after the CTMM, plain ones after its stride-4 decoder. Each block's
  last BatchNorm scale starts at zero, so blocks inserted into trained weights leave their
  output unchanged until they are trained (the same rule as the stride-2 refinement).
* Descriptors are produced at stride 8 and sampled bilinearly at keypoints (then re-normalised),
  as in SuperPoint; the loss is applied to the sampled descriptors.
"""
from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn
import torch.nn.functional as F  # noqa: N812 - the usual torch alias

from semfeat_ros import conf as common_conf
from semfeat_ros.model.errors import ModelConfigError, ModelInputError

TASKS = ('kp', 'desc', 'seg')
"""Order of the rows of the task-embedding matrix ``T`` and of the mixer attention weights."""

KP_STRIDE = 8
"""Stride (px) of the keypoint cells and of the descriptor map."""

SEG_STRIDE = 4
"""Stride (px) of the segmentation decoder (the logits' stride unless ``seg_stride`` is 2)."""


def conv_bn_relu(cin: int, cout: int, kernel: int = 3, stride: int = 1) -> nn.Sequential:
    """Convolution (no bias) + BatchNorm + ReLU; 'same' padding."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=False),
        nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def separable_bn_relu(cin: int, cout: int) -> nn.Sequential:
    """Depthwise 3x3 + pointwise 1x1 convolution + BatchNorm + ReLU (cheap at stride 4)."""
    return nn.Sequential(
        nn.Conv2d(cin, cin, 3, padding=1, groups=cin, bias=False),
        nn.Conv2d(cin, cout, 1, bias=False),
        nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class InvertedResidual(nn.Module):
    """``x + BN(1x1(ReLU(BN(dw3x3(ReLU(BN(1x1(x))))))))``, MobileNetV2's block (stride 1).

    The depthwise 3x3 convolution may be dilated (context at no extra cost). The last
    BatchNorm's scale starts at zero, so a new block is the identity: inserted into trained
    weights it leaves their output unchanged until it is trained.
    """

    def __init__(self, channels: int, expansion: int, dilation: int = 1) -> None:
        super().__init__()
        hidden = channels * expansion
        self.body = nn.Sequential(
            nn.Conv2d(channels, hidden, 1, bias=False), nn.BatchNorm2d(hidden),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, hidden, 3, padding=dilation, dilation=dilation, groups=hidden,
                      bias=False),
            nn.BatchNorm2d(hidden), nn.ReLU(inplace=True),
            nn.Conv2d(hidden, channels, 1, bias=False), nn.BatchNorm2d(channels))
        nn.init.zeros_(self.body[-1].weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, C, h, w) -> (B, C, h, w)."""
        return x + self.body(x)


CONTEXT_DILATIONS = (1, 2, 4, 8)
"""Dilations of the segmentation context blocks at stride 8, in turn (px at stride 8)."""


class CrossTaskMixer(nn.Module):
    """Cross-Task Mixer Module (CTMM), equations (1)-(5) of the paper.

    For every location ``(u, v)``: ``q = W_q z(u,v)`` (d), ``K = W_k T``, ``V = W_v T`` (3 x d
    here, i.e. the transposes of the paper's d x 3 matrices), ``alpha = softmax(q^T K / sqrt(d))``
    over the 3 tasks and ``z~(u,v) = sum_t alpha_t v_t``. ``forward`` then fuses ``z~`` with the
    input features according to ``fusion`` (see the module docstring).
    """

    def __init__(self, in_dim: int, task_dim: int, dim: int, fusion: str = 'concat') -> None:
        super().__init__()
        if fusion not in ('concat', 'add'):
            raise ModelConfigError(f"mixer_fusion must be 'concat' or 'add', got {fusion!r}")
        self.dim = dim
        self.fusion = fusion
        self.w_q = nn.Conv2d(in_dim, dim, 1, bias=False)  # W_q (d x d_enc), per location
        self.w_k = nn.Linear(task_dim, dim, bias=False)  # W_k (d x d_task)
        self.w_v = nn.Linear(task_dim, dim, bias=False)  # W_v (d x d_task)
        if fusion == 'concat':
            self.fuse = conv_bn_relu(in_dim + dim, in_dim, kernel=1)
        else:
            self.fuse = nn.Conv2d(dim, in_dim, 1, bias=False)

    def mix(self, z: torch.Tensor, tasks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Equations (2)-(5) only.

        Args:
            z: features, (B, d_enc, h, w).
            tasks: task embeddings T, (3, d_task), rows in the order of :data:`TASKS`.
        Returns:
            ``(z_tilde, alpha)``: mixed features (B, d, h, w) and attention weights (B, 3, h, w)
            (softmax over dim 1).
        """
        q = self.w_q(z)  # (B, d, h, w)
        keys = self.w_k(tasks)  # (3, d): row t is the column k_t of the paper's K
        values = self.w_v(tasks)  # (3, d): row t is v_t
        logits = F.conv2d(q, keys[:, :, None, None]) / math.sqrt(self.dim)  # (B, 3, h, w)
        alpha = logits.softmax(dim=1)
        z_tilde = F.conv2d(alpha, values.t()[:, :, None, None])  # (B, d, h, w)
        return z_tilde, alpha

    def forward(self, z: torch.Tensor, tasks: torch.Tensor) -> torch.Tensor:
        """Mix and fuse.

        Args:
            z: decoder features, (B, d_enc, h, w).
            tasks: task embeddings T, (3, d_task).
        Returns:
            fused features, (B, d_enc, h, w).
        """
        z_tilde, _ = self.mix(z, tasks)
        return self.combine(z, z_tilde)

    def combine(self, z: torch.Tensor, z_tilde: torch.Tensor) -> torch.Tensor:
        """Fuse z (B, d_enc, h, w) with the mixer output z~ (B, d, h, w) -> (B, d_enc, h, w)."""
        if self.fusion == 'concat':
            return self.fuse(torch.cat([z, z_tilde], dim=1))
        return z + self.fuse(z_tilde)


class Encoder(nn.Module):
    """Shared U-Net-style encoder: block n (1-based) outputs F_n at stride 2**n."""

    def __init__(self, in_channels: int, channels: list[int]) -> None:
        super().__init__()
        blocks = []
        cin = in_channels
        for i, c in enumerate(channels):
            if i == 0:  # stride-2 conv instead of a full-resolution conv + pool (cost)
                blocks.append(nn.Sequential(conv_bn_relu(cin, c, stride=2), conv_bn_relu(c, c)))
            else:
                blocks.append(nn.Sequential(nn.MaxPool2d(2), conv_bn_relu(cin, c),
                                            conv_bn_relu(c, c)))
            cin = c
        self.blocks = nn.ModuleList(blocks)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x (B, C_in, H, W) -> [F_1 (B, c_1, H/2, W/2), ..., F_N (B, c_N, H/2^N, W/2^N)]."""
        feats = []
        for block in self.blocks:
            x = block(x)
            feats.append(x)
        return feats


class Decoder1(nn.Module):
    """U-Net up-path from the bottleneck F_N to stride 8, with skips F_(N-1) .. F_3."""

    def __init__(self, enc_channels: list[int], width: int) -> None:
        super().__init__()
        self.reduce = conv_bn_relu(enc_channels[-1], width, kernel=1)
        n = len(enc_channels)
        # skip levels (0-based indices into the encoder outputs), coarse to fine, down to stride 8
        self.skip_idx = list(range(n - 2, 1, -1))
        self.ups = nn.ModuleList(
            [separable_bn_relu(width + enc_channels[i], width) for i in self.skip_idx])
        self.refine = conv_bn_relu(width, width) if not self.skip_idx else nn.Identity()

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        """feats [F_1..F_N] -> (B, width, H/8, W/8)."""
        x = self.reduce(feats[-1])
        for i, up in zip(self.skip_idx, self.ups):
            skip = feats[i]
            x = F.interpolate(x, size=skip.shape[-2:], mode='bilinear', align_corners=False)
            x = up(torch.cat([x, skip], dim=1))
        return self.refine(x)


class SemFeatNet(nn.Module):
    """Shared encoder + three (Decoder 1 -> CTMM -> Decoder 2 -> head) branches."""

    default_conf: dict[str, Any] = {
        'in_channels': 3,  # RGB input (grey images are replicated to 3 channels by the wrappers)
        'encoder_channels': [16, 32, 64, 128, 192],  # block n at stride 2**n; N >= 3 blocks
        'decoder_channels': 64,  # width of Decoder 1 / CTMM / Decoder 2 at stride 8
        'task_dim': 32,  # d_task, length of each learned task embedding z_kp, z_desc, z_seg
        'mixer_dim': 32,  # d, query/key/value width of the CTMM
        'mixer_fusion': 'concat',  # how z~ joins the decoder features: 'concat' or 'add'
        'kp_fine_channels': 32,  # channels of F1 (stride 2) folded to stride 8 for the kp head
        'kp_pixel_channels': 32,  # > 0: the grey input's 8x8 cells (pixel-unshuffled to 64
        #                           channels) through two 1x1 conv layers of this width also
        #                           feed the kp head (XFeat-style); 0: off
        'kp_head_layers': 2,  # hidden 1x1 conv + BN + ReLU layers of the kp head
        'kp_refine_channels': 0,  # > 0: three 3x3 conv layers of this width at full input
        #                           resolution on the grey image and the cell logits add a
        #                           per-pixel correction to the keypoint logits (0: off)
        'descriptor_dim': 64,  # D, length of the L2-normalised descriptors
        'seg_channels': 32,  # width of the segmentation decoder at stride 4
        'seg_layers': 1,  # separable 3x3 layers of the segmentation decoder at stride 4 (the
        #                   first sees the F2 skip)
        'seg_stride': 4,  # px, stride of the segmentation logits: 4 or 2 (config/model.yaml: a
        #                   residual refinement with the F1 skip over the stride-4 logits)
        'seg_context_blocks': 0,  # inverted-residual blocks on the segmentation branch's
        #                           stride-8 features after its CTMM, dilations 1, 2, 4, 8 in
        #                           turn (0: none)
        'seg_blocks': 0,  # inverted-residual blocks after the stride-4 segmentation decoder
        'seg_block_expansion': 3,  # hidden width / input width of those blocks
        'num_classes': 19,  # C, semantic classes (config/labels.yaml)
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.conf = conf = common_conf.merge_conf(self.default_conf, conf, ModelConfigError,
                                                  what='network config key')
        enc = [int(c) for c in conf['encoder_channels']]
        if len(enc) < 3 or min(enc) <= 0:
            raise ModelConfigError(
                f'encoder_channels needs >= 3 positive widths (stride 8 must exist), got {enc}')
        for key in ('decoder_channels', 'task_dim', 'mixer_dim', 'kp_fine_channels',
                    'descriptor_dim', 'seg_channels', 'num_classes', 'in_channels',
                    'kp_head_layers', 'seg_layers', 'seg_block_expansion'):
            if int(conf[key]) <= 0:
                raise ModelConfigError(f'{key} must be a positive integer, got {conf[key]!r}')
        for key in ('kp_pixel_channels', 'kp_refine_channels', 'seg_context_blocks',
                    'seg_blocks'):
            if int(conf[key]) < 0:
                raise ModelConfigError(f'{key} must be >= 0, got {conf[key]!r}')
        if int(conf['seg_stride']) not in (2, SEG_STRIDE):
            raise ModelConfigError(f'seg_stride must be 2 or 4, got {conf["seg_stride"]!r}')
        width = int(conf['decoder_channels'])
        self.stride = 2 ** len(enc)  # input sizes must be multiples of this (px)

        self.encoder = Encoder(int(conf['in_channels']), enc)
        # T: rows z_kp, z_desc, z_seg (order of TASKS)
        self.task_embeddings = nn.Parameter(torch.randn(3, int(conf['task_dim'])))
        self.decoder1 = nn.ModuleDict({t: Decoder1(enc, width) for t in TASKS})
        self.mixer = nn.ModuleDict({
            t: CrossTaskMixer(width, int(conf['task_dim']), int(conf['mixer_dim']),
                              conf['mixer_fusion']) for t in TASKS})

        # Decoder 2 + heads
        fine = int(conf['kp_fine_channels'])
        fold = KP_STRIDE // 2  # F1 is at stride 2
        # space-to-depth of F1 to stride 8 followed by a 1x1 conv == one 4x4 stride-4 conv
        self.kp_fine = nn.Sequential(
            nn.Conv2d(enc[0], fine, fold, stride=fold, bias=False),
            nn.BatchNorm2d(fine), nn.ReLU(inplace=True))
        pix = int(conf['kp_pixel_channels'])
        # raw grey 8x8 cells (64 values) -> two 1x1 layers at stride 8: exact pixel positions
        self.kp_pixels = nn.Sequential(
            conv_bn_relu(KP_STRIDE * KP_STRIDE, pix, kernel=1),
            conv_bn_relu(pix, pix, kernel=1)) if pix > 0 else None
        self.kp_decoder = conv_bn_relu(width, width)
        hidden = [conv_bn_relu(width + fine + pix, width, kernel=1)]
        hidden += [conv_bn_relu(width, width, kernel=1)
                   for _ in range(int(conf['kp_head_layers']) - 1)]
        self.kp_head = nn.Sequential(*hidden, nn.Conv2d(width, KP_STRIDE * KP_STRIDE, 1))
        ref = int(conf['kp_refine_channels'])
        # full-resolution correction of the depth-to-space logits; its last layer starts at zero,
        # so inserting it into trained weights leaves their heatmap unchanged
        self.kp_refine = nn.Sequential(
            nn.Conv2d(2, ref, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(ref, ref, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(ref, 1, 3, padding=1)) if ref > 0 else None
        if self.kp_refine is not None:
            nn.init.zeros_(self.kp_refine[-1].weight)
            nn.init.zeros_(self.kp_refine[-1].bias)
        self.desc_decoder = conv_bn_relu(width, width)
        self.desc_head = nn.Conv2d(width, int(conf['descriptor_dim']), 1)
        seg_c = int(conf['seg_channels'])
        expansion = int(conf['seg_block_expansion'])
        # residual blocks start as the identity; empty by default, so older weights keep their keys
        self.seg_context = nn.Sequential(*[
            InvertedResidual(width, expansion, CONTEXT_DILATIONS[i % len(CONTEXT_DILATIONS)])
            for i in range(int(conf['seg_context_blocks']))])
        self.seg_blocks = nn.Sequential(
            *[InvertedResidual(seg_c, expansion) for _ in range(int(conf['seg_blocks']))])
        self.seg_reduce = conv_bn_relu(width, seg_c, kernel=1)
        self.seg_decoder = separable_bn_relu(seg_c + enc[1], seg_c)
        # the layers after the first: empty with seg_layers 1, so checkpoints without seg_refine
        # keys load unchanged
        self.seg_refine = nn.Sequential(
            *[separable_bn_relu(seg_c, seg_c) for _ in range(int(conf['seg_layers']) - 1)])
        self.seg_head = nn.Conv2d(seg_c, int(conf['num_classes']), 1)
        self.seg_fine = self.seg_fine_head = None  # stride-2 refinement (absent at stride 4)
        if int(conf['seg_stride']) == 2:
            self.seg_fine = separable_bn_relu(seg_c + enc[0], seg_c)
            self.seg_fine_head = nn.Conv2d(seg_c, int(conf['num_classes']), 1)
            nn.init.zeros_(self.seg_fine_head.weight)  # starts as the upsampled stride-4 logits
            nn.init.zeros_(self.seg_fine_head.bias)

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """Run the network on a normalised image batch.

        Args:
            image: (B, C_in, H, W) float, normalised with :func:`normalize_image`; H and W must be
                multiples of ``self.stride`` (2**N px).
        Returns:
            dict with
            ``keypoint_logits`` (B, 1, H, W): pre-sigmoid heatmap logits (depth-to-space of the
                (B, 64, H/8, W/8) cell logits, plus the full-resolution correction when
                ``kp_refine_channels`` > 0);
            ``heatmap`` (B, H, W): H_kp = sigmoid(keypoint_logits) in [0, 1];
            ``descriptors`` (B, D, H/8, W/8): unit L2 norm along dim 1;
            ``segmentation_logits`` (B, C, H/s, W/s): class logits (softmax -> probabilities),
                s = ``seg_stride`` (4 or 2);
            ``mixer_attention`` (B, 3, 3, H/8, W/8): alpha of the kp/desc/seg mixers (dim 1) over
                the tasks (dim 2).
        """
        if image.ndim != 4 or image.shape[1] != self.conf['in_channels']:
            raise ModelInputError(
                f'image: expected (B, {self.conf["in_channels"]}, H, W), got {tuple(image.shape)}')
        h, w = image.shape[-2:]
        if h % self.stride or w % self.stride:
            raise ModelInputError(
                f'image: H and W must be multiples of {self.stride} px, got {h}x{w}')
        feats = self.encoder(image)
        tasks = self.task_embeddings
        mixed = {}
        attention = []
        for t in TASKS:
            x = self.decoder1[t](feats)
            z_tilde, alpha = self.mixer[t].mix(x, tasks)
            mixed[t] = self.mixer[t].combine(x, z_tilde)
            attention.append(alpha)

        fine = self.kp_fine(feats[0])  # (B, kp_fine_channels, H/8, W/8)
        kp = [self.kp_decoder(mixed['kp']), fine]
        grey = image.mean(dim=1, keepdim=True)  # (B, 1, H, W)
        if self.kp_pixels is not None:
            cells = F.pixel_unshuffle(grey, KP_STRIDE)  # (B, 64, H/8, W/8)
            kp.append(self.kp_pixels(cells))  # (B, kp_pixel_channels, H/8, W/8)
        cells = self.kp_head(torch.cat(kp, dim=1))  # (B, 64, H/8, W/8)
        logits = F.pixel_shuffle(cells, KP_STRIDE)  # (B, 1, H, W)
        if self.kp_refine is not None:
            logits = logits + self.kp_refine(torch.cat([grey, logits], dim=1))  # (B, 1, H, W)

        desc = self.desc_head(self.desc_decoder(mixed['desc']))
        desc = F.normalize(desc, p=2, dim=1, eps=1e-8)

        seg = self.seg_reduce(self.seg_context(mixed['seg']))
        skip = feats[1]
        seg = F.interpolate(seg, size=skip.shape[-2:], mode='bilinear', align_corners=False)
        seg_feat = self.seg_refine(self.seg_decoder(torch.cat([seg, skip], dim=1)))
        seg_feat = self.seg_blocks(seg_feat)
        seg = self.seg_head(seg_feat)  # (B, C, H/4, W/4)
        if self.seg_fine is not None:
            f1 = feats[0]  # (B, c_1, H/2, W/2)
            up = F.interpolate(seg_feat, size=f1.shape[-2:], mode='bilinear',
                               align_corners=False)
            fine = self.seg_fine_head(self.seg_fine(torch.cat([up, f1], dim=1)))
            seg = F.interpolate(seg, size=f1.shape[-2:], mode='bilinear',
                                align_corners=False) + fine  # (B, C, H/2, W/2)
        return {
            'keypoint_logits': logits,
            'heatmap': torch.sigmoid(logits[:, 0]),
            'descriptors': desc,
            'segmentation_logits': seg,
            'mixer_attention': torch.stack(attention, dim=1),
        }

    def encoder_parameters(self, levels: int) -> list[nn.Parameter]:
        """Parameters of the first ``levels`` encoder blocks (frozen during warm-up)."""
        return [p for b in self.encoder.blocks[:levels] for p in b.parameters()]


IMAGE_MEAN = (0.45, 0.45, 0.45)
"""Per-channel mean of the input normalisation (RGB in [0, 1])."""
IMAGE_STD = (0.25, 0.25, 0.25)
"""Per-channel standard deviation of the input normalisation."""


def normalize_image(image: torch.Tensor) -> torch.Tensor:
    """uint8 or [0, 1] float RGB (B, 3, H, W) -> network input ``(x - mean) / std``."""
    x = image.float()
    if image.dtype == torch.uint8:
        x = x / 255.0
    mean = torch.tensor(IMAGE_MEAN, dtype=x.dtype, device=x.device)[:, None, None]
    std = torch.tensor(IMAGE_STD, dtype=x.dtype, device=x.device)[:, None, None]
    return (x - mean) / std


def fuse_batchnorm(model: nn.Module) -> nn.Module:
    """Fold every ``Conv2d -> BatchNorm2d`` pair (inside an ``nn.Sequential``) into one conv.

    Inference only: ``model`` must be in eval mode; it is modified in place and returned. The
    outputs are unchanged up to float rounding (checked in the tests).
    """
    if model.training:
        raise ModelConfigError('fuse_batchnorm: the model must be in eval mode')
    for seq in model.modules():
        if not isinstance(seq, nn.Sequential):
            continue
        for i in range(len(seq) - 1):
            conv, bn = seq[i], seq[i + 1]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                seq[i] = torch.nn.utils.fusion.fuse_conv_bn_eval(conv, bn)
                seq[i + 1] = nn.Identity()
    return model


def count_parameters(model: nn.Module) -> int:
    """Number of trainable + frozen parameters of ``model``."""
    return sum(p.numel() for p in model.parameters())
