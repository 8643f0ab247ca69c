"""Smoke test of the middleware: sensor_msgs/Image between two processes over Fast DDS."""
from __future__ import annotations

import hashlib
from pathlib import Path
import subprocess
import sys

from conftest import ros_env
import pytest

sys.path.insert(0, str(Path(__file__).parent / 'helpers'))
from dds_peer import pattern  # noqa: E402

PEER = Path(__file__).parent / 'helpers' / 'dds_peer.py'


@pytest.mark.parametrize('domain', [71])
def test_image_crosses_process_boundary(domain: int) -> None:
    env = ros_env(domain)
    width, height = 640, 512
    sub = subprocess.Popen([sys.executable, str(PEER), 'sub', str(width), str(height), '30'],
                           env=env, stdout=subprocess.PIPE, text=True)
    pub = subprocess.Popen([sys.executable, str(PEER), 'pub', str(width), str(height), '30'],
                           env=env, stdout=subprocess.DEVNULL)
    try:
        out, _ = sub.communicate(timeout=45)
    finally:
        pub.terminate()
        pub.wait(timeout=10)
    assert sub.returncode == 0, out
    expected = hashlib.sha256(pattern(width, height).tobytes()).hexdigest()
    assert out.split() == ['OK', 'rgb8', 'camera_front_optical', expected]


def test_other_domain_is_isolated() -> None:
    """A subscriber on another domain id must not see the publisher (isolation really works)."""
    pub = subprocess.Popen([sys.executable, str(PEER), 'pub', '8', '8', '8'], env=ros_env(72),
                           stdout=subprocess.DEVNULL)
    try:
        sub = subprocess.run([sys.executable, str(PEER), 'sub', '8', '8', '4'], env=ros_env(73),
                             capture_output=True, text=True, timeout=30)
    finally:
        pub.terminate()
        pub.wait(timeout=10)
    assert sub.returncode == 1 and 'TIMEOUT' in sub.stdout
