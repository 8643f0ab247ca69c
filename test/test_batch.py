"""semfeat-batch on a local Ray instance: three tiny rendered recordings, one of them corrupt.

One Ray instance serves the module (started by the ``ray_local`` fixture, which only these
tests request); the Ctrl-C test runs the tool in a subprocess with its own local Ray. The
recordings are 160x128 px, 1.5 s at 4 Hz (6 frames), and the network runs at resize_max 160
(feature_node and mapping_node parameter files written by the test, with the simulator's
topic names).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
import yaml

from semfeat_ros.offline.report import FILES as MAP_FILES
from semfeat_ros.tools import batch

TS = get_typestore(Stores.ROS2_JAZZY)
GOOD = ('drive_a', 'drive_b')
BROKEN = 'drive_broken'


@pytest.fixture(scope='module')
def ray_local() -> object:
    """A local Ray instance of 2 CPUs for the module, started as the tool starts its own; the
    tool runs on it instead of starting one."""
    with batch.ray_session(batch.BatchConfig(num_cpus=2)) as cluster:
        yield cluster


@pytest.fixture(scope='module')
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A folder with two rendered recordings and a corrupt one (its MCAP cut short), and a
    feature_node parameter file with a small network input."""
    from semfeat_ros.sim.bag import BagConfig, write_bag

    root = tmp_path_factory.mktemp('batch_in')
    rec = root / 'recordings'
    rec.mkdir()
    for seed, name in enumerate(GOOD, start=1):
        write_bag(rec / name, BagConfig(seed=seed, duration=1.5, rate=4.0, size=(160, 128),
                                        start=10.0, gnss_rate=2.0, odom_rate=20.0),
                  progress=False)
    broken = rec / BROKEN
    broken.mkdir()
    src = rec / GOOD[0]
    (broken / 'metadata.yaml').write_bytes((src / 'metadata.yaml').read_bytes())
    mcap = next(src.glob('*.mcap'))
    (broken / mcap.name).write_bytes(mcap.read_bytes()[:4000])
    params = {'image_topic': '/camera/front/image_raw',
              'camera_info_topic': '/camera/front/camera_info',
              'features_topic': '/semfeat/features', 'mask_topic': '/semfeat/semantic_mask',
              'resize_max': 160}  # the other parameters: feature_node's defaults
    conf = root / 'feature_node_small.yaml'
    conf.write_text(yaml.safe_dump({'feature_node': {'ros__parameters': params}}))
    mapping = root / 'mapping_node.yaml'
    mapping.write_text(yaml.safe_dump({'mapping_node': {'ros__parameters': {
        'odom_topic': '/vehicle/odom', 'gnss_topic': '/gnss/fix'}}}))
    return {'recordings': rec, 'feature_config': conf, 'mapping_config': mapping}


