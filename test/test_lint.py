"""ament lint conventions (99 columns, single quotes, sorted imports) enforced with ruff."""
from __future__ import annotations

from pathlib import Path
import shutil
import subprocess
import sys

from conftest import REPO


def test_ruff_clean() -> None:
    ruff = shutil.which('ruff', path=str(Path(sys.executable).parent))
    assert ruff, 'ruff is part of the environment (requirements.txt)'
    proc = subprocess.run([ruff, 'check', '--no-cache', str(REPO)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
