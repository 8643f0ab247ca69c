"""semfeat-report: results tables rewritten in place from evaluation outputs."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from semfeat_ros.tools.errors import ReportInputError, ReportManifestError, ReportOutputError
from semfeat_ros.tools.report import cli, main

REPO = Path(__file__).resolve().parents[1]

MANIFEST = {
    'doc': 'docs/R.md',
    'sources': {
        'real': {'dir': 'out/real', 'command': 'semfeat-eval transforms --out {dir}'},
        'map': {'dir': 'out/map', 'command': 'semfeat-map bags/b --out {dir}'},
    },
    'tables': {
        'real': {
            'prefix': 'methods.{method}.summary',
            'label_header': 'method',
            'columns': [
                {'header': 'recall %', 'metric': 'keypoint_recall', 'scale': 100},
                {'header': 'MMA@3px %', 'metric': 'mma@3', 'scale': 100},
                {'header': 'H acc %', 'metric': 'homography_accuracy', 'scale': 100},
                {'header': 'verified', 'metric': 'n_verified', 'format': '.0f'},
            ],
            'rows': [{'label': 'SIFT + NN', 'source': 'real', 'method': 'sift_nn'},
                     {'label': 'semfeat + NN', 'source': 'real', 'method': 'semfeat_nn'}],
        },
        'map': {
            'file': 'metrics.json',
            'label_header': 'run',
            'columns': [{'header': 'ATE m', 'metric': 'trajectory.ate_m', 'format': '.3f'}],
            'rows': [{'label': 'bag', 'source': 'map'}],
        },
    },
}

DOC = """# Results

Prose before, kept as written.

<!-- semfeat-report:real -->
<!-- /semfeat-report -->

Prose between.

<!-- semfeat-report:map -->
old text
<!-- /semfeat-report -->

