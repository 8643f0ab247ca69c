"""``semfeat-eval sequence --images``: a real image sequence without ground truth, scored by
proposed / verified matches; here on a tiny synthetic sequence written as PNGs."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_eval_cli import texture

from semfeat_ros.evaluation.datasets import list_images, read_visp_camera_xml
from semfeat_ros.evaluation.errors import CameraFileError
from semfeat_ros.evaluation.metrics import pair_metrics, verify_fundamental
from semfeat_ros.tools.eval import cli

VISP = Path('/usr/share/visp-images-data/ViSP-images')
N_FRAMES = 12
FRAME_W, FRAME_H = 320, 240


def canvas(seed: int = 0) -> np.ndarray:
    """A textured RGB image larger than a frame: the shapes of ``test_eval_cli.texture`` on
    blurred noise (corners and blobs for every detector)."""
    rng = np.random.default_rng(seed)
    h, w = 420, 540
    coarse = cv2.resize(rng.uniform(-70, 70, (h // 12, w // 12)), (w, h),
                        interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.uniform(-70, 70, (h, w)), (0, 0), 1.5)
    return np.clip(texture(h, w, seed) + (coarse + fine)[:, :, None], 0, 255).astype(np.uint8)


def write_sequence(folder: Path, n: int = N_FRAMES) -> Path:
    """Frames ``frame_<k>.png`` (unpadded numbers): the canvas moved 3 px right, 2 px down and
    rotated 0.4 deg about the frame centre per frame, cropped to 320x240 px."""
    folder.mkdir(parents=True, exist_ok=True)
    img = canvas()
    for k in range(n):
        centre = (60 + FRAME_W / 2, 50 + FRAME_H / 2)
        M = cv2.getRotationMatrix2D(centre, 0.4 * k, 1.0)
        M[:, 2] += [-60 + 3 * k, -50 + 2 * k]
        frame = cv2.warpAffine(img, M, (FRAME_W, FRAME_H), flags=cv2.INTER_LINEAR)
        cv2.imwrite(str(folder / f'frame_{k}.png'), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    return folder


def _run(args: list[str], out: Path) -> int:
    return cli(['sequence', *args, '--out', str(out), '--no-progress', '--figures', '1'])


def test_natural_order_and_frame_selection(tmp_path: Path) -> None:
    d = tmp_path / 'names'
    d.mkdir()
    png = cv2.imencode('.png', np.zeros((8, 8), np.uint8))[1].tobytes()
    for name in ('frame_10.png', 'frame_2.png', 'frame_1.png', 'mask_1.png'):
        (d / name).write_bytes(png)
    for name in ('depth_1.bin', 'notes.txt'):
        (d / name).write_bytes(b'not an image')
    natural = [p.name for p in list_images(d, pattern='frame_*', natural=True)]
    assert natural == ['frame_1.png', 'frame_2.png', 'frame_10.png']
    plain = [p.name for p in list_images(d, pattern='frame_*')]
    assert plain == ['frame_1.png', 'frame_10.png', 'frame_2.png']


def test_sift_verified_matches_land_in_json(tmp_path: Path,
                                           capsys: pytest.CaptureFixture) -> None:
    frames = write_sequence(tmp_path / 'seq')
    out = tmp_path / 'out'
    assert _run(['--images', str(frames), '--stride', '1', '--methods', 'sift_nn,orb_nn'],
                out) == 0
    table = capsys.readouterr().out
    assert 'Inlier Ratio = verified / proposed' in table
    res = json.loads((out / 'results.json').read_text())
    assert res['mode'] == 'sequence' and res['ground_truth'] is False
    assert res['n_pairs'] == N_FRAMES - 1
    assert 'USAC_MAGSAC' in res['verification']
    sift = res['methods']['sift_nn']
    assert sum(sift['verification_pairs'].values()) == N_FRAMES - 1
    names = [p['pair'] for p in sift['per_pair']]
    # Natural order: frame_9 -> frame_10 -> frame_11, never frame_1 -> frame_10.
    assert names == [f'frame_{k}-frame_{k + 1}' for k in range(N_FRAMES - 1)]
    for p in sift['per_pair']:
        assert p['n_verified'] <= p['n_matches']
        assert p['n_verified'] >= 100 and p['verified_ratio'] > 0.8
        assert 'keypoint_recall' not in p and 'inlier_ratio' not in p  # no ground truth
    s = sift['summary']
    assert s['n_verified'] == pytest.approx(np.mean([p['n_verified'] for p in sift['per_pair']]))
    assert s['verified_ratio'] > 0.8 and s['extract_ms'] > 0 and s['match_ms'] > 0
    assert res['methods']['orb_nn']['summary']['n_verified'] > 0
    assert (out / 'results.md').is_file() and (out / 'bars_matching.png').is_file()
    assert len(list((out / 'matches').glob('sift_nn_000_frame_0-frame_1.png'))) == 1


def test_stride_max_pairs_and_pinhole_essential(tmp_path: Path) -> None:
    frames = write_sequence(tmp_path / 'seq')
    out = tmp_path / 'out'
    assert _run(['--images', str(frames), '--stride', '3', '--max-pairs', '2', '--methods',
                 'sift_nn', '--pinhole', '300,300,159.5,119.5'], out) == 0
    res = json.loads((out / 'results.json').read_text())
    assert [p['pair'] for p in res['methods']['sift_nn']['per_pair']] == [
        'frame_0-frame_3', 'frame_3-frame_6']
    assert 'essential-matrix' in res['verification']
    assert res['methods']['sift_nn']['summary']['n_verified'] >= 100
    assert any('fx 300.00' in n for n in res['notes'])


def test_camera_xml_visp_formats(tmp_path: Path) -> None:
    tracker = tmp_path / 'tracker.xml'
    tracker.write_text('<?xml version="1.0"?>\n<conf><klt><quality>0.01</quality></klt>'
                       '<camera><px>615.5</px><py>615.25</py><u0>312.2</u0><v0>243.4</v0>'
                       '</camera></conf>\n')
    intr = read_visp_camera_xml(tracker)
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.k1) == (615.5, 615.25, 312.2, 243.4, 0.0)
    parser = tmp_path / 'camera.xml'
    parser.write_text('<root><camera><name>Camera</name><image_width>640</image_width>'
                      '<model><type>perspectiveProjWithDistortion</type><px>600</px>'
                      '<py>601</py><u0>320</u0><v0>240</v0><kud>-0.2</kud><kdu>0.21</kdu>'
                      '</model></camera></root>')
    intr = read_visp_camera_xml(parser)
    assert (intr.fx, intr.k1) == (600.0, -0.2)
    cam = intr.camera(640, 480)
    assert cam.D[0] == -0.2 and cam.fy == 601.0
    bad = tmp_path / 'bad.xml'
    bad.write_text('<conf><camera><px>600</px></camera></conf>')
    with pytest.raises(CameraFileError, match='no element'):
        read_visp_camera_xml(bad)
    bad.write_text('<conf><camera><px>a</px><py>1</py><u0>1</u0><v0>1</v0></camera></conf>')
    with pytest.raises(CameraFileError, match='non-numeric'):
        read_visp_camera_xml(bad)
    bad.write_text('<conf><camera>')
    with pytest.raises(CameraFileError, match='cannot parse'):
        read_visp_camera_xml(bad)


@pytest.mark.skipif(not (VISP / 'mbt-depth/castel/chateau.xml').is_file(),
                    reason='visp-images-data is not installed')
def test_visp_castel_intrinsics() -> None:
    intr = read_visp_camera_xml(VISP / 'mbt-depth/castel/chateau.xml')
    assert intr.fx == pytest.approx(615.1674804688) and intr.cy == pytest.approx(243.4373779297)


def test_fundamental_verification_rejects_outliers() -> None:
    rng = np.random.default_rng(3)
    K = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
    X = np.c_[rng.uniform(-2, 2, (200, 2)), rng.uniform(4, 9, 200)]
    a = (X / X[:, 2:]) @ K.T
    c, s = np.cos(0.05), np.sin(0.05)
    Xb = X @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + [0.4, 0.05, 0.1]
    b = (Xb / Xb[:, 2:]) @ K.T
    a, b = a[:, :2], b[:, :2] + rng.normal(0, 0.3, (200, 2))
    wrong = rng.choice(200, 60, replace=False)
    b[wrong] = rng.uniform([0, 0], [640, 480], (60, 2))
    inl, how = verify_fundamental(a, b, 2.0)
    truth = np.ones(200, bool)
    truth[wrong] = False
    assert 'USAC_MAGSAC' in how
    assert np.count_nonzero(inl & truth) >= 130 and np.count_nonzero(inl & ~truth) <= 6
    assert not verify_fundamental(a[:7], b[:7])[0].any()
    static, how = verify_fundamental(a, a + rng.normal(0, 0.05, a.shape), 2.0)
    assert static.sum() >= 190  # a pair where nothing moves is verified too


def test_pair_metrics_without_ground_truth() -> None:
    kp = np.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    m = pair_metrics(kp, kp, np.array([[0, 0], [1, 1], [2, 2]]), None,
                     verified=np.array([True, False, True]))
    assert m == {'n_kpts_a': 3, 'n_kpts_b': 3, 'n_matches': 3, 'n_verified': 2,
                 'verified_ratio': pytest.approx(2 / 3)}


def test_bad_inputs_one_line_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    def run(args: list[str]) -> tuple[int, str]:
        rc = _run(args, tmp_path / 'o')
        return rc, capsys.readouterr().err

    rc, err = run(['--images', str(tmp_path / 'nope')])
    assert rc == 1 and err.count('\n') == 1 and 'image folder not found' in err
    one = tmp_path / 'one'
    write_sequence(one, n=1)
    rc, err = run(['--images', str(one)])
    assert rc == 1 and err.count('\n') == 1 and 'at least 2' in err and 'frame_0.png' in err
    seq = write_sequence(tmp_path / 'seq', n=2)
    rc, err = run(['--images', str(seq), '--glob', 'image_*'])
    assert rc == 1 and err.count('\n') == 1 and "matching 'image_*'" in err
    rc, err = run(['--images', str(seq), '--stride', '2'])
    assert rc == 1 and err.count('\n') == 1 and 'too few for stride 2' in err
    rc, err = run(['--images', str(seq), '--pinhole', '300,300,900,100'])
    assert rc == 1 and err.count('\n') == 1 and 'principal point' in err
    rc, err = run(['--images', str(seq), '--camera-xml', str(tmp_path / 'none.xml')])
    assert rc == 1 and err.count('\n') == 1 and 'camera XML not found' in err
    rc, err = run(['--images', str(seq), '--pinhole', '300,300,100'])
    assert rc == 2 and err.count('\n') == 1 and 'fx,fy,cx,cy' in err
    rc, err = run(['--shard', str(tmp_path / 'x.npz'), '--pinhole', '300,300,100,100'])
    assert rc == 1 and err.count('\n') == 1 and 'apply to --images only' in err


def test_semfeat_glue_on_a_sequence(tmp_path: Path) -> None:
    """semfeat_lg (SemfeatGlue on the network's descriptors) in sequence mode with a pinhole:
    most of its matches pass the essential-matrix verification, matcher time is reported."""
    pytest.importorskip('kornia')
    frames = write_sequence(tmp_path / 'seq', n=4)
    out = tmp_path / 'out'
    assert _run(['--images', str(frames), '--stride', '1', '--methods', 'semfeat_nn,semfeat_lg',
                 '--pinhole', '300,300,159.5,119.5', '--max-features', '500'], out) == 0
    res = json.loads((out / 'results.json').read_text())
    assert 'essential-matrix' in res['verification']
    lg = res['methods']['semfeat_lg']
    assert lg['label'] == 'Ours (semfeat + SemfeatGlue)'
    assert [p['pair'] for p in lg['per_pair']] == [f'frame_{k}-frame_{k + 1}' for k in range(3)]
    for p in lg['per_pair']:
        assert p['n_verified'] >= 50 and p['verified_ratio'] > 0.8, p
    s, nn = lg['summary'], res['methods']['semfeat_nn']['summary']
    assert s['match_ms'] > 0 and s['extract_ms'] == nn['extract_ms']
