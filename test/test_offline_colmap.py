"""The COLMAP peer: pycolmap's SIFT + sequential matching + incremental mapping on bag frames.

Smoke test on 20 frames of the ramp (every 2nd frame from 8 s, 2000 SIFT features, one thread:
deterministic, ~10 s) plus argument and bad-input handling.
"""
from __future__ import annotations

import json
from pathlib import Path

from conftest import REPO
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from msg_adapters import stamp_to_ns
from semfeat_ros.mapping import read_tum
from semfeat_ros.tools import colmap_peer as tool

BAG = REPO / 'bags' / 'garage_ramp_seed0'
CAMERA = '/camera/front/image_raw/compressed'


def test_colmap_peer_smoke(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / 'colmap'
    rc = tool.cli([str(BAG), '--out', str(out), '--max-frames', '20', '--stride', '2',
                   '--start', '8', '--max-features', '2000', '--quiet'])
    assert rc == 0, capsys.readouterr().err
    m = json.loads((out / 'metrics.json').read_text())
    # frames exported under their header stamps (the recorded JPEG bytes)
    ts = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([BAG], default_typestore=ts) as reader:
        conns = [c for c in reader.connections if c.topic == CAMERA]
        start = reader.start_time + 8_000_000_000
        msgs = [reader.deserialize(raw, c.msgtype)
                for c, t, raw in reader.messages(connections=conns, start=start)][:40:2]
    names = sorted(p.name for p in (out / 'images').iterdir())
    assert names == sorted(f'{stamp_to_ns(msg)}.jpg' for msg in msgs)
    assert (out / 'images' / f'{stamp_to_ns(msgs[0])}.jpg').read_bytes() == bytes(msgs[0].data)
    assert m['frames'] == 20 and m['camera_model'] == 'OPENCV_FISHEYE'
    assert m['camera_params'].startswith('186.6666667,186.6666667,319.6666667,255.6666667,')
    assert set(m['wall_time_s']) >= {'extract_s', 'match_s', 'mapping_s', 'colmap_s'}
    assert m['registered_frames'] >= 10
    stamps, poses = read_tum(out / 'trajectory.tum')
    assert len(stamps) == m['registered_frames']
    assert {f'{s}.jpg' for s in stamps} <= set(names)
    # COLMAP on 20 frames of forward motion: ~0.8 m Sim(3) ATE over ~20 m (this run); the
    # bound catches a broken stamp/pose conversion (metres of error), not COLMAP's accuracy
    assert m['gt_length_m'] > 10.0
    assert m['ate_sim3_rmse_m'] < 2.0
    assert (out / 'trajectory_top.png').is_file() and (out / 'altitude.png').is_file()


def one_line_error(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and err.startswith('colmap_peer: error: '), err
    return err


def test_colmap_peer_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert tool.cli([str(tmp_path / 'nope'), '--out', str(tmp_path / 'o'), '--quiet']) == 1
    assert 'does not exist' in one_line_error(capsys)
    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--max-frames', '1']) == 1
    assert '--max-frames must be >= 2' in one_line_error(capsys)
    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--stride', '0']) == 1
    assert '--stride must be >= 1' in one_line_error(capsys)
    assert tool.cli([str(BAG), '--out', str(tmp_path / 'o'), '--topic', '/gnss/fix']) == 1
    assert 'expected sensor_msgs/msg/Image or' in one_line_error(capsys)
    used = tmp_path / 'used'
    used.mkdir()
    (used / 'database.db').write_bytes(b'')
    assert tool.cli([str(BAG), '--out', str(used), '--quiet']) == 1
    assert 'exists (an earlier run?)' in one_line_error(capsys)
    with pytest.raises(SystemExit):
        tool.cli([str(BAG)])  # --out is required (argparse usage error, exit 2)
