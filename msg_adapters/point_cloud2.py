"""``sensor_msgs/PointCloud2`` <-> numpy structured arrays, for any field layout.

Read path (:func:`pointcloud2_to_array`)
    Every PointField datatype (INT8 .. FLOAT64), ``count > 1`` (a subarray field of shape
    ``(count,)``), padding inside ``point_step`` and at the end of rows (``row_step``), both
    byte orders and ``height > 1``. The result is a **zero-copy view** of the message's
    ``data``: a structured dtype with the fields' offsets and ``itemsize = point_step``, rows
    ``row_step`` bytes apart. It is read-only when the message buffer is (rosbags). Big-endian
    data gives a view with big-endian field dtypes (values read correctly by numpy);
    ``native=True`` converts to native byte order (a copy).

    Shape: ``(width,)`` if ``height == 1`` (unorganised clouds, all product topics), else
    ``(height, width)`` (organised clouds); ``flat=True`` always gives ``(height * width,)``
    (a copy only when rows are padded).

    Checks: unknown datatype, ``count == 0``, empty or duplicate names, a field beyond
    ``point_step``, overlapping fields (:class:`PointFieldError`); ``row_step < width *
    point_step`` (:class:`StepMismatchError`); ``len(data) < row_step * height``
    (:class:`DataLengthError`). Trailing bytes are ignored.

NaN policy
    The generic read and write paths pass NaN / inf through untouched (a LiDAR marks missing
    returns with NaN). :func:`array_to_pointcloud2` sets ``is_dense`` to whether every float
    value is finite unless told. The product builders of :mod:`msg_adapters.layouts` reject
    non-finite values with :class:`NonFiniteError` unless ``allow_nonfinite=True``.

Write path (:func:`array_to_pointcloud2`)
    From a structured array of shape ``(N,)`` (height 1) or ``(H, W)``. Field offsets, padding
    and ``itemsize`` of the dtype are kept (``point_step = itemsize``, rows unpadded); padding
    bytes are zero. Subarray fields ``(dtype, (count,))`` become ``count``. If every multi-byte
    field is big-endian the message is big-endian, otherwise data is written little-endian.
"""
from __future__ import annotations

import sys
from typing import Any

import numpy as np

from msg_adapters._flavour import (
    byte_view,
    construct,
    resolve_class,
    sibling_class,
    uint8_field,
)
from msg_adapters.errors import (
    ArrayShapeError,
    DataLengthError,
    PointFieldError,
    StepMismatchError,
)
from msg_adapters.stamp import make_header

POINT_CLOUD2_TYPE = 'sensor_msgs/msg/PointCloud2'
POINT_FIELD_TYPE = 'sensor_msgs/msg/PointField'

#: PointField datatype constant -> numpy element type (byte order applied separately).
DATATYPES: dict[int, np.dtype] = {
    1: np.dtype(np.int8), 2: np.dtype(np.uint8), 3: np.dtype(np.int16), 4: np.dtype(np.uint16),
    5: np.dtype(np.int32), 6: np.dtype(np.uint32), 7: np.dtype(np.float32),
    8: np.dtype(np.float64),
}
_DATATYPE_OF = {(dt.kind, dt.itemsize): code for code, dt in DATATYPES.items()}
_DATATYPE_NAMES = {1: 'INT8', 2: 'UINT8', 3: 'INT16', 4: 'UINT16', 5: 'INT32', 6: 'UINT32',
                   7: 'FLOAT32', 8: 'FLOAT64'}
_NATIVE = '<' if sys.byteorder == 'little' else '>'


