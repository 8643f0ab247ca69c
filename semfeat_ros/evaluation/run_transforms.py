"""Mode ``transforms``: the paper's protocol on any image folder or image topic of a bag.

Each pair is (image, image warped by a random transform of :mod:`.transforms`); the ground truth
is that homography, exactly. Pixels that leave the frame or the image circle are excluded.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from semfeat_ros.evaluation.datasets import (
    bag_image_count,
    find_companion,
    iter_bag_images,
    list_images,
    read_image,
    read_keypoint_file,
    read_label_image,
    select_indices,
)
from semfeat_ros.evaluation.errors import ConfigError
from semfeat_ros.evaluation.groundtruth import HomographyGroundTruth, Pair
from semfeat_ros.evaluation.masks import MaskSource
from semfeat_ros.evaluation.pipeline import EvalConf, evaluate
from semfeat_ros.evaluation.segmentation import IGNORE
from semfeat_ros.evaluation.transforms import (
    TransformConf,
    sample_transform,
    warp_image,
)


@dataclass(frozen=True)
class TransformsPaths:
    """Inputs and output folder. Exactly one of ``images`` (folder) and ``bag``. ``labels``: a
    folder of ``<stem>.png`` mono8 GT class ids; ``gt_keypoints``: a folder of ``<stem>.npy`` /
    ``<stem>.txt`` (K, 2) px GT keypoint sets; ``camera``: calibration YAML (image circle)."""

    out: Path
    images: Path | None = None
    bag: Path | None = None
    topic: str | None = None
    labels: Path | None = None
    gt_keypoints: Path | None = None
    camera: Path | None = None


@dataclass(frozen=True)
class TransformsConf:
    """``pairs`` pairs, images used in turn (evenly spread, cycling when fewer than pairs)."""

    eval: EvalConf = field(default_factory=EvalConf)
    pairs: int = 48
    transform: TransformConf = field(default_factory=TransformConf)
    image_circle: str = 'auto'
    mask_margin_px: int = 8
    distortion_model: str | None = None
    fov_deg: float | None = None

    def __post_init__(self) -> None:
        if self.pairs < 1:
            raise ConfigError(f'--pairs must be >= 1, got {self.pairs}')


def make_transform_pair(name: str, image: np.ndarray, rng: np.random.Generator,
                        masks: MaskSource, tconf: TransformConf | None = None, *,
                        labels: np.ndarray | None = None,
                        gt_keypoints: np.ndarray | None = None) -> Pair:
    """Build one pair from ``image`` (H, W, 3) RGB: B = A warped by a sampled transform."""
    h, w = image.shape[:2]
    t = sample_transform(rng, w, h, tconf)
    raw_a = masks(image)
    raw_b = warp_image(raw_a.astype(np.uint8) * 255, t.H, nearest=True) > 127
    mask_a, mask_b = masks.final(raw_a), masks.final(raw_b)
    labels_b = None
    if labels is not None:
        labels_b = warp_image(labels, t.H, nearest=True, border_value=IGNORE)
    gt = HomographyGroundTruth(t.H, mask_a, mask_b)
    meta: dict[str, object] = {'transform': t.as_dict()}
    return Pair(name, image, warp_image(image, t.H), mask_a, mask_b, gt, H=t.H,
                labels_a=labels, labels_b=labels_b, gt_keypoints_a=gt_keypoints, meta=meta)


def _rngs(seed: int, n: int) -> list[np.random.Generator]:
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]


def iter_pairs(conf: TransformsConf, paths: TransformsPaths,
               masks: MaskSource) -> tuple[Iterator[Pair], str]:
    """The pairs (lazily: one image in memory at a time) and a description of the source."""
    if (paths.images is None) == (paths.bag is None):
        raise ConfigError('transforms: give exactly one of --images DIR and --bag BAG')
    rngs = _rngs(conf.eval.seed, conf.pairs)
    if paths.images is not None:
        files = list_images(paths.images)
        schedule = select_indices(len(files), conf.pairs)

        def gen_files() -> Iterator[Pair]:
            for k, idx in enumerate(schedule):
                f = files[idx]
                image = read_image(f)
                lab_file = find_companion(paths.labels, f, ('.png',))
                if paths.labels is not None and lab_file is None:
                    raise ConfigError(f'no label image {f.stem}.png in {paths.labels}')
                labels = read_label_image(lab_file, image.shape[:2]) if lab_file else None
                kp_file = find_companion(paths.gt_keypoints, f, ('.npy', '.txt'))
                gtk = read_keypoint_file(kp_file) if kp_file else None
                yield make_transform_pair(f'{k:03d}_{f.stem}', image, rngs[k], masks,
                                          conf.transform, labels=labels, gt_keypoints=gtk)

        return gen_files(), f'{len(files)} images in {paths.images}'

    topic, n = bag_image_count(paths.bag, paths.topic)
    schedule = select_indices(n, conf.pairs)

    def gen_bag() -> Iterator[Pair]:
        for start in range(0, conf.pairs, n):
            ks = list(range(start, min(start + n, conf.pairs)))
            by_frame = {schedule[k]: k for k in ks}
            for idx, _stamp, image in iter_bag_images(paths.bag, topic, list(by_frame)):
                k = by_frame[idx]
                yield make_transform_pair(f'{k:03d}_{topic.strip("/").replace("/", "_")}_{idx}',
                                          image, rngs[k], masks, conf.transform)

    return gen_bag(), f'{n} frames of {topic} in {paths.bag}'


def main(conf: TransformsConf, paths: TransformsPaths) -> dict:
    """Run the transforms protocol and write the outputs to ``paths.out``; returns results."""
    kind = conf.image_circle
    if paths.camera is not None and kind == 'auto':
        kind = 'camera'
    masks = MaskSource(kind, camera_yaml=paths.camera, distortion_model=conf.distortion_model,
                       fov_deg=conf.fov_deg, margin_px=conf.mask_margin_px)
    pairs, source = iter_pairs(conf, paths, masks)
    tc = conf.transform
    notes = [f'transforms: rotation +-{tc.max_rotation_deg:g} deg, translation +-'
             f'{tc.max_translation_px:g} px, scale {tc.min_scale:g}-{tc.max_scale:g}, '
             f'perspective +-{tc.max_perspective:g} (corner denominator)']
    return evaluate(pairs, conf.eval, paths.out, mode='transforms', source=source,
                    n_pairs=conf.pairs, mask_description=masks.describe(), notes=notes)
