"""Every module of the package imports, and the architecture boundaries hold."""
from __future__ import annotations

import ast
import importlib
import pkgutil
import re

from conftest import REPO
import pytest

PACKAGES = ('semfeat_ros', 'msg_adapters')


def all_modules() -> list[str]:
    names = []
    for top in PACKAGES:
        pkg = importlib.import_module(top)
        names.append(top)
        names += [m.name for m in pkgutil.walk_packages(pkg.__path__, prefix=f'{top}.')]
    return sorted(names)


@pytest.mark.parametrize('module', all_modules())
def test_module_imports(module: str) -> None:
    importlib.import_module(module)


@pytest.mark.parametrize('lib,allowed', [
    ('rclpy', ('semfeat_ros/nodes/', 'semfeat_ros/tools/')),
    ('torch', ('semfeat_ros/model/',)),
    ('gtsam', ('semfeat_ros/mapping/',)),
])
def test_library_boundaries(lib: str, allowed: tuple[str, ...]) -> None:
    """rclpy only in nodes/tools, torch only in model, gtsam only in mapping
    (docs/ARCHITECTURE.md, Package boundaries)."""
    pattern = re.compile(rf'^\s*(import {lib}\b|from {lib}\b)', re.MULTILINE)
    offenders = []
    for top in PACKAGES:
        for path in (REPO / top).rglob('*.py'):
            rel = path.relative_to(REPO).as_posix()
            if pattern.search(path.read_text()) and not rel.startswith(allowed):
                offenders.append(rel)
    assert not offenders, f'{lib} imported outside {allowed}: {offenders}'


def test_no_private_names_imported_across_modules() -> None:
    """A name with a leading underscore stays in its module: what another module needs is
    public there (package code and tests alike)."""
    found = []
    for path in sorted([*REPO.glob('semfeat_ros/**/*.py'), *REPO.glob('msg_adapters/**/*.py'),
                        *REPO.glob('test/**/*.py')]):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split('.')[0] in (
                    'semfeat_ros', 'msg_adapters', 'conftest', 'helpers'):
                found += [f'{path.relative_to(REPO)}: {node.module}.{a.name}' for a in node.names
                          if a.name.startswith('_') and not a.name.startswith('__')]
    assert not found, found