def fields_to_dtype(fields: Any, point_step: int, *, bigendian: bool = False) -> np.dtype:
    """Structured dtype (``itemsize = point_step``) of a list of PointFields (either flavour).

    Raises :class:`PointFieldError` for an unknown datatype, ``count == 0``, an empty or
    duplicate name, a field reaching beyond ``point_step`` or two fields overlapping.
    """
    order = '>' if bigendian else '<'
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    spans: list[tuple[int, int, str]] = []
    for index, field in enumerate(fields):
        name, offset = str(field.name), int(field.offset)
        datatype, count = int(field.datatype), int(field.count)
        if not name:
            raise PointFieldError(f'PointCloud2.fields[{index}].name is empty')
        if name in names:
            raise PointFieldError(f'PointCloud2.fields: duplicate name {name!r}')
        if datatype not in DATATYPES:
            raise PointFieldError(
                f'PointCloud2.fields[{index}] ({name!r}).datatype: unknown {datatype}, expected '
                f'1..8 (INT8..FLOAT64)')
        if count < 1:
            raise PointFieldError(
                f'PointCloud2.fields[{index}] ({name!r}).count: expected >= 1, got {count}')
        base = DATATYPES[datatype]
        end = offset + base.itemsize * count
        if offset < 0 or end > point_step:
            raise PointFieldError(
                f'PointCloud2.fields[{index}] ({name!r}): bytes [{offset}, {end}) reach beyond '
                f'point_step = {point_step}')
        names.append(name)
        dt = base.newbyteorder(order) if base.itemsize > 1 else base
        formats.append(dt if count == 1 else (dt, (count,)))
        offsets.append(offset)
        spans.append((offset, end, name))
    spans.sort()
    for (_, end_a, name_a), (start_b, _, name_b) in zip(spans, spans[1:]):
        if start_b < end_a:
            raise PointFieldError(
                f'PointCloud2.fields: {name_a!r} (ends at byte {end_a}) overlaps {name_b!r} '
                f'(starts at byte {start_b})')
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                     'itemsize': int(point_step)})


