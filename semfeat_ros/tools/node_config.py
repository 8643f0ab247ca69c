"""Write config/<node>.yaml and docs/PARAMETERS.md from the nodes' typed configs.

usage: python -m semfeat_ros.tools.node_config [--check]
With ``--check`` nothing is written; the exit code says whether the shipped files are current.
"""
from __future__ import annotations

import argparse
import importlib
from pathlib import Path
import sys

import yaml

from semfeat_ros.nodes.params import describe, to_yaml_dict

REPO = Path(__file__).resolve().parents[2]

NODES: dict[str, tuple[str, str]] = {
    'feature_node': ('semfeat_ros.nodes.feature_node', 'FeatureNodeConfig'),
    'matcher_node': ('semfeat_ros.nodes.matcher_node', 'MatcherNodeConfig'),
    'mapping_node': ('semfeat_ros.nodes.mapping_node', 'MappingNodeConfig'),
}


def config_class(node: str) -> type:
    module, name = NODES[node]
    return getattr(importlib.import_module(module), name)


def render_yaml(node: str) -> str:
    cls = config_class(node)
    head = (f'# Parameters of {node}; generated from {cls.__module__}.{cls.__name__} by\n'
            '# `python -m semfeat_ros.tools.node_config` (do not edit by hand).\n')
    return head + yaml.safe_dump(to_yaml_dict(node, cls), sort_keys=False, width=99)


def render_markdown() -> str:
    lines = ['# Node parameters', '',
             "Generated from the nodes' typed configs by "
             '`python -m semfeat_ros.tools.node_config`; the shipped `config/<node>.yaml` files '
             'come from the same source.', '']
    for node in NODES:
        lines += [f'## {node}', '', '| parameter | type | default | description |',
                  '| --- | --- | --- | --- |']
        for info in describe(config_class(node)):
            notes = []
            if info.range is not None:
                notes.append(f'range [{info.range[0]}, {info.range[1]}]')
            if info.choices:
                notes.append('one of ' + ', '.join(f'`{c}`' for c in info.choices))
            if info.read_only:
                notes.append('read-only')
            extra = f' ({"; ".join(notes)})' if notes else ''
            lines.append(f'| `{info.name}` | {info.type_name} | `{info.default!r}` | '
                         f'{info.description}{extra} |')
        lines.append('')
    return '\n'.join(lines)


def expected_files() -> dict[Path, str]:
    files = {REPO / 'config' / f'{node}.yaml': render_yaml(node) for node in NODES}
    files[REPO / 'docs' / 'PARAMETERS.md'] = render_markdown()
    return files


def cli(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true', help='only check, write nothing')
    args = parser.parse_args(argv)
    stale = [p for p, text in expected_files().items()
             if not p.is_file() or p.read_text() != text]
    if args.check:
        for p in stale:
            print(f'stale: {p.relative_to(REPO)}', file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(expected_files()[p])
        print(f'wrote {p.relative_to(REPO)}')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
