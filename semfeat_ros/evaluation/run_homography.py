"""Mode ``homography``: planar sequences in the Oxford (``img1..imgN`` + ``H1to{k}p``) or
HPatches (``1..N`` + ``H_1_{k}``) layout; pairs are (image 1, image k) with the given H."""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from semfeat_ros.evaluation.datasets import (
    find_companion,
    find_homography_sequences,
    read_image,
    read_keypoint_file,
)
from semfeat_ros.evaluation.errors import ConfigError
from semfeat_ros.evaluation.groundtruth import HomographyGroundTruth, Pair
from semfeat_ros.evaluation.masks import MaskSource
from semfeat_ros.evaluation.pipeline import EvalConf, evaluate


@dataclass(frozen=True)
class HomographyPaths:
    """``dataset``: one sequence folder or a folder of sequences; ``gt_keypoints``: optional
    folder of ``<sequence>.npy`` / ``.txt`` GT keypoints of each reference image (px)."""

    dataset: Path
    out: Path
    gt_keypoints: Path | None = None
    camera: Path | None = None


@dataclass(frozen=True)
class HomographyConf:
    eval: EvalConf = field(default_factory=EvalConf)
    image_circle: str = 'none'
    mask_margin_px: int = 0
    max_pairs: int | None = None
    distortion_model: str | None = None
    fov_deg: float | None = None

    def __post_init__(self) -> None:
        if self.max_pairs is not None and self.max_pairs < 1:
            raise ConfigError(f'--max-pairs must be >= 1, got {self.max_pairs}')


def iter_pairs(conf: HomographyConf, paths: HomographyPaths,
               masks: MaskSource) -> tuple[Iterator[Pair], int, str]:
    """All (1, k) pairs of all sequences (validated up front: every H file must exist)."""
    seqs = find_homography_sequences(paths.dataset)
    jobs = [(s, img, H) for s in seqs for img, H in s.targets]
    if conf.max_pairs is not None:
        jobs = jobs[: conf.max_pairs]

    def gen() -> Iterator[Pair]:
        cache: dict[Path, tuple] = {}
        for seq, target, H in jobs:
            if seq.reference not in cache:
                cache.clear()
                img = read_image(seq.reference)
                gtk_file = find_companion(paths.gt_keypoints, Path(seq.name), ('.npy', '.txt'))
                cache[seq.reference] = (img, masks.final(masks(img)),
                                        read_keypoint_file(gtk_file) if gtk_file else None)
            image_a, mask_a, gtk = cache[seq.reference]
            image_b = read_image(target)
            mask_b = masks.final(masks(image_b))
            yield Pair(f'{seq.name}_1-{target.stem}', image_a, image_b, mask_a, mask_b,
                       HomographyGroundTruth(H, mask_a, mask_b), H=H, gt_keypoints_a=gtk)

    return gen(), len(jobs), f'{len(seqs)} sequence(s) in {paths.dataset}'


def main(conf: HomographyConf, paths: HomographyPaths) -> dict:
    """Evaluate every method on the sequences and write the outputs to ``paths.out``."""
    kind = 'camera' if paths.camera is not None and conf.image_circle == 'none' else \
        conf.image_circle
    masks = MaskSource(kind, camera_yaml=paths.camera, distortion_model=conf.distortion_model,
                       fov_deg=conf.fov_deg, margin_px=conf.mask_margin_px)
    pairs, n, source = iter_pairs(conf, paths, masks)
    return evaluate(pairs, conf.eval, paths.out, mode='homography', source=source, n_pairs=n,
                    mask_description=masks.describe())