def pointcloud2_to_array(msg: Any, *, flat: bool = False, native: bool = False) -> np.ndarray:
    """Points of a ``sensor_msgs/PointCloud2`` (rclpy or rosbags) as a structured array view.

    Shape ``(width,)`` for ``height == 1`` else ``(height, width)``; ``flat=True`` gives
    ``(height * width,)``. ``native=True`` returns native byte order (copies big-endian data).
    See the module docstring for the checks.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    dtype = fields_to_dtype(msg.fields, point_step, bigendian=bool(msg.is_bigendian))
    if row_step < width * point_step:
        raise StepMismatchError(
            f'PointCloud2.row_step: {row_step} bytes is less than width*point_step = '
            f'{width}*{point_step} = {width * point_step}')
    buf = byte_view(msg.data)
    needed = row_step * height
    if buf.size < needed:
        raise DataLengthError(
            f'PointCloud2.data: {buf.size} bytes, expected row_step*height = {row_step}*'
            f'{height} = {needed}')
    if height == 0 or width == 0:
        arr = np.zeros((height, width), dtype=dtype)
    else:
        arr = np.ndarray((height, width), dtype=dtype, buffer=buf, offset=0,
                         strides=(row_step, point_step))
    if native and msg.is_bigendian:
        arr = arr.astype(dtype.newbyteorder('<' if _NATIVE == '<' else '>'))
    if flat:
        return arr.reshape(-1)
    return arr[0] if height == 1 else arr


def dtype_to_fields(dtype: np.dtype) -> tuple[list[tuple[str, int, int, int]], bool]:
    """``([(name, offset, datatype, count), ...], bigendian)`` of a structured dtype.

    Raises :class:`ArrayShapeError` for nested structures, multi-dimensional subarrays or
    element types without a PointField datatype (bool, float16, int64, ...).
    """
    if dtype.names is None:
        raise ArrayShapeError(f'expected a structured array, got dtype {dtype}')
    fields: list[tuple[str, int, int, int]] = []
    orders: set[str] = set()
    for name in dtype.names:
        field_dtype, offset = dtype.fields[name][:2]
        base, shape = field_dtype, ()
        if field_dtype.subdtype is not None:
            base, shape = field_dtype.subdtype
        if len(shape) > 1:
            raise ArrayShapeError(f'field {name!r}: subarray shape {shape} is not 1-D')
        code = _DATATYPE_OF.get((base.kind, base.itemsize))
        if code is None or base.names is not None:
            raise ArrayShapeError(
                f'field {name!r}: dtype {base} has no PointField datatype (int8..uint32, '
                f'float32, float64)')
        if base.itemsize > 1:
            orders.add(_NATIVE if base.byteorder in '=|' else base.byteorder)
        count = int(shape[0]) if shape else 1
        if count < 1:
            raise ArrayShapeError(f'field {name!r}: subarray of length 0')
        fields.append((str(name), int(offset), code, count))
    return fields, orders == {'>'}


def _all_finite(arr: np.ndarray) -> bool:
    for name in arr.dtype.names or ():
        column = arr[name]
        if column.dtype.kind == 'f' or (column.dtype.subdtype is not None
                                        and column.dtype.subdtype[0].kind == 'f'):
            if not np.isfinite(column).all():
                return False
    return True


def array_to_pointcloud2(arr: np.ndarray, *, stamp_ns: int, frame_id: str, msg_cls: Any,
                         is_dense: bool | None = None, typestore: Any | None = None) -> Any:
    """A ``sensor_msgs/PointCloud2`` of the flavour of ``msg_cls`` from a structured array.

    ``arr`` has shape ``(N,)`` (height 1, width N) or ``(H, W)``. ``is_dense`` defaults to
    "every float value is finite". ``msg_cls`` is the PointCloud2 class (rclpy or rosbags) or
    a rosbags typestore; ``stamp_ns`` the header stamp (ns).
    """
    a = np.asarray(arr)
    if a.dtype.names is None:
        raise ArrayShapeError(f'array_to_pointcloud2: expected a structured array, got {a.dtype}')
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2:
        raise ArrayShapeError(
            f'array_to_pointcloud2: expected shape (N,) or (H, W), got {a.shape}')
    specs, bigendian = dtype_to_fields(a.dtype)
    out_dtype = fields_to_dtype(
        [_Spec(*spec) for spec in specs], a.dtype.itemsize, bigendian=bigendian)
    out = np.zeros(a.shape, dtype=out_dtype)
    for name in a.dtype.names:
        out[name] = a[name]
    height, width = a.shape
    cls = resolve_class(msg_cls, POINT_CLOUD2_TYPE, typestore)
    field_cls = sibling_class(cls, POINT_FIELD_TYPE, typestore)
    fields = [construct(field_cls, name=name, offset=offset, datatype=code, count=count)
              for name, offset, code, count in specs]
    dense = _all_finite(a) if is_dense is None else bool(is_dense)
    return construct(
        cls, header=make_header(stamp_ns, frame_id, cls, typestore=typestore),
        height=int(height), width=int(width), fields=fields, is_bigendian=bool(bigendian),
        point_step=int(a.dtype.itemsize), row_step=int(width * a.dtype.itemsize),
        data=uint8_field(cls, out.reshape(-1).view(np.uint8)), is_dense=dense)


class _Spec:
    """A PointField-like record (name, offset, datatype, count) for :func:`fields_to_dtype`."""

    __slots__ = ('name', 'offset', 'datatype', 'count')

    def __init__(self, name: str, offset: int, datatype: int, count: int) -> None:
        self.name, self.offset, self.datatype, self.count = name, offset, datatype, count


def field_summary(msg: Any) -> str:
    """Human-readable field list of a PointCloud2, e.g. ``'u:FLOAT32@0 descriptor:FLOAT32x64@16'``.
    """
    parts = []
    for f in msg.fields:
        name = _DATATYPE_NAMES.get(int(f.datatype), str(int(f.datatype)))
        count = f'x{int(f.count)}' if int(f.count) != 1 else ''
        parts.append(f'{f.name}:{name}{count}@{int(f.offset)}')
    return ' '.join(parts)
