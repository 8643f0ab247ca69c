"""Mode ``sequence`` on a tiny ray-cast room (exact depth, poses, labels), from a simulator shard
and from a bag; plus a plug-in method that exercises the segmentation metrics."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from semfeat_ros.camera import FisheyeCamera, load_camera_yaml
from semfeat_ros.evaluation import methods as methods_mod
from semfeat_ros.evaluation.methods import Features, NNMethod, OpenCVExtractor
from semfeat_ros.evaluation.pipeline import EvalConf, evaluate
from semfeat_ros.evaluation.run_sequence import (
    Frame,
    SequenceConf,
    SequencePaths,
    header_stamp_ns,
    main,
    make_depth_pair,
    pair_indices,
    shard_frames,
)
from semfeat_ros.evaluation.segmentation import confusion_matrix, iou_from_confusion
from semfeat_ros.sim.groundtruth import warp_pixels
from semfeat_ros.tools.eval import cli

CAM = FisheyeCamera(192, 144, 48.0, 48.0, 95.5, 71.5, k=(0.0, 0.0, 0.0, 0.0), fov_deg=190.0)
# Optical frame (z fwd, x right, y down) of a camera looking along map +x (z up).
R_MAP_OPT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
LO, HI = np.array([-6.0, -6.0, 0.0]), np.array([6.0, 6.0, 4.0])
ROAD, WALL, CEILING, CAR = 0, 6, 8, 17


def pose(k: int) -> np.ndarray:
    yaw = np.radians(3.0 * k)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_MAP_OPT
    T[:3, 3] = [0.3 * k - 1.0, 0.1 * k, 1.5]
    return T


def render(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB, range (m, NaN outside the circle) and labels of the textured box room."""
    u, v = np.meshgrid(np.arange(CAM.width, dtype=float), np.arange(CAM.height, dtype=float))
    rays = CAM.unproject(np.stack([u.ravel(), v.ravel()], 1), check=False)
    ok = np.isfinite(rays[:, 0])
    d = np.where(ok[:, None], rays, [0.0, 0.0, 1.0]) @ T[:3, :3].T
    o = T[:3, 3]
    with np.errstate(divide='ignore', invalid='ignore'):
        t_axes = np.where(d > 0, (HI - o) / d, (LO - o) / d)
    t_axes = np.where(np.isfinite(t_axes) & (t_axes > 0), t_axes, np.inf)
    axis = np.argmin(t_axes, axis=1)
    t = t_axes[np.arange(len(d)), axis]
    p = o + t[:, None] * d
    cells = np.floor(p / 0.5).astype(np.int64)
    key = (cells[:, 0] * 73856093) ^ (cells[:, 1] * 19349663) ^ (cells[:, 2] * 83492791) \
        ^ (axis * 2654435761)
    rgb = np.stack([(key >> s) % 200 + 40 for s in (3, 11, 19)], axis=1).astype(np.uint8)
    labels = np.full(len(d), WALL, np.uint8)
    labels[(axis == 2) & (d[:, 2] < 0)] = ROAD
    labels[(axis == 2) & (d[:, 2] > 0)] = CEILING
    labels[(axis == 0) & (d[:, 0] > 0) & (np.abs(p[:, 1]) < 1.0) & (p[:, 2] < 1.5)] = CAR
    rgb[~ok] = 0
    labels[~ok] = 255
    rng = np.where(ok, t, np.nan).astype(np.float32)
    shape = (CAM.height, CAM.width)
    return rgb.reshape(*shape, 3), rng.reshape(shape), labels.reshape(shape)


def floor_corners(T: np.ndarray) -> np.ndarray:
    """Exact GT keypoints: the floor's cell corners visible in the frame (px)."""
    g = np.arange(-5.5, 6.0, 0.5)
    X, Y = np.meshgrid(g, g)
    pts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    cam = (pts - T[:3, 3]) @ T[:3, :3]
    uv, valid = CAM.project(cam)
    keep = valid & CAM.in_image(uv, border=2.0)
    return uv[keep]


