"""The package is a correct ament_python package: a real colcon build, resolved like ros2 run."""
from __future__ import annotations

import ast
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import time

from catkin_pkg.package import parse_package
from conftest import REPO, ros_env
import pytest

PKG = 'semfeat_ros'
NODES = ('feature_node', 'matcher_node', 'mapping_node')


def console_scripts() -> list[str]:
    """Names of the console scripts declared in setup.py (parsed, not executed)."""
    tree = ast.parse((REPO / 'setup.py').read_text())
    for node in ast.walk(tree):
        targets = getattr(node, 'targets', None) or [getattr(node, 'target', None)]
        if any(getattr(t, 'id', None) == 'CONSOLE_SCRIPTS' for t in targets if t is not None):
            return [s.split('=')[0].strip() for s in ast.literal_eval(node.value)]
    raise AssertionError('CONSOLE_SCRIPTS not found in setup.py')


def test_package_xml_is_valid_format3() -> None:
    pkg = parse_package(str(REPO / 'package.xml'))  # raises InvalidPackage when malformed
    pkg.validate()
    assert pkg.name == PKG and pkg.package_format == 3
    assert pkg.get_build_type() == 'ament_python'
    deps = {d.name for d in pkg.exec_depends}
    assert {'rclpy', 'sensor_msgs', 'std_msgs', 'geometry_msgs', 'nav_msgs', 'diagnostic_msgs',
            'std_srvs'} <= deps


