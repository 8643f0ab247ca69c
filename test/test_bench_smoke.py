"""Smoke test of ``semfeat-bench`` on a few frames (plumbing only: never asserts a speed)."""
from __future__ import annotations

import json
import os
from pathlib import Path
import time

import numpy as np
import pytest

from semfeat_ros.bench import frames, machine, stages, stats
from semfeat_ros.labels import load_labels
from semfeat_ros.model.semfeatnet import SemFeatNet
from semfeat_ros.model.weights_io import save_weights
from semfeat_ros.tools import bench

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def untrained_weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import torch

    torch.manual_seed(0)
    return save_weights(SemFeatNet(), tmp_path_factory.mktemp('w') / 'untrained.safetensors',
                        {'class_names': list(load_labels().names), 'input_size': [640, 512]})


def test_statistics_helpers() -> None:
    s = stats.summarize([1.0, 2.0, 3.0, 4.0, 100.0])
    assert s['n'] == 5 and s['p50'] == 3.0 and 4.0 < s['p95'] < 100.0
    assert stats.summarize([])['p50'] is None
    assert stats.ratio(6.0, 3.0) == 2.0 and stats.ratio(1.0, 0.0) is None
    assert stats.ratio(None, 1.0) is None
    x = np.array([1.0, 1.0, 50.0, 1.0, 1.0, 2.0, 2.0])
    assert np.allclose(stats.rolling_median(x, 3), [1, 1, 1, 1, 1, 2, 2])
    assert stats.rolling_median(x, 1).tolist() == x.tolist()
    edge = stats.rolling_median(np.array([316.0, 18.0, 18.0, 18.0, 20.0]), 5)
    assert edge.tolist() == [18.0, 18.0, 18.0, 18.0, 18.0]  # shrinking window at the ends
    t = np.linspace(0.0, 10.0, 21)
    assert stats.linear_slope(t, 3.0 * t + 7.0) == pytest.approx(3.0)
    assert stats.linear_slope(np.ones(4), np.arange(4.0)) is None


def test_proc_sampler_reads_this_process() -> None:
    cpu0, rss = machine.read_proc(os.getpid())
    assert cpu0 > 0.0 and rss > 10.0
    with machine.ProcSampler(period_s=0.05) as sampler:
        t_end = time.perf_counter() + 0.3
        while time.perf_counter() < t_end:  # keep one core busy
            np.sort(np.random.default_rng(0).random(20_000))
    assert len(sampler.t_s) >= 3
    assert len(sampler.rss_mb) == len(sampler.cpu_pct) == len(sampler.t_s)
    assert all(r > 10.0 for r in sampler.rss_mb)
    assert max(sampler.cpu_pct) > 0.0
    with pytest.raises(OSError):
        machine.read_proc(2 ** 22 + 12345)  # above the kernel's pid_max


def test_forward_variants_tiny(untrained_weights: Path) -> None:
    res = stages.measure_forward(str(untrained_weights), (64, 64), repeats=1, warmup=0)
    assert set(res) == {'fp32', 'fp32_fused_channels_last', 'bf16_channels_last', 'onnxruntime'}
    assert all(v > 0.0 for v in res.values())


def test_wrong_bag_is_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    doc = tmp_path / 'docs' / 'BENCHMARKS.md'
    rc = bench.cli(['--bag', str(tmp_path / 'no_such_bag'), '--out', str(tmp_path / 'out'),
                    '--doc', str(doc), '--quick', '--quiet'])
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert len(err.splitlines()) == 1 and err.startswith('semfeat-bench: error:')
    assert 'no_such_bag' in err
    assert not doc.exists() and not (tmp_path / 'out').exists()


def test_bad_option_is_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rc = bench.cli(['--out', str(tmp_path / 'out'), '--doc', str(tmp_path / 'B.md'),
                    '--frames', '1', '--quiet'])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and len(err.splitlines()) == 1 and '--frames' in err


