"""Map and trajectory files: PLY point clouds with semantics and TUM trajectories.

Every file is written to a fresh temporary file in the target's directory (created with
``O_CREAT | O_EXCL | O_NOFOLLOW``), flushed to disk and then renamed over the target with
``os.replace``: a reader sees the old file or the new one, never half of one, and a symlink
planted at the target is refused (a rename would replace the link, never write through it).
:func:`save_map` writes a cloud and its trajectory as one unit, confined to one directory.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
import hashlib
import json
import os
from pathlib import Path
import secrets
import stat
from typing import BinaryIO

import numpy as np

from semfeat_ros.mapping.cloud import SemanticCloud
from semfeat_ros.mapping.errors import MapWriteError, PlyFormatError, TumFormatError
from semfeat_ros.rotations import matrix_to_quaternion, quaternion_to_matrix

# PLY property name -> (PLY type, numpy dtype); the order written.
_PLY_PROPS: tuple[tuple[str, str, str], ...] = (
    ('x', 'float', '<f4'), ('y', 'float', '<f4'), ('z', 'float', '<f4'),
    ('red', 'uchar', 'u1'), ('green', 'uchar', 'u1'), ('blue', 'uchar', 'u1'),
    ('label', 'uchar', 'u1'), ('floor', 'uchar', 'u1'),
    ('landmark_id', 'uint', '<u4'), ('n_obs', 'ushort', '<u2'),
)
_PLY_TYPES = {
    'char': 'i1', 'int8': 'i1', 'uchar': 'u1', 'uint8': 'u1', 'short': '<i2', 'int16': '<i2',
    'ushort': '<u2', 'uint16': '<u2', 'int': '<i4', 'int32': '<i4', 'uint': '<u4',
    'uint32': '<u4', 'float': '<f4', 'float32': '<f4', 'double': '<f8', 'float64': '<f8',
}


def write_ply(path: str | Path, cloud: SemanticCloud, *, binary: bool = True) -> Path:
    """Write ``cloud`` as PLY with x y z (m) red green blue label floor landmark_id n_obs
    (atomically, see the module docstring).

    Raises:
        MapWriteError: ``path`` is a symlink or cannot be written.
    """
    p = Path(path)
    with _open_dir(p.parent) as dir_fd:
        tmp = _write_temp(dir_fd, p.name, lambda f: _ply_body(f, cloud, binary))
        _commit(dir_fd, tmp, p.name, p.parent)
    return p


def _ply_body(f: BinaryIO, cloud: SemanticCloud, binary: bool) -> None:
    n = len(cloud)
    arr = np.zeros(n, dtype=[(name, dt) for name, _, dt in _PLY_PROPS])
    arr['x'], arr['y'], arr['z'] = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    arr['red'], arr['green'], arr['blue'] = cloud.rgb[:, 0], cloud.rgb[:, 1], cloud.rgb[:, 2]
    arr['label'], arr['floor'] = cloud.label, cloud.floor
    arr['landmark_id'], arr['n_obs'] = cloud.landmark_id, cloud.n_obs
    fmt = 'binary_little_endian' if binary else 'ascii'
    header = [
        'ply', f'format {fmt} 1.0', 'comment semfeat_ros semantic map, frame map (z up, m)',
        f'element vertex {n}']
    header += [f'property {ptype} {name}' for name, ptype, _ in _PLY_PROPS]
    header.append('end_header')
    f.write(('\n'.join(header) + '\n').encode('ascii'))
    if binary:
        f.write(arr.tobytes())
    else:
        for row in arr:
            f.write((' '.join(
                f'{row[name]:.6f}' if ptype == 'float' else str(int(row[name]))
                for name, ptype, _ in _PLY_PROPS) + '\n').encode('ascii'))


def read_ply(path: str | Path) -> SemanticCloud:
    """Read a PLY written by :func:`write_ply` (binary little-endian or ascii)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f'PLY file not found: {p}')
    data = p.read_bytes()
    end = data.find(b'end_header')
    if not data.startswith(b'ply') or end < 0:
        raise PlyFormatError(f'{p}: not a PLY file (missing "ply" magic or end_header)')
    body_start = data.index(b'\n', end) + 1
    lines = data[:end].decode('ascii', errors='replace').splitlines()
    fmt, n, props, in_vertex = None, None, [], False
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == 'format':
            fmt = parts[1]
        elif parts[0] == 'element':
            in_vertex = parts[1] == 'vertex'
            if in_vertex:
                n = int(parts[2])
        elif parts[0] == 'property' and in_vertex:
            if parts[1] == 'list' or parts[1] not in _PLY_TYPES:
                raise PlyFormatError(f'{p}: unsupported property {" ".join(parts[1:])!r}')
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if n is None or fmt not in ('ascii', 'binary_little_endian'):
        raise PlyFormatError(
            f'{p}: need a vertex element and format ascii or binary_little_endian, got {fmt}')
    names = [name for name, _ in props]
    missing = [name for name, _, _ in _PLY_PROPS if name not in names]
    if missing:
        raise PlyFormatError(f'{p}: missing vertex properties {missing}')
    dtype = np.dtype(props)
    if fmt == 'binary_little_endian':
        if len(data) - body_start < n * dtype.itemsize:
            raise PlyFormatError(
                f'{p}: truncated body, expected {n * dtype.itemsize} bytes, got '
                f'{len(data) - body_start}')
        arr = np.frombuffer(data, dtype=dtype, count=n, offset=body_start)
    else:
        rows = data[body_start:].decode('ascii').split('\n')
        rows = [r for r in rows if r.strip()]
        if len(rows) < n:
            raise PlyFormatError(f'{p}: expected {n} vertex lines, got {len(rows)}')
        arr = np.zeros(n, dtype=dtype)
        for i in range(n):
            vals = rows[i].split()
            if len(vals) != len(props):
                raise PlyFormatError(f'{p}: vertex line {i} has {len(vals)} values, '
                                     f'expected {len(props)}')
            arr[i] = tuple(float(v) if np.dtype(dt).kind == 'f' else int(v)
                           for v, (_, dt) in zip(vals, props))
    return SemanticCloud(
        np.stack([arr['x'], arr['y'], arr['z']], axis=1).astype(np.float32),
        arr['label'].astype(np.uint8), arr['floor'].astype(np.uint8),
        arr['landmark_id'].astype(np.uint32), arr['n_obs'].astype(np.uint16),
        np.stack([arr['red'], arr['green'], arr['blue']], axis=1).astype(np.uint8))


