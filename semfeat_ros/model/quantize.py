"""Reduced-precision ONNX Runtime variants of the network and how far they move its outputs.

usage: python -m semfeat_ros.model.quantize [--sim-train DIR] [--photos DIR] [--sim-val DIR]
           [--real DIR] [--calib-sim N] [--calib-photos N] [--frames N] [--repeats N]
           [--threads T] [--no-fp16] [--no-bf16] [--out results.json]

The fp32 graph is the one :class:`~semfeat_ros.model.onnx_backend.OrtNetwork` exports in memory
from the safetensors weights (BatchNorm folded). From it:

* **int8** (:func:`quantize_int8`): ``onnxruntime.quantization.quantize_static`` in the QDQ
  format, weights int8 per output channel, activations uint8 (the u8s8 pairing of the x86
  integer kernels), activation ranges calibrated (min / max) on network inputs of the target
  size, the heads' final layers kept float32 (:func:`head_nodes`). The study calibrates on
  rendered frames of the training shards and real photographs (never the evaluation frames);
  :class:`BundledInt8` (the extractor's ``onnxruntime_int8`` backend) on frames of the
  bundled bag, the only frames a fresh clone has.
* **fp16** (:func:`convert_fp16`): weights and activations float16 with float32 inputs and
  outputs (``onnxruntime.transformers.float16``); ONNX Runtime's CPU provider runs the
  operators it has no float16 kernel for behind inserted casts.
* **bf16** (:class:`TorchBf16`): ONNX Runtime's CPU provider has no bfloat16 convolution, so
  this is the extractor's other bf16 path: torch eager, channels-last, ``torch.autocast``
  bfloat16 (the ``bf16`` conf key of the torch backend).

:func:`measure_speed` times the sessions interleaved frame by frame (median ms, ratio to fp32);
:func:`compare_outputs` scores a variant against fp32 on the same input: descriptor cosine at
the same cells, overlap of the top-k keypoints after NMS and segmentation label agreement.
Nothing is written but ``--out``; the graphs live in memory (the quantiser's own temporary
files are in a temporary directory, removed afterwards).

Measured on the 2-core Xeon (avx512_vnni, amx_int8, amx_bf16) with ONNX Runtime 1.32 and
stage 7's weights (``config/distill_stage7.yaml``) while a training job shared the CPU
(1-minute load average 2-4), by
``python -m semfeat_ros.model.quantize --real ../shared/data/real_fisheye_calib``
(32 rendered + 32 photo calibration frames, 24 held-out rendered frames at 640x512, the 24
real fisheye frames at 640x416, 2 threads):

===================================  =======  =======  ==========
vs fp32 onnxruntime                  int8     fp16     bf16 torch
===================================  =======  =======  ==========
forward time ratio (640x512)         1.05     1.02     0.85
descriptor cosine, real (mean)       0.998    1.000    1.000
keypoints within 1 px, real          86.0 %   99.97 %  38.9 %
segmentation agreement, real         96.5 %   99.9 %   99.1 %
===================================  =======  =======  ==========

In the optimised int8 graph every trunk convolution is a ``QLinearConv`` (NHWC, MLAS's u8s8
integer GEMM), joined by Transpose / Resize / QuantizeLinear nodes; the fp32 graph's
convolutions are ``nchwc`` AVX-512 kernels, which the integer path does not beat for this
network's narrow layers. The fp16 graph runs as fp32 convolutions behind Cast nodes (the CPU
provider has no float16 convolution on x86). bf16 autocast is faster but moves the keypoints
(bfloat16 rounds the inputs the keypoint head reads).

On the real fisheye frames (``semfeat-eval transforms --images
../shared/data/real_fisheye_calib --pairs 48 --seed 0 --methods semfeat_nn,sift_nn``, run with
``FeatureExtractor.default_conf['backend']`` set to each backend) the ``onnxruntime_int8``
backend scores keypoint recall 63.9 against 64.6 %, inlier ratio 66.5 against 67.7 % and
repeatability 63.7 against 64.9 %; ``semfeat-map bags/garage_ramp_seed0`` with
``backend: onnxruntime_int8`` in the feature config maps both floors with ATE 0.099 against
0.088 m and floor accuracy 0.938 against 0.959. It is therefore an option, not the default.
"""
from __future__ import annotations

