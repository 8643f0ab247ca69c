"""The demo's ``--param NODE.NAME=VALUE`` overrides: parsed against the nodes' typed configs and
passed to the node processes as ``-p name:=value``."""
from __future__ import annotations

from pathlib import Path

import pytest

from semfeat_ros.tools import demo
from semfeat_ros.tools.launcher import Pipeline, PipelineConfig


def test_params_reach_the_node_command_lines(tmp_path: Path) -> None:
    params = demo.parse_params(['feature_node.frontend=xfeat', 'matcher_node.matcher=learned',
                                'feature_node.max_keypoints=800'])
    assert params == {'feature_node': {'frontend': 'xfeat', 'max_keypoints': '800'},
                      'matcher_node': {'matcher': 'learned'}}
    pipe = Pipeline(PipelineConfig(output_dir=tmp_path, node_params=params))
    fargv = pipe.node_argv('feature_node')
    assert ['-p', 'frontend:=xfeat'] == fargv[fargv.index('frontend:=xfeat') - 1:][:2]
    assert 'max_keypoints:=800' in fargv and 'matcher:=learned' not in fargv
    margv = pipe.node_argv('matcher_node')
    assert 'matcher:=learned' in margv and 'frontend:=xfeat' not in margv
    assert not any(a.startswith(('frontend', 'matcher:=')) for a in pipe.node_argv('mapping_node'))


@pytest.mark.parametrize('item, message', [
    ('feature_node.frontend', 'NODE.NAME=VALUE'),
    ('frontend=xfeat', 'NODE.NAME=VALUE'),
    ('feature_node.frontend=', 'NODE.NAME=VALUE'),
    ('camera_node.rate=10', "unknown node 'camera_node'"),
    ('matcher_node.resize_max=320', "matcher_node has no parameter 'resize_max'"),
])
def test_a_bad_param_is_one_line_and_exit_1(item: str, message: str, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(demo.DemoError, match=message):
        demo.parse_params([item])
    assert demo.cli(['--out', str(tmp_path / 'demo'), '--param', item]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith('semfeat demo: ') and '\n' not in err and message in err
    assert not (tmp_path / 'demo').exists()  # nothing started, nothing written