def _stamp_str(ns: int) -> str:
    sign = '-' if ns < 0 else ''
    ns = abs(int(ns))
    return f'{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}'


def write_tum(path: str | Path, stamps_ns: np.ndarray, poses: np.ndarray) -> Path:
    """Write ``timestamp tx ty tz qx qy qz qw`` lines (s with ns digits, m) of 4x4 poses
    (atomically, see the module docstring).

    Raises:
        TumFormatError: stamps and poses differ in number.
        MapWriteError: ``path`` is a symlink or cannot be written.
    """
    body = _tum_body(stamps_ns, poses)
    p = Path(path)
    with _open_dir(p.parent) as dir_fd:
        tmp = _write_temp(dir_fd, p.name, lambda f: f.write(body))
        _commit(dir_fd, tmp, p.name, p.parent)
    return p


def _tum_body(stamps_ns: np.ndarray, poses: np.ndarray) -> bytes:
    stamps = np.asarray(stamps_ns, dtype=np.int64).ravel()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(stamps) != len(poses):
        raise TumFormatError(f'{len(stamps)} stamps but {len(poses)} poses')
    lines = ['# timestamp tx ty tz qx qy qz qw (map -> base_link, m)\n']
    for ns, T in zip(stamps, poses):
        q = matrix_to_quaternion(T[:3, :3])
        t = T[:3, 3]
        lines.append(f'{_stamp_str(int(ns))} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} '
                     f'{q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}\n')
    return ''.join(lines).encode('ascii')


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``(stamps_ns (K,) int64, poses (K, 4, 4))``."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f'TUM file not found: {p}')
    stamps, poses = [], []
    for lineno, line in enumerate(p.read_text(encoding='ascii').splitlines(), 1):
        s = line.strip()
        if not s or s.startswith('#'):
            continue
        parts = s.split()
        if len(parts) != 8:
            raise TumFormatError(f'{p}:{lineno}: expected 8 columns, got {len(parts)}')
        try:
            stamps.append(int(Decimal(parts[0]) * 1_000_000_000))
            vals = np.array([float(v) for v in parts[1:]])
        except (InvalidOperation, ValueError) as exc:
            raise TumFormatError(f'{p}:{lineno}: non-numeric value ({exc})') from exc
        if not np.isfinite(vals).all() or np.linalg.norm(vals[3:]) < 1e-9:
            raise TumFormatError(f'{p}:{lineno}: non-finite value or zero quaternion')
        T = np.eye(4)
        T[:3, :3] = quaternion_to_matrix(vals[3:])
        T[:3, 3] = vals[:3]
        poses.append(T)
    return np.array(stamps, dtype=np.int64), np.array(poses).reshape(-1, 4, 4)


