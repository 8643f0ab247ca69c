"""Where the package's shipped files live, in a source checkout and in an ament install."""
from __future__ import annotations

import os
from pathlib import Path
import tempfile

PACKAGE = 'semfeat_ros'


def share_dir() -> Path:
    """Directory holding ``config/`` (and ``launch/``): the ament share dir when installed.

    In a source checkout (or an editable install) this is the repository root. In a colcon
    install it is ``<prefix>/share/semfeat_ros`` found through the ament index.
    """
    repo = Path(__file__).resolve().parent.parent
    if (repo / 'config' / 'labels.yaml').is_file():
        return repo
    try:
        from ament_index_python.packages import get_package_share_directory
    except ImportError as exc:  # pragma: no cover - only without the ROS wheels
        raise FileNotFoundError(
            f'cannot find the {PACKAGE} config directory next to {repo} and '
            'ament_index_python is not importable') from exc
    return Path(get_package_share_directory(PACKAGE))


def config_path(name: str) -> Path:
    """Path of a shipped file in ``config/`` (e.g. ``labels.yaml``)."""
    path = share_dir() / 'config' / name
    if not path.is_file():
        raise FileNotFoundError(f'shipped config file not found: {path}')
    return path


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary file in its directory renamed over
    it: a reader sees the old file or the new one, never half of one."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f'.{path.name}.', suffix='.tmp')
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
