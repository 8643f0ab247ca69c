"""``semfeat-eval`` end to end: smoke runs of the image modes and bad-input handling."""
from __future__ import annotations

import json
from pathlib import Path
import shutil

import cv2
import numpy as np
import pytest

from semfeat_ros.tools.eval import cli

# Real fisheye frames of shared/ (next to the repository, as on the developers' machines and CI).
REAL = next((p for p in (Path(__file__).resolve().parents[2] / 'shared/data/real_fisheye_calib',
                         Path('/work/shared/data/real_fisheye_calib')) if p.is_dir()),
            Path('/work/shared/data/real_fisheye_calib'))
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f'real fisheye frames not at {REAL}')
CLASSICAL = 'sift_nn,orb_nn,akaze_nn,brisk_nn'


def texture(h: int, w: int, seed: int) -> np.ndarray:
    """A structured RGB test image: random rectangles and disks on a gradient, slightly noisy."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = np.linspace(30, 90, w, dtype=np.uint8)[None, :, None]
    for _ in range(40):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(6, 40)),
                                        y + int(rng.integers(6, 40))), color, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, 18)), color, -1)
    noise = rng.normal(0, 3, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def _folder(tmp_path: Path, n: int = 2, size: tuple[int, int] = (180, 240)) -> Path:
    d = tmp_path / 'imgs'
    d.mkdir()
    for k in range(n):
        cv2.imwrite(str(d / f'im{k}.png'), texture(*size, seed=k))
    return d


def write_image_bag(path: Path, topic: str, images: list[np.ndarray]) -> Path:
    """A rosbag2 with one rgb8 Image topic (stamps 0.1 s apart)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from msg_adapters.image import numpy_to_image

    ts = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=9) as w:
        conn = w.add_connection(topic, 'sensor_msgs/msg/Image', typestore=ts)
        for k, img in enumerate(images):
            stamp = (k + 1) * 100_000_000
            msg = numpy_to_image(img, 'rgb8', stamp_ns=stamp, frame_id='cam', msg_cls=ts)
            w.write(conn, stamp, ts.serialize_cdr(msg, 'sensor_msgs/msg/Image'))
    return path


def _load(out: Path) -> dict:
    return json.loads((out / 'results.json').read_text())


