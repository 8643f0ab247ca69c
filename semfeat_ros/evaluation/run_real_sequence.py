"""Mode ``sequence --images``: an ordered folder of real camera frames, without ground truth.

Frames are the folder's images whose name matches ``--glob`` (JPG/PNG/PPM/PGM; other files such as
``depth_*.bin`` are never listed) in natural order (``frame_2`` before ``frame_10``); pairs are
``(i, i + stride)`` (:func:`.run_sequence.pair_indices`). With no ground truth, each method is
scored by its proposed matches per pair, the matches geometric verification accepts (verified)
and their ratio, plus extraction / matching time (docs/METRICS.md). Verification depends on the
intrinsics given:

* pinhole intrinsics (``--pinhole``, ``--camera-xml``, or a plumb_bob ``--camera`` YAML):
  essential-matrix RANSAC (OpenCV) on the calibrated bearings, threshold ``ransac_px / fx``;
* a fisheye ``--camera`` YAML: the product matcher's bearing verification (valid over the whole
  field of view), threshold ``ransac_px / fx`` rad;
* none: a fundamental matrix, OpenCV USAC_MAGSAC at ``ransac_px`` px.

``semfeat_seq`` verifies itself with the product's sequential matcher at the same threshold
(``ransac_px / fx`` rad on the camera's bearings, or ``ransac_px / width`` on pinhole
pseudo-bearings when no intrinsics are given).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from semfeat_ros.evaluation.datasets import (
    PinholeIntrinsics,
    list_images,
    read_image,
    read_visp_camera_xml,
)
from semfeat_ros.evaluation.errors import ConfigError, DatasetError
from semfeat_ros.evaluation.groundtruth import Pair
from semfeat_ros.evaluation.masks import camera_for_size
from semfeat_ros.evaluation.pipeline import (
    BearingVerifier,
    default_bearing_verifier,
    evaluate,
    verify_bearings_opencv,
)
from semfeat_ros.evaluation.run_sequence import SequenceConf, SequencePaths, pair_indices
from semfeat_ros.evaluation.transforms import erode_mask


def sequence_frames(folder: str | Path, pattern: str = '*') -> list[Path]:
    """The frames of a real sequence: images of ``folder`` matching ``pattern``, natural order.

    Raises:
        DatasetError: the folder does not exist or holds fewer than 2 matching images.
    """
    frames = list_images(folder, pattern=pattern, natural=True)
    if len(frames) < 2:
        raise DatasetError(f'image sequence {folder}: {len(frames)} image '
                           f'({frames[0].name}); a sequence needs at least 2')
    return frames


def sequence_camera(paths: SequencePaths, fov_deg: float | None, width: int,
                    height: int) -> tuple[object | None, str]:
    """The camera model of the frames (``width x height`` px) from at most one of
    ``paths.camera`` (calibration YAML, scaled to the frame size at the same aspect ratio),
    ``paths.camera_xml`` (ViSP XML) and ``paths.pinhole`` (fx, fy, cx, cy px), and its
    description; ``(None, ...)`` when none is given."""
    given = [name for name, v in (('--camera', paths.camera), ('--camera-xml', paths.camera_xml),
                                  ('--pinhole', paths.pinhole)) if v is not None]
    if len(given) > 1:
        raise ConfigError(f'sequence --images: give at most one of --camera, --camera-xml and '
                          f'--pinhole, got {" and ".join(given)}')
    if paths.camera is not None:
        from semfeat_ros.camera import load_camera_yaml

        camera, _ = load_camera_yaml(paths.camera, fov_deg=fov_deg)
        camera = camera_for_size(camera, width, height, f'camera {paths.camera}')
        return camera, (f'calibration YAML {paths.camera} ({camera.distortion_model}, '
                        f'fx {camera.fx:.2f} px)')
    if paths.camera_xml is not None:
        intr = read_visp_camera_xml(paths.camera_xml)
    elif paths.pinhole is not None:
        if len(paths.pinhole) != 4:
            raise ConfigError(f'--pinhole: expected fx,fy,cx,cy (px), got {paths.pinhole}')
        intr = PinholeIntrinsics(*(float(v) for v in paths.pinhole), source='--pinhole')
    else:
        return None, 'no intrinsics given (uncalibrated verification)'
    text = (f'pinhole fx {intr.fx:.2f}, fy {intr.fy:.2f}, cx {intr.cx:.2f}, cy {intr.cy:.2f} px'
            + (f', k1 {intr.k1:g}' if intr.k1 else '') + f' from {intr.source}')
    return intr.camera(width, height), text


def _verifier(camera: object | None) -> tuple[BearingVerifier | None, str]:
    from semfeat_ros.camera import PinholeCamera

    if camera is None:
        return None, ''
    if isinstance(camera, PinholeCamera):
        return verify_bearings_opencv, ('essential-matrix RANSAC on calibrated bearings '
                                        '(OpenCV, threshold ransac_px / fx)')
    return default_bearing_verifier()


def main(conf: SequenceConf, paths: SequencePaths) -> dict:
    """Evaluate every method on the pairs of a real image sequence (``paths.images``); outputs
    go to ``paths.out``."""
    if paths.images is None:
        raise ConfigError('sequence: the real-sequence mode needs --images DIR')
    frames = sequence_frames(paths.images, paths.pattern)
    pairs = pair_indices(len(frames), conf.stride, conf.max_pairs)
    if not pairs:
        raise DatasetError(f'image sequence {paths.images}: {len(frames)} frames, too few for '
                           f'stride {conf.stride}')
    first = read_image(frames[0])
    height, width = first.shape[:2]
    camera, camera_note = sequence_camera(paths, conf.fov_deg, width, height)
    valid = camera.valid_mask() if camera is not None else np.ones((height, width), bool)
    mask = erode_mask(valid, conf.mask_margin_px)
    verifier, verifier_name = _verifier(camera)

    def gen() -> Iterator[Pair]:
        cache: dict[int, np.ndarray] = {0: first}

        def load(k: int) -> np.ndarray:
            if k not in cache:
                img = read_image(frames[k])
                if img.shape[:2] != (height, width):
                    raise DatasetError(
                        f'{frames[k]}: {img.shape[1]}x{img.shape[0]} px, but the first frame '
                        f'{frames[0].name} is {width}x{height} px')
                cache[k] = img
            return cache[k]

        for a, b in pairs:
            image_a, image_b = load(a), load(b)
            for k in [k for k in cache if k != b]:
                del cache[k]
            yield Pair(f'{frames[a].stem}-{frames[b].stem}', image_a, image_b, mask, mask, None,
                       camera=camera, meta={'frames': [frames[a].name, frames[b].name]})

    notes = [
        f'frames: {len(frames)} images matching {paths.pattern!r} in natural order '
        f'({frames[0].name} .. {frames[-1].name}); pairs (i, i + {conf.stride})',
        f'camera: {camera_note}',
        'no ground truth: verified matches are those geometric verification accepts, an upper '
        'bound on the correct ones; Inlier Ratio = verified / proposed',
        'semfeat_seq verifies itself (the sequential matcher) at the same threshold '
        + ('(ransac_px / fx rad on the calibrated bearings)' if camera is not None else
           '(ransac_px / width rad on pinhole pseudo-bearings, f = image width)'),
    ]
    region = 'camera image circle' if camera is not None and not valid.all() else 'whole frame'
    return evaluate(gen(), replace(conf.eval, seq_threshold_from_ransac_px=True), paths.out,
                    mode='sequence', source=f'{len(frames)} frames in {paths.images}',
                    n_pairs=len(pairs),
                    mask_description=f'{region}, margin {conf.mask_margin_px} px', notes=notes,
                    bearing_verifier=verifier, bearing_verifier_name=verifier_name)
