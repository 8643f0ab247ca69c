"""Shared fixtures: isolated ROS 2 domains and paths."""
from __future__ import annotations

import os
from pathlib import Path
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / 'shared'


def ros_env(domain_id: int, **extra: str) -> dict[str, str]:
    """Environment for a subprocess on an isolated, localhost-only ROS 2 domain."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1', **extra)
    env.pop('ROS_LOCALHOST_ONLY', None)
    env['PATH'] = f'{Path(sys.executable).parent}{os.pathsep}{env.get("PATH", "")}'
    return env


@pytest.fixture
def isolated_ros(monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest):
    """Set an isolated domain in this process (domain id from the test's ``ros_domain`` marker)."""
    marker = request.node.get_closest_marker('ros_domain')
    if marker is None:
        raise RuntimeError('tests using isolated_ros need @pytest.mark.ros_domain(N)')
    monkeypatch.setenv('ROS_DOMAIN_ID', str(marker.args[0]))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.delenv('ROS_LOCALHOST_ONLY', raising=False)
    return marker.args[0]