def test_top_level_layout() -> None:
    for path in ('package.xml', 'setup.py', 'setup.cfg', 'resource/semfeat_ros', 'semfeat_ros',
                 'msg_adapters', 'config', 'test', 'bags', 'README.md', '.ci/run'):
        assert (REPO / path).exists(), path
    cfg = (REPO / 'setup.cfg').read_text()
    assert 'install_scripts=$base/lib/semfeat_ros' in cfg
    assert 'script_dir=$base/lib/semfeat_ros' in cfg


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Build the package with colcon into a temporary workspace; return the install base."""
    ws = tmp_path_factory.mktemp('ws')
    colcon = shutil.which('colcon', path=str(Path(sys.executable).parent))
    assert colcon, 'colcon is part of the environment (requirements.txt)'
    proc = subprocess.run(
        [colcon, 'build', '--paths', str(REPO), '--build-base', str(ws / 'build'),
         '--install-base', str(ws / 'install'), '--event-handlers', 'console_direct-'],
        cwd=ws, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return ws / 'install'


def sourced_env(install: Path, domain: int) -> dict[str, str]:
    """The environment after ``. install/setup.sh``, as a ROS user would have it."""
    out = subprocess.run(['sh', '-c', f'. "{install}/setup.sh" && env -0'], env=ros_env(domain),
                         capture_output=True, timeout=60, check=True).stdout
    return dict(item.split('=', 1) for item in out.decode().split('\0') if '=' in item)


def test_colcon_install_layout(colcon_install: Path) -> None:
    prefix = colcon_install / PKG
    assert (prefix / 'share/ament_index/resource_index/packages' / PKG).is_file()
    assert (prefix / 'share' / PKG / 'package.xml').is_file()
    shipped = {p.name for p in (REPO / 'config').glob('*.yaml')}
    installed = {p.name for p in (prefix / 'share' / PKG / 'config').glob('*.yaml')}
    assert shipped and shipped <= installed
    # colcon treated it as an ament_python package: its environment hooks exist.
    assert (prefix / 'share' / PKG / 'package.dsv').is_file()
    for exe in console_scripts():
        path = prefix / 'lib' / PKG / exe
        assert path.is_file() and os.access(path, os.X_OK), exe


def test_ros2_run_resolution(colcon_install: Path) -> None:
    """Resolve every node as ``ros2 run`` does: ament index prefix + lib/<pkg>/<exe>."""
    env = sourced_env(colcon_install, 74)
    assert str(colcon_install / PKG) in env['AMENT_PREFIX_PATH'].split(os.pathsep)
    code = ('from ament_index_python.packages import get_package_prefix, '
            'get_package_share_directory as s; '
            f'print(get_package_prefix("{PKG}")); print(s("{PKG}"))')
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    assert out == [str(colcon_install / PKG), str(colcon_install / PKG / 'share' / PKG)]
    scripts = console_scripts()
    for node in NODES:
        assert node in scripts, f'{node} missing from setup.py console scripts'
        assert (Path(out[0]) / 'lib' / PKG / node).is_file()


def test_installed_node_comes_up(colcon_install: Path, tmp_path: Path) -> None:
    """Start the installed nodes from the install space: each logs 'ready', joins the graph and
    keeps running."""
    env = sourced_env(colcon_install, 75)
    files = {name: tmp_path / f'{name}.log' for name in NODES}
    procs = {}
    for name in NODES:
        with files[name].open('w') as log:  # a file, so the test can read it while it runs
            procs[name] = subprocess.Popen([str(colcon_install / PKG / 'lib' / PKG / name)],
                                           env=env, stdout=log, stderr=subprocess.STDOUT)
    probe = ('import rclpy, time\nrclpy.init()\nn = rclpy.create_node("probe")\n'
             f't = time.monotonic()\nwant = set({NODES!r})\n'
             'while time.monotonic() - t < 60 and not want <= set(n.get_node_names()):\n'
             '    rclpy.spin_once(n, timeout_sec=0.2)\n'
             'print("FOUND" if want <= set(n.get_node_names()) else "MISSING")\n')
    try:
        out = subprocess.run([sys.executable, '-c', probe], env=env, capture_output=True,
                             text=True, timeout=120).stdout
        # a node joins the graph before it is ready (feature_node readies the network first,
        # seconds on 2 busy cores): wait for every 'ready' line, or for a node to exit
        deadline = time.monotonic() + 90.0
        while time.monotonic() < deadline and not all(
                f'{name} ready' in files[name].read_text() or procs[name].poll() is not None
                for name in NODES):
            time.sleep(0.2)
        time.sleep(3.0)  # a node that fails right after start-up would be gone by now
        alive = {name: p.poll() is None for name, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    logs = {name: files[name].read_text() for name in NODES}
    for name in NODES:
        assert alive[name], logs[name]
        assert f'{name} ready' in logs[name], logs[name]
        assert procs[name].returncode == 0, logs[name]  # clean exit on Ctrl-C
    assert 'FOUND' in out, logs


class _Recorder:
    """Stand-in for a launch class: remembers its constructor arguments."""

    made: list[_Recorder] = []

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs
        _Recorder.made.append(self)


def _load_launch_file(share: Path) -> list[_Recorder]:
    """Execute launch/semfeat.launch.py with launch/launch_ros replaced by recorders."""
    import importlib.util
    import types

    fake = {}
    for mod, names in {
        'launch': ['LaunchDescription'],
        'launch.actions': ['DeclareLaunchArgument'],
        'launch.conditions': ['IfCondition', 'UnlessCondition'],
        'launch.substitutions': ['LaunchConfiguration', 'PathJoinSubstitution'],
        'launch_ros.actions': ['Node'],
        'launch_ros.parameter_descriptions': ['ParameterValue'],
        'launch_ros.substitutions': ['FindPackageShare'],
    }.items():
        m = types.ModuleType(mod)
        for n in names:
            setattr(m, n, type(n, (_Recorder,), {}))
        fake[mod] = m
    fake['launch_ros'] = types.ModuleType('launch_ros')
    saved = {k: sys.modules.get(k) for k in fake}
    sys.modules.update(fake)
    _Recorder.made = []
    try:
        spec = importlib.util.spec_from_file_location('semfeat_launch',
                                                      share / 'launch' / 'semfeat.launch.py')
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        module.generate_launch_description()
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    return _Recorder.made


def test_launch_file_names_installed_things(colcon_install: Path) -> None:
    """Every executable and parameter file the launch file names exists in the install."""
    share = colcon_install / PKG / 'share' / PKG
    made = _load_launch_file(share)
    nodes = [r for r in made if type(r).__name__ == 'Node' and r.kwargs['package'] == PKG]
    # the plain nodes unless managed:=true, their managed variants (same names) if it is
    by_condition = {}
    for n in nodes:
        cond = n.kwargs['condition']
        assert cond.args[0].args == ('managed',)
        by_condition.setdefault(type(cond).__name__, []).append(n)
    assert sorted(by_condition) == ['IfCondition', 'UnlessCondition']
    assert sorted(n.kwargs['executable'] for n in by_condition['UnlessCondition']) == \
        sorted(NODES)
    assert sorted(n.kwargs['executable'] for n in by_condition['IfCondition']) == \
        sorted(f'{name}_managed' for name in NODES)
    for group in by_condition.values():
        assert sorted(n.kwargs['name'] for n in group) == sorted(NODES)
    declared = {r.args[0] for r in made if type(r).__name__ == 'DeclareLaunchArgument'}
    assert {'namespace', 'use_sim_time', 'image_topic', 'camera_info_topic', 'odom_topic',
            'gnss_topic', 'input_transport', 'input_reliability', 'camera_config', 'output_dir',
            'rviz', 'managed'} <= declared
    for node in nodes:
        assert node.kwargs['namespace'].args == ('namespace',)
        # every LaunchConfiguration a node reads is a declared argument
        values = [v for p in node.kwargs['parameters'] if isinstance(p, dict)
                  for v in p.values()]
        used = {(v.args[0] if type(v).__name__ == 'ParameterValue' else v).args[0]
                for v in values}
        assert used <= declared, used - declared
        assert node.kwargs['package'] == PKG
        assert (colcon_install / PKG / 'lib' / PKG / node.kwargs['executable']).is_file()
        files = [p for p in node.kwargs['parameters'] if type(p).__name__ ==
                 'PathJoinSubstitution']
        assert len(files) == 1
        parts = files[0].args[0]
        assert parts[-1] == f'{node.kwargs["name"]}.yaml'
        assert (share / 'config' / parts[-1]).is_file()
    # the default config_dir is <share of semfeat_ros>/config
    config_arg = next(r for r in made if type(r).__name__ == 'DeclareLaunchArgument'
                      and r.args[0] == 'config_dir')
    default = config_arg.kwargs['default_value'].args[0]
    assert default[0].args == (PKG,) and default[1] == 'config'
    (rviz,) = [r for r in made if type(r).__name__ == 'Node' and r.kwargs['package'] == 'rviz2']
    assert rviz.kwargs['condition'].args[0].args == ('rviz',)
    path = rviz.kwargs['arguments'][1].args[0]
    assert (share / path[1] / path[2]).is_file()  # rviz/semfeat.rviz installed
