"""Smoke test of the matching benchmark command (the real run is a separate command)."""
from __future__ import annotations

import pytest

from semfeat_ros.matching import bench


def test_bench_smoke(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.cli(['--n', '120', '--repeat', '1']) == 0
    out = capsys.readouterr().out
    assert 'verify_bearings' in out and 'match_float' in out and 'SequentialMatcher' in out
    res = bench.main(n=120, repeat=1)
    assert all(r['median_ms'] > 0 for r in res.values())


def test_bench_rejects_bad_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.cli(['--n', '3']) == 2
    assert 'error' in capsys.readouterr().err
