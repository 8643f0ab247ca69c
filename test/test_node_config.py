"""Shipped node parameter files and docs match the typed configs; parameters declare right."""
from __future__ import annotations

import yaml

from semfeat_ros.nodes.params import check_value, describe
from semfeat_ros.tools import node_config


def test_shipped_files_are_generated_from_configs() -> None:
    for path, text in node_config.expected_files().items():
        assert path.is_file(), f'{path} missing: run python -m semfeat_ros.tools.node_config'
        assert path.read_text() == text, f'{path} is stale: run the generator'


def test_yaml_is_a_ros_params_file() -> None:
    for node in node_config.NODES:
        data = yaml.safe_load(node_config.render_yaml(node))
        params = data[node]['ros__parameters']
        assert set(params) == {i.name for i in describe(node_config.config_class(node))}


def test_ranges_and_choices_are_checked() -> None:
    infos = {i.name: i for i in describe(node_config.config_class('feature_node'))}
    assert check_value(infos['max_keypoints'], 100) is None
    assert 'outside' in check_value(infos['max_keypoints'], 10**6)
    assert 'not one of' in check_value(infos['input_transport'], 'h264')
