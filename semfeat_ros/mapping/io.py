"""Map and trajectory files: PLY point clouds with semantics and TUM trajectories."""
from __future__ import annotations

from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from semfeat_ros.mapping.cloud import SemanticCloud
from semfeat_ros.mapping.errors import PlyFormatError, TumFormatError
from semfeat_ros.mapping.geometry import matrix_to_quaternion, quaternion_to_matrix

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
    """Write ``cloud`` as PLY with x y z (m) red green blue label floor landmark_id n_obs."""
    p = Path(path)
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
    with open(p, 'wb') as f:
        f.write(('\n'.join(header) + '\n').encode('ascii'))
        if binary:
            f.write(arr.tobytes())
        else:
            for row in arr:
                f.write((' '.join(
                    f'{row[name]:.6f}' if ptype == 'float' else str(int(row[name]))
                    for name, ptype, _ in _PLY_PROPS) + '\n').encode('ascii'))
    return p


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
    """Write ``timestamp tx ty tz qx qy qz qw`` lines (s with ns digits, m) of 4x4 poses."""
    stamps = np.asarray(stamps_ns, dtype=np.int64).ravel()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(stamps) != len(poses):
        raise TumFormatError(f'{len(stamps)} stamps but {len(poses)} poses')
    p = Path(path)
    with open(p, 'w', encoding='ascii') as f:
        f.write('# timestamp tx ty tz qx qy qz qw (map -> base_link, m)\n')
        for ns, T in zip(stamps, poses):
            q = matrix_to_quaternion(T[:3, :3])
            t = T[:3, 3]
            f.write(f'{_stamp_str(int(ns))} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} '
                    f'{q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}\n')
    return p


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