def args(inputs: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return [str(inputs['recordings']), '--out', str(out), '--quiet',
            '--feature-config', str(inputs['feature_config']),
            '--mapping-config', str(inputs['mapping_config']), *extra]


def summary(out: Path) -> tuple[dict, dict[str, dict]]:
    data = json.loads((out / 'summary.json').read_text())
    return data, {r['recording']: r for r in data['rows']}


@pytest.fixture(scope='module')
def runs(ray_local: object, inputs: dict[str, Path],
         tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The tool run twice on the same folder (the second run must skip finished work)."""
    out = tmp_path_factory.mktemp('batch_out') / 'out'
    rc1 = batch.cli(args(inputs, out))
    first = summary(out)
    md = (out / 'summary.md').read_text()
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob('*') if p.is_file()
              and not p.name.startswith('summary.')}
    rc2 = batch.cli(args(inputs, out))
    second = summary(out)
    return {'out': out, 'rc': (rc1, rc2), 'first': first, 'second': second, 'stamps': stamps,
            'first_md': md, 'second_md': (out / 'summary.md').read_text()}


def test_per_recording_outputs(runs: dict) -> None:
    out = runs['out']
    _, rows = runs['first']
    for name in GOOD:
        d = out / name
        assert {p.name for p in d.iterdir()} == {
            'features', 'map', 'eval', 'features.done.json', 'map.done.json',
            'eval.done.json'}
        # features/: the bag semfeat-features writes, one message per processed frame
        with AnyReader([d / 'features'], default_typestore=TS) as reader:
            counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts['/semfeat/features'] == counts['/semfeat/semantic_mask'] == 6
        assert counts['/camera/front/camera_info'] == 6
        # map/: semfeat-map's files, metrics of this recording with its ground truth
        assert {p.name for p in (d / 'map').iterdir()} == set(MAP_FILES.values())
        metrics = json.loads((d / 'map' / 'metrics.json').read_text())
        assert metrics['bag'] == rows[name]['bag']
        assert metrics['frames_read'] == 6 and metrics['has_ground_truth']
        # eval/: semfeat-eval sequence's results for both default methods, 5 pairs (i, i+1)
        results = json.loads((d / 'eval' / 'results.json').read_text())
        assert results['n_pairs'] == 5
        assert set(results['methods']) == set(batch.EVAL_METHODS)
        assert (d / 'eval' / 'results.md').is_file()
        marker = json.loads((d / 'map.done.json').read_text())
        assert marker['outcome']['status'] == 'ok'
        assert marker['outcome']['result']['keyframes'] == metrics['keyframes']
    # the corrupt recording left no step output behind
    assert not any((out / BROKEN).iterdir())
    assert rows[BROKEN]['status'] == 'failed'


def test_summary_rows_and_failure(runs: dict) -> None:
    out = runs['out']
    data, rows = runs['first']
    assert runs['rc'][0] == 1  # one recording failed
    assert data['counts'] == {'ok': 2, 'skipped': 0, 'failed': 1, 'interrupted': 0}
    assert data['tasks_run'] == 9 and not data['interrupted']
    assert data['cluster']['cpus_per_task'] == 1 and data['cluster']['concurrent_tasks'] == 2
    bad = rows[BROKEN]
    assert bad['error'].startswith('features: cannot open bag')
    assert 'broken or truncated' in bad['error'] and '\n' not in bad['error']
    assert {s: o['status'] for s, o in bad['steps'].items()} == dict.fromkeys(batch.STEPS,
                                                                               'failed')
    for name in GOOD:
        r = rows[name]
        metrics = json.loads((out / name / 'map' / 'metrics.json').read_text())
        assert r['status'] == 'ok' and r['error'] is None
        assert r['frames'] == 6 and 1.2 < r['duration_s'] < 1.6
        assert r['keyframes'] == metrics['keyframes'] >= 2
        assert r['ate_sim3_rmse_m'] == metrics['ate_sim3_rmse_m'] is not None
        assert r['points'] == metrics['cloud_points']
        assert r['floors'] == len(metrics['run']['cloud_per_floor'])
        assert r['eval_pairs'] == 5
        assert r['wall_s'] > 0 and r['peak_rss_mb'] > 100
    table = [ln for ln in runs['first_md'].splitlines() if ln.startswith('| drive')]
    assert [ln.split('|')[1].strip() for ln in table] == sorted((*GOOD, BROKEN))
    assert '| failed |' in table[-1] and 'cannot open bag' in table[-1]
    assert all('| ok |' in ln for ln in table[:2])


def test_tasks_ran_in_parallel(runs: dict) -> None:
    """Two task slots: some tasks of different recordings overlapped in time."""
    _, rows = runs['first']
    spans = [(o['started'], o['finished'], name) for name in GOOD
             for o in rows[name]['steps'].values()]
    overlaps = [(a, b) for a in spans for b in spans
                if a[2] < b[2] and a[0] < b[1] and b[0] < a[1]]
    assert overlaps


def test_second_run_skips_finished_work(runs: dict) -> None:
    data, rows = runs['second']
    assert runs['rc'][1] == 1
    assert data['counts'] == {'ok': 0, 'skipped': 2, 'failed': 1, 'interrupted': 0}
    assert data['tasks_run'] == 3  # the corrupt recording's steps only
    first = runs['first'][1]
    for name in GOOD:
        assert rows[name]['status'] == 'skipped'
        for key in ('frames', 'keyframes', 'ate_sim3_rmse_m', 'points', 'eval_pairs'):
            assert rows[name][key] == first[name][key]
    assert rows[BROKEN]['status'] == 'failed'
    table = [ln for ln in runs['second_md'].splitlines() if ln.startswith('| drive_')]
    assert all('| skipped |' in ln for ln in table[:2]) and '| failed |' in table[2]
    now = {p: p.stat().st_mtime_ns for p in runs['stamps']}
    assert now == runs['stamps']  # no output or marker rewritten


def test_step_without_marker_is_redone(runs: dict, inputs: dict[str, Path]) -> None:
    """A step whose marker is missing (an interrupted run) is run again, its old output first
    removed; the other steps stay skipped."""
    out = runs['out']
    (out / 'drive_b' / 'map.done.json').unlink()
    stale = out / 'drive_b' / 'map' / 'stale.txt'
    stale.write_text('left by an interrupted run\n')
    rc = batch.cli(args(inputs, out, '--steps', 'map'))
    data, rows = summary(out)
    assert rc == 1 and data['tasks_run'] == 2  # drive_b's map and the corrupt recording's
    assert rows['drive_b']['status'] == 'ok' and rows['drive_a']['status'] == 'skipped'
    assert rows['drive_b']['steps']['map']['status'] == 'ok'
    assert not stale.exists() and (out / 'drive_b' / 'map.done.json').is_file()
    assert {p.name for p in (out / 'drive_b' / 'map').iterdir()} == set(MAP_FILES.values())


@pytest.mark.parametrize('case,expected', [
    ('missing input', 'does not exist'),
    ('empty folder', 'holds no recording'),
    ('same name twice', 'would both write into'),
    ('unknown step', '--steps: expected'),
    ('out inside a recording', 'overlaps the recording'),
])
def test_bad_input_one_line_error(case: str, expected: str, inputs: dict[str, Path],
                                  tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rec = inputs['recordings']
    (tmp_path / 'empty').mkdir()
    argv = {
        'missing input': [str(tmp_path / 'nope'), '--out', str(tmp_path / 'o')],
        'empty folder': [str(tmp_path / 'empty'), '--out', str(tmp_path / 'o')],
        'same name twice': [str(rec / GOOD[0]), str(tmp_path / 'copy' / GOOD[0]),
                            '--out', str(tmp_path / 'o')],
        'unknown step': [str(rec), '--out', str(tmp_path / 'o'), '--steps', 'map,fly'],
        'out inside a recording': [str(rec / GOOD[0]), '--out', str(rec)],
    }[case]
    if case == 'same name twice':
        (tmp_path / 'copy' / GOOD[0]).mkdir(parents=True)
        (tmp_path / 'copy' / GOOD[0] / 'metadata.yaml').write_text('x: 1\n')
    assert batch.cli(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('semfeat-batch: error: ') and expected in err[0]
    assert not (tmp_path / 'o').exists()


def processes() -> dict[int, tuple[int, str, bytes]]:
    """Live processes (not zombies): pid -> (parent pid, command line, environment)."""
    found = {}
    for d in Path('/proc').glob('[0-9]*'):
        try:
            fields = (d / 'stat').read_text().rsplit(')', 1)[1].split()
            cmd = (d / 'cmdline').read_bytes().replace(b'\0', b' ').decode(errors='replace')
            env = (d / 'environ').read_bytes()
        except (OSError, IndexError):
            continue
        if fields[0] != 'Z':
            found[int(d.name)] = (int(fields[1]), cmd, env)
    return found


def started_by(root: int, tag: str, procs: dict[int, tuple[int, str, bytes]]) -> set[int]:
    """Pids below ``root`` or carrying ``BATCH_TEST_TAG=tag`` in their environment (a worker
    that renamed itself may have overwritten its environment block, hence both)."""
    mark = f'BATCH_TEST_TAG={tag}'.encode()
    found = {p for p, (_, _, env) in procs.items() if mark in env.split(b'\0')}
    todo = [root]
    while todo:
        parent = todo.pop()
        for p, (ppid, _, _) in procs.items():
            if ppid == parent and p not in found:
                found.add(p)
                todo.append(p)
    found.discard(root)
    return found


@pytest.mark.parametrize('when', ['starting', 'running'])
def test_ctrl_c_leaves_no_process(when: str, inputs: dict[str, Path], tmp_path: Path) -> None:
    """SIGINT while Ray starts (its agents are up, ray.init has not returned) or while tasks
    run: exit 130, the summary says interrupted, and no process the tool started (Ray's
    services, agents and workers) is left."""
    out = tmp_path / 'out'
    tag = f'{os.getpid()}-{when}-{time.monotonic_ns()}'
    proc = subprocess.Popen([sys.executable, '-m', 'semfeat_ros.tools.batch',
                             *args(inputs, out, '--steps', 'features', '--num-cpus', '1')],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, 'PYTHONUNBUFFERED': '1', 'BATCH_TEST_TAG': tag},
                            preexec_fn=_default_sigint)
    ready = 'ray::DashboardAgent' if when == 'starting' else 'ray::features:'
    seen: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            procs = processes()
            seen |= started_by(proc.pid, tag, procs)
            if any(procs[p][1].startswith(ready) for p in seen if p in procs):
                break
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.1)
        else:
            pytest.fail(f'no {ready} process within 60 s')
        proc.send_signal(signal.SIGINT)
        while proc.poll() is None and time.monotonic() < deadline + 60:
            seen |= started_by(proc.pid, tag, processes())
            time.sleep(0.1)
        _, err = proc.communicate(timeout=5)
    finally:
        if proc.poll() is None:  # the test failed: end the tool and what it started
            seen |= started_by(proc.pid, tag, processes())
            proc.kill()
            proc.wait()
            for pid in seen & set(processes()):
                os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert 'interrupted' in err
    deadline = time.monotonic() + 15
    while True:
        procs = processes()
        left = (seen & set(procs)) | started_by(-1, tag, procs)
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    for pid in left:  # left by the tool: end them so that a failure here leaves none behind
        os.kill(pid, signal.SIGKILL)
    assert not left, [procs[p][1] for p in left]
    data, rows = summary(out)
    assert data['interrupted'] and data['counts']['ok'] < 2
    assert {r['status'] for r in rows.values()} <= {'interrupted', 'ok', 'failed'}


def _default_sigint() -> None:
    """Ctrl-C's default action in the child (a shell's background job inherits it ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