@pytest.fixture(scope='module')
def frames() -> list[Frame]:
    out = []
    for k in range(4):
        rgb, depth, labels = render(pose(k))
        out.append(Frame(k, (k + 1) * 100_000_000, rgb, depth, pose(k), labels))
    return out


def test_render_is_consistent_with_warp(frames: list[Frame]) -> None:
    # The rendered depth + poses make the sim's warp agree with a re-render: a floor corner
    # seen in frame 0 lands on the same corner in frame 1.
    c0 = floor_corners(frames[0].T_map_cam)
    uv1, valid = warp_pixels(c0, frames[0].depth, frames[0].T_map_cam, frames[1].T_map_cam, CAM,
                             depth_b=frames[1].depth)
    assert valid.sum() > 10
    c1 = floor_corners(frames[1].T_map_cam)
    d = np.linalg.norm(uv1[valid][:, None] - c1[None], axis=2).min(axis=1)
    assert np.median(d) < 0.3


def test_pair_indices_and_header_stamp() -> None:
    assert pair_indices(7, 2) == [(0, 2), (2, 4), (4, 6)]
    assert pair_indices(7, 2, max_pairs=2) == [(0, 2), (2, 4)]
    assert pair_indices(2, 3) == []
    raw = bytes([0, 1, 0, 0]) + np.array([5], '<i4').tobytes() + np.array([7], '<u4').tobytes()
    assert header_stamp_ns(raw) == 5_000_000_007


def test_dynamic_pixels_never_visible(frames: list[Frame]) -> None:
    dynamic = np.zeros(256, bool)
    dynamic[CAR] = True
    pair = make_depth_pair('p', frames[0], frames[1], CAM, CAM.valid_mask(), 2, warp_pixels,
                           dynamic)
    vs, us = np.nonzero(frames[0].labels == CAR)
    assert len(us) > 20
    _, vis = pair.gt.a_to_b(np.stack([us, vs], 1).astype(float))
    assert not vis.any()


def _save_shard(path: Path, frames: list[Frame]) -> Path:
    from semfeat_ros.sim.dataset import camera_to_json, save_shard

    n = len(frames)
    return save_shard(path, {
        'rgb': np.stack([f.rgb for f in frames]),
        'label': np.stack([f.labels for f in frames]),
        'depth': np.stack([f.depth for f in frames]).astype(np.float16),
        'instance': np.zeros((n, CAM.height, CAM.width), np.uint16),
        'T_map_cam': np.stack([f.T_map_cam for f in frames]),
        'T_map_base': np.stack([f.T_map_cam for f in frames]),
        'time_s': np.arange(n, dtype=np.float64)[::-1].copy(),  # stored out of time order
        'frame_index': np.arange(n, dtype=np.int32), 'seed': np.array(1),
        'camera': np.array(camera_to_json(CAM)), 'pairs': np.zeros((0, 2), np.int32),
        'corr_uv_a': np.zeros((0, 0, 2), np.float32),
        'corr_uv_b': np.zeros((0, 0, 2), np.float32), 'corr_count': np.zeros(0, np.int32),
        'pair_overlap': np.zeros(0, np.float32), 'moving_instances': np.zeros(0, np.int64)})


