"""FeatureExtractor (inference API), weights I/O, NMS and sub-pixel refinement."""
from __future__ import annotations

from pathlib import Path
import sys

import numpy as np
import pytest
import torch

from semfeat_ros.camera.models import FisheyeCamera
from semfeat_ros.model import weights_io
from semfeat_ros.model.errors import (
    ModelConfigError,
    ModelInputError,
    WeightsFormatError,
    WeightsNotFoundError,
)
from semfeat_ros.model.extractor import (
    FeatureExtractor,
    class_map,
    refine_softargmax,
    refine_subpixel,
    simple_nms,
)
from semfeat_ros.model.semfeatnet import SemFeatNet

sys.path.insert(0, str(Path(__file__).parent / 'helpers'))
from nets import perturb_batchnorm  # noqa: E402

NAMES = ['road', 'sidewalk', 'parking_line', 'lane_divider', 'road_marking', 'curb', 'wall',
         'pillar', 'ceiling', 'light', 'sign', 'pole', 'railing', 'barrier', 'building',
         'vegetation', 'sky', 'car', 'pedestrian']
SMALL = {'encoder_channels': [8, 16, 16, 24], 'decoder_channels': 16, 'descriptor_dim': 32,
         'seg_channels': 8, 'task_dim': 8, 'mixer_dim': 8, 'seg_stride': 2}  # as shipped


class PeakNet(SemFeatNet):
    """Random-init network whose heatmap is replaced by known peaks (tests the wrapper only)."""

    peaks: list[tuple[int, int, float]] = []  # (u, v, score) at network resolution
    seg_class = 0

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        out = super().forward(image)
        heat = torch.zeros_like(out['heatmap'])
        for u, v, s in self.peaks:
            heat[:, v, u] = s
        seg = torch.zeros_like(out['segmentation_logits'])
        seg[:, self.seg_class] = 10.0
        out = dict(out)
        out['heatmap'] = heat
        out['segmentation_logits'] = seg
        return out


def _extractor(net: SemFeatNet, **conf: object) -> FeatureExtractor:
    return FeatureExtractor(net, {'num_threads': 2, **conf}, class_names=NAMES)