Prose after.
"""


def summary(recall: float, verified: float) -> dict:
    return {'summary': {'keypoint_recall': recall, 'n_verified': verified,
                        'mma': [0.1, 0.2, 0.3, 0.4], 'mma_thresholds_px': [1, 2, 3, 4],
                        'homography_accuracy': {'1': 0.5, '3': 0.75, '5': 1.0}}}


@pytest.fixture
def project(tmp_path: Path) -> Path:
    (tmp_path / 'out/real').mkdir(parents=True)
    (tmp_path / 'out/map').mkdir(parents=True)
    (tmp_path / 'out/real/results.json').write_text(json.dumps(
        {'methods': {'sift_nn': summary(0.7612, 457.9), 'semfeat_nn': summary(0.6458, 351.6),
                     'xfeat_nn': summary(0.9, 1.0)}}))
    (tmp_path / 'out/map/metrics.json').write_text(json.dumps({'trajectory': {'ate_m': 0.0879}}))
    (tmp_path / 'docs').mkdir()
    (tmp_path / 'docs/R.md').write_text(DOC)
    (tmp_path / 'report.yaml').write_text(yaml.safe_dump(MANIFEST, sort_keys=False))
    return tmp_path


def run(project: Path, *args: str) -> int:
    return cli(['--manifest', str(project / 'report.yaml'), '--root', str(project), *args])


def test_round_trip_generate_check_edit(project: Path, capsys: pytest.CaptureFixture[str]
                                        ) -> None:
    doc = project / 'docs/R.md'
    assert run(project, '--check') == 1  # the blocks are empty: they differ from the inputs
    assert 'real, map' in capsys.readouterr().err
    assert doc.read_text() == DOC  # --check writes nothing
    assert run(project) == 0
    text = doc.read_text()
    assert '| SIFT + NN | 76.1 | 30.0 | 50.0/75.0/100.0 | 458 |' in text
    assert '| semfeat + NN | 64.6 | 30.0 | 50.0/75.0/100.0 | 352 |' in text
    assert '| bag | 0.088 |' in text and 'old text' not in text
    assert 'xfeat' not in text  # the manifest selects the methods
    assert '`out/real/results.json`: `semfeat-eval transforms --out out/real`' in text
    for prose in ('Prose before, kept as written.\n', '\nProse between.\n', '\nProse after.\n'):
        assert prose in text
    assert text.startswith('# Results\n') and text.endswith('Prose after.\n')
    assert run(project, '--check') == 0
    assert run(project) == 0 and doc.read_text() == text  # idempotent
    doc.write_text(text.replace('| 64.6 |', '| 64.7 |'))  # a hand edit of one number
    capsys.readouterr()
    assert run(project, '--check') == 1
    assert 'tables differ from their inputs: real (run' in capsys.readouterr().err
    results = project / 'out/real/results.json'
    data = json.loads(results.read_text())
    data['methods']['sift_nn']['summary']['n_verified'] = 500.0  # new results on disk
    results.write_text(json.dumps(data))
    assert run(project) == 0
    assert '| SIFT + NN | 76.1 | 30.0 | 50.0/75.0/100.0 | 500 |' in doc.read_text()
    assert '| semfeat + NN | 64.6 |' in doc.read_text()


def test_set_reads_a_source_from_another_directory(project: Path) -> None:
    (project / 'out/map2').mkdir()
    (project / 'out/map2/metrics.json').write_text(json.dumps({'trajectory': {'ate_m': 0.1}}))
    assert run(project, '--set', 'map=out/map2') == 0
    text = (project / 'docs/R.md').read_text()
    assert '| bag | 0.100 |' in text and 'semfeat-map bags/b --out out/map2' in text
    with pytest.raises(ReportManifestError, match="no source 'nope'"):
        main(project / 'report.yaml', root=project, overrides={'nope': 'x'})


def test_mean_of_row_averages_its_sources(project: Path) -> None:
    (project / 'out/map2').mkdir()
    (project / 'out/map2/metrics.json').write_text(json.dumps({'trajectory': {'ate_m': 0.1}}))
    spec = yaml.safe_load(yaml.safe_dump(MANIFEST, sort_keys=False))
    spec['sources']['map2'] = {'dir': 'out/map2', 'command': 'semfeat-map bags/c --out {dir}'}
    spec['tables']['map']['rows'].append({'label': 'mean', 'mean_of': ['map', 'map2']})
    (project / 'report.yaml').write_text(yaml.safe_dump(spec, sort_keys=False))
    assert run(project) == 0
    text = (project / 'docs/R.md').read_text()
    assert '| bag | 0.088 |\n| mean | 0.094 |' in text  # (0.0879 + 0.1) / 2
    assert '`out/map2/metrics.json`: `semfeat-map bags/c --out out/map2`' in text
    spec['tables']['map']['rows'][-1]['source'] = 'map'
    (project / 'report.yaml').write_text(yaml.safe_dump(spec, sort_keys=False))
    with pytest.raises(ReportManifestError, match='mean_of replaces source'):
        main(project / 'report.yaml', root=project)
    spec['tables']['map']['rows'][-1] = {'label': 'mean', 'mean_of': []}
    (project / 'report.yaml').write_text(yaml.safe_dump(spec, sort_keys=False))
    with pytest.raises(ReportManifestError, match='non-empty list of sources'):
        main(project / 'report.yaml', root=project)
    spec['tables']['map']['rows'][-1] = {'label': 'mean', 'mean_of': ['map', 'map2']}
    (project / 'report.yaml').write_text(yaml.safe_dump(spec, sort_keys=False))
    (project / 'out/map2/metrics.json').write_text(json.dumps({'trajectory': {'ate_m': 'x'}}))
    with pytest.raises(ReportInputError, match="mean_of needs numbers, got 'x'"):
        main(project / 'report.yaml', root=project)


def test_missing_input_is_one_line_and_non_zero(project: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert run(project, '--set', 'real=out/absent') == 1
    err = capsys.readouterr().err
    assert err.startswith('semfeat-report: error: table real, row ') and err.count('\n') == 1
    assert 'input directory out/absent (source real) not found' in err
    assert 'semfeat-eval transforms --out out/absent' in err
    assert (project / 'docs/R.md').read_text() == DOC
    (project / 'out/map/metrics.json').write_text('{}')
    with pytest.raises(ReportInputError, match=r'no value at trajectory\.ate_m'):
        main(project / 'report.yaml', root=project)


def test_manifest_and_markers_must_agree(project: Path) -> None:
    bad = yaml.safe_load(yaml.safe_dump(MANIFEST, sort_keys=False))
    bad['tables']['real']['rows'][0]['colour'] = 'red'
    (project / 'report.yaml').write_text(yaml.safe_dump(bad, sort_keys=False))
    with pytest.raises(ReportManifestError, match=r'tables\.real\.rows\[0\]\.colour'):
        main(project / 'report.yaml', root=project)
    (project / 'report.yaml').write_text(yaml.safe_dump(MANIFEST, sort_keys=False))
    doc = project / 'docs/R.md'
    doc.write_text(DOC.replace('semfeat-report:map', 'semfeat-report:other'))
    with pytest.raises(ReportManifestError, match='blocks without a table: other; tables '
                                                  'without a block: map'):
        main(project / 'report.yaml', root=project)
    doc.write_text(DOC + '<!-- semfeat-report:real -->\n')
    with pytest.raises(ReportManifestError, match='unbalanced'):
        main(project / 'report.yaml', root=project)
    (project / 'report.yaml').write_text('!!python/object/apply:os.system ["true"]\n')
    with pytest.raises(ReportManifestError, match='not valid YAML'):
        main(project / 'report.yaml', root=project)


def test_refuses_to_write_through_a_symlink(project: Path, tmp_path_factory: pytest.TempPathFactory
                                            ) -> None:
    outside = tmp_path_factory.mktemp('outside') / 'R.md'
    outside.write_text(DOC)
    doc = project / 'docs/R.md'
    doc.unlink()
    doc.symlink_to(outside)
    with pytest.raises(ReportOutputError, match='symbolic link'):
        main(project / 'report.yaml', root=project)
    assert outside.read_text() == DOC


def test_shipped_results_doc_matches_its_manifest() -> None:
    """docs/RESULTS.md's marker blocks are exactly the manifest's tables (the inputs under out/
    are not in the repository, so only the names are compared)."""
    manifest = yaml.safe_load((REPO / 'config/report.yaml').read_text())
    text = (REPO / manifest['doc']).read_text()
    blocks = [line.removeprefix('<!-- semfeat-report:').removesuffix(' -->')
              for line in text.splitlines() if line.startswith('<!-- semfeat-report:')]
    assert blocks == list(manifest['tables'])
    assert text.count('<!-- /semfeat-report -->') == len(blocks)
    named = {name for t in manifest['tables'].values() for row in t['rows']
             for name in [row.get('source'), *row.get('mean_of', []),
                          *row.get('sources', {}).values()] if name is not None}
    assert named and set(manifest['sources']) >= named