def test_sequence_from_shard(tmp_path: Path, frames: list[Frame]) -> None:
    shard = _save_shard(tmp_path / 's.npz', frames)
    fr, cam = shard_frames(shard)
    assert [f.index for f in fr] == [3, 2, 1, 0]  # time order
    gtk = tmp_path / 'gtk'
    gtk.mkdir()
    for f in frames:
        np.save(gtk / f'{f.index}.npy', floor_corners(f.T_map_cam))
    out = tmp_path / 'out'
    res = main(SequenceConf(eval=EvalConf(methods=('sift_nn', 'orb_nn'), n_figures=1,
                                          progress=False), stride=1, mask_margin_px=2),
               SequencePaths(out=out, shard=shard, gt_keypoints=gtk))
    assert res['n_pairs'] == 3
    assert "matcher's bearing verification" in res['verification']
    s = res['methods']['sift_nn']['summary']
    assert s['inlier_ratio'] > 0.5 and s['keypoint_recall'] > 0.2
    assert s['n_gt_keypoint_recall'] == 3 and 0.0 <= s['gt_keypoint_recall'] <= 1.0
    assert s['inlier_ratio_verified'] >= s['inlier_ratio']
    assert 'homography_accuracy' not in s  # no planar GT in a 3-D scene
    assert json.loads((out / 'results.json').read_text())['mode'] == 'sequence'