import argparse
from collections.abc import Iterable, Sequence
import copy
import json
from pathlib import Path
import sys
import tempfile
import time
from typing import Any

import cv2
import numpy as np
import torch
from tqdm import tqdm

from semfeat_ros.model.errors import ModelConfigError
from semfeat_ros.model.onnx_backend import OUTPUTS, open_session
from semfeat_ros.model.semfeatnet import normalize_image

IMAGE_SUFFIXES = ('.jpg', '.jpeg', '.png', '.ppm', '.pgm')


class QuantizationError(ModelConfigError):
    """A reduced-precision graph cannot be built (no calibration frames, quantiser failure)."""


def fit_frame(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """An RGB / grey uint8 ``image`` centre-cropped to the aspect ratio of ``size`` = (w, h) px
    and resized to it (area interpolation when shrinking); (h, w, 3) uint8 RGB."""
    w, h = size
    img = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
    ih, iw = img.shape[:2]
    if iw * h > ih * w:  # too wide: crop the sides
        cw = max(1, round(ih * w / h))
        x0 = (iw - cw) // 2
        img = img[:, x0:x0 + cw]
    else:
        ch = max(1, round(iw * h / w))
        y0 = (ih - ch) // 2
        img = img[y0:y0 + ch]
    ih, iw = img.shape[:2]
    interp = cv2.INTER_AREA if iw > w else cv2.INTER_LINEAR
    return np.ascontiguousarray(cv2.resize(img, (w, h), interpolation=interp))


def network_array(image: np.ndarray) -> np.ndarray:
    """(1, 3, H, W) float32 network input of an (H, W, 3) uint8 RGB image (normalised as
    :meth:`FeatureExtractor.network_input` does)."""
    x = normalize_image(torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None])
    return np.ascontiguousarray(x.numpy(), dtype=np.float32)


