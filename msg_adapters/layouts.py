"""The three product PointCloud2 layouts of the topic contract (README), builders and readers.

Alignment choice: fields in the contract's order, each at the next offset that is a multiple of
its element size (natural alignment, as a C struct), ``point_step`` rounded up to a multiple of
4. Floats are therefore 4-byte aligned for readers that map the buffer directly, at the cost of
a few padding bytes (zero-filled). Data is little-endian (``is_bigendian = False``), height 1.

``/semfeat/features`` (:func:`features_dtype`, point_step = 16 + 4 D)::

    u f32 @0 (px), v f32 @4 (px), score f32 @8, label u8 @12, [3 pad], descriptor f32 x D @16

``/semfeat/tracks`` (:data:`TRACKS_DTYPE`, point_step = 36)::

    u f32 @0, v f32 @4 (px), bx f32 @8, by f32 @12, bz f32 @16 (unit bearing, optical frame),
    label u8 @20, [3 pad], track_id u32 @24, age u16 @28, [2 pad], score f32 @32

``/semantic_cloud`` (:data:`SEMANTIC_CLOUD_DTYPE`, point_step = 28)::

    x f32 @0, y f32 @4, z f32 @8 (m, frame map), rgb f32 @12 (PCL-packed), label u8 @16,
    floor u8 @17, [2 pad], landmark_id u32 @20, n_obs u16 @24, [2 pad]

``rgb`` follows PCL's packing: the uint32 ``0x00RRGGBB`` reinterpreted as float32 (alpha byte
0, so the float is always finite), which RViz's RGB8 colour transformer reads.

Value policy of the builders: float columns must be finite (:class:`NonFiniteError`, unless
``allow_nonfinite=True``); ``label``, ``floor`` (0..255), ``track_id``, ``landmark_id``
(0..2^32-1) out of range -> :class:`ValueRangeError`; the counters ``age`` and ``n_obs`` saturate
at 65535. Readers accept any producer with the same field names and datatypes (offsets, extra
fields, padding and byte order may differ) and return native, contiguous copies.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.errors import (
    ArrayShapeError,
    LayoutMismatchError,
    NonFiniteError,
    ValueRangeError,
)
from msg_adapters.point_cloud2 import array_to_pointcloud2, field_summary, pointcloud2_to_array
from msg_adapters.stamp import header_info

_F4, _U1, _U2, _U4 = np.dtype('<f4'), np.dtype('u1'), np.dtype('<u2'), np.dtype('<u4')
_FLOAT32, _UINT8, _UINT16, _UINT32 = 7, 2, 4, 6


def aligned_dtype(spec: Sequence[tuple[str, np.dtype, int]], align: int = 4) -> np.dtype:
    """Structured dtype with naturally aligned fields ``(name, element dtype, count)``.

    Each field starts at the next multiple of its element size; the itemsize is rounded up to
    a multiple of ``align`` bytes.
    """
    names, formats, offsets = [], [], []
    offset = 0
    for name, base, count in spec:
        size = np.dtype(base).itemsize
        offset = -(-offset // size) * size
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
        offset += size * count
    itemsize = -(-offset // align) * align
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                     'itemsize': itemsize})


def features_dtype(descriptor_dim: int) -> np.dtype:
    """dtype of ``/semfeat/features`` points with ``descriptor_dim`` (D >= 1) floats."""
    if int(descriptor_dim) < 1:
        raise ArrayShapeError(f'descriptor_dim: expected >= 1, got {descriptor_dim}')
    return aligned_dtype([('u', _F4, 1), ('v', _F4, 1), ('score', _F4, 1), ('label', _U1, 1),
                          ('descriptor', _F4, int(descriptor_dim))])


#: dtype of ``/semfeat/tracks`` points (point_step 36).
TRACKS_DTYPE = aligned_dtype([
    ('u', _F4, 1), ('v', _F4, 1), ('bx', _F4, 1), ('by', _F4, 1), ('bz', _F4, 1),
    ('label', _U1, 1), ('track_id', _U4, 1), ('age', _U2, 1), ('score', _F4, 1)])

#: dtype of ``/semantic_cloud`` points (point_step 28).
SEMANTIC_CLOUD_DTYPE = aligned_dtype([
    ('x', _F4, 1), ('y', _F4, 1), ('z', _F4, 1), ('rgb', _F4, 1), ('label', _U1, 1),
    ('floor', _U1, 1), ('landmark_id', _U4, 1), ('n_obs', _U2, 1)])


# ----------------------------------------------------------------------------- rgb packing

def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """``(N, 3)`` uint8 RGB -> ``(N,)`` float32 PCL-packed (bits of uint32 ``0x00RRGGBB``)."""
    a = _integer_column('rgb', rgb, (3,), None, 0, 255)
    packed = (a[:, 0].astype(np.uint32) << 16) | (a[:, 1].astype(np.uint32) << 8) | a[:, 2]
    return packed.astype(np.uint32).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """PCL-packed float32 (or uint32) ``(N,)`` -> ``(N, 3)`` uint8 RGB (bit-exact, no casts)."""
    a = np.asarray(packed)
    if a.dtype.itemsize != 4 or a.dtype.kind not in 'fui':
        raise ArrayShapeError(f'unpack_rgb: expected float32 or uint32, got {a.dtype}')
    bits = a.view(np.dtype('u4').newbyteorder(a.dtype.byteorder)).astype(np.uint32)
    bits = bits.reshape(-1)
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF],
                    axis=1).astype(np.uint8)


# ----------------------------------------------------------------------------- validation

def _array(name: str, values: Any) -> np.ndarray:
    """``values`` as an array; ArrayShapeError (not numpy's bare ValueError) when it is ragged
    or cannot be converted."""
    try:
        return np.asarray(values)
    except (ValueError, TypeError) as exc:
        raise ArrayShapeError(f'{name}: not a regular array ({" ".join(str(exc).split())})'
                              ) from exc


def _float_column(name: str, values: Any, tail: tuple[int, ...], n: int | None,
                  allow_nonfinite: bool) -> np.ndarray:
    a = _array(name, values)
    if a.dtype.kind not in 'fiub' or a.ndim != 1 + len(tail) or a.shape[1:] != tail or (
            n is not None and a.shape[0] != n):
        want = ('N' if n is None else str(n),) + tuple(str(t) for t in tail)
        raise ArrayShapeError(
            f'{name}: expected a numeric array of shape ({", ".join(want)}), got shape '
            f'{a.shape} dtype {a.dtype}')
    a = a.astype(np.float32)
    if not allow_nonfinite:
        bad = ~np.isfinite(a)
        if bad.any():
            rows = np.flatnonzero(bad.reshape(a.shape[0], -1).any(axis=1))
            raise NonFiniteError(
                f'{name}: {rows.size} row(s) contain NaN or inf, first at index {rows[0]} '
                f'({a[rows[0]].tolist()})')
    return a


def _integer_column(name: str, values: Any, tail: tuple[int, ...], n: int | None,
                    low: int, high: int, saturate: bool = False) -> np.ndarray:
    a = _array(name, values)
    if a.ndim != 1 + len(tail) or a.shape[1:] != tail or (n is not None and a.shape[0] != n):
        want = ('N' if n is None else str(n),) + tuple(str(t) for t in tail)
        raise ArrayShapeError(
            f'{name}: expected shape ({", ".join(want)}), got {a.shape}')
    if a.size and a.dtype.kind == 'f' and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
        a = a.astype(np.int64)
    if a.dtype.kind not in 'iub':
        raise ArrayShapeError(f'{name}: expected integers, got dtype {a.dtype}')
    if a.size:
        lo, hi = int(a.min()), int(a.max())
        if lo < low or (hi > high and not saturate):
            bad = lo if lo < low else hi
            raise ValueRangeError(f'{name}: value {bad} outside [{low}, {high}]')
        if saturate and hi > high:
            a = np.minimum(a, high)
    return a.astype(np.int64) if a.dtype.kind == 'b' else a


def _check_layout(msg: Any, required: dict[str, tuple[int, int | None]], what: str) -> None:
    present = {str(f.name): (int(f.datatype), int(f.count)) for f in msg.fields}
    for name, (datatype, count) in required.items():
        got = present.get(name)
        if got is None or got[0] != datatype or (count is not None and got[1] != count):
            want = f'datatype {datatype}' + (f' count {count}' if count is not None else '')
            have = 'missing' if got is None else f'datatype {got[0]} count {got[1]}'
            raise LayoutMismatchError(
                f'{what}: field {name!r} needs {want}, {have} (fields: {field_summary(msg)})')


def _native(column: np.ndarray, dtype: Any) -> np.ndarray:
    return np.ascontiguousarray(column, dtype=np.dtype(dtype).newbyteorder('='))


# ----------------------------------------------------------------------------- features

@dataclass(frozen=True)
class Features:
    """Columns of a ``/semfeat/features`` cloud."""

    stamp_ns: int
    frame_id: str
    keypoints: np.ndarray  #: (N, 2) float32 (u, v) px
    scores: np.ndarray  #: (N,) float32
    labels: np.ndarray  #: (N,) uint8 class ids
    descriptors: np.ndarray  #: (N, D) float32


def features_to_msg(keypoints: np.ndarray, scores: np.ndarray, labels: np.ndarray,
                    descriptors: np.ndarray, *, stamp_ns: int, frame_id: str, msg_cls: Any,
                    allow_nonfinite: bool = False, typestore: Any | None = None) -> Any:
    """``/semfeat/features`` PointCloud2: keypoints (N, 2) px, scores (N,), labels (N,) 0..255,
    descriptors (N, D) (D >= 1; the D of an empty set is taken from its shape (0, D))."""
    desc = _array('descriptors', descriptors)
    if desc.ndim != 2 or desc.shape[1] < 1:
        raise ArrayShapeError(f'descriptors: expected shape (N, D) with D >= 1, got {desc.shape}')
    n, dim = desc.shape
    arr = np.zeros(n, dtype=features_dtype(dim))
    kp = _float_column('keypoints', keypoints, (2,), n, allow_nonfinite)
    arr['u'], arr['v'] = kp[:, 0], kp[:, 1]
    arr['score'] = _float_column('scores', scores, (), n, allow_nonfinite)
    arr['label'] = _integer_column('labels', labels, (), n, 0, 255)
    arr['descriptor'] = _float_column('descriptors', desc, (dim,), n, allow_nonfinite)
    return array_to_pointcloud2(arr, stamp_ns=stamp_ns, frame_id=frame_id, msg_cls=msg_cls,
                                typestore=typestore)


def features_from_msg(msg: Any) -> Features:
    """Read a ``/semfeat/features`` PointCloud2 (any producer with the same field types)."""
    desc_field = next((f for f in msg.fields if str(f.name) == 'descriptor'), None)
    _check_layout(msg, {'u': (_FLOAT32, 1), 'v': (_FLOAT32, 1), 'score': (_FLOAT32, 1),
                        'label': (_UINT8, 1), 'descriptor': (_FLOAT32, None)}, 'features')
    dim = int(desc_field.count)
    arr = pointcloud2_to_array(msg, flat=True)
    stamp_ns, frame_id = header_info(msg)
    desc = _native(arr['descriptor'], np.float32).reshape(arr.shape[0], dim)
    return Features(stamp_ns, frame_id,
                    keypoints=np.stack([_native(arr['u'], np.float32),
                                        _native(arr['v'], np.float32)], axis=1),
                    scores=_native(arr['score'], np.float32),
                    labels=_native(arr['label'], np.uint8), descriptors=desc)


# ----------------------------------------------------------------------------- tracks

@dataclass(frozen=True)
class Tracks:
    """Columns of a ``/semfeat/tracks`` cloud."""

    stamp_ns: int
    frame_id: str
    uv: np.ndarray  #: (N, 2) float32 px
    bearings: np.ndarray  #: (N, 3) float32 unit vectors, camera optical frame
    labels: np.ndarray  #: (N,) uint8
    track_ids: np.ndarray  #: (N,) uint32
    ages: np.ndarray  #: (N,) uint16 frames tracked
    scores: np.ndarray  #: (N,) float32 match confidence


def tracks_to_msg(uv: np.ndarray, bearings: np.ndarray, labels: np.ndarray,
                  track_ids: np.ndarray, ages: np.ndarray, scores: np.ndarray, *,
                  stamp_ns: int, frame_id: str, msg_cls: Any, allow_nonfinite: bool = False,
                  typestore: Any | None = None) -> Any:
    """``/semfeat/tracks`` PointCloud2: uv (N, 2) px, bearings (N, 3), labels (N,),
    track_ids (N,) 0..2^32-1, ages (N,) frames (saturated at 65535), scores (N,)."""
    px = _float_column('uv', uv, (2,), None, allow_nonfinite)
    n = px.shape[0]
    rays = _float_column('bearings', bearings, (3,), n, allow_nonfinite)
    arr = np.zeros(n, dtype=TRACKS_DTYPE)
    arr['u'], arr['v'] = px[:, 0], px[:, 1]
    arr['bx'], arr['by'], arr['bz'] = rays[:, 0], rays[:, 1], rays[:, 2]
    arr['label'] = _integer_column('labels', labels, (), n, 0, 255)
    arr['track_id'] = _integer_column('track_ids', track_ids, (), n, 0, 2 ** 32 - 1)
    arr['age'] = _integer_column('ages', ages, (), n, 0, 65535, saturate=True)
    arr['score'] = _float_column('scores', scores, (), n, allow_nonfinite)
    return array_to_pointcloud2(arr, stamp_ns=stamp_ns, frame_id=frame_id, msg_cls=msg_cls,
                                typestore=typestore)


def tracks_from_msg(msg: Any) -> Tracks:
    """Read a ``/semfeat/tracks`` PointCloud2 (any producer with the same field types)."""
    f4 = (_FLOAT32, 1)
    _check_layout(msg, {'u': f4, 'v': f4, 'bx': f4, 'by': f4, 'bz': f4, 'label': (_UINT8, 1),
                        'track_id': (_UINT32, 1), 'age': (_UINT16, 1), 'score': f4}, 'tracks')
    arr = pointcloud2_to_array(msg, flat=True)
    stamp_ns, frame_id = header_info(msg)

    def col(name: str, dtype: Any = np.float32) -> np.ndarray:
        return _native(arr[name], dtype)

    return Tracks(stamp_ns, frame_id, uv=np.stack([col('u'), col('v')], axis=1),
                  bearings=np.stack([col('bx'), col('by'), col('bz')], axis=1),
                  labels=col('label', np.uint8), track_ids=col('track_id', np.uint32),
                  ages=col('age', np.uint16), scores=col('score'))


# ----------------------------------------------------------------------------- semantic cloud

@dataclass(frozen=True)
class SemanticCloud:
    """Columns of a ``/semantic_cloud``."""

    stamp_ns: int
    frame_id: str
    xyz: np.ndarray  #: (N, 3) float32 m
    rgb: np.ndarray  #: (N, 3) uint8 class colour
    labels: np.ndarray  #: (N,) uint8
    floors: np.ndarray  #: (N,) uint8 level index
    landmark_ids: np.ndarray  #: (N,) uint32
    n_obs: np.ndarray  #: (N,) uint16 observations


def semantic_cloud_to_msg(xyz: np.ndarray, rgb: np.ndarray, label: np.ndarray,
                          floor: np.ndarray, landmark_id: np.ndarray, n_obs: np.ndarray, *,
                          stamp_ns: int, frame_id: str, msg_cls: Any,
                          allow_nonfinite: bool = False, typestore: Any | None = None) -> Any:
    """``/semantic_cloud`` PointCloud2: xyz (N, 3) m, rgb (N, 3) 0..255, label, floor (N,)
    0..255, landmark_id (N,) 0..2^32-1, n_obs (N,) (saturated at 65535)."""
    pts = _float_column('xyz', xyz, (3,), None, allow_nonfinite)
    n = pts.shape[0]
    arr = np.zeros(n, dtype=SEMANTIC_CLOUD_DTYPE)
    arr['x'], arr['y'], arr['z'] = pts[:, 0], pts[:, 1], pts[:, 2]
    colours = _integer_column('rgb', rgb, (3,), n, 0, 255)
    arr['rgb'] = pack_rgb(colours.astype(np.uint8))
    arr['label'] = _integer_column('label', label, (), n, 0, 255)
    arr['floor'] = _integer_column('floor', floor, (), n, 0, 255)
    arr['landmark_id'] = _integer_column('landmark_id', landmark_id, (), n, 0, 2 ** 32 - 1)
    arr['n_obs'] = _integer_column('n_obs', n_obs, (), n, 0, 65535, saturate=True)
    return array_to_pointcloud2(arr, stamp_ns=stamp_ns, frame_id=frame_id, msg_cls=msg_cls,
                                typestore=typestore)


def semantic_cloud_from_msg(msg: Any) -> SemanticCloud:
    """Read a ``/semantic_cloud`` PointCloud2 (any producer with the same field types)."""
    f4 = (_FLOAT32, 1)
    _check_layout(msg, {'x': f4, 'y': f4, 'z': f4, 'rgb': f4, 'label': (_UINT8, 1),
                        'floor': (_UINT8, 1), 'landmark_id': (_UINT32, 1),
                        'n_obs': (_UINT16, 1)}, 'semantic cloud')
    arr = pointcloud2_to_array(msg, flat=True)
    stamp_ns, frame_id = header_info(msg)
    xyz = np.stack([_native(arr[c], np.float32) for c in 'xyz'], axis=1)
    return SemanticCloud(stamp_ns, frame_id, xyz=xyz, rgb=unpack_rgb(arr['rgb']),
                         labels=_native(arr['label'], np.uint8),
                         floors=_native(arr['floor'], np.uint8),
                         landmark_ids=_native(arr['landmark_id'], np.uint32),
                         n_obs=_native(arr['n_obs'], np.uint16))
