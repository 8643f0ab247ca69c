"""Training shards and the ``semfeat-sim`` command line."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from semfeat_ros.sim.dataset import (
    DatasetConfig,
    camera_from_json,
    camera_to_json,
    load_shard,
    parse_seeds,
    render_shard,
    save_shard,
)
from semfeat_ros.sim.errors import ShardError
from semfeat_ros.sim.groundtruth import warp_pixels
from semfeat_ros.tools.sim import cli


@pytest.fixture(scope='module')
def shard(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp('ds')
    assert cli(['dataset', '--out', str(out), '--seeds', '7', '--frames', '4', '--size',
                '96x80', '--corr', '64']) == 0
    return out / 'shard_00007.npz'


def test_shard_layout_and_correspondences(shard: Path) -> None:
    d = load_shard(shard)
    n = 4
    assert d['rgb'].shape == (n, 80, 96, 3) and d['rgb'].dtype == np.uint8
    assert d['label'].shape == (n, 80, 96) and d['depth'].dtype == np.float16
    assert d['instance'].dtype == np.uint16 and d['T_map_cam'].shape == (n, 4, 4)
    assert d['seed'] == 7 and d['camera_model'].width == 96
    assert d['pairs'].shape == (5, 2) and d['corr_uv_a'].shape == (5, 64, 2)
    cam = d['camera_model']
    for i, (a, b) in enumerate(d['pairs']):
        k = d['corr_count'][i]
        assert k > 0 and 0 < d['pair_overlap'][i] <= 1
        assert np.isnan(d['corr_uv_a'][i, k:]).all()
        ua, ub = d['corr_uv_a'][i, :k], d['corr_uv_b'][i, :k]
        # stored correspondences agree with a fresh occlusion-checked warp
        ref, ok = warp_pixels(ua, d['depth'][a].astype(np.float32), d['T_map_cam'][a],
                              d['T_map_cam'][b], cam, d['depth'][b].astype(np.float32))
        assert ok.mean() > 0.95
        np.testing.assert_allclose(ref[ok], ub[ok], atol=0.15)  # float16 depth rounding
        # never on a moving agent
        iu, iv = ua[:, 0].astype(int), ua[:, 1].astype(int)
        assert not np.isin(d['instance'][a][iv, iu], d['moving_instances']).any()


def test_shard_is_deterministic_and_validated(shard: Path, tmp_path: Path) -> None:
    d = load_shard(shard)
    again = render_shard(7, DatasetConfig(frames=4, size=(96, 80), corr_per_pair=64))
    assert np.array_equal(again['rgb'], d['rgb'])
    assert np.array_equal(again['corr_uv_b'], d['corr_uv_b'], equal_nan=True)
    broken = dict(again)
    broken['label'] = broken['label'][:, :-1]
    with pytest.raises(ShardError, match='label'):
        save_shard(tmp_path / 'bad.npz', broken)
    (tmp_path / 'junk.npz').write_bytes(b'not a zip')
    with pytest.raises(ShardError, match='not a readable'):
        load_shard(tmp_path / 'junk.npz')
    with pytest.raises(FileNotFoundError):
        load_shard(tmp_path / 'missing.npz')
    assert camera_from_json(camera_to_json(d['camera_model'])) == d['camera_model']


def test_parse_seeds() -> None:
    assert parse_seeds('3-5') == [3, 4, 5]
    assert parse_seeds('1,4') == [1, 4] and parse_seeds('9') == [9]
    for bad in ('5-3', 'x', '', '-2'):
        with pytest.raises(ShardError):
            parse_seeds(bad)


def test_cli_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(['--out', str(tmp_path / 'b'), '--config', str(tmp_path / 'nope.yaml')]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'nope.yaml' in err[0]
    (tmp_path / 'exists').mkdir()
    assert cli(['--out', str(tmp_path / 'exists'), '--duration', '0.1', '--size', '32x32',
                '--quiet']) == 2
    assert 'exists' in capsys.readouterr().err
    assert cli(['dataset', '--out', str(tmp_path / 'd'), '--seeds', 'a-b']) == 2
    assert 'seeds' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli(['--out', str(tmp_path / 'c'), '--size', '12x3'])


def test_cli_bag_info_and_preview(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(['--out', str(tmp_path / 'bag'), '--duration', '0.2', '--rate', '10',
                '--size', '64x48', '--start', 'ramp', '--quiet']) == 0
    assert (tmp_path / 'bag' / 'metadata.yaml').is_file()
    assert 'frames' in capsys.readouterr().out
    assert cli(['info', '--seed', '0']) == 0
    assert 'ramp' in capsys.readouterr().out
    png = tmp_path / 'sheet.png'
    assert cli(['preview', '--out', str(png), '--size', '96x80']) == 0
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] == 3 * 96