def test_doc_directory_is_rejected(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rc = bench.cli(['--out', str(tmp_path / 'out'), '--doc', str(tmp_path), '--quick',
                    '--quiet'])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and len(err.splitlines()) == 1 and '--doc' in err
    assert not (tmp_path / 'out').exists()


def test_cli_smoke_writes_document_figures_and_results(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, untrained_weights: Path) -> None:
    monkeypatch.chdir(tmp_path)
    out = tmp_path / 'bench_out'
    doc = tmp_path / 'docs' / 'BENCHMARKS.md'
    argv = ['--out', str(out), '--doc', str(doc), '--weights', str(untrained_weights),
            '--frames', '3', '--hires-frames', '2', '--hires-size', '160x128',
            '--e2e-frames', '3', '--soak-minutes', '0.02', '--keyframes', '10',
            '--warmup', '0', '--forward-repeats', '0', '--quiet']
    assert bench.cli(argv) == 0
    # outputs stay inside --out and next to --doc
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bench_out', 'docs']
    assert sorted(p.name for p in (tmp_path / 'docs').iterdir()) == ['BENCHMARKS.md', 'img']
    pngs = sorted((tmp_path / 'docs' / 'img').iterdir())
    assert [p.name for p in pngs] == ['bench_isam2.png', 'bench_soak.png', 'bench_stages.png']
    assert all(p.read_bytes()[:8] == PNG_MAGIC for p in pngs)
    assert sorted(p.name for p in out.iterdir()) == ['frames_160x128', 'results.json']

    res = json.loads((out / 'results.json').read_text())
    assert list(res['stages']) == ['640x512', '160x128']
    for name, st in res['stages'].items():
        assert st['samples'] == 3
        s = st['stats']
        for fe in stages.FRONTENDS:
            for stage in ('decode', 'features', 'total'):
                assert s[fe][stage]['n'] >= 1 and s[fe][stage]['p50'] > 0.0, (name, fe, stage)
        assert s['semfeat']['network']['p50'] > 0.0 and s['semfeat']['post']['n'] == 3
        # the ratios are the ratios of the medians written next to them
        assert st['ratios']['total']['orb'] == pytest.approx(
            s['semfeat']['total']['p50'] / s['orb']['total']['p50'])
        assert st['ratios']['features']['sift'] == pytest.approx(
            s['semfeat']['features']['p50'] / s['sift']['features']['p50'])
        assert st['ratios']['total']['xfeat'] == pytest.approx(
            s['semfeat']['total']['p50'] / s['xfeat']['total']['p50'])
        assert 'network' not in s['xfeat']  # XFeat's own extract, without the network
        assert st['counts']['xfeat']['keypoints'] > 0
    e2e = res['end_to_end']
    assert set(e2e) == set(stages.FRONTENDS)
    assert all(e2e[fe]['frames'] == 3 and e2e[fe]['sustained_hz'] > 0 for fe in e2e)
    assert e2e['xfeat']['description'].startswith('XFeat')
    assert 'labels from the segmentation' in e2e['xfeat']['description']
    assert 'labels from' not in e2e['sift']['description']
    soak = res['soak']
    assert soak['frames'] >= 1 and soak['samples'] >= 2
    assert len(soak['series']['rss_mb']) == soak['samples']
    assert len(soak['series']['frame_ms']) == len(soak['series']['frame_t_min']) >= 1
    assert 'frame_ms_slope_after_warmup_per_min' in soak
    assert res['isam2']['keyframes'] >= 9
    assert 'forward' not in res
    assert res['machine']['load_average_end'] and res['machine']['usable_cpus'] >= 1

    text = doc.read_text()
    for needle in ('# Benchmarks', '## Machine', '### 640x512', '### 160x128',
                   '### Ratios', '## End-to-end sustained rate', '## Soak',
                   '## iSAM2 update time', 'img/bench_isam2.png', 'img/bench_soak.png',
                   'frame time slope',
                   'semfeat-bench --out'):
        assert needle in text, needle
    p50 = res['stages']['640x512']['stats']['orb']['features']['p50']
    assert f'{p50:.1f}' in text  # the document carries the measured numbers
    # the XFeat baseline: a column pair in every stage table, a ratio column, an end-to-end row
    assert text.count('| XFeat p50 | XFeat p95 |') == 2
    assert '| 640x512 / XFeat |' in text and '| 160x128 / XFeat |' in text
    xrow = next(line for line in text.splitlines() if line.startswith('| xfeat | '))
    assert xrow.split(' | ')[1] == f'{e2e["xfeat"]["sustained_hz"]:.2f}'
    xp50 = res['stages']['640x512']['stats']['xfeat']['features']['p50']
    assert f'{xp50:.1f}' in text
    assert 'Rate ratios (semfeat Hz / baseline Hz): ORB ' in text and ', XFeat ' in text

    # the rendered frames are cached and reused (no re-rendering)
    cache = out / 'frames_160x128'
    stamps = {p.name: p.stat().st_mtime_ns for p in cache.iterdir()}
    fs = frames.rendered_frames(out.resolve(), 2, (160, 128), 0, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in cache.iterdir()} == stamps
    assert len(fs.msgs) == 2 and fs.camera.width == 160
