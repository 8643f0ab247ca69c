"""Output locations of the offline tools: every file stays inside the output directory."""
from __future__ import annotations

import os
from pathlib import Path

from semfeat_ros.offline.errors import OutputPathError


def prepare_out_dir(out: str | os.PathLike[str]) -> Path:
    """Create the output directory ``out`` (parents too) and return its resolved path.

    Raises:
        OutputPathError: ``out`` exists and is not a directory, or cannot be created.
    """
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise OutputPathError(f'--out {str(p)!r} exists and is not a directory')
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputPathError(f'cannot create --out {str(p)!r}: {exc.strerror or exc}') from exc
    return p.resolve()


def confined(out_dir: Path, name: str | os.PathLike[str]) -> Path:
    """``out_dir / name`` after checking that it stays inside ``out_dir``.

    Rejects absolute names, ``..`` components and existing symbolic links that lead outside
    (the path is resolved, following links, before the check).

    Raises:
        OutputPathError: the path would escape ``out_dir``.
    """
    root = Path(out_dir).resolve()
    rel = Path(name)
    if rel.is_absolute() or '..' in rel.parts or not rel.parts:
        raise OutputPathError(
            f'output name {str(name)!r} must be a relative path inside {str(root)!r}')
    target = (root / rel).resolve()
    if target != root and root not in target.parents:
        raise OutputPathError(
            f'output {str(root / rel)!r} resolves to {str(target)!r}, outside the output '
            f'directory {str(root)!r} (symbolic link?)')
    return target