# ------------------------------------------------------------------ safe, confined writes

MANIFEST = 'map.json'
"""Name of the manifest :func:`save_map` writes last, naming the pair it belongs to."""


@dataclass(frozen=True)
class SavedMap:
    """What :func:`save_map` wrote: absolute paths and sizes (points, poses)."""

    cloud: Path
    trajectory: Path
    manifest: Path
    n_points: int
    n_poses: int


def _plain_name(name: str) -> str:
    """``name`` when it is a single path component inside a directory, else MapWriteError."""
    if not name or name in ('.', '..') or '/' in name or '\0' in name:
        raise MapWriteError(f'{name!r} is not a plain file name inside the output directory')
    return name


@contextmanager
def _open_dir(path: Path) -> Iterator[int]:
    """A file descriptor of the existing directory ``path`` (its last component must not be
    a symlink); closed on exit."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        raise MapWriteError(f'cannot open the output directory {path}: {exc.strerror}') from exc
    try:
        yield fd
    finally:
        os.close(fd)


def _write_temp(dir_fd: int, target: str, fill: Callable[[BinaryIO], object]) -> str:
    """A new temporary file next to ``target`` (inside ``dir_fd``) filled by ``fill`` and
    flushed to disk; returns its name. On any failure nothing is left behind."""
    tmp = f'.{_plain_name(target)}.{secrets.token_hex(6)}.tmp'
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                     0o644, dir_fd=dir_fd)
    except OSError as exc:
        raise MapWriteError(f'cannot create a file for {target}: {exc.strerror}') from exc
    try:
        with os.fdopen(fd, 'wb') as f:
            fill(f)
            f.flush()
            os.fsync(f.fileno())
    except BaseException as exc:
        _unlink(dir_fd, tmp)
        if isinstance(exc, OSError) and not isinstance(exc, MapWriteError):
            raise MapWriteError(f'cannot write {target}: {exc.strerror or exc}') from exc
        raise
    return tmp


def _unlink(dir_fd: int, name: str) -> None:
    try:
        os.unlink(name, dir_fd=dir_fd)
    except FileNotFoundError:
        pass


def _refuse_symlink(dir_fd: int, name: str, where: Path) -> None:
    """MapWriteError when ``name`` exists in the directory and is not a regular file."""
    try:
        st = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except FileNotFoundError:
        return
    if not stat.S_ISREG(st.st_mode):
        kind = 'a symlink' if stat.S_ISLNK(st.st_mode) else 'not a regular file'
        raise MapWriteError(f'refusing to replace {where / name}: it is {kind}')


def _commit(dir_fd: int, tmp: str, target: str, where: Path) -> None:
    """Rename the temporary file ``tmp`` over ``target`` (both inside ``dir_fd``)."""
    try:
        _refuse_symlink(dir_fd, target, where)
        os.replace(tmp, target, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
    except BaseException as exc:
        _unlink(dir_fd, tmp)
        if isinstance(exc, OSError) and not isinstance(exc, MapWriteError):
            raise MapWriteError(f'cannot replace {where / target}: {exc.strerror}') from exc
        raise


def _sha256(dir_fd: int, name: str) -> str:
    fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=dir_fd)
    with os.fdopen(fd, 'rb') as f:
        return hashlib.sha256(f.read()).hexdigest()


def save_map(out_dir: Path, cloud: SemanticCloud, stamps_ns: np.ndarray, poses: np.ndarray, *,
             subdir: str | None = None, stamp_ns: int = 0) -> SavedMap:
    """Write ``cloud.ply``, ``trajectory.tum`` and the manifest ``map.json`` as one unit.

    Args:
        out_dir: the output directory, absolute and already resolved (symlinks followed once,
            by the caller); created when missing. Nothing is written outside it.
        cloud: the map.
        stamps_ns, poses: the trajectory, (K,) ns and (K, 4, 4) map -> base_link (m).
        subdir: optional plain name of a sub-directory of ``out_dir`` to write into instead
            (created; must not be a symlink).
        stamp_ns: stream time of the map (ns), recorded in the manifest.
    Both files are written completely to temporary files before either replaces its target;
    the manifest, written last, names the pair (sizes, SHA-256, counts), so a pair whose
    renames were interrupted is detectable. Targets that are symlinks are refused.

    Raises:
        MapWriteError: a target is a symlink, the directory is not writable or a write failed;
            the previous files are then left as they were.
        TumFormatError: stamps and poses differ in number.
    """
    if not out_dir.is_absolute():
        raise MapWriteError(f'output directory {out_dir} must be an absolute, resolved path')
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MapWriteError(f'cannot create the output directory {out_dir}: '
                            f'{exc.strerror}') from exc
    with _open_dir(out_dir) as top_fd:
        if subdir is None:
            return _save_pair(top_fd, out_dir, cloud, stamps_ns, poses, stamp_ns)
        name = _plain_name(subdir)
        try:
            os.mkdir(name, 0o755, dir_fd=top_fd)
        except FileExistsError:
            pass
        except OSError as exc:
            raise MapWriteError(f'cannot create {out_dir / name}: {exc.strerror}') from exc
        try:
            sub_fd = os.open(name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC,
                             dir_fd=top_fd)
        except OSError as exc:
            raise MapWriteError(f'cannot open {out_dir / name} (a symlink or not a '
                                f'directory?): {exc.strerror}') from exc
        try:
            return _save_pair(sub_fd, out_dir / name, cloud, stamps_ns, poses, stamp_ns)
        finally:
            os.close(sub_fd)


def _save_pair(dir_fd: int, where: Path, cloud: SemanticCloud, stamps_ns: np.ndarray,
               poses: np.ndarray, stamp_ns: int) -> SavedMap:
    names = {'cloud': 'cloud.ply', 'trajectory': 'trajectory.tum'}
    for name in (*names.values(), MANIFEST):
        _refuse_symlink(dir_fd, name, where)
    tum = _tum_body(stamps_ns, poses)  # a format error before anything is written
    n_poses = tum.count(b'\n') - 1
    temps: dict[str, str] = {}
    try:
        temps['cloud'] = _write_temp(dir_fd, names['cloud'],
                                     lambda f: _ply_body(f, cloud, True))
        temps['trajectory'] = _write_temp(dir_fd, names['trajectory'], lambda f: f.write(tum))
    except BaseException:
        for tmp in temps.values():
            _unlink(dir_fd, tmp)
        raise
    files = {}
    for key in ('cloud', 'trajectory'):
        files[names[key]] = {'sha256': _sha256(dir_fd, temps[key]),
                             'bytes': os.stat(temps[key], dir_fd=dir_fd).st_size}
    try:
        for key in ('cloud', 'trajectory'):
            _commit(dir_fd, temps.pop(key), names[key], where)
    finally:
        for tmp in temps.values():
            _unlink(dir_fd, tmp)
    manifest = json.dumps({'files': files, 'points': len(cloud), 'poses': n_poses,
                           'stamp_ns': int(stamp_ns)}, indent=2).encode('ascii') + b'\n'
    _commit(dir_fd, _write_temp(dir_fd, MANIFEST, lambda f: f.write(manifest)), MANIFEST, where)
    return SavedMap(where / names['cloud'], where / names['trajectory'], where / MANIFEST,
                    len(cloud), n_poses)
