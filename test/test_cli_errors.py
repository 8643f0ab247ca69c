"""The offline tools on broken input: one line on stderr, a non-zero exit, no traceback, and
success messages that name only the files written."""
from __future__ import annotations

from pathlib import Path
import sys

from conftest import REPO
import pytest

sys.path.insert(0, str(Path(__file__).parent / 'helpers'))
from bagcraft import craft  # noqa: E402

BAG = REPO / 'bags' / 'garage_ramp_seed0'


@pytest.fixture(scope='module')
def broken_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp('broken')
    garbage = d / 'garbage_metadata'
    garbage.mkdir()
    (garbage / 'metadata.yaml').write_text('rosbag2_bagfile_information: [\n  garbage: {')
    truncated = d / 'truncated'
    truncated.mkdir()
    (truncated / 'metadata.yaml').write_bytes((BAG / 'metadata.yaml').read_bytes())
    (truncated / 'garage_ramp_seed0.mcap').write_bytes(
        (BAG / 'garage_ramp_seed0.mcap').read_bytes()[:200_000])
    not_a_bag = d / 'notes.mcap'
    not_a_bag.write_text('hello\n')
    return {'garbage metadata': garbage, 'truncated mcap': truncated, 'not a bag': not_a_bag}


def one_error_line(err: str, prog: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'{prog}: error: '), err
    assert 'Traceback' not in err
    return lines[0]


@pytest.mark.parametrize('command', ['transforms', 'sequence'])
def test_eval_on_broken_bags_is_one_line(command: str, broken_bags: dict[str, Path],
                                         tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from semfeat_ros.tools.eval import cli

    for what, bag in broken_bags.items():
        rc = cli([command, '--bag', str(bag), '--out', str(tmp_path / 'out')])
        line = one_error_line(capsys.readouterr().err, 'semfeat-eval')
        assert rc == 1, (what, line)
        assert str(bag) in line, line


@pytest.fixture(scope='module')
def undecodable_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp('undecodable') / 'bag'
    counts = craft(BAG, bag, seconds=1.0, corrupt_all=True)
    assert counts['frames'] >= 5
    return bag


def test_map_fails_when_no_frame_decodes(undecodable_bag: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture) -> None:
    from semfeat_ros.tools import map as tool

    rc = tool.cli([str(undecodable_bag), '--out', str(tmp_path / 'map'), '--frontend', 'orb',
                   '--quiet', '--no-figures'])
    line = one_error_line(capsys.readouterr().err, 'semfeat-map')
    assert rc == 1 and 'no frame' in line and 'rejected' in line, line
    assert not (tmp_path / 'map' / 'cloud.ply').exists()


def test_features_fails_when_no_frame_decodes(undecodable_bag: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture) -> None:
    from semfeat_ros.tools import features as tool

    out = tmp_path / 'features'
    rc = tool.cli([str(undecodable_bag), '--out', str(out), '--quiet'])
    line = one_error_line(capsys.readouterr().err, 'semfeat-features')
    assert rc == 1 and 'no frame' in line, line
    assert not out.exists()


def test_map_lists_only_the_files_it_wrote(tmp_path: Path,
                                           capsys: pytest.CaptureFixture) -> None:
    from semfeat_ros.offline.report import FILES
    from semfeat_ros.tools import map as tool

    out = tmp_path / 'map'
    rc = tool.cli([str(BAG), '--out', str(out), '--frontend', 'orb', '--quiet', '--no-figures',
                   '--max-frames', '12'])
    said = capsys.readouterr().out.splitlines()[0]
    assert rc == 0, said
    written = sorted(p.name for p in out.iterdir())
    assert written == sorted(v for k, v in FILES.items() if not k.startswith('figure'))
    for name in FILES.values():
        assert (name in said) == (name in written), said


def test_eval_names_only_the_outputs_written(tmp_path: Path) -> None:
    from semfeat_ros.tools.eval import written_summary

    (tmp_path / 'results.json').write_text('{}')
    (tmp_path / 'results.md').write_text('')
    (tmp_path / 'matches').mkdir()  # created, but no figure drawn (--figures 0)
    said = written_summary(tmp_path)
    assert 'results.json' in said and 'results.md' in said
    assert 'chart' not in said and 'matches' not in said
    (tmp_path / 'recall.png').write_bytes(b'')
    (tmp_path / 'matches' / 'a_000.png').write_bytes(b'')
    assert '1 charts (recall.png)' in written_summary(tmp_path)
    assert '1 match figures' in written_summary(tmp_path)