def test_transforms_smoke_and_outputs(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    imgs = _folder(tmp_path)
    out = tmp_path / 'out'
    rc = cli(['transforms', '--images', str(imgs), '--pairs', '3', '--seed', '1', '--out',
              str(out), '--figures', '1', '--no-progress', '--weights',
              str(tmp_path / 'missing.safetensors')])
    assert rc == 0
    res = _load(out)
    assert res['mode'] == 'transforms' and res['n_pairs'] == 3
    assert res['verification'] == 'RANSAC homography (OpenCV)'
    for name in CLASSICAL.split(','):
        s = res['methods'][name]['summary']
        assert s['n_pairs'] == 3
        assert 0.0 <= s['keypoint_recall'] <= 1.0 and 0.0 <= s['inlier_ratio'] <= 1.0
        assert len(s['mma']) == 10 and set(s['homography_accuracy']) == {'1', '3', '5'}
        assert len(res['methods'][name]['figures']) == 1
        assert (out / res['methods'][name]['figures'][0]).is_file()
    # SIFT on synthetic transforms of a structured image: clearly better than chance.
    assert res['methods']['sift_nn']['summary']['inlier_ratio'] > 0.5
    # The network's weights are missing: the semfeat methods are skipped with the reason.
    for name in ('semfeat_nn', 'semfeat_semantic'):
        assert res['methods'][name]['summary'] is None
        assert 'weights' in res['methods'][name]['skipped']
    md = (out / 'results.md').read_text()
    assert '| Method | Keypoint Recall (%) | Inlier Ratio (%) |' in md
    assert '| SIFT + NN |' in md and 'Skipped' in md
    for png in ('bars_matching.png', 'bars_homography.png', 'bars_time.png', 'mma.png'):
        assert cv2.imread(str(out / png)) is not None
    assert 'Keypoint Recall' in capsys.readouterr().out


def test_transforms_is_deterministic(tmp_path: Path) -> None:
    imgs = _folder(tmp_path, n=1)
    runs = []
    for k in range(2):
        out = tmp_path / f'out{k}'
        assert cli(['transforms', '--images', str(imgs), '--pairs', '2', '--seed', '5',
                    '--methods', 'orb_nn,sift_nn', '--out', str(out), '--figures', '0',
                    '--no-progress']) == 0
        per_pair = _load(out)['methods']['orb_nn']['per_pair']
        runs.append([{k: v for k, v in p.items() if not k.endswith('_ms')} for p in per_pair])
    assert runs[0] == runs[1]
    other = tmp_path / 'other'
    assert cli(['transforms', '--images', str(imgs), '--pairs', '2', '--seed', '6',
                '--methods', 'orb_nn', '--out', str(other), '--figures', '0',
                '--no-progress']) == 0
    other_pp = [{k: v for k, v in p.items() if not k.endswith('_ms')}
                for p in _load(other)['methods']['orb_nn']['per_pair']]
    assert other_pp != runs[0]  # another seed draws other transforms


@needs_real
def test_transforms_real_fisheye_images(tmp_path: Path) -> None:
    d = tmp_path / 'real'
    d.mkdir()
    for name in ('left-0003.png', 'left-0010.png'):
        shutil.copy(REAL / name, d / name)
    out = tmp_path / 'out'
    assert cli(['transforms', '--images', str(d), '--pairs', '2', '--methods', 'sift_nn',
                '--out', str(out), '--figures', '0', '--no-progress', '--camera',
                str(REAL / 'ost.yaml'), '--distortion-model', 'equidistant']) == 0
    res = _load(out)
    assert 'camera image circle' in res['mask']
    s = res['methods']['sift_nn']['summary']
    assert s['keypoint_recall'] > 0.3 and s['inlier_ratio'] > 0.5


def test_transforms_from_bag(tmp_path: Path) -> None:
    imgs = [texture(120, 160, seed=k) for k in range(3)]
    bag = write_image_bag(tmp_path / 'bag', '/camera/front/image_raw', imgs)
    out = tmp_path / 'out'
    assert cli(['transforms', '--bag', str(bag), '--topic', '/camera/front/image_raw',
                '--pairs', '4', '--methods', 'orb_nn', '--out', str(out), '--figures', '0',
                '--no-progress']) == 0
    res = _load(out)
    assert res['n_pairs'] == 4
    names = [p['pair'] for p in res['methods']['orb_nn']['per_pair']]
    assert sorted(names) == ['000_camera_front_image_raw_0', '001_camera_front_image_raw_1',
                             '002_camera_front_image_raw_2', '003_camera_front_image_raw_0']


def test_homography_mode(tmp_path: Path) -> None:
    seq = tmp_path / 'ds' / 'boat'
    seq.mkdir(parents=True)
    ref = texture(180, 240, seed=3)
    cv2.imwrite(str(seq / 'img1.ppm'), ref)
    Hs = [np.array([[1.0, 0.05, 4.0], [-0.04, 1.0, 2.0], [0.0, 0.0, 1.0]]),
          np.array([[0.9, -0.1, 20.0], [0.1, 0.9, -5.0], [2e-4, 1e-4, 1.0]])]
    for k, H in enumerate(Hs, start=2):
        cv2.imwrite(str(seq / f'img{k}.ppm'), cv2.warpPerspective(ref, H, (240, 180)))
        (seq / f'H1to{k}p').write_text('\n'.join(' '.join(map(str, r)) for r in H))
    out = tmp_path / 'out'
    assert cli(['homography', '--dataset', str(tmp_path / 'ds'), '--methods', 'sift_nn,orb_nn',
                '--out', str(out), '--figures', '1', '--no-progress']) == 0
    res = _load(out)
    assert res['n_pairs'] == 2
    s = res['methods']['sift_nn']['summary']
    assert s['homography_accuracy']['5'] == 1.0  # an exact warp: SIFT recovers H well
    assert s['inlier_ratio_verified'] > 0.9


def test_bad_inputs_one_line_and_nonzero(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    def run(args: list[str]) -> tuple[int, str]:
        rc = cli(args + ['--out', str(tmp_path / 'o'), '--no-progress'])
        err = capsys.readouterr().err
        return rc, err

    empty = tmp_path / 'empty'
    empty.mkdir()
    rc, err = run(['transforms', '--images', str(empty), '--pairs', '1'])
    assert rc == 1 and err.count('\n') == 1 and 'no images' in err

    bad = tmp_path / 'bad'
    bad.mkdir()
    (bad / 'x.png').write_bytes(b'this is not a png')
    rc, err = run(['transforms', '--images', str(bad), '--pairs', '1'])
    assert rc == 1 and err.count('\n') == 1 and 'x.png' in err

    trunc = tmp_path / 'trunc'
    trunc.mkdir()
    ok, buf = cv2.imencode('.png', texture(60, 80, 0))
    (trunc / 't.png').write_bytes(buf.tobytes()[:200])  # valid signature, truncated data
    rc, err = run(['transforms', '--images', str(trunc), '--pairs', '1'])
    assert rc == 1 and err.count('\n') == 1 and 't.png' in err

    seq = tmp_path / 'seq'
    seq.mkdir()
    for k in (1, 2):
        cv2.imwrite(str(seq / f'img{k}.ppm'), texture(40, 50, k))
    rc, err = run(['homography', '--dataset', str(seq)])
    assert rc == 1 and err.count('\n') == 1 and 'missing homography file' in err
    assert 'H1to2p' in err

    bag = write_image_bag(tmp_path / 'bag', '/cam', [texture(30, 40, 0)])
    rc, err = run(['transforms', '--bag', str(bag), '--topic', '/nope', '--pairs', '1'])
    assert rc == 1 and err.count('\n') == 1 and 'topic /nope not in bag' in err

    rc, err = run(['transforms', '--images', str(seq), '--methods', 'sift_nn,magic'])
    assert rc == 2 and err.count('\n') == 1 and 'magic' in err
    rc, err = run(['transforms', '--images', str(seq), '--bag', str(bag)])
    assert rc == 2 and err.count('\n') == 1
    rc, err = run(['transforms', '--images', str(seq), '--pairs', '0'])
    assert rc == 1 and '--pairs' in err


def test_transforms_gt_keypoints_and_labels(tmp_path: Path,
                                            capsys: pytest.CaptureFixture) -> None:
    imgs = _folder(tmp_path)
    gtk = tmp_path / 'gtk'
    gtk.mkdir()
    labels = tmp_path / 'labels'
    labels.mkdir()
    for k in range(2):
        gray = cv2.cvtColor(cv2.imread(str(imgs / f'im{k}.png')), cv2.COLOR_BGR2GRAY)
        corners = cv2.goodFeaturesToTrack(gray, 100, 0.05, 5).reshape(-1, 2)
        np.savetxt(gtk / f'im{k}.txt', corners)
        cv2.imwrite(str(labels / f'im{k}.png'), np.full(gray.shape, 6, np.uint8))
    out = tmp_path / 'out'
    assert cli(['transforms', '--images', str(imgs), '--pairs', '2', '--methods', 'sift_nn',
                '--gt-keypoints', str(gtk), '--labels', str(labels), '--out', str(out),
                '--figures', '0', '--no-progress']) == 0
    s = _load(out)['methods']['sift_nn']['summary']
    assert s['n_gt_keypoint_recall'] == 2
    assert 0.0 < s['gt_keypoint_recall'] <= s['gt_keypoint_detection'] <= 1.0
    (labels / 'im1.png').unlink()
    rc = cli(['transforms', '--images', str(imgs), '--pairs', '2', '--methods', 'sift_nn',
              '--labels', str(labels), '--out', str(out), '--no-progress'])
    err = capsys.readouterr().err
    assert rc == 1 and 'no label image im1.png' in err
