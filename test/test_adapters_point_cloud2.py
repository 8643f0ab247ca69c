"""msg_adapters.point_cloud2: any PointCloud2 layout, property-based, both flavours."""
from __future__ import annotations

import array
import struct
import time
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
import sensor_msgs.msg

from msg_adapters import (
    DATATYPES,
    ArrayShapeError,
    DataLengthError,
    PointFieldError,
    StepMismatchError,
    array_to_pointcloud2,
    pointcloud2_to_array,
    stamp_to_ns,
)

TS = get_typestore(Stores.ROS2_JAZZY)
PC2 = 'sensor_msgs/msg/PointCloud2'
FLAVOURS = {'rclpy': sensor_msgs.msg.PointCloud2, 'rosbags': TS.types[PC2]}
STRUCT_CODES = {1: 'b', 2: 'B', 3: 'h', 4: 'H', 5: 'i', 6: 'I', 7: 'f', 8: 'd'}
Field = tuple[str, int, int, int]  # name, offset, datatype, count


def cdr_round_trip(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return TS.deserialize_cdr(bytes(TS.serialize_cdr(msg, PC2)), PC2)
    return deserialize_message(serialize_message(msg), type(msg))


def cross(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return deserialize_message(bytes(TS.serialize_cdr(msg, PC2)),
                                   sensor_msgs.msg.PointCloud2)
    return TS.deserialize_cdr(serialize_message(msg), PC2)


def build_cloud(flavour: str, fields: list[Field], *, point_step: int, row_step: int,
                width: int, height: int, data: bytes, bigendian: bool = False) -> Any:
    """A PointCloud2 assembled field by field, as a foreign producer would (no adapter)."""
    if flavour == 'rclpy':
        msg = sensor_msgs.msg.PointCloud2()
        msg.header.frame_id = 'lidar'
        msg.header.stamp.sec, msg.header.stamp.nanosec = 3, 4
        msg.fields = [sensor_msgs.msg.PointField(name=n, offset=o, datatype=d, count=c)
                      for n, o, d, c in fields]
        msg.height, msg.width, msg.is_bigendian = height, width, bigendian
        msg.point_step, msg.row_step, msg.is_dense = point_step, row_step, True
        msg.data = array.array('B', data)
        return msg
    point_field = TS.types['sensor_msgs/msg/PointField']
    header = TS.types['std_msgs/msg/Header'](
        stamp=TS.types['builtin_interfaces/msg/Time'](sec=3, nanosec=4), frame_id='lidar')
    return TS.types[PC2](
        header=header, height=height, width=width,
        fields=[point_field(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
        is_bigendian=bigendian, point_step=point_step, row_step=row_step,
        data=np.frombuffer(data, np.uint8).copy(), is_dense=True)


def random_values(rng: np.random.Generator, datatype: int, shape: tuple[int, ...]) -> np.ndarray:
    dtype = DATATYPES[datatype]
    if dtype.kind == 'f':
        values = rng.normal(0.0, 1e3, shape).astype(dtype)
        if values.size:
            values.reshape(-1)[0] = np.nan  # NaN passes through the read path
        return values
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, shape, dtype=dtype, endpoint=True)


def pack_cloud(fields: list[Field], values: dict[str, np.ndarray], *, point_step: int,
               row_step: int, width: int, height: int, bigendian: bool) -> bytes:
    """Serialise points with struct.pack_into (independent of the numpy read path)."""
    buf = bytearray(b'\x5a' * (row_step * height))  # non-zero filler in all padding
    order = '>' if bigendian else '<'
    for name, offset, datatype, count in fields:
        code = order + STRUCT_CODES[datatype]
        size = DATATYPES[datatype].itemsize
        column = values[name]
        for r in range(height):
            for c in range(width):
                for k in range(count):
                    pos = r * row_step + c * point_step + offset + k * size
                    struct.pack_into(code, buf, pos, column[r, c, k].item())
    return bytes(buf)


@st.composite
def layouts(draw: Any) -> dict[str, Any]:
    n_fields = draw(st.integers(1, 6))
    names = draw(st.lists(st.text('xyzabcdefghijklmnopqrstuvw_0123456789', min_size=1,
                                  max_size=8), min_size=n_fields, max_size=n_fields,
                          unique=True))
    fields: list[Field] = []
    offset = 0
    for name in names:
        offset += draw(st.integers(0, 3))  # padding between fields (also unaligned offsets)
        datatype = draw(st.integers(1, 8))
        count = draw(st.integers(1, 4))
        fields.append((name, offset, datatype, count))
        offset += DATATYPES[datatype].itemsize * count
    order = draw(st.permutations(range(n_fields)))  # PointField list not sorted by offset
    width = draw(st.integers(0, 5))
    point_step = offset + draw(st.integers(0, 8))
    return {
        'fields': [fields[i] for i in order], 'point_step': point_step, 'width': width,
        'height': draw(st.integers(1, 3)),
        'row_step': width * point_step + draw(st.integers(0, 9)),
        'bigendian': draw(st.booleans()), 'seed': draw(st.integers(0, 2 ** 32 - 1)),
    }


@settings(max_examples=200, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(layout=layouts())
def test_read_any_layout_both_flavours(layout: dict[str, Any]) -> None:
    rng = np.random.default_rng(layout['seed'])
    fields, height, width = layout['fields'], layout['height'], layout['width']
    values = {name: random_values(rng, datatype, (height, width, count))
              for name, _, datatype, count in fields}
    geometry = {k: layout[k] for k in ('point_step', 'row_step', 'width', 'height')}
    data = pack_cloud(fields, values, bigendian=layout['bigendian'], **geometry)
    for flavour in FLAVOURS:
        msg = build_cloud(flavour, fields, data=data, bigendian=layout['bigendian'], **geometry)
        for received in (cdr_round_trip(msg), cross(msg)):
            arr = pointcloud2_to_array(received)
            assert arr.shape == ((width,) if height == 1 else (height, width))
            assert arr.dtype.itemsize == layout['point_step']
            if arr.size:
                assert np.shares_memory(arr, np.frombuffer(received.data, np.uint8))
            organised = arr.reshape(height, width)
            for name, _, _, count in fields:
                got = organised[name].reshape(height, width, count)
                np.testing.assert_array_equal(got, values[name], err_msg=name)
            native = pointcloud2_to_array(received, native=True, flat=True)
            assert native.shape == (height * width,)
            assert all(native.dtype.fields[n][0].base.isnative for n in native.dtype.names)
            for name, _, _, count in fields:
                np.testing.assert_array_equal(native[name].reshape(height, width, count),
                                              values[name])
            # write path: the view -> a new message -> the same values and layout
            rebuilt = array_to_pointcloud2(organised, stamp_ns=7, frame_id='lidar',
                                           msg_cls=FLAVOURS[flavour])
            assert rebuilt.point_step == layout['point_step']
            assert rebuilt.row_step == width * layout['point_step']
            assert sorted((f.name, f.offset, f.datatype, f.count)
                          for f in rebuilt.fields) == sorted(fields)
            multibyte = any(DATATYPES[d].itemsize > 1 for _, _, d, _ in fields)
            assert bool(rebuilt.is_bigendian) == (layout['bigendian'] and multibyte)
            again = pointcloud2_to_array(cross(rebuilt)).reshape(height, width)
            for name, _, _, count in fields:
                np.testing.assert_array_equal(again[name].reshape(height, width, count),
                                              values[name])


def _xyz_cloud(flavour: str, n: int = 4) -> Any:
    arr = np.zeros(n, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('i', '<u2')])
    arr['x'] = np.arange(n)
    return array_to_pointcloud2(arr, stamp_ns=1, frame_id='lidar', msg_cls=FLAVOURS[flavour])


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_write_read_and_header(flavour: str) -> None:
    dtype = np.dtype({'names': ['x', 'y', 'z', 'rgb', 'normal'],
                      'formats': ['<f4', '<f4', '<f4', '<u4', ('<f8', (3,))],
                      'offsets': [0, 4, 8, 16, 24], 'itemsize': 56})
    rng = np.random.default_rng(0)
    arr = np.zeros((3, 4), dtype=dtype)
    for name in ('x', 'y', 'z'):
        arr[name] = rng.normal(size=(3, 4))
    arr['rgb'] = rng.integers(0, 2 ** 32, (3, 4), dtype=np.uint32)
    arr['normal'] = rng.normal(size=(3, 4, 3))
    msg = array_to_pointcloud2(arr, stamp_ns=1_600_000_000_000_000_123, frame_id='lidar',
                               msg_cls=FLAVOURS[flavour])
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (3, 4, 56, 224)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1), ('rgb', 16, 6, 1), ('normal', 24, 8, 3)]
    assert msg.is_dense and not msg.is_bigendian
    raw = np.frombuffer(msg.data, np.uint8).reshape(12, 56)
    assert not raw[:, 12:16].any() and not raw[:, 20:24].any()  # padding zero-filled
    for received in (cdr_round_trip(msg), cross(msg)):
        out = pointcloud2_to_array(received)
        assert out.shape == (3, 4)
        for name in dtype.names:
            np.testing.assert_array_equal(out[name], arr[name])
        assert stamp_to_ns(received) == 1_600_000_000_000_000_123
        flat = pointcloud2_to_array(received, flat=True)
        np.testing.assert_array_equal(flat['normal'], arr['normal'].reshape(12, 3))


def test_is_dense_and_nan_pass_through() -> None:
    arr = np.zeros(3, dtype=[('x', '<f4'), ('v', '<f8', (2,))])
    assert array_to_pointcloud2(arr, stamp_ns=0, frame_id='', msg_cls=TS).is_dense
    arr['v'][1, 1] = np.nan
    msg = array_to_pointcloud2(arr, stamp_ns=0, frame_id='', msg_cls=TS)
    assert not msg.is_dense
    assert np.isnan(pointcloud2_to_array(cdr_round_trip(msg))['v'][1, 1])
    assert array_to_pointcloud2(arr, stamp_ns=0, frame_id='', msg_cls=TS, is_dense=True).is_dense


def test_big_endian_write_and_read() -> None:
    arr = np.zeros(5, dtype=[('x', '>f4'), ('id', '>u4'), ('flag', 'u1')])
    arr['x'] = np.linspace(-1, 1, 5)
    arr['id'] = [1, 2 ** 31, 3, 4, 2 ** 32 - 1]
    msg = array_to_pointcloud2(arr, stamp_ns=0, frame_id='', msg_cls=TS)
    assert msg.is_bigendian
    assert bytes(msg.data[:4]) == struct.pack('>f', -1.0)
    out = pointcloud2_to_array(cdr_round_trip(msg))
    np.testing.assert_array_equal(out['id'], arr['id'])
    assert out['x'].dtype.byteorder == '>'
    native = pointcloud2_to_array(msg, native=True)
    assert native['x'].dtype.isnative
    np.testing.assert_array_equal(native['x'], arr['x'])
    mixed = np.zeros(2, dtype=[('a', '>f4'), ('b', '<f4')])
    mixed['a'], mixed['b'] = [1, 2], [3, 4]
    msg = array_to_pointcloud2(mixed, stamp_ns=0, frame_id='', msg_cls=TS)
    assert not msg.is_bigendian  # mixed orders are written little-endian
    out = pointcloud2_to_array(msg)
    np.testing.assert_array_equal(out['a'], [1, 2])
    np.testing.assert_array_equal(out['b'], [3, 4])


def test_cdr_byte_identical_across_flavours() -> None:
    arr = np.zeros(7, dtype=[('x', '<f4'), ('label', 'u1'), ('d', '<f4', (3,))])
    arr['x'] = np.arange(7)
    arr['d'] = np.arange(21).reshape(7, 3)
    rc = array_to_pointcloud2(arr, stamp_ns=5, frame_id='map',
                              msg_cls=sensor_msgs.msg.PointCloud2)
    rb = array_to_pointcloud2(arr, stamp_ns=5, frame_id='map', msg_cls=TS)
    raw_rc, raw_rb = serialize_message(rc), bytes(TS.serialize_cdr(rb, PC2))
    a, b = np.frombuffer(raw_rc, np.uint8), np.frombuffer(raw_rb, np.uint8)
    assert a.shape == b.shape and np.all(b[a != b] == 0)
    assert bytes(TS.serialize_cdr(TS.deserialize_cdr(raw_rc, PC2), PC2)) == raw_rb


def test_empty_cloud() -> None:
    arr = np.zeros(0, dtype=[('x', '<f4'), ('y', '<f4')])
    for cls in FLAVOURS.values():
        msg = cdr_round_trip(array_to_pointcloud2(arr, stamp_ns=0, frame_id='', msg_cls=cls))
        assert (msg.width, msg.height, len(msg.data)) == (0, 1, 0)
        out = pointcloud2_to_array(msg)
        assert out.shape == (0,) and out.dtype.names == ('x', 'y')


# ----------------------------------------------------------------------------- bad input

GOOD: list[Field] = [('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1)]


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('fields,point_step,pattern', [
    ([('x', 0, 7, 1), ('y', 2, 7, 1)], 12, "'x'.*overlaps 'y'"),
    ([('x', 0, 7, 1), ('d', 4, 8, 2), ('e', 16, 2, 1)], 24, "'d'.*overlaps 'e'"),
    ([('x', 0, 7, 1), ('y', 10, 7, 1)], 12, r'\[10, 14\) reach beyond point_step = 12'),
    ([('v', 0, 7, 4)], 12, r'\[0, 16\) reach beyond'),
    ([('x', 0, 9, 1)], 12, 'datatype: unknown 9'),
    ([('x', 0, 0, 1)], 12, 'datatype: unknown 0'),
    ([('x', 0, 7, 1), ('x', 4, 7, 1)], 12, "duplicate name 'x'"),
    ([('x', 0, 7, 0)], 12, 'count: expected >= 1, got 0'),
    ([('', 0, 7, 1)], 12, 'name is empty'),
])
def test_bad_fields(flavour: str, fields: list[Field], point_step: int, pattern: str) -> None:
    msg = build_cloud(flavour, fields, point_step=point_step, row_step=point_step * 2, width=2,
                      height=1, data=bytes(point_step * 2))
    with pytest.raises(PointFieldError, match=pattern):
        pointcloud2_to_array(cdr_round_trip(msg))


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_bad_geometry(flavour: str) -> None:
    short = build_cloud(flavour, GOOD, point_step=12, row_step=36, width=3, height=2,
                        data=bytes(71))
    with pytest.raises(DataLengthError, match=r'71 bytes, expected row_step\*height = 36\*2'):
        pointcloud2_to_array(short)
    narrow = build_cloud(flavour, GOOD, point_step=12, row_step=30, width=3, height=2,
                         data=bytes(72))
    with pytest.raises(StepMismatchError, match=r'30 bytes .* 3\*12 = 36'):
        pointcloud2_to_array(narrow)
    forged = build_cloud(flavour, GOOD, point_step=12, row_step=12 * 10 ** 9, width=10 ** 9,
                         height=10 ** 6, data=bytes(36))
    t0 = time.perf_counter()
    with pytest.raises(DataLengthError):
        pointcloud2_to_array(forged)
    assert time.perf_counter() - t0 < 0.5
    # organised with padded rows: flat=True has to copy and still be right
    rows = np.arange(2 * 40, dtype=np.uint8).reshape(2, 40)
    padded = build_cloud(flavour, [('a', 0, 2, 1), ('b', 1, 2, 2)], point_step=4,
                         row_step=40, width=9, height=2, data=rows.tobytes())
    flat = pointcloud2_to_array(padded, flat=True)
    np.testing.assert_array_equal(flat['a'], np.concatenate([rows[0, 0:36:4],
                                                             rows[1, 0:36:4]]))
    assert pointcloud2_to_array(padded).shape == (2, 9)


def test_write_rejects_unsupported_arrays() -> None:
    kw = {'stamp_ns': 0, 'frame_id': '', 'msg_cls': TS}
    with pytest.raises(ArrayShapeError, match='structured'):
        array_to_pointcloud2(np.zeros(3, np.float32), **kw)
    with pytest.raises(ArrayShapeError, match='no PointField datatype'):
        array_to_pointcloud2(np.zeros(3, dtype=[('ok', bool)]), **kw)
    with pytest.raises(ArrayShapeError, match='no PointField datatype'):
        array_to_pointcloud2(np.zeros(3, dtype=[('t', '<i8')]), **kw)
    with pytest.raises(ArrayShapeError, match='not 1-D'):
        array_to_pointcloud2(np.zeros(3, dtype=[('m', '<f4', (2, 2))]), **kw)
    with pytest.raises(ArrayShapeError, match=r'\(N,\) or \(H, W\)'):
        array_to_pointcloud2(np.zeros((2, 2, 2), dtype=[('x', '<f4')]), **kw)
    with pytest.raises(ArrayShapeError, match='no PointField datatype'):
        array_to_pointcloud2(np.zeros(2, dtype=[('s', [('a', '<f4')])]), **kw)
    assert pointcloud2_to_array(_xyz_cloud('rosbags'))['i'].dtype == np.dtype('<u2')