def _write_bag(path: Path, frames: list[Frame], base_link: bool) -> Path:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation

    from msg_adapters.camera_info import model_to_camera_info
    from msg_adapters.image import numpy_to_image

    ts = get_typestore(Stores.ROS2_JAZZY)
    T_base_cam = load_camera_yaml(None)[1].T_base_cam
    PoseStamped = ts.types['geometry_msgs/msg/PoseStamped']  # noqa: N806
    Pose = ts.types['geometry_msgs/msg/Pose']  # noqa: N806
    Point = ts.types['geometry_msgs/msg/Point']  # noqa: N806
    Quaternion = ts.types['geometry_msgs/msg/Quaternion']  # noqa: N806
    Header = ts.types['std_msgs/msg/Header']  # noqa: N806
    Time = ts.types['builtin_interfaces/msg/Time']  # noqa: N806
    with Writer(path, version=9) as w:
        c_img = w.add_connection('/camera/front/image_raw', 'sensor_msgs/msg/Image', typestore=ts)
        c_dep = w.add_connection('/ground_truth/depth', 'sensor_msgs/msg/Image', typestore=ts)
        c_lab = w.add_connection('/ground_truth/semantic', 'sensor_msgs/msg/Image', typestore=ts)
        c_pose = w.add_connection('/ground_truth/pose', 'geometry_msgs/msg/PoseStamped',
                                  typestore=ts)
        c_info = w.add_connection('/camera/front/camera_info', 'sensor_msgs/msg/CameraInfo',
                                  typestore=ts)
        for f in frames:
            st = f.stamp_ns
            T = f.T_map_cam @ np.linalg.inv(T_base_cam) if base_link else f.T_map_cam
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            msg = PoseStamped(Header(Time(st // 10**9, st % 10**9), 'map'),
                              Pose(Point(*T[:3, 3]), Quaternion(*q)))
            w.write(c_pose, st, ts.serialize_cdr(msg, 'geometry_msgs/msg/PoseStamped'))
            info = model_to_camera_info(CAM, stamp_ns=st, frame_id='cam', msg_cls=ts)
            w.write(c_info, st, ts.serialize_cdr(info, 'sensor_msgs/msg/CameraInfo'))
            for conn, arr, enc in ((c_img, f.rgb, 'rgb8'), (c_dep, f.depth, '32FC1'),
                                   (c_lab, f.labels, 'mono8')):
                m = numpy_to_image(arr, enc, stamp_ns=st, frame_id='cam', msg_cls=ts)
                w.write(conn, st, ts.serialize_cdr(m, 'sensor_msgs/msg/Image'))
    return path


@pytest.mark.parametrize('base_link', [True, False])
def test_sequence_from_bag_cli(tmp_path: Path, frames: list[Frame], base_link: bool) -> None:
    bag = _write_bag(tmp_path / 'bag', frames, base_link)
    out = tmp_path / 'out'
    args = ['sequence', '--bag', str(bag), '--stride', '1', '--max-pairs', '2', '--methods',
            'sift_nn', '--out', str(out), '--figures', '1', '--no-progress', '--margin', '2']
    if not base_link:
        args += ['--pose-frame', 'camera', '--gt-keypoints', 'none']
    assert cli(args) == 0
    res = json.loads((out / 'results.json').read_text())
    assert res['n_pairs'] == 2
    assert 'GT labels: yes' in ' '.join(res['notes'])
    s = res['methods']['sift_nn']['summary']
    assert s['inlier_ratio'] > 0.5  # wrong poses or extrinsic would make this ~0
    if base_link:  # default: GT keypoints of the rendered geometry (the paper's reading)
        assert s['n_gt_keypoint_recall'] == 2 and 0.0 < s['gt_keypoint_recall'] <= 1.0
        assert 'keypoint_candidates' in ' '.join(res['notes'])
    else:
        assert 'gt_keypoint_recall' not in s


def test_sequence_bag_errors(tmp_path: Path, frames: list[Frame],
                             capsys: pytest.CaptureFixture) -> None:
    bag = _write_bag(tmp_path / 'bag', frames[:2], False)
    rc = cli(['sequence', '--bag', str(bag), '--depth-topic', '/depth', '--out',
              str(tmp_path / 'o'), '--no-progress'])
    err = capsys.readouterr().err
    assert rc == 1 and err.count('\n') == 1 and 'topic /depth not in bag' in err
    rc = cli(['sequence', '--bag', str(bag), '--stride', '3', '--pose-frame', 'camera',
              '--out', str(tmp_path / 'o'), '--no-progress'])
    err = capsys.readouterr().err
    assert rc == 1 and 'too few frames for stride 3' in err


class _ConstantSegmentation:
    """Test plug-in extractor: SIFT keypoints and a segmentation that says "wall" everywhere."""

    def __init__(self) -> None:
        self._sift = OpenCVExtractor('sift', 300)
        self.key = 'test_constant_seg'

    def extract(self, image: np.ndarray, mask: np.ndarray) -> Features:
        f = self._sift.extract(image, mask)
        f.segmentation = np.full((image.shape[0] // 2, image.shape[1] // 2), WALL, np.uint8)
        return f


def test_plugin_method_and_segmentation(tmp_path: Path, frames: list[Frame],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import cv2

    monkeypatch.setitem(methods_mod._REGISTRY, 'const_seg', (
        'Const seg', lambda conf: NNMethod('const_seg', 'Const seg', _ConstantSegmentation(),
                                           cv2.NORM_L2)))
    dynamic = np.zeros(256, bool)
    pairs = [make_depth_pair(f'p{k}', frames[k], frames[k + 1], CAM, CAM.valid_mask(), 2,
                             warp_pixels, dynamic) for k in range(2)]
    res = evaluate(iter(pairs), EvalConf(methods=('const_seg',), n_figures=0, progress=False),
                   tmp_path, mode='sequence', source='test', n_pairs=2)
    assert res['methods']['const_seg']['summary']['n_pairs'] == 2
    seg = res['segmentation']['test_constant_seg']
    assert seg['n_images'] == 4
    cm = sum(confusion_matrix(np.full(f.labels.shape, WALL, np.uint8), f.labels, 19,
                              valid=p.mask_a if k == 0 else p.mask_b)
             for p in pairs for k, f in enumerate((frames[int(p.name[1])],
                                                   frames[int(p.name[1]) + 1])))
    assert seg['iou']['wall'] == pytest.approx(iou_from_confusion(cm)[WALL])
    assert seg['iou']['road'] == 0.0 and seg['iou']['sky'] is None
    assert (tmp_path / 'confusion_test_constant_seg.png').is_file()


def test_sequential_matcher_adapter_with_camera(frames: list[Frame]) -> None:
    from semfeat_ros.evaluation.methods import SequentialMatcherMethod
    from semfeat_ros.evaluation.metrics import match_errors

    pair = make_depth_pair('p', frames[0], frames[1], CAM, CAM.valid_mask(), 2, warp_pixels)
    method = SequentialMatcherMethod('seq', 'Seq', OpenCVExtractor('sift', 500))
    fa = method.extractor.extract(pair.image_a, pair.mask_a)
    fb = method.extractor.extract(pair.image_b, pair.mask_b)
    res = method.match(fa, fb, pair)
    assert 'its own bearing verification' in res.verification
    proj, vis = pair.gt.a_to_b(fa.keypoints)
    correct = match_errors(proj, vis, fb.keypoints, res.matches) <= 3.0
    assert res.verified.sum() > 20
    assert correct[res.verified].mean() > 0.8 > correct[~res.verified].mean()


def test_semfeat_methods_with_untrained_weights(tmp_path: Path, frames: list[Frame]) -> None:
    """The three semfeat methods and the segmentation metrics run end to end with a weights
    file (random initialisation: the numbers are meaningless, the plumbing is tested)."""
    torch = pytest.importorskip('torch')
    from semfeat_ros.labels import load_labels
    from semfeat_ros.model import SemFeatNet, save_weights

    torch.manual_seed(0)
    w = save_weights(SemFeatNet(), tmp_path / 'w' / 'semfeat.safetensors',
                     {'class_names': list(load_labels().names), 'input_size': [144, 192]})
    shard = _save_shard(tmp_path / 's.npz', frames[:2])
    out = tmp_path / 'out'
    assert cli(['sequence', '--shard', str(shard), '--weights', str(w), '--resize-max', '192',
                '--methods', 'semfeat_nn,semfeat_semantic,semfeat_seq', '--out', str(out),
                '--figures', '1', '--no-progress', '--margin', '2']) == 0
    res = json.loads((out / 'results.json').read_text())
    for name in ('semfeat_nn', 'semfeat_semantic', 'semfeat_seq'):
        s = res['methods'][name]['summary']
        assert s is not None and s['n_pairs'] == 1 and s['n_kpts_a'] > 0
        assert len(res['methods'][name]['figures']) == 1
    # Both semfeat methods share one extraction per image (same time recorded).
    assert res['methods']['semfeat_nn']['per_pair'][0]['extract_ms'] == \
        res['methods']['semfeat_semantic']['per_pair'][0]['extract_ms']
    assert 'sequential matcher' in res['methods']['semfeat_seq']['verification']
    seg = res['segmentation']['semfeat']
    assert seg['n_images'] == 2 and 0.0 <= seg['pixel_accuracy'] <= 1.0
    assert (out / 'confusion_semfeat.png').is_file()


def test_extractor_set_reaches_the_network_and_bad_keys_fail_in_one_line(
        tmp_path: Path, frames: list[Frame], capsys: pytest.CaptureFixture[str]) -> None:
    torch = pytest.importorskip('torch')
    from semfeat_ros.labels import load_labels
    from semfeat_ros.model import SemFeatNet, save_weights

    torch.manual_seed(0)
    w = save_weights(SemFeatNet(), tmp_path / 'w' / 'semfeat.safetensors',
                     {'class_names': list(load_labels().names), 'input_size': [144, 192]})
    shard = _save_shard(tmp_path / 's.npz', frames[:2])
    base = ['sequence', '--shard', str(shard), '--weights', str(w), '--resize-max', '192',
            '--methods', 'semfeat_nn', '--figures', '0', '--no-progress', '--margin', '2']
    assert cli(base + ['--extractor-set', 'max_keypoints=7', '--extractor-set',
                       'detection_threshold=0.0', '--out', str(tmp_path / 'ok')]) == 0
    s = json.loads((tmp_path / 'ok' / 'results.json').read_text())['methods']['semfeat_nn']
    assert s['summary']['n_kpts_a'] == 7
    capsys.readouterr()
    assert cli(base + ['--extractor-set', 'no_such_key=1', '--out', str(tmp_path / 'bad')]) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'no_such_key' in err
    assert cli(base + ['--extractor-set', 'subpixel', '--out', str(tmp_path / 'bad2')]) == 2
    assert 'KEY=VALUE' in capsys.readouterr().err