def test_missing_shipped_weights_raise_with_train_command(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(weights_io, 'SHIPPED_WEIGHTS', tmp_path / 'none.safetensors')
    with pytest.raises(WeightsNotFoundError, match='semfeat-train --config config/train.yaml'):
        FeatureExtractor()
    with pytest.raises(WeightsNotFoundError, match='not found'):
        FeatureExtractor(tmp_path / 'missing.safetensors')


def test_weights_roundtrip_and_format_errors(tmp_path: Path) -> None:
    torch.manual_seed(0)
    net = SemFeatNet(SMALL).eval()
    path = weights_io.save_weights(net, tmp_path / 'w', {'class_names': NAMES,
                                                         'input_size': [640, 512]})
    assert path == tmp_path / 'w' / 'semfeat.safetensors' and path.with_suffix('.json').is_file()
    loaded, config = weights_io.load_weights(tmp_path / 'w')
    assert config['class_names'] == NAMES and loaded.conf == net.conf
    assert weights_io.state_dict_allclose(net, loaded)
    image = np.random.default_rng(0).integers(0, 255, (96, 128, 3), dtype=np.uint8)
    a = FeatureExtractor(path, {'detection_threshold': 0.0}).extract(image)
    b = _extractor(net, detection_threshold=0.0).extract(image)
    np.testing.assert_allclose(a.keypoints, b.keypoints)
    np.testing.assert_allclose(a.descriptors, b.descriptors, atol=1e-5)

    jpath = path.with_suffix('.json')
    jpath.write_text('{"format": "other"}')
    with pytest.raises(WeightsFormatError, match='format'):
        weights_io.load_weights(path)
    jpath.write_text('not json')
    with pytest.raises(WeightsFormatError, match='unreadable JSON'):
        weights_io.load_weights(path)
    weights_io.save_weights(SemFeatNet({**SMALL, 'descriptor_dim': 16}), path,
                            {'class_names': NAMES, 'input_size': [640, 512]})
    jpath.write_text(jpath.read_text().replace('"descriptor_dim": 16', '"descriptor_dim": 32'))
    with pytest.raises(WeightsFormatError, match='do not match'):
        weights_io.load_weights(path)
    path.write_bytes(b'garbage')
    with pytest.raises(WeightsFormatError, match='unreadable safetensors'):
        weights_io.load_weights(path)


def test_extract_full_size_fisheye_frame() -> None:
    torch.manual_seed(0)
    net = SemFeatNet(SMALL)
    ext = _extractor(net, detection_threshold=0.0, max_keypoints=300, drop_classes=[])
    rng = np.random.default_rng(1)
    image = rng.integers(0, 255, (1536, 1920, 3), dtype=np.uint8)
    cam = FisheyeCamera(1920, 1536, 560.0, 560.0, 960.0, 768.0, k=(0.02, -0.004, 0.0005, -1e-4))
    assert ext.network_size(1920, 1536) == (640, 512)
    f = ext.extract(image, camera=cam)
    assert len(f) == 300
    assert f.keypoints.dtype == np.float32 and f.keypoints.shape == (300, 2)
    assert f.scores.dtype == np.float32 and np.all(np.diff(f.scores) <= 0)
    assert f.descriptors.shape == (300, 32) and f.descriptors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
    assert f.labels.dtype == np.uint8 and f.labels.max() < 19
    # the default mask is the stride-2 logit grid: 320x256, 6 input px per mask px
    assert f.mask.shape == (256, 320) and f.mask.dtype == np.uint8
    assert f.mask_scale == (6.0, 6.0) and f.image_size == (1920, 1536)
    # every keypoint lies inside the image circle
    rays = cam.unproject(f.keypoints.astype(np.float64), check=False)
    assert np.isfinite(rays).all()
    # labels agree with the mask under each keypoint (bilinear logits vs cell argmax: mostly)
    cells = np.clip(((f.keypoints + 0.5) / 6.0).astype(int), 0, [319, 255])
    assert np.mean(f.mask[cells[:, 1], cells[:, 0]] == f.labels) > 0.7
    # outside the image circle the mask says 'no class' (255), inside it holds class ids
    circle = cam.scaled(320, 256).valid_mask()
    assert (~circle).any() and (f.mask[~circle] == 255).all() and f.mask[circle].max() < 19
    # the input-resolution mask is the seg-grid mask resized nearest (blocks of 6 px)
    f_in = _extractor(net, detection_threshold=0.0, max_keypoints=300, drop_classes=[],
                      mask_resolution='input').extract(image, camera=cam)
    assert f_in.mask.shape == (1536, 1920) and f_in.mask_scale == (1.0, 1.0)
    full = cam.valid_mask()
    both = circle & full[3::6, 3::6]  # (the two circles differ on their rim cells only)
    assert both.sum() > 0.99 * circle.sum()
    np.testing.assert_array_equal(f_in.mask[3::6, 3::6][both], f.mask[both])
    assert (f_in.mask[~full] == 255).all()


def test_grey_input_and_mask_resolutions() -> None:
    torch.manual_seed(0)
    net = SemFeatNet(SMALL)
    grey = np.random.default_rng(2).integers(0, 255, (300, 400), dtype=np.uint8)
    for res, shape in (('network', (480, 640)), ('input', (300, 400))):
        ext = _extractor(net, mask_resolution=res, detection_threshold=0.0)
        f = ext.extract(grey)
        assert f.mask.shape == shape
        assert f.mask_scale == pytest.approx((400 / shape[1], 300 / shape[0]))
        assert (f.keypoints[:, 0] >= 0).all() and (f.keypoints[:, 0] <= 399).all()
        assert (f.keypoints[:, 1] >= 0).all() and (f.keypoints[:, 1] <= 299).all()
    f3 = _extractor(net, detection_threshold=0.0).extract(np.repeat(grey[:, :, None], 3, 2))
    f1 = _extractor(net, detection_threshold=0.0).extract(grey)
    np.testing.assert_allclose(f1.keypoints, f3.keypoints)


def test_rescaling_subpixel_borders_and_semantic_filter() -> None:
    net = PeakNet(SMALL)
    net.seg_class = 0
    # 1920x1536 -> 640x512 network input, scale 3 in both axes
    net.peaks = [(100, 50, 0.9), (101, 51, 0.5), (300, 200, 0.8), (2, 200, 0.99),
                 (400, 300, 0.01)]
    image = np.zeros((1536, 1920, 3), np.uint8)
    ext = _extractor(net, detection_threshold=0.05, nms_radius=3, remove_borders=4,
                     subpixel='none', drop_classes=['sky'])
    f = ext.extract(image)
    # (101, 51) is suppressed by NMS, (2, 200) by the border, (400, 300) by the threshold
    np.testing.assert_allclose(f.scores, [0.9, 0.8], atol=1e-6)
    expected = np.array([[100, 50], [300, 200]], np.float64)
    np.testing.assert_allclose(f.keypoints, (expected + 0.5) * 3.0 - 0.5, atol=1e-4)
    assert (f.labels == 0).all()
    net.seg_class = 16  # everything is sky -> all dropped (the extractor copies the net)
    assert len(_extractor(net, drop_classes=['sky']).extract(image)) == 0
    assert len(_extractor(net, drop_classes=['car']).extract(image)) == 2
    net.seg_class = 0
    assert len(_extractor(net, max_keypoints=1, subpixel='none').extract(image)) == 1
    # with a valid mask covering only the right half, the left peaks disappear
    vm = np.zeros((1536, 1920), bool)
    vm[:, 960:] = True
    f = ext.extract(image, valid_mask=vm)
    assert len(f) == 0
    vm[:, :] = True
    assert len(ext.extract(image, valid_mask=vm)) == 2


def test_input_and_conf_validation() -> None:
    net = SemFeatNet(SMALL)
    ext = _extractor(net)
    with pytest.raises(ModelInputError, match='uint8'):
        ext.extract(np.zeros((64, 64, 3), np.float32))
    with pytest.raises(ModelInputError, match='shape'):
        ext.extract(np.zeros((64, 64, 4), np.uint8))
    with pytest.raises(ModelInputError, match='sides'):
        ext.extract(np.zeros((8, 64), np.uint8))
    with pytest.raises(ModelInputError, match='numpy'):
        ext.extract([[0, 1]])
    with pytest.raises(ModelInputError, match='valid_mask'):
        ext.extract(np.zeros((64, 64), np.uint8), valid_mask=np.ones((32, 32), bool))
    cam = FisheyeCamera(1920, 1536, 560.0, 560.0, 960.0, 768.0)
    with pytest.raises(ModelInputError, match='camera'):
        ext.extract(np.zeros((64, 64), np.uint8), camera=cam)
    with pytest.raises(ModelConfigError, match='unknown extractor'):
        _extractor(net, top_k=5)
    with pytest.raises(ModelConfigError, match='drop_classes'):
        _extractor(net, drop_classes=['unicorn'])
    with pytest.raises(ModelConfigError, match='max_keypoints'):
        _extractor(net, max_keypoints=0)
    with pytest.raises(ModelConfigError, match='mask_resolution'):
        _extractor(net, mask_resolution='full')
    with pytest.raises(ModelConfigError, match='subpixel must'):
        _extractor(net, subpixel=True)
    with pytest.raises(ModelConfigError, match='subpixel_power'):
        _extractor(net, subpixel_power=0.0)
    with pytest.raises(ModelConfigError, match='kp_refine must be true or false'):
        _extractor(net, kp_refine='no')


def test_kp_refine_off_is_the_cell_logits_alone() -> None:
    """kp_refine False skips the full-resolution keypoint correction: the heatmap is the
    sigmoid of the depth-to-space cell logits; the caller's network keeps its layers."""
    torch.manual_seed(0)
    net = SemFeatNet({**SMALL, 'kp_refine_channels': 4}).eval()
    torch.nn.init.normal_(net.kp_refine[-1].weight, std=0.5)  # a correction that matters
    image = (np.random.default_rng(0).random((64, 96, 3)) * 255).astype(np.uint8)
    on = _extractor(net, backend='torch', fuse_batchnorm=False)
    off = _extractor(net, backend='torch', fuse_batchnorm=False, kp_refine=False)
    assert net.kp_refine is not None and on.model.kp_refine is not None
    assert off.model.kp_refine is None
    heat_on = on.forward(image)[0]['heatmap']
    heat_off = off.forward(image)[0]['heatmap']
    assert heat_on.shape == heat_off.shape
    assert not torch.allclose(heat_on, heat_off, atol=1e-3)
    net.kp_refine = None  # the same network without the correction gives the same heatmap
    plain = _extractor(net, backend='torch', fuse_batchnorm=False).forward(image)[0]['heatmap']
    torch.testing.assert_close(heat_off, plain)


def test_caller_model_is_not_modified() -> None:
    net = SemFeatNet(SMALL).train()
    _extractor(net)
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    assert net.training


def test_fast_paths_agree_with_plain_fp32() -> None:
    torch.manual_seed(0)
    net = SemFeatNet(SMALL).eval()
    image = np.random.default_rng(3).integers(0, 255, (256, 320, 3), dtype=np.uint8)
    plain = _extractor(net, channels_last=False, fuse_batchnorm=False, detection_threshold=0.0)
    fast = _extractor(net, channels_last=True, fuse_batchnorm=True, detection_threshold=0.0)
    pa, _ = plain.forward(image)
    pb, _ = fast.forward(image)
    for k in ('heatmap', 'descriptors', 'segmentation_logits'):
        torch.testing.assert_close(pa[k], pb[k], atol=1e-4, rtol=1e-4)
    bf = _extractor(net, bf16=True, detection_threshold=0.0)
    pc, _ = bf.forward(image)
    assert pc['heatmap'].dtype == torch.float32
    assert (pc['heatmap'] - pa['heatmap']).abs().max() < 0.1


def test_simple_nms_and_subpixel() -> None:
    s = torch.zeros(1, 9, 9)
    s[0, 4, 4] = 1.0
    s[0, 4, 5] = 0.5
    s[0, 1, 1] = 0.3
    out = simple_nms(s, 1)
    assert out[0, 4, 4] == 1.0 and out[0, 4, 5] == 0.0 and out[0, 1, 1] == 0.3
    # parabola peak at (4.3, 3.8)
    v, u = torch.meshgrid(torch.arange(9.0), torch.arange(9.0), indexing='ij')
    heat = 1.0 - 0.1 * ((u - 4.3) ** 2 + (v - 3.8) ** 2)
    ref = refine_subpixel(heat, torch.tensor([[4.0, 4.0], [0.0, 3.0]]))
    torch.testing.assert_close(ref[0], torch.tensor([4.3, 3.8]), atol=1e-5, rtol=0)
    torch.testing.assert_close(ref[1], torch.tensor([0.0, 3.0]))  # border: unchanged


def test_softargmax_takes_the_blob_centre_not_its_argmax_pixel() -> None:
    # a flat-topped blob over columns 4..6 of row 4, peak pixel at its left end
    heat = torch.zeros(9, 12)
    heat[4, 4:7] = torch.tensor([1.0, 0.999, 0.998])
    heat[3, 5] = heat[5, 5] = 0.5
    ref = refine_softargmax(heat, torch.tensor([[4.0, 4.0]]), radius=3, power=2.0)
    w = torch.tensor([1.0, 0.999 ** 2, 0.998 ** 2, 0.25, 0.25])
    u = (w * torch.tensor([4.0, 5.0, 6.0, 5.0, 5.0])).sum() / w.sum()
    torch.testing.assert_close(ref[0], torch.stack([u, torch.tensor(4.0)]), atol=1e-5, rtol=0)
    # an isolated peak stays put; a window over the map border only weighs pixels inside it
    one = torch.zeros(9, 12)
    one[2, 3] = 0.8
    one[0, 3] = 0.8
    ref = refine_softargmax(one, torch.tensor([[3.0, 2.0], [3.0, 0.0]]), radius=1, power=2.0)
    torch.testing.assert_close(ref[0], torch.tensor([3.0, 2.0]))
    torch.testing.assert_close(ref[1], torch.tensor([3.0, 0.0]))
    # radius 0: no refinement
    torch.testing.assert_close(refine_softargmax(one, torch.tensor([[3.0, 2.0]]), 0, 2.0),
                               torch.tensor([[3.0, 2.0]]))


def test_benchmark_runs_and_labels_random_init(tmp_path: Path) -> None:
    from semfeat_ros.model.benchmark import cli, run
    image = np.random.default_rng(0).integers(0, 255, (256, 320, 3), dtype=np.uint8)
    res = run(None, True, 1, 2, image, sizes=((128, 96),), warmup=0)
    assert res['weights'] == 'random-init (timing only)'
    for key in ('fp32', 'fp32_fused_channels_last', 'bf16_channels_last', 'onnxruntime'):
        assert res['forward_128x96'][key] > 0
    assert res['extract_backend'] == 'onnxruntime'
    assert res['extract_320x256'] > 0 and res['extract_320x256_torch'] > 0
    assert res['sift_1000_320x256'] > 0
    assert res['extract_640x512'] > 0 and res['xfeat_1000_640x512'] > 0  # same frame, interleaved
    assert res['extract_over_xfeat_640x512'] == pytest.approx(
        res['extract_640x512'] / res['xfeat_1000_640x512'])
    assert cli(['--weights', str(tmp_path / 'none.safetensors'), '--repeats', '1']) == 1


def test_load_model_yaml_errors(tmp_path: Path) -> None:
    from semfeat_ros.model import load_model_yaml
    p = tmp_path / 'model.yaml'
    p.write_text('extractor: {topk: 3}\n')
    with pytest.raises(ModelConfigError, match='unknown extractor keys'):
        load_model_yaml(p)
    p.write_text('network: [1, 2]\n')
    with pytest.raises(ModelConfigError, match='network must be a mapping'):
        load_model_yaml(p)
    p.write_text('extractor: {max_keypoints: 50}\n')
    assert load_model_yaml(p)['extractor']['max_keypoints'] == 50
    with pytest.raises(FileNotFoundError):
        load_model_yaml(tmp_path / 'missing.yaml')


def test_weights_of_the_v1_layout_still_load(tmp_path: Path) -> None:
    # a weights JSON written before kp_pixel_channels / kp_head_layers existed
    import json

    net = SemFeatNet({**SMALL, **weights_io.LEGACY_NETWORK_CONF}).eval()
    path = weights_io.save_weights(net, tmp_path, {'class_names': NAMES,
                                                   'input_size': [640, 512]})
    cfg = json.loads(path.with_suffix('.json').read_text())
    for key in weights_io.LEGACY_NETWORK_CONF:
        del cfg['network'][key]
    path.with_suffix('.json').write_text(json.dumps(cfg))
    loaded, _ = weights_io.load_weights(path)
    assert loaded.kp_pixels is None and weights_io.state_dict_allclose(net, loaded)


@pytest.mark.parametrize('extra', [{}, {'seg_stride': 2, 'seg_context_blocks': 2,
                                        'seg_blocks': 1, 'kp_refine_channels': 4}])
def test_onnxruntime_backend_agrees_with_torch(extra: dict) -> None:
    torch.manual_seed(0)
    net = SemFeatNet({**SMALL, **extra}).eval()
    perturb_batchnorm(net, ('seg_context', 'seg_blocks'))  # blocks away from the identity
    if net.kp_refine is not None:
        torch.nn.init.normal_(net.kp_refine[-1].weight, std=0.2)
    image = np.random.default_rng(5).integers(0, 255, (300, 400, 3), dtype=np.uint8)
    eager = _extractor(net, backend='torch', detection_threshold=0.0, max_keypoints=200)
    ort = _extractor(net, backend='onnxruntime', detection_threshold=0.0, max_keypoints=200)
    assert (eager.backend, ort.backend) == ('torch', 'onnxruntime')
    pa, size_a = eager.forward(image)
    pb, size_b = ort.forward(image)
    assert size_a == size_b == (640, 480)  # upscaled to resize_max
    for k in ('heatmap', 'descriptors', 'segmentation_logits'):
        assert pb[k].dtype == torch.float32 and pb[k].shape == pa[k].shape
        torch.testing.assert_close(pa[k], pb[k], atol=1e-4, rtol=1e-4)
    fa, fb = eager.extract(image), ort.extract(image)
    assert len(fa) == len(fb) == 200
    # the same peaks (scores equal to ~1e-6, so near-ties may swap places in the ranking)
    oa = np.lexsort(np.round(fa.keypoints, 1).T)
    ob = np.lexsort(np.round(fb.keypoints, 1).T)
    np.testing.assert_allclose(fa.keypoints[oa], fb.keypoints[ob], atol=1e-2)
    np.testing.assert_allclose(fa.descriptors[oa], fb.descriptors[ob], atol=1e-4)
    np.testing.assert_array_equal(fa.labels[oa], fb.labels[ob])
    np.testing.assert_array_equal(fa.mask, fb.mask)
    with pytest.raises(ModelInputError, match='multiples'):  # the export runs the shape checks
        ort._ort(torch.zeros(1, 3, 100, 100))


def test_onnxruntime_sessions_per_size_and_prepare(monkeypatch: pytest.MonkeyPatch) -> None:
    from semfeat_ros.model import onnx_backend

    torch.manual_seed(0)
    ext = _extractor(SemFeatNet(SMALL).eval(), backend='onnxruntime', resize_max=160)
    exports: list[tuple[int, int]] = []
    real = onnx_backend.OrtNetwork.export

    def counting(self: onnx_backend.OrtNetwork, height: int, width: int) -> bytes:
        exports.append((height, width))
        return real(self, height, width)

    monkeypatch.setattr(onnx_backend.OrtNetwork, 'export', counting)
    ext.prepare(1920, 1536)  # 160x128 at the network
    ext.prepare(640, 512)  # same network size: no second export
    image = np.zeros((512, 640), np.uint8)
    ext.extract(image)
    assert exports == [(128, 160)]
    ext.extract(np.zeros((200, 400), np.uint8))  # another aspect: its own graph, 160x80
    assert exports == [(128, 160), (80, 160)]
    ext.extract(np.zeros((1536, 1920, 3), np.uint8))
    assert len(exports) == 2


def test_onnxruntime_sessions_are_bounded_lru() -> None:
    from semfeat_ros.model.onnx_backend import MAX_SESSIONS

    torch.manual_seed(0)
    ext = _extractor(SemFeatNet(SMALL).eval(), backend='onnxruntime', resize_max=128)
    ort = ext._ort
    stride = ext.model.stride
    sizes = [(128, stride * (i + 1)) for i in range(MAX_SESSIONS + 3)]  # (w, h) network sizes
    for w, h in sizes:
        assert ext.network_size(w * 2, h * 2) == (w, h)
        ext.extract(np.zeros((h * 2, w * 2), np.uint8))
        assert len(ort._sessions) <= MAX_SESSIONS
    assert list(ort._sessions) == [(h, w) for w, h in sizes[-MAX_SESSIONS:]]
    assert ort.evicted == 3
    ort.session(*sizes[-MAX_SESSIONS][::-1])  # used again: the most recent now
    assert list(ort._sessions)[-1] == sizes[-MAX_SESSIONS][::-1]


def test_onnxruntime_session_build_does_not_block_inference(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import threading

    from semfeat_ros.model import onnx_backend

    torch.manual_seed(0)
    ext = _extractor(SemFeatNet(SMALL).eval(), backend='onnxruntime', resize_max=64)
    ext.prepare(64, 48)  # a ready size
    release, building = threading.Event(), threading.Event()
    real = onnx_backend.OrtNetwork._open

    def slow_open(self: onnx_backend.OrtNetwork, height: int, width: int) -> object:
        building.set()
        assert release.wait(30)
        return real(self, height, width)

    monkeypatch.setattr(onnx_backend.OrtNetwork, '_open', slow_open)
    preparer = threading.Thread(target=ext.prepare, args=(64, 32))  # another size: slow build
    preparer.start()
    try:
        assert building.wait(30)
        done = threading.Event()
        runner = threading.Thread(target=lambda: (ext.extract(np.zeros((48, 64), np.uint8)),
                                                  done.set()))
        runner.start()
        # the ready size runs while the other one is still being built
        assert done.wait(30), 'inference waited for the session being built'
        runner.join()
    finally:
        release.set()
        preparer.join(30)
    assert (32, 64) in ext._ort._sessions


def test_backend_choice_and_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    from semfeat_ros.model import extractor as extractor_module
    from semfeat_ros.model import onnx_backend

    net = SemFeatNet(SMALL).eval()
    assert _extractor(net).backend == 'onnxruntime'  # installed with requirements.txt
    assert _extractor(net, bf16=True).backend == 'torch'
    assert _extractor(net, backend='torch')._ort is None
    with pytest.raises(ModelConfigError, match='bf16'):
        _extractor(net, backend='onnxruntime', bf16=True)
    with pytest.raises(ModelConfigError, match='backend'):
        _extractor(net, backend='tensorrt')
    for module in (extractor_module, onnx_backend):
        monkeypatch.setattr(module, 'onnxruntime_available', lambda: False)
    assert _extractor(net).backend == 'torch'
    with pytest.raises(ModelConfigError, match='pip install'):
        _extractor(net, backend='onnxruntime')


def test_class_map_is_the_argmax_over_classes() -> None:
    torch.manual_seed(0)
    logits = torch.randn(1, 19, 12, 20)
    logits[0, 3, 0, 0] = logits[0, 7, 0, 0] = 50.0  # a tie goes to the lower class
    m = class_map(logits)
    assert m.dtype == np.uint8 and m.shape == (12, 20) and m[0, 0] == 3
    np.testing.assert_array_equal(m, logits[0].argmax(dim=0).numpy())
