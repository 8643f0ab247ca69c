"""Losses of the paper: BCE on the keypoint heatmap, contrastive margin loss on descriptors,
cross-entropy on segmentation, and their weighted sum.

All three are *means* over the terms the paper sums (valid pixels, pairs, labelled pixels), so
the task weights do not depend on the image size or the number of sampled points.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 - the usual torch alias

from semfeat_ros import conf as common_conf
from semfeat_ros.model.errors import ModelConfigError, ModelInputError
from semfeat_ros.model.semfeatnet import KP_STRIDE

IGNORE_LABEL = 255
"""Label value excluded from the segmentation loss (outside the image circle, unlabelled)."""

default_loss_conf: dict[str, Any] = {
    'w_kp': 1.0,  # alpha of L_total = alpha L_kp + beta L_desc + gamma L_seg
    'w_desc': 1.0,  # beta
    'w_seg': 0.5,  # gamma
    'kp_pos_weight': 20.0,  # BCE weight of positive (keypoint) pixels; ~1% of pixels are positive
    'kp_cell_weight': 0.0,  # weight of the cell localisation term added to L_kp (0: BCE only, as
    #                         the paper); see keypoint_cell_loss
    'desc_pos_margin': 1.0,  # m: positives are penalised by max(0, m - cos)
    'desc_neg_margin': 0.2,  # alpha (paper): negatives are penalised by max(0, cos - alpha)
    'desc_neg_radius': 8.0,  # px (input resolution): candidates closer than this are not negatives
    'desc_negatives': 'hardest',  # 'hardest' (HardNet-style mining), 'all' (every candidate pair
    #                               beyond the radius, averaged over the candidates) or 'sum' (the
    #                               paper's sum over negative pairs, divided like the positive sum
    #                               by the number of positives: violators are not diluted by the
    #                               many negatives that already satisfy the margin)
    'seg_loss_stride': 4,  # px: CE on labels sampled every s px, logits upsampled bilinearly to
    #                        that grid (1: every pixel, the paper; the logit stride 4: no
    #                        upsampling, ~16x cheaper); see segmentation_loss
    'seg_class_balance': 0.0,  # exponent p of the class weights (median freq / freq) ** p
    #                            (0: plain CE as in the paper; 0.5: rare classes such as parking
    #                            lines, curbs and pillars count more)
    'seg_max_class_weight': 10.0,  # upper clip of those weights
    'seg_lovasz_weight': 0.0,  # weight of the Lovasz-softmax term (a surrogate of the per-class
    #                            IoU, on the same grid) added to L_seg; 0: CE only (the paper)
    'distill_desc_weight': 0.0,  # weight of L_distill_desc (1 - cosine to a real-image teacher's
    #                              descriptor map, every covered cell); needs a teacher
    'distill_kp_weight': 0.0,  # weight of L_distill_kp (cross-entropy of each cell's 65-way
    #                            distribution against the teacher's); needs a teacher
    'desc_dsm_weight': 0.0,  # weight of L_dsm, the dual-softmax matching NLL of each pair's
    #                          correspondences (see dual_softmax_loss); 0: off (the paper)
    'desc_dsm_temperature': 0.1,  # cosine similarities are divided by this before the softmax
    'desc_dsm_neg_radius': None,  # px: L_dsm's exclusion radius around the true match (None:
    #                               desc_neg_radius). Mutual NN fails when a point's partner is
    #                               not detected and a keypoint a few px away is matched
    #                               instead; only candidates beyond the radius teach it not to
    'kp_repeat_weight': 0.0,  # weight of L_repeat, the cross-view consistency of the predicted
    #                           heatmaps (see keypoint_repeat_loss); needs data.dense_flow; 0: off
    'kp_repeat_patch': 16,  # px, side of the square windows L_repeat and L_peaky read (stride
    #                         half that)
    'kp_peaky_weight': 0.0,  # weight of L_peaky, the peakiness of the predicted heatmap in each
    #                          window (see keypoint_peaky_loss); 0: off
    'kp_reproj_weight': 0.0,  # weight of L_reproj, the reprojection error (px) of the refined
    #                           heatmap peaks (see keypoint_reprojection_loss); needs
    #                           data.dense_flow; 0: off
    'kp_reproj_radius': 3,  # px, L_reproj's window half side (the extractor's nms_radius)
    'kp_reproj_power': 4.0,  # L_reproj's centroid weight exponent (the extractor's
    #                          subpixel_power)
    'kp_reproj_top_k': 128,  # view-a peaks per image that L_reproj moves into view b
    'kp_photo_targets': 1.0,  # 1: the ground-truth keypoint terms also train on photo pairs
    #                           (homographically adapted corners); 0: photos' keypoints are
    #                           learnt from the teacher only
}


def keypoint_loss(logits: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None,
                  pos_weight: float = 1.0) -> torch.Tensor:
    """Binary cross-entropy between the heatmap and the ground-truth keypoint map (paper eq. 6).

    Args:
        logits: (B, 1, H, W) or (B, H, W) pre-sigmoid heatmap logits.
        target: (B, H, W) float in [0, 1] (1 at ground-truth keypoints).
        valid: optional (B, H, W) bool, pixels that take part (others are ignored).
        pos_weight: weight of the positive term (keypoints are ~1% of the pixels).
    Returns:
        scalar: weighted BCE averaged over valid pixels (0 if none).
    """
    if logits.ndim == 4:
        logits = logits[:, 0]
    if logits.shape != target.shape:
        raise ModelInputError(f'keypoint_loss: logits {tuple(logits.shape)} vs target '
                              f'{tuple(target.shape)}')
    pw = torch.tensor(float(pos_weight), dtype=logits.dtype, device=logits.device)
    loss = F.binary_cross_entropy_with_logits(logits, target.to(logits.dtype), reduction='none',
                                              pos_weight=pw)
    if valid is None:
        return loss.mean()
    valid = valid.to(loss.dtype)
    return (loss * valid).sum() / valid.sum().clamp(min=1.0)


def keypoint_cell_loss(logits: torch.Tensor, target: torch.Tensor,
                       valid: torch.Tensor | None = None) -> torch.Tensor:
    """Localisation term: cross-entropy of each keypoint cell's softmax over its 64 pixels.

    Per-pixel BCE scores every pixel independently, so a peak one pixel off costs little more
    than the right one. SuperPoint's detector loss is a softmax over the 64 pixels of each 8x8
    cell instead; this term applies that softmax to the cells that hold at least one ground-truth
    keypoint (and only valid pixels), with the target spread evenly over the cell's keypoints.
    It sharpens where the peak sits inside a cell; cells without keypoints are left to the BCE.

    Args:
        logits: (B, 1, H, W) or (B, H, W) pre-sigmoid heatmap logits; H, W multiples of 8.
        target: (B, H, W) float in [0, 1] (1 at ground-truth keypoints).
        valid: optional (B, H, W) bool; invalid pixels take no part in a cell's softmax.
    Returns:
        scalar: mean over cells with a valid keypoint (0 if none).
    """
    if logits.ndim == 4:
        logits = logits[:, 0]
    if logits.shape != target.shape:
        raise ModelInputError(f'keypoint_cell_loss: logits {tuple(logits.shape)} vs target '
                              f'{tuple(target.shape)}')
    cells = F.pixel_unshuffle(logits[:, None], KP_STRIDE)  # (B, 64, h, w)
    tgt = F.pixel_unshuffle(target[:, None].to(logits.dtype), KP_STRIDE)
    if valid is not None:
        ok = F.pixel_unshuffle(valid[:, None].to(logits.dtype), KP_STRIDE) > 0
        cells = cells.masked_fill(~ok, -1e4)
        tgt = tgt * ok
    mass = tgt.sum(dim=1)  # (B, h, w)
    has = mass > 0
    if not has.any():
        return logits.sum() * 0.0
    logp = F.log_softmax(cells.float(), dim=1)
    ce = -(tgt * logp).sum(dim=1) / mass.clamp(min=1e-6)
    return ce[has].mean()


def _check_pair_flow(caller: str, logits: torch.Tensor, flow: torch.Tensor,
                     flow_valid: torch.Tensor) -> tuple[int, int, int]:
    """``(B, H, W)`` of (2B, 1, H, W) pair logits and their (B, H, W, 2) flow and (B, H, W)
    validity; raises ModelInputError naming ``caller`` otherwise."""
    if logits.ndim != 4 or logits.shape[1] != 1:
        raise ModelInputError(f'{caller}: logits {tuple(logits.shape)}, expected (2B, 1, H, W)')
    b = logits.shape[0] // 2
    h, w = logits.shape[-2:]
    if flow.shape != (b, h, w, 2) or flow_valid.shape != (b, h, w):
        raise ModelInputError(f'{caller}: flow {tuple(flow.shape)} / valid '
                              f'{tuple(flow_valid.shape)} vs logits {tuple(logits.shape)}')
    return b, h, w


def keypoint_repeat_loss(logits: torch.Tensor, flow: torch.Tensor, flow_valid: torch.Tensor,
                         patch: int = 16, min_valid: float = 0.5) -> torch.Tensor:
    """Cross-view consistency of the predicted heatmaps (R2D2's repeatability loss).

    The targets of the other keypoint terms are fixed candidate points; this term asks the
    network's own heatmap to fire at the same scene points in both views of a pair, wherever
    it fires. View b's heatmap is warped into view a through the pair's dense correspondence
    (bilinear), and each ``patch`` x ``patch`` window (stride ``patch / 2``) of view a's heatmap
    is compared with the warped one by cosine similarity: the loss is 1 - its mean. Windows with
    less than ``min_valid`` of their pixels corresponding are skipped.

    Args:
        logits: (2B, 1, H, W) pre-sigmoid heatmap logits, views a then views b.
        flow: (B, H, W, 2) float px, each view-a pixel's position in view b.
        flow_valid: (B, H, W) bool, pixels whose correspondence exists.
        patch: px, window side (even).
        min_valid: fraction of a window's pixels that must correspond.
    Returns:
        scalar in [0, 1] (0 if no window qualifies).
    """
    b, h, w = _check_pair_flow('keypoint_repeat_loss', logits, flow, flow_valid)
    heat = torch.sigmoid(logits.float())
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], dtype=heat.dtype)
    grid = flow.to(heat.dtype) * scale - 1.0  # pixel centres at integers: align_corners=True
    warped = F.grid_sample(heat[b:], grid, mode='bilinear', padding_mode='zeros',
                           align_corners=True)
    valid = flow_valid[:, None].to(heat.dtype)
    ha, hb = heat[:b] * valid, warped * valid
    stride = patch // 2
    dot = F.avg_pool2d(ha * hb, patch, stride)
    norm2 = F.avg_pool2d(ha * ha, patch, stride) * F.avg_pool2d(hb * hb, patch, stride)
    cos = dot / torch.sqrt(norm2.clamp(min=1e-16))  # clamped inside: sqrt has no gradient at 0
    ok = F.avg_pool2d(valid, patch, stride) >= min_valid
    if not ok.any():
        return logits.sum() * 0.0
    return 1.0 - cos[ok].mean()


def _window_centroid(heat: torch.Tensor, n: torch.Tensor, rows: torch.Tensor,
                     cols: torch.Tensor, radius: int, power: float
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable heatmap centroid of the (2r+1)^2 windows at integer centres.

    The weights are ``h ** power`` normalised over the window, i.e. the extractor's soft-argmax
    refinement (``(h / h_peak) ** power``, the peak's value cancels in the normalisation).

    Args:
        heat: (N, H, W) heatmap in [0, 1].
        n, rows, cols: (K,) long image index and window centre (px); every window must lie
            inside the map.
    Returns:
        ``(u, v)``, each (K,) float px.
    """
    d = torch.arange(-radius, radius + 1)
    rr = rows[:, None, None] + d[None, :, None]
    cc = cols[:, None, None] + d[None, None, :]
    patch = heat[n[:, None, None], rr, cc]  # (K, 2r+1, 2r+1)
    wgt = patch.clamp(min=1e-6) ** power
    wgt = wgt / wgt.sum(dim=(1, 2), keepdim=True)
    u = cols.to(heat.dtype) + (wgt * d[None, None, :].to(heat.dtype)).sum(dim=(1, 2))
    v = rows.to(heat.dtype) + (wgt * d[None, :, None].to(heat.dtype)).sum(dim=(1, 2))
    return u, v


def _bilinear_points(field: torch.Tensor, n: torch.Tensor, u: torch.Tensor, v: torch.Tensor
                     ) -> torch.Tensor:
    """(B, H, W, C) field at float (K,) points ``(u, v)`` px of images ``n`` -> (K, C)."""
    h, w = field.shape[1:3]
    u0 = u.detach().floor().long().clamp(0, w - 2)
    v0 = v.detach().floor().long().clamp(0, h - 2)
    fu = (u - u0.to(u.dtype)).clamp(0.0, 1.0)[:, None]
    fv = (v - v0.to(v.dtype)).clamp(0.0, 1.0)[:, None]
    return (field[n, v0, u0] * (1 - fu) * (1 - fv) + field[n, v0, u0 + 1] * fu * (1 - fv)
            + field[n, v0 + 1, u0] * (1 - fu) * fv + field[n, v0 + 1, u0 + 1] * fu * fv)


def keypoint_reprojection_loss(logits: torch.Tensor, flow: torch.Tensor,
                               flow_valid: torch.Tensor, radius: int = 3, power: float = 4.0,
                               top_k: int = 128, threshold: float = 0.05) -> torch.Tensor:
    """Reprojection error of the refined heatmap peaks (ALIKED's reprojection loss).

    :func:`keypoint_repeat_loss` compares the two views' heatmaps window by window, which
    rewards firing at the same place but barely at the same sub-pixel position; the matching
    tolerance (3 px at the input, 2.4 px at the network on an 800 px frame run at 640 px) is
    spent on exactly that. This term trains the position the extractor returns: view a's
    ``top_k`` NMS peaks above ``threshold`` (selection without gradient) are refined as the
    extractor refines them (:func:`_window_centroid`), moved into view b by the pair's dense
    correspondence, and view b's heatmap is refined in the same window around the nearest
    pixel; the loss is the mean distance between the moved point and view b's refined one.

    Args:
        logits: (2B, 1, H, W) pre-sigmoid heatmap logits, views a then views b.
        flow: (B, H, W, 2) float px, each view-a pixel's position in view b.
        flow_valid: (B, H, W) bool, pixels whose correspondence exists.
        radius: px, half side of the window (the extractor's ``nms_radius``).
        power: weight exponent (the extractor's ``subpixel_power``).
        top_k: peaks per view-a image.
        threshold: minimum heatmap value of a peak.
    Returns:
        scalar px (0 if no peak lands inside view b).
    """
    b, h, w = _check_pair_flow('keypoint_reprojection_loss', logits, flow, flow_valid)
    heat = torch.sigmoid(logits.float())[:, 0]  # (2B, H, W)
    ha, hb = heat[:b], heat[b:]
    r = int(radius)
    with torch.no_grad():
        peak = ha == F.max_pool2d(ha[:, None], 2 * r + 1, 1, r)[:, 0]
        inner = torch.zeros_like(peak)
        inner[:, r:h - r, r:w - r] = True
        score = torch.where(peak & inner & flow_valid & (ha > threshold), ha,
                            torch.zeros_like(ha)).flatten(1)
        k = min(int(top_k), score.shape[1])
        top, idx = score.topk(k, dim=1)
        n = torch.arange(b)[:, None].expand(b, k)[top > 0]
        idx = idx[top > 0]
        rows, cols = idx // w, idx % w
    if not len(n):
        return logits.sum() * 0.0
    ua, va = _window_centroid(ha, n, rows, cols, r, power)
    moved = _bilinear_points(flow.to(heat.dtype), n, ua, va)  # (K, 2) px in view b
    with torch.no_grad():
        cb = moved.round().long()
        ok = (cb[:, 0] >= r) & (cb[:, 0] < w - r) & (cb[:, 1] >= r) & (cb[:, 1] < h - r)
    if not ok.any():
        return logits.sum() * 0.0
    ub, vb = _window_centroid(hb, n[ok], cb[ok, 1], cb[ok, 0], r, power)
    err = torch.stack([ub - moved[ok, 0], vb - moved[ok, 1]], dim=1)
    return torch.sqrt((err * err).sum(dim=1) + 1e-8).mean()


def keypoint_peaky_loss(logits: torch.Tensor, valid: torch.Tensor, patch: int = 16,
                        min_valid: float = 0.5) -> torch.Tensor:
    """Peakiness of the predicted heatmap (R2D2's peaky loss, the partner of its repeatability
    loss, :func:`keypoint_repeat_loss`).

    The consistency term is as happy with a flat heatmap as with a peaked one. This term asks
    each ``patch`` x ``patch`` window (stride ``patch / 2``) for a clear maximum: the loss is 1 -
    the mean over windows of (window max - window mean) of the sigmoid heatmap, over the
    ``valid`` pixels. Windows with less than ``min_valid`` of their pixels valid are skipped.

    Args:
        logits: (N, 1, H, W) pre-sigmoid heatmap logits.
        valid: (N, H, W) bool, pixels that count (inside the crop and the image circle).
        patch: px, window side (even).
        min_valid: fraction of a window's pixels that must be valid.
    Returns:
        scalar in [0, 1] (0 if no window qualifies).
    """
    if logits.ndim != 4 or logits.shape[1] != 1:
        raise ModelInputError(f'keypoint_peaky_loss: logits {tuple(logits.shape)}, expected '
                              f'(N, 1, H, W)')
    if valid.shape != (logits.shape[0], *logits.shape[-2:]):
        raise ModelInputError(f'keypoint_peaky_loss: valid {tuple(valid.shape)} vs logits '
                              f'{tuple(logits.shape)}')
    mask = valid[:, None].to(torch.float32)
    heat = torch.sigmoid(logits.float()) * mask  # >= 0, so masked pixels never win the max
    stride = patch // 2
    cover = F.avg_pool2d(mask, patch, stride)
    mean = F.avg_pool2d(heat, patch, stride) / cover.clamp(min=1e-6)
    peak = F.max_pool2d(heat, patch, stride)
    ok = cover >= min_valid
    if not ok.any():
        return logits.sum() * 0.0
    return 1.0 - (peak - mean)[ok].mean()


def distill_descriptor_loss(desc: torch.Tensor, teacher: torch.Tensor,
                            valid: torch.Tensor | None = None) -> torch.Tensor:
    """Dense descriptor distillation: mean ``1 - cos`` between student and teacher maps.

    Args:
        desc: (B, D, h, w) student descriptors at stride 8, unit L2 norm along dim 1.
        teacher: (B, D, h, w) teacher descriptors, unit L2 norm along dim 1.
        valid: optional (B, h, w) bool cells that take part.
    Returns:
        scalar in [0, 2]: mean over valid cells (0 if none).
    """
    if desc.shape != teacher.shape:
        raise ModelInputError(f'distill_descriptor_loss: student {tuple(desc.shape)} vs teacher '
                              f"{tuple(teacher.shape)} (descriptor_dim must be the teacher's)")
    cos = (desc * teacher.to(desc.dtype)).sum(dim=1)  # (B, h, w)
    if valid is None:
        return (1.0 - cos).mean()
    if not valid.any():
        return desc.sum() * 0.0
    return (1.0 - cos[valid]).mean()


def distill_keypoint_loss(logits: torch.Tensor, teacher_cells: torch.Tensor,
                          valid: torch.Tensor | None = None) -> torch.Tensor:
    """Dense keypoint distillation on the teacher's 65-way cell distributions.

    The student's heatmap is per-pixel Bernoulli; read as a cell distribution its 64 logits
    join a dustbin logit fixed at 0 (``softmax([s_1 .. s_64, 0])``, where a single peak has the
    probability ``sigmoid(s_i)``). Each cell's cross-entropy against the teacher's softmax
    teaches both which cells hold a keypoint and where in the cell it sits.

    Args:
        logits: (B, 1, H, W) or (B, H, W) student heatmap logits; H, W multiples of 8.
        teacher_cells: (B, 65, H/8, W/8) teacher logits (64 pixels in ``pixel_unshuffle``
            order, then the dustbin).
        valid: optional (B, H/8, W/8) bool cells that take part.
    Returns:
        scalar: mean cross-entropy over valid cells (0 if none).
    """
    if logits.ndim == 3:
        logits = logits[:, None]
    cells = F.pixel_unshuffle(logits, KP_STRIDE)  # (B, 64, h, w)
    if teacher_cells.shape[1] != KP_STRIDE * KP_STRIDE + 1 or \
            teacher_cells.shape[-2:] != cells.shape[-2:] or \
            teacher_cells.shape[0] != cells.shape[0]:
        raise ModelInputError(f'distill_keypoint_loss: teacher {tuple(teacher_cells.shape)} vs '
                              f'student cells {tuple(cells.shape)} (+1 dustbin channel)')
    dustbin = torch.zeros_like(cells[:, :1])
    logp = F.log_softmax(torch.cat([cells, dustbin], dim=1).float(), dim=1)
    target = F.softmax(teacher_cells.float(), dim=1)
    ce = -(target * logp).sum(dim=1)  # (B, h, w)
    if valid is None:
        return ce.mean()
    if not valid.any():
        return logits.sum() * 0.0
    return ce[valid].mean()


def sample_descriptors(desc: torch.Tensor, points: torch.Tensor,
                       stride: int = KP_STRIDE) -> torch.Tensor:
    """Bilinearly sample a stride-``stride`` descriptor map at points and re-normalise.

    Args:
        desc: (B, D, h, w) descriptor map (cell (i, j) centred at input px (8j + 3.5, 8i + 3.5)).
        points: (B, M, 2) (u, v) px at the input resolution ``(h * stride, w * stride)``; pixel
            centres at integers.
    Returns:
        (B, M, D) unit-norm descriptors.
    """
    b, _, h, w = desc.shape
    # px -> normalised coordinates of the map (align_corners=False: -1 = left edge of cell 0)
    grid = (points + 0.5) / torch.tensor([w * stride, h * stride], dtype=points.dtype,
                                         device=points.device) * 2.0 - 1.0
    out = F.grid_sample(desc, grid[:, None].to(desc.dtype), mode='bilinear',
                        padding_mode='border', align_corners=False)  # (B, D, 1, M)
    return F.normalize(out[:, :, 0].transpose(1, 2), p=2, dim=-1, eps=1e-8)


def _pair_similarity(caller: str, desc_a: torch.Tensor, desc_b: torch.Tensor,
                     points_a: torch.Tensor, points_b: torch.Tensor, valid: torch.Tensor,
                     neg_radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The pair's sampled similarities and which candidates lie far from the true match.

    Args: as :func:`descriptor_loss` (``caller`` names it in the shape error).
    Returns:
        ``(sim, far)``: (B, M, M) ``sim[b, i, j] = <a_i, b_j>`` and (B, M, M) bool, point j
        farther than ``neg_radius`` px from point i in both views.
    """
    if points_a.shape != points_b.shape or points_a.shape[:2] != valid.shape:
        raise ModelInputError(
            f'{caller}: points_a {tuple(points_a.shape)}, points_b '
            f'{tuple(points_b.shape)}, valid {tuple(valid.shape)} must agree (B, M, 2)/(B, M)')
    da = sample_descriptors(desc_a, points_a)
    db = sample_descriptors(desc_b, points_b)
    far = (torch.cdist(points_a, points_a) > neg_radius) & \
        (torch.cdist(points_b, points_b) > neg_radius)
    return da @ db.transpose(1, 2), far


def descriptor_loss(desc_a: torch.Tensor, desc_b: torch.Tensor, points_a: torch.Tensor,
                    points_b: torch.Tensor, valid: torch.Tensor, pos_margin: float = 1.0,
                    neg_margin: float = 0.2, neg_radius: float = 8.0, negatives: str = 'hardest'
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Contrastive margin loss on cosine similarity (paper eq. 7) with hardest negatives.

    Positive pairs are the ground-truth correspondences ``(points_a[i], points_b[i])``. For each
    positive, the negative is the hardest (most similar) *other* sampled point of the same pair
    whose position lies farther than ``neg_radius`` px from the true match, searched in both
    directions (a_i against all b_j, and b_i against all a_j), as in HardNet.

    Args:
        desc_a, desc_b: (B, D, h, w) unit-norm descriptor maps of the two views.
        points_a, points_b: (B, M, 2) corresponding (u, v) px in view a and view b.
        valid: (B, M) bool, correspondence exists (padding rows are False).
        pos_margin: m, positives cost ``max(0, m - sim)``.
        neg_margin: alpha, negatives cost ``max(0, sim - alpha)``.
        neg_radius: px, exclusion radius around the true match for negatives.
        negatives: 'hardest' (one mined negative per point and direction), 'all' (the mean
            of ``max(0, sim - alpha)`` over every candidate pair beyond ``neg_radius``) or 'sum'
            (the sum of that term over every candidate pair, divided by the number of valid
            positives: eq. 7 with both sums normalised by |P|).
    Returns:
        ``(loss, stats)``: scalar loss (mean positive term + mean negative term, 0 if no valid
        pair) and detached statistics ``pos_sim``, ``neg_sim`` (means).
    """
    sim, far = _pair_similarity('descriptor_loss', desc_a, desc_b, points_a, points_b, valid,
                                neg_radius)
    pos = sim.diagonal(dim1=1, dim2=2)  # (B, M)
    vf = valid.to(sim.dtype)
    n_valid = vf.sum()
    if n_valid < 1:
        zero = sim.sum() * 0.0
        return zero, {'pos_sim': zero.detach(), 'neg_sim': zero.detach()}
    # negatives must be valid points farther than neg_radius from the true match in *both* views
    cand = far & valid[:, None, :] & valid[:, :, None]
    masked = sim.masked_fill(~cand, -2.0)
    hard_ab = masked.max(dim=2).values  # hardest b_j for each a_i
    hard_ba = masked.max(dim=1).values  # hardest a_j for each b_i
    has_ab = cand.any(dim=2) & valid
    has_ba = cand.any(dim=1) & valid
    pos_term = (F.relu(pos_margin - pos) * vf).sum() / n_valid
    if negatives == 'all':
        cf = cand.to(sim.dtype)
        neg_term = (F.relu(sim - neg_margin) * cf).sum() / cf.sum().clamp(min=1)
    elif negatives == 'sum':
        cf = cand.to(sim.dtype)
        neg_term = (F.relu(sim - neg_margin) * cf).sum() / n_valid
    elif negatives == 'hardest':
        neg_ab = F.relu(hard_ab - neg_margin) * has_ab.to(sim.dtype)
        neg_ba = F.relu(hard_ba - neg_margin) * has_ba.to(sim.dtype)
        n_neg = (has_ab.sum() + has_ba.sum()).clamp(min=1).to(sim.dtype)
        neg_term = (neg_ab.sum() + neg_ba.sum()) / n_neg
    else:
        raise ModelConfigError(
            f"desc_negatives must be 'hardest', 'all' or 'sum', got {negatives!r}")
    stats = {
        'pos_sim': ((pos * vf).sum() / n_valid).detach(),
        'neg_sim': ((hard_ab * has_ab).sum() / has_ab.sum().clamp(min=1)).detach(),
    }
    return pos_term + neg_term, stats


def dual_softmax_loss(desc_a: torch.Tensor, desc_b: torch.Tensor, points_a: torch.Tensor,
                      points_b: torch.Tensor, valid: torch.Tensor, temperature: float = 0.1,
                      neg_radius: float = 8.0) -> torch.Tensor:
    """Dual-softmax matching NLL of the ground-truth correspondences.

    Mutual nearest-neighbour matching succeeds when a point's true partner is the most similar
    candidate in both directions; this loss asks for that directly: with ``S = sim / T`` over
    the pair's sampled points, the negative log-likelihood of the true partner under the row
    softmax (a_i against every b_j) plus the column softmax (b_i against every a_j). Candidates
    closer than ``neg_radius`` px to the true match in either view are left out of both
    softmaxes (they share interpolation support with the partner on the stride-8 grid).

    Args:
        desc_a, desc_b: (B, D, h, w) unit-norm descriptor maps of the two views.
        points_a, points_b: (B, M, 2) corresponding (u, v) px in view a and view b.
        valid: (B, M) bool, correspondence exists (padding rows are False).
        temperature: T > 0 dividing the cosine similarities.
        neg_radius: px, exclusion radius around the true match.
    Returns:
        scalar: mean over valid points and both directions (0 if no valid pair).
    """
    if temperature <= 0:
        raise ModelConfigError(f'dual_softmax_loss: temperature must be > 0, got {temperature!r}')
    sim, far = _pair_similarity('dual_softmax_loss', desc_a, desc_b, points_a, points_b, valid,
                                neg_radius)
    if not valid.any():
        return sim.sum() * 0.0
    eye = torch.eye(sim.shape[-1], dtype=torch.bool, device=sim.device)[None]
    keep = (far & valid[:, None, :] & valid[:, :, None]) | eye
    logits = (sim.float() / temperature).masked_fill(~keep, float('-inf'))  # (B, M, M)
    nll_ab = -F.log_softmax(logits, dim=2).diagonal(dim1=1, dim2=2)  # (B, M)
    nll_ba = -F.log_softmax(logits, dim=1).diagonal(dim1=1, dim2=2)
    return 0.5 * (nll_ab[valid].mean() + nll_ba[valid].mean())


def assignment_nll(log_assignment: torch.Tensor, matches0: torch.Tensor,
                   matches1: torch.Tensor) -> torch.Tensor:
    """LightGlue's assignment loss: NLL of the ground-truth matches and of the unmatched.

    The positive term is the mean ``-log P[i, j]`` over the true matches (i, j); the negative
    term the mean ``-log P[i, unmatched]`` over the unmatched keypoints of image 0 and
    ``-log P[unmatched, j]`` over those of image 1; the loss is the average of the terms that
    have members (LightGlue's balancing factor 0.5). Keypoints marked ignore (between the match
    and the unmatched tolerance) take no part.

    Args:
        log_assignment: (B, M + 1, N + 1) log assignment with the unmatched column and row.
        matches0: (B, M) int64: index in image 1 of each keypoint's match, -1 unmatched,
            -2 ignore.
        matches1: (B, N) int64: the same for image 1.
    Returns:
        scalar (0 if there is neither a match nor an unmatched keypoint).
    """
    b, m1, n1 = log_assignment.shape
    if tuple(matches0.shape) != (b, m1 - 1) or tuple(matches1.shape) != (b, n1 - 1):
        raise ModelInputError(f'assignment_nll: matches {tuple(matches0.shape)} / '
                              f'{tuple(matches1.shape)} do not fit the log assignment '
                              f'{tuple(log_assignment.shape)}')
    la = log_assignment.float()
    pos = matches0 >= 0
    zero = la.sum() * 0.0
    nll_pos = -la[:, :-1, :].gather(2, matches0.clamp(min=0)[..., None])[..., 0][pos]
    neg0, neg1 = matches0 == -1, matches1 == -1
    nll_neg = torch.cat([-la[:, :-1, -1][neg0], -la[:, -1, :-1][neg1]])
    terms = [t.mean() for t in (nll_pos, nll_neg) if t.numel()]
    return zero if not terms else sum(terms) / len(terms)


def token_confidence_loss(log_assignments: list[torch.Tensor],
                          logits0: list[torch.Tensor], logits1: list[torch.Tensor]
                          ) -> torch.Tensor:
    """LightGlue's early-exit target: will a point's match change after this layer?

    After layer i, a point's prediction is its row's (image 0) or column's (image 1) most
    likely entry of that layer's log assignment, the unmatched slot included. The token
    confidence of layer i is trained with binary cross-entropy to say whether that prediction
    already equals the last layer's. Targets come from detached assignments.

    Args:
        log_assignments: L tensors (B, M + 1, N + 1), every layer's log assignment.
        logits0, logits1: L - 1 tensors (B, M) / (B, N), pre-sigmoid token confidences of
            layers 0 .. L - 2.
    Returns:
        scalar: mean over the layers and both images.
    """
    if len(logits0) != len(log_assignments) - 1 or len(logits1) != len(logits0):
        raise ModelInputError(f'token_confidence_loss: {len(log_assignments)} layers need '
                              f'{len(log_assignments) - 1} confidences per image, got '
                              f'{len(logits0)} / {len(logits1)}')
    final = log_assignments[-1].detach()
    final0, final1 = final[:, :-1, :].argmax(-1), final[:, :, :-1].argmax(-2)
    total = log_assignments[-1].new_zeros(())
    for la, c0, c1 in zip(log_assignments[:-1], logits0, logits1):
        la = la.detach()
        same0 = (la[:, :-1, :].argmax(-1) == final0).to(c0.dtype)
        same1 = (la[:, :, :-1].argmax(-2) == final1).to(c1.dtype)
        total = total + 0.5 * (F.binary_cross_entropy_with_logits(c0, same0)
                               + F.binary_cross_entropy_with_logits(c1, same1))
    return total / max(len(logits0), 1)


def _on_loss_grid(logits: torch.Tensor, labels: torch.Tensor, stride: int
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Logits (B, C, h, w) and labels (B, H, W) on the loss grid of ``stride`` px (see
    :func:`segmentation_loss`): ``((B, C, H/s, W/s) logits, (B, H/s, W/s) long labels)``."""
    if labels.ndim != 3 or logits.ndim != 4 or labels.shape[0] != logits.shape[0]:
        raise ModelInputError(f'segmentation_loss: logits {tuple(logits.shape)} (B, C, h, w) '
                              f'vs labels {tuple(labels.shape)} (B, H, W)')
    H, W = labels.shape[-2:]
    if stride < 1 or H % stride or W % stride:
        raise ModelInputError(f'segmentation_loss: labels {tuple(labels.shape)} are not a '
                              f'multiple of the loss stride {stride}')
    h, w = H // stride, W // stride
    if (h, w) != logits.shape[-2:]:
        s = W // logits.shape[-1]
        if s < stride or W != s * logits.shape[-1] or H != s * logits.shape[-2]:
            raise ModelInputError(f'segmentation_loss: labels {tuple(labels.shape)} are not '
                                  f'an integer multiple of logits {tuple(logits.shape)} or the '
                                  f'logits are finer than the loss stride {stride}')
        # bilinear, align_corners=False: logit cell centres land on the centres of the grid
        logits = F.interpolate(logits, size=(h, w), mode='bilinear', align_corners=False)
    labels = labels.long()
    if stride > 1:
        labels = labels[:, stride // 2::stride, stride // 2::stride]
    return logits, labels


def lovasz_softmax_loss(logits: torch.Tensor, labels: torch.Tensor, stride: int = 1
                        ) -> torch.Tensor:
    """Lovasz-softmax loss (Berman et al., CVPR 2018): a convex surrogate of 1 - IoU per class.

    For every class present in the batch the pixel errors ``|[y == c] - p_c|`` are sorted in
    decreasing order and weighted by the gradient of the Jaccard loss along that order; the
    loss is the mean over those classes. Unlike the (class-weighted) cross-entropy it penalises
    false positives of a rare class as much as its misses, which is what the mIoU counts.

    Args:
        logits: (B, C, h, w) class logits at stride ``H / h``.
        labels: (B, H, W) integer class ids, :data:`IGNORE_LABEL` ignored.
        stride: loss grid (px), as in :func:`segmentation_loss`.
    Returns:
        scalar (0 if every pixel is ignored).
    """
    logits, labels = _on_loss_grid(logits, labels, stride)
    probs = logits.softmax(dim=1).permute(0, 2, 3, 1).reshape(-1, logits.shape[1])
    labels = labels.reshape(-1)
    keep = labels != IGNORE_LABEL
    if not keep.any():
        return logits.sum() * 0.0
    probs, labels = probs[keep], labels[keep]
    losses = []
    for c in torch.unique(labels).tolist():
        fg = (labels == c).to(probs.dtype)
        errors, order = torch.sort((fg - probs[:, c]).abs(), descending=True)
        fg = fg[order]
        total = fg.sum()
        intersection = total - fg.cumsum(0)
        union = total + (1.0 - fg).cumsum(0)
        jaccard = 1.0 - intersection / union
        grad = torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]])
        losses.append(torch.dot(errors, grad))
    return torch.stack(losses).mean()


def segmentation_loss(logits: torch.Tensor, labels: torch.Tensor,
                      class_weights: torch.Tensor | None = None,
                      stride: int = 1) -> torch.Tensor:
    """Multi-class cross-entropy (paper eq. 8).

    Args:
        logits: (B, C, h, w) class logits at stride ``s = H / h`` (integer).
        labels: (B, H, W) integer class ids, :data:`IGNORE_LABEL` (255) ignored.
        class_weights: optional (C,) per-class weights.
        stride: ``s`` (px), the grid the CE is taken on: labels are sampled at the centres of
            the ``s x s`` cells (pixel ``s*i + s//2``) and logits coarser than that grid are
            upsampled bilinearly to it. 1: every pixel (the paper); the logit stride (4): no
            upsampling, ~16x cheaper, but the samples miss a 2 px wide line at half of its
            possible positions; 2: ~4x cheaper than 1, and every line 2 px wide is sampled.
    Returns:
        scalar: mean CE over labelled pixels (0 if every pixel is ignored).
    """
    logits, labels = _on_loss_grid(logits, labels, stride)
    if not (labels != IGNORE_LABEL).any():
        return logits.sum() * 0.0
    return F.cross_entropy(logits, labels, weight=class_weights, ignore_index=IGNORE_LABEL)


def class_balance_weights(counts: np.ndarray, power: float, max_weight: float) -> np.ndarray:
    """Per-class CE weights ``clip((median(f) / f) ** power, 1 / max_weight, max_weight)``.

    Args:
        counts: (C,) labelled pixel counts per class in the training data.
        power: p; 0 gives all ones (plain CE).
        max_weight: clip of the weights (a class absent from the data gets ``max_weight``).
    Returns:
        (C,) float32 weights.
    """
    counts = np.asarray(counts, np.float64)
    if counts.ndim != 1 or (counts < 0).any():
        raise ModelConfigError(f'class counts must be a 1-D array >= 0, got {counts!r}')
    if power == 0 or counts.sum() <= 0:
        return np.ones(len(counts), np.float32)
    freq = counts / counts.sum()
    med = float(np.median(freq[freq > 0]))
    with np.errstate(divide='ignore'):
        w = np.where(freq > 0, (med / np.maximum(freq, 1e-12)) ** power, max_weight)
    return np.clip(w, 1.0 / max_weight, max_weight).astype(np.float32)


class MultiTaskLoss:
    """L_total = w_kp L_kp + w_desc L_desc + w_seg L_seg (paper eq. 9: alpha, beta, gamma)."""

    def __init__(self, conf: dict[str, Any] | None = None,
                 class_weights: np.ndarray | None = None) -> None:
        """Args:
            conf: loss config (keys of :data:`default_loss_conf`).
            class_weights: optional (C,) segmentation CE weights (see
                :func:`class_balance_weights`); None: unweighted.
        """
        self.class_weights = None if class_weights is None else torch.as_tensor(
            np.asarray(class_weights, np.float32))
        self.conf = conf = common_conf.merge_conf(default_loss_conf, conf, ModelConfigError,
                                                  name='loss', what='loss config key')
        for key, value in conf.items():
            if key == 'seg_loss_stride':
                if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                    raise ModelConfigError(f'loss.{key} must be an integer >= 1 (px), got '
                                           f'{value!r}')
                continue
            if key == 'kp_repeat_patch':
                if not isinstance(value, int) or isinstance(value, bool) or value < 2 or value % 2:
                    raise ModelConfigError(f'loss.{key} must be an even integer >= 2 (px), got '
                                           f'{value!r}')
                continue
            if key in ('kp_reproj_radius', 'kp_reproj_top_k'):
                if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                    raise ModelConfigError(f'loss.{key} must be an integer >= 1, got '
                                           f'{value!r}')
                continue
            if key == 'desc_dsm_neg_radius' and value is None:
                continue
            if key == 'desc_negatives':
                if value not in ('hardest', 'all', 'sum'):
                    raise ModelConfigError(
                        f"loss.{key} must be 'hardest', 'all' or 'sum', got {value!r}")
                continue
            if not isinstance(value, int | float) or isinstance(value, bool) or value < 0:
                raise ModelConfigError(f'loss.{key} must be a number >= 0, got {value!r}')
        if conf['kp_photo_targets'] not in (0, 1):
            raise ModelConfigError(f'loss.kp_photo_targets must be 0 or 1, got '
                                   f'{conf["kp_photo_targets"]!r}')
        if conf['desc_dsm_temperature'] <= 0:
            raise ModelConfigError(f'loss.desc_dsm_temperature must be > 0, got '
                                   f'{conf["desc_dsm_temperature"]!r}')
        if conf['seg_max_class_weight'] < 1:
            raise ModelConfigError(f'loss.seg_max_class_weight must be >= 1, got '
                                   f'{conf["seg_max_class_weight"]!r}')

    def __call__(self, pred: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]
                 ) -> tuple[torch.Tensor, dict[str, float]]:
        """Total loss of a pair batch.

        Args:
            pred: network output on ``cat([image_a, image_b])`` (batch 2B, see SemFeatNet).
            batch: ``kp_target`` (2B, H, W) float, ``kp_valid`` (2B, H, W) bool,
                ``label`` (2B, H, W) int (255 ignored), ``points_a``/``points_b`` (B, M, 2) px,
                ``corr_valid`` (B, M) bool; optional ``photo`` (2B,) bool (views of real
                photographs) and, for distillation, the teacher's ``teacher_desc``
                (2B, D, H/8, W/8), ``teacher_cells`` (2B, 65, H/8, W/8) and ``teacher_valid``
                (2B, H/8, W/8) bool covered cells; for ``kp_repeat_weight``, ``flow`` (B, H, W, 2)
                px and ``flow_valid`` (B, H, W) bool (view a's pixels in view b; also for
                ``kp_reproj_weight``).
        Returns:
            ``(total, logs)``, logs holding floats ``loss``, ``kp``, ``desc``, ``seg``,
            ``pos_sim``, ``neg_sim`` (and ``distill_desc``, ``distill_kp``, ``repeat``,
            ``reproj``, ``peaky`` when computed).
        """
        c = self.conf
        for key in ('kp_repeat_weight', 'kp_reproj_weight'):
            if c[key] > 0 and 'flow' not in batch:
                raise ModelInputError(f"loss.{key} > 0 needs the batch's dense flow "
                                      '(data.dense_flow: true)')
        kp_valid = batch['kp_valid']
        if c['kp_photo_targets'] == 0 and 'photo' in batch:
            kp_valid = kp_valid & ~batch['photo'][:, None, None]
        l_kp = keypoint_loss(pred['keypoint_logits'], batch['kp_target'], kp_valid,
                             c['kp_pos_weight'])
        l_cell = None
        if c['kp_cell_weight'] > 0:
            l_cell = keypoint_cell_loss(pred['keypoint_logits'], batch['kp_target'], kp_valid)
            l_kp = l_kp + c['kp_cell_weight'] * l_cell
        desc = pred['descriptors']
        half = desc.shape[0] // 2
        l_repeat = None
        if c['kp_repeat_weight'] > 0:
            l_repeat = keypoint_repeat_loss(pred['keypoint_logits'], batch['flow'],
                                            batch['flow_valid'], c['kp_repeat_patch'])
        l_reproj = None
        if c['kp_reproj_weight'] > 0:
            l_reproj = keypoint_reprojection_loss(
                pred['keypoint_logits'], batch['flow'], batch['flow_valid'],
                c['kp_reproj_radius'], c['kp_reproj_power'], c['kp_reproj_top_k'])
        l_peaky = None
        if c['kp_peaky_weight'] > 0:
            l_peaky = keypoint_peaky_loss(pred['keypoint_logits'], batch['kp_valid'],
                                          c['kp_repeat_patch'])
        l_desc, stats = descriptor_loss(
            desc[:half], desc[half:], batch['points_a'], batch['points_b'], batch['corr_valid'],
            c['desc_pos_margin'], c['desc_neg_margin'], c['desc_neg_radius'],
            c['desc_negatives'])
        l_dsm = None
        if c['desc_dsm_weight'] > 0:
            l_dsm = dual_softmax_loss(
                desc[:half], desc[half:], batch['points_a'], batch['points_b'],
                batch['corr_valid'], c['desc_dsm_temperature'],
                c['desc_neg_radius'] if c['desc_dsm_neg_radius'] is None
                else c['desc_dsm_neg_radius'])
        l_seg = segmentation_loss(pred['segmentation_logits'], batch['label'],
                                  class_weights=self.class_weights,
                                  stride=c['seg_loss_stride'])
        l_lovasz = None
        if c['seg_lovasz_weight'] > 0:
            l_lovasz = lovasz_softmax_loss(pred['segmentation_logits'], batch['label'],
                                           stride=c['seg_loss_stride'])
            l_seg = l_seg + c['seg_lovasz_weight'] * l_lovasz
        total = c['w_kp'] * l_kp + c['w_desc'] * l_desc + c['w_seg'] * l_seg
        if l_dsm is not None:
            total = total + c['desc_dsm_weight'] * l_dsm
        if l_repeat is not None:
            total = total + c['kp_repeat_weight'] * l_repeat
        if l_reproj is not None:
            total = total + c['kp_reproj_weight'] * l_reproj
        if l_peaky is not None:
            total = total + c['kp_peaky_weight'] * l_peaky
        distill = {}
        if 'teacher_desc' in batch and c['distill_desc_weight'] > 0:
            distill['distill_desc'] = distill_descriptor_loss(desc, batch['teacher_desc'],
                                                              batch['teacher_valid'])
            total = total + c['distill_desc_weight'] * distill['distill_desc']
        if 'teacher_cells' in batch and c['distill_kp_weight'] > 0:
            distill['distill_kp'] = distill_keypoint_loss(
                pred['keypoint_logits'], batch['teacher_cells'], batch['teacher_valid'])
            total = total + c['distill_kp_weight'] * distill['distill_kp']
        logs = {'loss': float(total.detach()), 'kp': float(l_kp.detach()),
                'desc': float(l_desc.detach()), 'seg': float(l_seg.detach()),
                'pos_sim': float(stats['pos_sim']), 'neg_sim': float(stats['neg_sim'])}
        if l_cell is not None:
            logs['kp_cell'] = float(l_cell.detach())
        if l_lovasz is not None:
            logs['seg_lovasz'] = float(l_lovasz.detach())
        if l_dsm is not None:
            logs['dsm'] = float(l_dsm.detach())
        if l_repeat is not None:
            logs['repeat'] = float(l_repeat.detach())
        if l_reproj is not None:
            logs['reproj'] = float(l_reproj.detach())
        if l_peaky is not None:
            logs['peaky'] = float(l_peaky.detach())
        logs.update({k: float(v.detach()) for k, v in distill.items()})
        return total, logs