def shard_frames(paths: Sequence[Path], n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``n`` RGB frames (uint8, as rendered) drawn evenly over the ``rgb`` arrays of simulator
    shards (``semfeat_ros.sim.dataset``), ``rng`` picking the frame of each shard."""
    if n <= 0 or not paths:
        return []
    out: list[np.ndarray] = []
    per = int(np.ceil(n / len(paths)))
    for p in paths:
        with np.load(p, allow_pickle=False) as d:
            rgb = d['rgb']
        idx = rng.choice(len(rgb), size=min(per, len(rgb)), replace=False)
        out += [rgb[i] for i in sorted(idx)]
        if len(out) >= n:
            break
    return out[:n]


def folder_images(folder: Path, n: int, rng: np.random.Generator | None = None
                  ) -> list[np.ndarray]:
    """Up to ``n`` images (RGB uint8; grey as 3 channels) of ``folder``: a random draw when
    ``rng`` is given, else the first ``n`` in name order."""
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if rng is not None and len(files) > n:
        files = [files[i] for i in sorted(rng.choice(len(files), size=n, replace=False))]
    out = []
    for p in files[:n]:
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is not None:
            out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return out


def bundled_bag_frames(n: int) -> list[np.ndarray]:
    """``n`` camera frames (RGB uint8) spread over the bundled bag ``bags/garage_ramp_seed0``.

    Raises:
        QuantizationError: the bag is missing or has no frames.
    """
    from msg_adapters import to_rgb_or_mono
    from semfeat_ros.offline.bag import BagSource
    from semfeat_ros.offline.errors import OfflineError
    from semfeat_ros.paths import share_dir

    bag = share_dir() / 'bags' / 'garage_ramp_seed0'
    try:
        with BagSource(bag) as source:
            topic = source.image_topic(None, '/camera/front/image_raw/compressed')
            msgs = [m.msg for m in source.messages([topic])]
    except (OfflineError, OSError) as exc:
        raise QuantizationError(f'int8 calibration: cannot read the bundled bag {bag}: '
                                f'{exc}') from exc
    if not msgs:
        raise QuantizationError(f'int8 calibration: no camera frames in {bag}')
    idx = np.unique(np.linspace(0, len(msgs) - 1, max(1, n)).round().astype(int))
    frames = []
    for i in idx:
        img = to_rgb_or_mono(msgs[i])
        frames.append(img if img.ndim == 3 else np.repeat(img[:, :, None], 3, axis=2))
    return frames


class _Reader:
    """``onnxruntime.quantization.CalibrationDataReader`` over a list of network inputs."""

    def __init__(self, inputs: Sequence[np.ndarray]) -> None:
        self._it = iter(list(inputs))

    def get_next(self) -> dict[str, np.ndarray] | None:
        x = next(self._it, None)
        return None if x is None else {'image': x}


def head_nodes(model: Any) -> list[str]:
    """Names of the nodes between the graph's outputs and the last convolution of each head
    (those convolutions included): the output heads' final layers."""
    producer = {o: n for n in model.graph.node for o in n.output}
    names: list[str] = []
    stack = [o.name for o in model.graph.output]
    seen: set[str] = set()
    while stack:
        node = producer.get(stack.pop())
        if node is None or node.name in seen:
            continue
        seen.add(node.name)
        names.append(node.name)
        if node.op_type != 'Conv':
            stack += [i for i in node.input if i]
    return names


def quantize_int8(graph: bytes, calibration: Iterable[np.ndarray],
                  per_channel: bool = True, float_heads: bool = True) -> bytes:
    """Static int8 QDQ graph of the fp32 ``graph``.

    Args:
        graph: serialized fp32 ONNX graph with input ``image`` (1, 3, H, W).
        calibration: network inputs (1, 3, H, W) float32 of that size; their activation
            minima / maxima set the activation scales.
        per_channel: one weight scale per output channel (else per tensor).
        float_heads: keep the heads' final layers (:func:`head_nodes`: the last convolution of
            each head and what follows it) in float32, so the heatmap, descriptors and
            segmentation logits are not rounded to 256 levels.
    Returns:
        The serialized QDQ graph (weights int8, activations uint8).
    Raises:
        QuantizationError: no calibration input, or the quantiser failed.
    """
    import onnx
    from onnxruntime.quantization import (
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    inputs = list(calibration)
    if not inputs:
        raise QuantizationError('int8 calibration: no calibration frames')
    with tempfile.TemporaryDirectory(prefix='semfeat_int8_') as tmp:
        src, pre, dst = (Path(tmp) / n for n in ('fp32.onnx', 'pre.onnx', 'int8.onnx'))
        src.write_bytes(graph)
        try:
            quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
            exclude = head_nodes(onnx.load(str(pre))) if float_heads else None
            quantize_static(str(pre), str(dst), _Reader(inputs),
                            quant_format=QuantFormat.QDQ, per_channel=per_channel,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                            calibrate_method=CalibrationMethod.MinMax,
                            nodes_to_exclude=exclude)
        except (RuntimeError, ValueError, onnx.checker.ValidationError) as exc:
            raise QuantizationError(f'int8 quantisation failed: {exc}') from exc
        return dst.read_bytes()


def convert_fp16(graph: bytes) -> bytes:
    """float16 weights and activations of the fp32 ``graph``, float32 inputs and outputs."""
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    model = onnx.load_from_string(graph)
    return convert_float_to_float16(model, keep_io_types=True).SerializeToString()


class BundledInt8:
    """Graph transform of the ``onnxruntime_int8`` backend: :func:`quantize_int8` calibrated
    on ``frames`` frames of the bundled bag fitted to each input size (read once)."""

    def __init__(self, frames: int = 16) -> None:
        if frames < 1:
            raise ModelConfigError(f'int8_calibration_frames must be >= 1, got {frames}')
        self.frames = int(frames)
        self._images: list[np.ndarray] | None = None

    def __call__(self, graph: bytes, height: int, width: int) -> bytes:
        if self._images is None:
            self._images = bundled_bag_frames(self.frames)
        return quantize_int8(graph, [network_array(fit_frame(im, (width, height)))
                                     for im in self._images])


class TorchBf16:
    """The network in torch under bfloat16 autocast (channels-last), with the ``run`` call of
    an ONNX Runtime session so :func:`measure_speed` and :func:`compare_outputs` take it."""

    def __init__(self, model: torch.nn.Module) -> None:
        self.model = copy.deepcopy(model).eval().to(memory_format=torch.channels_last)

    def run(self, names: Sequence[str], feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        x = torch.from_numpy(feeds['image']).contiguous(memory_format=torch.channels_last)
        with torch.inference_mode(), torch.autocast('cpu', dtype=torch.bfloat16):
            pred = self.model(x)
        return [pred[n].float().contiguous().numpy() for n in names]


def _run(sess: Any, x: np.ndarray) -> dict[str, np.ndarray]:
    return dict(zip(OUTPUTS, sess.run(list(OUTPUTS), {'image': x})))


def measure_speed(sessions: dict[str, Any], inputs: Sequence[np.ndarray], repeats: int = 1,
                  progress: bool = False) -> dict[str, Any]:
    """Forward time (ms) of every session on the same inputs, interleaved: for every input
    each session runs in turn (order rotated per input so none always runs first), ``repeats``
    passes over ``inputs`` after one untimed warm-up run each.

    Returns ``{'median_ms': {name: ms}, 'ratio_to_fp32': {name: median of the per-input
    time / fp32 time}, 'n': timed runs per session}``; ratios need a session named 'fp32'.
    """
    names = list(sessions)
    for n in names:
        _run(sessions[n], inputs[0])
    times: dict[str, list[float]] = {n: [] for n in names}
    total = repeats * len(inputs)
    with tqdm(total=total, desc='speed', unit='frame', disable=not progress) as bar:
        for k in range(total):
            x = inputs[k % len(inputs)]
            order = names[k % len(names):] + names[:k % len(names)]
            for n in order:
                t0 = time.perf_counter()
                _run(sessions[n], x)
                times[n].append((time.perf_counter() - t0) * 1e3)
            bar.update(1)
    out: dict[str, Any] = {'median_ms': {n: float(np.median(t)) for n, t in times.items()},
                           'n': total}
    if 'fp32' in times:
        ref = np.asarray(times['fp32'])
        out['ratio_to_fp32'] = {n: float(np.median(np.asarray(t) / ref))
                                for n, t in times.items()}
    return out


def _topk_keypoints(heat: np.ndarray, k: int, threshold: float, nms_radius: int = 3,
                    border: int = 4) -> np.ndarray:
    """(<= k, 2) int (u, v) px of the ``k`` strongest NMS maxima above ``threshold`` of an
    (H, W) heatmap (the extractor's detection without its masks)."""
    from semfeat_ros.model.extractor import detect_keypoints

    kpts, _ = detect_keypoints(torch.from_numpy(np.ascontiguousarray(heat, np.float32)), None,
                               nms_radius, threshold, border)
    return kpts[:k].numpy().astype(np.int64)


def compare_outputs(ref: dict[str, np.ndarray], out: dict[str, np.ndarray], k: int = 1000,
                    threshold: float = 0.15, radius_px: float = 1.0) -> dict[str, float]:
    """How far ``out`` moved from the fp32 outputs ``ref`` of the same input.

    Returns:
        ``desc_cos_mean`` / ``desc_cos_p5``: cosine of the descriptors (unit-normalised) at
        every stride-8 cell; ``topk_exact`` / ``topk_within``: share of ref's top-``k`` NMS
        keypoints (NMS maxima above ``threshold``, the extractor's detection) found by
        ``out``'s at the same pixel / within ``radius_px`` px; ``keypoints_ref`` /
        ``keypoints_out``: their counts;
        ``seg_agreement``: share of segmentation cells with the same arg-max class;
        ``heat_abs_err``: mean absolute heatmap difference (heatmap in [0, 1]).
    """
    da, db = ref['descriptors'][0], out['descriptors'][0]  # (D, h, w)
    da = da / np.maximum(np.linalg.norm(da, axis=0, keepdims=True), 1e-12)
    db = db / np.maximum(np.linalg.norm(db, axis=0, keepdims=True), 1e-12)
    cos = (da * db).sum(axis=0).ravel()
    ka = _topk_keypoints(ref['heatmap'][0], k, threshold)
    kb = _topk_keypoints(out['heatmap'][0], k, threshold)
    if len(ka) and len(kb):
        d2 = ((ka[:, None, :] - kb[None, :, :]) ** 2).sum(-1)
        exact = float((d2.min(axis=1) == 0).mean())
        within = float((d2.min(axis=1) <= radius_px ** 2).mean())
    else:
        exact = within = float(len(ka) == len(kb))
    seg = float((ref['segmentation_logits'][0].argmax(0)
                 == out['segmentation_logits'][0].argmax(0)).mean())
    return {'desc_cos_mean': float(cos.mean()), 'desc_cos_p5': float(np.percentile(cos, 5)),
            'topk_exact': exact, 'topk_within': within, 'keypoints_ref': float(len(ka)),
            'keypoints_out': float(len(kb)), 'seg_agreement': seg,
            'heat_abs_err': float(np.abs(ref['heatmap'] - out['heatmap']).mean())}


def _build(fp32: bytes, size: tuple[int, int], calib: Sequence[np.ndarray], fp16: bool,
           threads: int, bf16_model: torch.nn.Module | None = None) -> dict[str, Any]:
    """Sessions fp32 / int8 (/ fp16) at network size ``size`` = (w, h) px, and the torch
    bf16 runner of ``bf16_model`` when given."""
    graphs = {'fp32': fp32,
              'int8': quantize_int8(fp32, [network_array(fit_frame(im, size)) for im in calib])}
    if fp16:
        graphs['fp16'] = convert_fp16(fp32)
    sessions: dict[str, Any] = {n: open_session(g, threads) for n, g in graphs.items()}
    if bf16_model is not None:
        sessions['bf16_torch'] = TorchBf16(bf16_model)
    return sessions


def _accuracy(sessions: dict[str, Any], images: Sequence[np.ndarray], size: tuple[int, int],
              k: int, threshold: float, desc: str, progress: bool
              ) -> dict[str, dict[str, float]]:
    """Means over ``images`` (fitted to ``size``) of :func:`compare_outputs` per variant."""
    acc: dict[str, list[dict[str, float]]] = {n: [] for n in sessions if n != 'fp32'}
    for im in tqdm(images, desc=desc, unit='frame', disable=not progress):
        x = network_array(fit_frame(im, size))
        ref = _run(sessions['fp32'], x)
        for n in acc:
            acc[n].append(compare_outputs(ref, _run(sessions[n], x), k, threshold))
    return {n: {m: float(np.mean([r[m] for r in rows])) for m in rows[0]}
            for n, rows in acc.items() if rows}


def study(sim_train: Path, photos: Path, sim_val: Path, real: Path | None, calib_sim: int,
          calib_photos: int, frames: int, repeats: int, threads: int, fp16: bool, bf16: bool,
          seed: int, progress: bool) -> dict[str, Any]:
    """Build the variants, time them at 640x512 and compare them with fp32 on held-out
    rendered frames (``sim_val`` shards, 640x512) and on the real frames in ``real`` (at the
    network size the extractor gives them). Returns the numbers as a JSON-able dict."""
    import onnxruntime as ort

    from semfeat_ros.model.extractor import FeatureExtractor

    rng = np.random.default_rng(seed)
    fx = FeatureExtractor(None, {'backend': 'onnxruntime', 'num_threads': threads})
    ortnet = fx._ort
    if ortnet is None:
        raise QuantizationError('the onnxruntime backend is not available')
    bf16_model = fx.model if bf16 else None  # BatchNorm folded, as the graph
    calib = (shard_frames(sorted(Path(sim_train).glob('*.npz')), calib_sim, rng)
             + folder_images(Path(photos), calib_photos, rng))
    if not calib:
        raise QuantizationError(f'no calibration frames in {sim_train} or {photos}')
    held = shard_frames(sorted(Path(sim_val).glob('*.npz')), frames, rng)
    if not held:
        raise QuantizationError(f'no held-out shards in {sim_val}')
    size = fx.network_size(held[0].shape[1], held[0].shape[0])
    res: dict[str, Any] = {
        'onnxruntime': ort.__version__, 'threads': threads, 'seed': seed,
        'calibration': {'rendered': min(calib_sim, len(calib)),
                        'photos': len(calib) - min(calib_sim, len(calib))},
        'size': list(size)}
    t0 = time.perf_counter()
    sessions = _build(ortnet.export(size[1], size[0]), size, calib, fp16, threads, bf16_model)
    res['build_s'] = time.perf_counter() - t0
    inputs = [network_array(fit_frame(im, size)) for im in held]
    res['speed'] = measure_speed(sessions, inputs, repeats, progress)
    k, thr = int(fx.conf['max_keypoints']), float(fx.conf['detection_threshold'])
    res['accuracy'] = {'rendered': _accuracy(sessions, held, size, k, thr,
                                             'accuracy rendered', progress)}
    res['accuracy']['rendered_frames'] = len(held)
    if real is not None:
        real_imgs = folder_images(Path(real), 10 ** 6)
        if real_imgs:
            rsize = fx.network_size(real_imgs[0].shape[1], real_imgs[0].shape[0])
            rs = _build(ortnet.export(rsize[1], rsize[0]), rsize, calib, fp16, threads,
                        bf16_model)
            res['accuracy']['real'] = _accuracy(rs, real_imgs, rsize, k, thr, 'accuracy real',
                                                progress)
            res['accuracy']['real_frames'] = len(real_imgs)
            res['accuracy']['real_size'] = list(rsize)
    return res


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='python -m semfeat_ros.model.quantize',
        description='int8 (static QDQ) and fp16 ONNX Runtime variants of the network: speed '
        'against fp32 (interleaved) and output agreement with fp32.')
    p.add_argument('--sim-train', type=Path, default=Path('out/sim_train'),
                   help='training shards: rendered calibration frames (default out/sim_train)')
    p.add_argument('--photos', type=Path, default=Path('out/photos/images'),
                   help='real photographs for calibration (default out/photos/images)')
    p.add_argument('--sim-val', type=Path, default=Path('out/sim_val'),
                   help='held-out shards: speed and accuracy frames (default out/sim_val)')
    p.add_argument('--real', type=Path, default=None,
                   help='folder of real frames for the accuracy only (never calibration)')
    p.add_argument('--calib-sim', type=int, default=32, help='rendered calibration frames')
    p.add_argument('--calib-photos', type=int, default=32, help='photo calibration frames')
    p.add_argument('--frames', type=int, default=24, help='held-out rendered frames')
    p.add_argument('--repeats', type=int, default=2, help='timed passes over the frames')
    p.add_argument('--threads', type=int, default=2, help='ONNX Runtime intra-op threads')
    p.add_argument('--no-fp16', action='store_true', help='skip the fp16 variant')
    p.add_argument('--no-bf16', action='store_true', help='skip the torch bf16 variant')
    p.add_argument('--seed', type=int, default=0, help='frame draw seed')
    p.add_argument('--out', type=Path, default=None, help='write the results as JSON here')
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Command line of the study; prints the results as JSON; returns the exit status."""
    a = build_parser().parse_args(argv)
    for name, v, low in (('--calib-sim', a.calib_sim, 0), ('--calib-photos', a.calib_photos, 0),
                         ('--frames', a.frames, 1), ('--repeats', a.repeats, 1),
                         ('--threads', a.threads, 1)):
        if v < low:
            print(f'quantize: error: {name} must be >= {low}, got {v}', file=sys.stderr)
            return 2
    try:
        res = study(a.sim_train, a.photos, a.sim_val, a.real, a.calib_sim, a.calib_photos,
                    a.frames, a.repeats, a.threads, not a.no_fp16, not a.no_bf16, a.seed,
                    not a.quiet)
    except (QuantizationError, OSError) as exc:
        print(f'quantize: error: {exc}', file=sys.stderr)
        return 1
    text = json.dumps(res, indent=1)
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text + '\n')
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
