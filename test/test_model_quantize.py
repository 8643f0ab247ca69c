"""int8 / fp16 ONNX Runtime variants of the network (semfeat_ros.model.quantize) and the
extractor's ``onnxruntime_int8`` backend, on an untrained network at small sizes."""
from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
import torch

from semfeat_ros.model import quantize as q
from semfeat_ros.model.errors import ModelConfigError
from semfeat_ros.model.extractor import FeatureExtractor
from semfeat_ros.model.onnx_backend import OrtNetwork, open_session
from semfeat_ros.model.semfeatnet import SemFeatNet, fuse_batchnorm

pytest.importorskip('onnxruntime')


@pytest.fixture(scope='module')
def net() -> SemFeatNet:
    torch.manual_seed(0)
    return fuse_batchnorm(SemFeatNet().eval())


@pytest.fixture(scope='module')
def fp32_graph(net: SemFeatNet) -> bytes:
    return OrtNetwork(net, 1).export(64, 96)


def _images(n: int, size: tuple[int, int], seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    w, h = size
    out = []
    for _ in range(n):  # smooth random images: blurred noise with a gradient
        img = rng.integers(0, 256, (h // 4, w // 4, 3), dtype=np.uint8)
        big = np.kron(img, np.ones((4, 4, 1), np.uint8))
        out.append(np.ascontiguousarray(big))
    return out


def test_fit_frame_crops_to_the_aspect_then_resizes() -> None:
    wide = np.zeros((100, 400, 3), np.uint8)
    wide[:, :100] = 255  # left quarter white: cropped away for a 2:1 target
    out = q.fit_frame(wide, (64, 32))
    assert out.shape == (32, 64, 3) and out.dtype == np.uint8
    assert out.max() == 0
    tall = np.zeros((400, 100), np.uint8)
    tall[175:225] = 200  # the centre band survives a centre crop
    out = q.fit_frame(tall, (50, 50))
    assert out.shape == (50, 50, 3) and out[25, 25, 0] == 200 and out[0, 0, 0] == 0


def test_network_array_matches_the_extractor_input(net: SemFeatNet) -> None:
    fx = FeatureExtractor(net, {'resize_max': 96, 'backend': 'torch',
                                'channels_last': False, 'drop_classes': []})
    img = _images(1, (96, 64))[0]
    x, size = fx.network_input(img)
    assert size == (96, 64)
    np.testing.assert_allclose(q.network_array(img), x.numpy(), atol=1e-6)


def test_int8_graph_is_per_channel_qdq_and_close_to_fp32(fp32_graph: bytes) -> None:
    import onnx

    calib = [q.network_array(im) for im in _images(4, (96, 64))]
    int8 = q.quantize_int8(fp32_graph, calib)
    model = onnx.load_from_string(int8)
    ops = [n.op_type for n in model.graph.node]
    assert ops.count('QuantizeLinear') > 10 and ops.count('DequantizeLinear') > 10
    inits = {t.name: t for t in model.graph.initializer}
    per_channel = [n for n in model.graph.node if n.op_type == 'DequantizeLinear'
                   and n.input[0] in inits and inits[n.input[0]].data_type == onnx.TensorProto.INT8
                   and len(inits[n.input[1]].dims) == 1 and inits[n.input[1]].dims[0] > 1]
    assert per_channel, 'weights are not quantised per output channel'
    s32, s8 = open_session(fp32_graph, 1), open_session(int8, 1)
    x = q.network_array(_images(1, (96, 64), seed=5)[0])
    ref = q._run(s32, x)
    out = q._run(s8, x)
    assert {k: v.shape for k, v in out.items()} == {k: v.shape for k, v in ref.items()}
    acc = q.compare_outputs(ref, out, k=200, threshold=0.0)
    assert acc['desc_cos_mean'] > 0.95
    assert acc['seg_agreement'] > 0.8
    assert acc['desc_cos_mean'] < 1.0 - 1e-6  # int8 really changed the arithmetic


def test_int8_without_calibration_frames_is_an_error(fp32_graph: bytes) -> None:
    with pytest.raises(q.QuantizationError, match='no calibration frames'):
        q.quantize_int8(fp32_graph, [])


def test_fp16_graph_runs_and_stays_close(fp32_graph: bytes) -> None:
    import onnx

    fp16 = q.convert_fp16(fp32_graph)
    model = onnx.load_from_string(fp16)
    assert model.graph.input[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert any(t.data_type == onnx.TensorProto.FLOAT16 for t in model.graph.initializer)
    x = q.network_array(_images(1, (96, 64), seed=3)[0])
    acc = q.compare_outputs(q._run(open_session(fp32_graph, 1), x),
                            q._run(open_session(fp16, 1), x), k=200, threshold=0.0)
    assert acc['desc_cos_mean'] > 0.999 and acc['seg_agreement'] > 0.97


def _outputs(rng: np.random.Generator) -> dict[str, np.ndarray]:
    heat = np.zeros((1, 64, 96), np.float32)
    heat[0, 10:50:8, 10:80:9] = rng.uniform(0.3, 1.0, (5, 8))
    return {'heatmap': heat,
            'descriptors': rng.normal(size=(1, 16, 8, 12)).astype(np.float32),
            'segmentation_logits': rng.normal(size=(1, 5, 16, 24)).astype(np.float32)}


def test_compare_outputs_scores_identity_and_changes() -> None:
    rng = np.random.default_rng(0)
    ref = _outputs(rng)
    same = q.compare_outputs(ref, ref, k=100)
    assert same['desc_cos_mean'] == pytest.approx(1.0)
    assert same['desc_cos_p5'] == pytest.approx(1.0)
    assert same['topk_exact'] == 1.0 and same['seg_agreement'] == 1.0
    assert same['keypoints_ref'] == 40.0 and same['heat_abs_err'] == 0.0
    moved = {'heatmap': np.roll(ref['heatmap'], 1, axis=2),  # every peak 1 px to the right
             'descriptors': -ref['descriptors'],
             'segmentation_logits': ref['segmentation_logits'][:, ::-1].copy()}
    res = q.compare_outputs(ref, moved, k=100)
    assert res['desc_cos_mean'] == pytest.approx(-1.0)
    assert res['topk_exact'] == 0.0 and res['topk_within'] == 1.0
    assert res['seg_agreement'] < 0.5
    below = {**ref, 'heatmap': ref['heatmap'] * 0.1}  # peaks fall under the threshold
    assert q.compare_outputs(ref, below, k=100, threshold=0.15)['keypoints_out'] == 0.0


class _Fake:
    def __init__(self, name: str, delay_s: float, log: list[str]) -> None:
        self.name, self.delay_s, self.log = name, delay_s, log

    def run(self, names: Any, feeds: Any) -> list[np.ndarray]:
        self.log.append(self.name)
        time.sleep(self.delay_s)
        return [np.zeros(1)] * len(names)


def test_measure_speed_interleaves_and_rotates_the_order() -> None:
    log: list[str] = []
    sessions = {'fp32': _Fake('fp32', 0.02, log), 'int8': _Fake('int8', 0.005, log)}
    res = q.measure_speed(sessions, [np.zeros(1)] * 3, repeats=2)
    assert res['n'] == 6
    timed = log[2:]  # after one warm-up run each
    assert len(timed) == 12
    firsts = [timed[i] for i in range(0, 12, 2)]
    assert firsts == ['fp32', 'int8'] * 3  # each input starts with the other session
    assert res['median_ms']['fp32'] > res['median_ms']['int8']
    assert res['ratio_to_fp32']['fp32'] == 1.0 and res['ratio_to_fp32']['int8'] < 1.0


def test_extractor_int8_backend(net: SemFeatNet, monkeypatch: pytest.MonkeyPatch) -> None:
    frames = _images(3, (160, 128), seed=9)
    calls: list[int] = []

    def fake_bag(n: int) -> list[np.ndarray]:
        calls.append(n)
        return frames[:n]

    monkeypatch.setattr(q, 'bundled_bag_frames', fake_bag)
    conf = {'resize_max': 96, 'backend': 'onnxruntime_int8', 'int8_calibration_frames': 2,
            'num_threads': 1, 'detection_threshold': 0.0, 'max_keypoints': 50,
            'drop_classes': []}
    fx = FeatureExtractor(net, conf)
    assert fx.backend == 'onnxruntime_int8'
    ref = FeatureExtractor(net, {**conf, 'backend': 'onnxruntime'})
    img = _images(1, (160, 128), seed=11)[0]
    f8, f32 = fx.extract(img), ref.extract(img)
    assert calls == [2]  # the bag is read once, for the first input size
    assert len(f8) == 50 and f8.descriptors.shape == f32.descriptors.shape
    assert np.allclose(np.linalg.norm(f8.descriptors, axis=1), 1.0, atol=1e-4)
    assert (f8.mask == f32.mask).mean() > 0.8
    assert not np.array_equal(f8.descriptors, f32.descriptors)


def test_int8_backend_conf_errors(net: SemFeatNet) -> None:
    with pytest.raises(ModelConfigError, match='int8_calibration_frames'):
        FeatureExtractor(net, {'backend': 'onnxruntime_int8', 'int8_calibration_frames': 0,
                               'drop_classes': []})
    with pytest.raises(ModelConfigError, match='bf16'):
        FeatureExtractor(net, {'backend': 'onnxruntime_int8', 'bf16': True,
                               'drop_classes': []})
    with pytest.raises(ModelConfigError, match='onnxruntime_int8'):
        FeatureExtractor(net, {'backend': 'int4', 'drop_classes': []})


def test_float_heads_keep_the_output_layers_unquantised(fp32_graph: bytes) -> None:
    import onnx

    model = onnx.load_from_string(fp32_graph)
    heads = q.head_nodes(model)
    by_name = {n.name: n for n in model.graph.node}
    convs = [n for n in heads if by_name[n].op_type == 'Conv']
    assert len(convs) >= 3  # at least one final convolution per output
    assert len(heads) < len(model.graph.node) // 3  # only the tails, not the trunk
    calib = [q.network_array(im) for im in _images(2, (96, 64))]
    for float_heads in (True, False):
        qm = onnx.load_from_string(q.quantize_int8(fp32_graph, calib, float_heads=float_heads))
        weights_dq = {n.output[0] for n in qm.graph.node if n.op_type == 'DequantizeLinear'}
        plain = [n.name for n in qm.graph.node
                 if n.op_type == 'Conv' and n.input[1] not in weights_dq]
        assert sorted(plain) == (sorted(convs) if float_heads else [])


def test_torch_bf16_runner_is_close_to_fp32(net: SemFeatNet, fp32_graph: bytes) -> None:
    x = q.network_array(_images(1, (96, 64), seed=4)[0])
    ref = q._run(open_session(fp32_graph, 1), x)
    out = q._run(q.TorchBf16(net), x)
    acc = q.compare_outputs(ref, out, k=200, threshold=0.0)
    assert 0.98 < acc['desc_cos_mean'] < 1.0 - 1e-7
