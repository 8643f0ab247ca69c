"""msg_adapters.image: raw sensor_msgs/Image <-> numpy, both flavours, CDR round trips."""
from __future__ import annotations

import dataclasses
import struct
import time
from typing import Any

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
import sensor_msgs.msg

from msg_adapters import (
    ArrayShapeError,
    DataLengthError,
    ImageSizeError,
    ImageTooLargeError,
    StepMismatchError,
    UnsupportedEncodingError,
    WrongMessageTypeError,
    depth_to_metres,
    image_to_numpy,
    numpy_to_image,
    stamp_to_ns,
    to_rgb_or_mono,
)

TS = get_typestore(Stores.ROS2_JAZZY)
IMAGE = 'sensor_msgs/msg/Image'
FLAVOURS = {'rclpy': sensor_msgs.msg.Image, 'rosbags': TS.types[IMAGE]}


def cdr_round_trip(msg: Any) -> Any:
    """Serialise and deserialise with the message's own flavour."""
    if hasattr(msg, '__msgtype__'):
        return TS.deserialize_cdr(bytes(TS.serialize_cdr(msg, msg.__msgtype__)), msg.__msgtype__)
    return deserialize_message(serialize_message(msg), type(msg))


def cross(msg: Any) -> Any:
    """Serialise with one flavour, deserialise with the other."""
    if hasattr(msg, '__msgtype__'):
        raw = bytes(TS.serialize_cdr(msg, msg.__msgtype__))
        return deserialize_message(raw, sensor_msgs.msg.Image)
    return TS.deserialize_cdr(serialize_message(msg), IMAGE)


def assert_cdr_equivalent(raw_rclpy: bytes, raw_rosbags: bytes, msgtype: str) -> None:
    """Byte-identical CDR except alignment padding (Fast CDR leaves it uninitialised)."""
    a = np.frombuffer(raw_rclpy, np.uint8)
    b = np.frombuffer(raw_rosbags, np.uint8)
    assert a.shape == b.shape
    diff = np.flatnonzero(a != b)
    assert np.all(b[diff] == 0), 'only zero padding bytes may differ'
    normalised = bytes(TS.serialize_cdr(TS.deserialize_cdr(raw_rclpy, msgtype), msgtype))
    assert normalised == raw_rosbags


def with_fields(msg: Any, **fields: Any) -> Any:
    """A copy of ``msg`` with some fields replaced (bytes data allowed for both flavours)."""
    if hasattr(msg, '__msgtype__'):
        if isinstance(fields.get('data'), (bytes, bytearray)):
            fields['data'] = np.frombuffer(bytes(fields['data']), np.uint8).copy()
        return dataclasses.replace(msg, **fields)
    out = cdr_round_trip(msg)
    for name, value in fields.items():
        setattr(out, name, value)
    return out


def random_image(rng: np.random.Generator, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    dtype = np.dtype(dtype)
    if dtype.kind == 'f':
        return rng.normal(0, 100, shape).astype(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, shape, dtype=dtype, endpoint=True)


ENCODINGS = [
    ('rgb8', np.uint8, 3), ('bgr8', np.uint8, 3), ('rgba8', np.uint8, 4),
    ('bgra8', np.uint8, 4), ('mono8', np.uint8, 1), ('mono16', np.uint16, 1),
    ('16UC1', np.uint16, 1), ('32FC1', np.float32, 1), ('8UC3', np.uint8, 3),
    ('16SC1', np.int16, 1), ('32SC2', np.int32, 2), ('64FC1', np.float64, 1),
    ('rgb16', np.uint16, 3), ('bayer_rggb8', np.uint8, 1), ('yuv422', np.uint8, 2),
    ('8SC4', np.int8, 4),
]


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('encoding,dtype,channels', ENCODINGS)
def test_round_trip_through_cdr(flavour: str, encoding: str, dtype: Any, channels: int) -> None:
    rng = np.random.default_rng(7)
    shape = (5, 7) if channels == 1 else (5, 7, channels)
    arr = random_image(rng, shape, dtype)
    msg = numpy_to_image(arr, encoding, stamp_ns=1_700_000_000_000_000_001,
                         frame_id='camera_front_optical', msg_cls=FLAVOURS[flavour])
    assert msg.step == 7 * channels * np.dtype(dtype).itemsize
    assert msg.is_bigendian == 0
    for received in (cdr_round_trip(msg), cross(msg)):
        out = image_to_numpy(received)
        assert out.dtype == np.dtype(dtype) and out.dtype.isnative
        assert out.shape == shape
        np.testing.assert_array_equal(out, arr)
        assert stamp_to_ns(received) == 1_700_000_000_000_000_001
        assert received.header.frame_id == 'camera_front_optical'


@pytest.mark.parametrize('encoding,dtype,channels',
                         [('rgb8', np.uint8, 3), ('mono16', np.uint16, 1),
                          ('32FC1', np.float32, 1)])
def test_cdr_byte_identical_across_flavours(encoding: str, dtype: Any, channels: int) -> None:
    rng = np.random.default_rng(3)
    arr = random_image(rng, (4, 6) if channels == 1 else (4, 6, channels), dtype)
    kw = {'stamp_ns': 42_000_000_123, 'frame_id': 'cam'}
    rc = numpy_to_image(arr, encoding, msg_cls=sensor_msgs.msg.Image, **kw)
    rb = numpy_to_image(arr, encoding, msg_cls=TS, **kw)
    assert_cdr_equivalent(serialize_message(rc), bytes(TS.serialize_cdr(rb, IMAGE)), IMAGE)


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('encoding,dtype,channels',
                         [('rgb8', np.uint8, 3), ('mono16', np.uint16, 1),
                          ('32FC1', np.float32, 1), ('bgra8', np.uint8, 4)])
def test_step_padding_gives_zero_copy_view(flavour: str, encoding: str, dtype: Any,
                                           channels: int) -> None:
    rng = np.random.default_rng(11)
    h, w, pad = 6, 5, 13
    shape = (h, w) if channels == 1 else (h, w, channels)
    arr = random_image(rng, shape, dtype)
    row = w * channels * np.dtype(dtype).itemsize
    little = np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder('<'))
    rows = little.view(np.uint8).reshape(h, row)
    padded = np.full((h, row + pad), 0xAB, np.uint8)
    padded[:, :row] = rows
    base = numpy_to_image(arr, encoding, stamp_ns=0, frame_id='c', msg_cls=FLAVOURS[flavour])
    msg = cdr_round_trip(with_fields(base, step=row + pad, data=padded.tobytes()))
    out = image_to_numpy(msg)
    np.testing.assert_array_equal(out, arr)
    data_view = np.frombuffer(msg.data, np.uint8)
    assert np.shares_memory(out, data_view), 'padded rows must be a view, not a copy'
    assert out.strides[0] == row + pad
    copied = image_to_numpy(msg, copy=True)
    assert copied.flags.c_contiguous and copied.flags.writeable
    assert not np.shares_memory(copied, data_view)
    np.testing.assert_array_equal(copied, arr)
    # cross flavour keeps the padding semantics
    np.testing.assert_array_equal(image_to_numpy(cross(msg)), arr)


def test_rosbags_view_is_read_only_and_rclpy_view_writable() -> None:
    arr = np.arange(12, dtype=np.uint8).reshape(3, 4)
    rb = cdr_round_trip(numpy_to_image(arr, 'mono8', stamp_ns=0, frame_id='', msg_cls=TS))
    out = image_to_numpy(rb)
    with pytest.raises(ValueError):
        out[0, 0] = 1
    rc = cdr_round_trip(numpy_to_image(arr, 'mono8', stamp_ns=0, frame_id='',
                                       msg_cls=sensor_msgs.msg.Image))
    view = image_to_numpy(rc)
    view[0, 0] = 99
    assert rc.data[0] == 99  # shares the message's memory


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('encoding,fmt,dtype', [('mono16', 'H', np.uint16),
                                                ('32FC1', 'f', np.float32),
                                                ('16SC1', 'h', np.int16)])
def test_big_endian_round_trip(flavour: str, encoding: str, fmt: str, dtype: Any) -> None:
    rng = np.random.default_rng(5)
    h, w, pad = 4, 3, 2
    arr = random_image(rng, (h, w), dtype)
    # independent construction of the big-endian bytes with struct, rows padded
    raw = b''.join(struct.pack(f'>{w}{fmt}', *arr[r].tolist()) + b'\xee' * pad
                   for r in range(h))
    base = numpy_to_image(arr, encoding, stamp_ns=0, frame_id='c', msg_cls=FLAVOURS[flavour])
    msg = cdr_round_trip(with_fields(base, is_bigendian=1, step=w * arr.itemsize + pad,
                                     data=raw))
    for received in (msg, cross(msg)):
        out = image_to_numpy(received)
        assert out.dtype.isnative and out.dtype == np.dtype(dtype)
        np.testing.assert_array_equal(out, arr)
    # the builder's own big-endian output equals the struct bytes without padding
    big = numpy_to_image(arr, encoding, stamp_ns=0, frame_id='c', msg_cls=FLAVOURS[flavour],
                         bigendian=True)
    assert big.is_bigendian == 1
    assert bytes(np.frombuffer(big.data, np.uint8)) == b''.join(
        struct.pack(f'>{w}{fmt}', *arr[r].tolist()) for r in range(h))
    np.testing.assert_array_equal(image_to_numpy(cdr_round_trip(big)), arr)


def test_empty_image_round_trip() -> None:
    arr = np.zeros((0, 5, 3), np.uint8)
    msg = cdr_round_trip(numpy_to_image(arr, 'rgb8', stamp_ns=0, frame_id='', msg_cls=TS))
    assert image_to_numpy(msg).shape == (0, 5, 3)
    with pytest.raises(ImageSizeError, match='empty'):
        to_rgb_or_mono(msg)


# ----------------------------------------------------------------------------- bad input

def _mono8(flavour: str, h: int = 4, w: int = 6) -> Any:
    arr = np.arange(h * w, dtype=np.uint8).reshape(h, w)
    return numpy_to_image(arr, 'mono8', stamp_ns=0, frame_id='c', msg_cls=FLAVOURS[flavour])


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_unknown_encoding(flavour: str) -> None:
    msg = with_fields(_mono8(flavour), encoding='mono12p')
    with pytest.raises(UnsupportedEncodingError, match="'mono12p'"):
        image_to_numpy(msg)
    with pytest.raises(UnsupportedEncodingError):
        numpy_to_image(np.zeros((2, 2), np.uint8), 'jpeg', stamp_ns=0, frame_id='',
                       msg_cls=TS)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_step_smaller_than_row(flavour: str) -> None:
    msg = with_fields(_mono8(flavour), encoding='rgb8')  # step 6 < 6 px * 3 bytes
    with pytest.raises(StepMismatchError, match=r'Image.step: 6 bytes .* 6\*3 = 18'):
        image_to_numpy(msg)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_truncated_data(flavour: str) -> None:
    msg = with_fields(_mono8(flavour), data=bytes(23))
    with pytest.raises(DataLengthError, match=r'23 bytes, expected step\*height = 6\*4 = 24'):
        image_to_numpy(msg)
    msg = with_fields(_mono8(flavour), step=7)  # padding claimed but not present
    with pytest.raises(DataLengthError):
        image_to_numpy(msg)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_forged_huge_header_rejected_without_allocation(flavour: str) -> None:
    msg = with_fields(_mono8(flavour), width=200_000, height=200_000, step=600_000,
                      encoding='rgb8')
    t0 = time.perf_counter()
    with pytest.raises(ImageTooLargeError, match='200000\\*200000'):
        image_to_numpy(msg)
    assert time.perf_counter() - t0 < 0.5
    # within the pixel limit but far beyond the data: a length error, still no allocation
    msg = with_fields(_mono8(flavour), width=7000, height=7000, step=21000, encoding='rgb8')
    with pytest.raises(DataLengthError):
        image_to_numpy(msg)
    with pytest.raises(ImageTooLargeError):
        image_to_numpy(_mono8(flavour), max_pixels=23)
    assert image_to_numpy(_mono8(flavour), max_pixels=24).shape == (4, 6)


def test_builder_rejects_wrong_array_and_class() -> None:
    kw = {'stamp_ns': 0, 'frame_id': ''}
    with pytest.raises(ArrayShapeError, match='needs dtype uint8'):
        numpy_to_image(np.zeros((2, 2, 3), np.float32), 'rgb8', msg_cls=TS, **kw)
    with pytest.raises(ArrayShapeError, match=r'\(height, width, 3\)'):
        numpy_to_image(np.zeros((2, 2), np.uint8), 'rgb8', msg_cls=TS, **kw)
    with pytest.raises(ArrayShapeError, match=r'\(height, width\)'):
        numpy_to_image(np.zeros((2, 2, 3), np.uint16), 'mono16', msg_cls=TS, **kw)
    with pytest.raises(WrongMessageTypeError, match='sensor_msgs/msg/Image'):
        numpy_to_image(np.zeros((2, 2), np.uint8), 'mono8',
                       msg_cls=sensor_msgs.msg.CompressedImage, **kw)
    one_channel = numpy_to_image(np.zeros((2, 3, 1), np.uint8), 'mono8', msg_cls=TS, **kw)
    assert (one_channel.height, one_channel.width, one_channel.step) == (2, 3, 3)


# ----------------------------------------------------------------------------- to_rgb_or_mono

@pytest.mark.parametrize('flavour', FLAVOURS)
def test_to_rgb_or_mono_colour_orders(flavour: str) -> None:
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    cls = FLAVOURS[flavour]
    kw = {'stamp_ns': 0, 'frame_id': 'c', 'msg_cls': cls}
    cases = {
        'rgb8': rgb, 'bgr8': rgb[..., ::-1],
        'rgba8': np.dstack([rgb, np.full((4, 5), 7, np.uint8)]),
        'bgra8': np.dstack([rgb[..., ::-1], np.full((4, 5), 7, np.uint8)]),
        'rgb16': rgb.astype(np.uint16) << 8, 'bgr16': rgb[..., ::-1].astype(np.uint16) << 8,
    }
    for encoding, arr in cases.items():
        out = to_rgb_or_mono(cdr_round_trip(numpy_to_image(arr, encoding, **kw)))
        assert out.dtype == np.uint8 and out.shape == (4, 5, 3), encoding
        np.testing.assert_array_equal(out, rgb, err_msg=encoding)
    mono = rng.integers(0, 256, (4, 5), dtype=np.uint8)
    for encoding, arr in {'mono8': mono, '8UC1': mono,
                          'mono16': (mono.astype(np.uint16) << 8) | 0xFF,
                          '16UC1': mono.astype(np.uint16) << 8}.items():
        out = to_rgb_or_mono(cdr_round_trip(numpy_to_image(arr, encoding, **kw)))
        assert out.shape == (4, 5) and out.dtype == np.uint8
        np.testing.assert_array_equal(out, mono, err_msg=encoding)
    twelve_bit = mono.astype(np.uint16) << 4
    msg = numpy_to_image(twelve_bit, 'mono16', **kw)
    np.testing.assert_array_equal(to_rgb_or_mono(msg, bit_depth=12), mono)


@pytest.mark.parametrize('pattern', ['rggb', 'bggr', 'gbrg', 'grbg'])
@pytest.mark.parametrize('bits', [8, 16])
def test_bayer_demosaic(pattern: str, bits: int) -> None:
    colour = np.array([200, 100, 50], np.uint8)  # R, G, B
    h, w = 16, 20
    index = {'r': 0, 'g': 1, 'b': 2}
    mosaic = np.zeros((h, w), np.uint8)
    for dy in (0, 1):
        for dx in (0, 1):
            mosaic[dy::2, dx::2] = colour[index[pattern[2 * dy + dx]]]
    arr = mosaic if bits == 8 else mosaic.astype(np.uint16) << 8
    msg = numpy_to_image(arr, f'bayer_{pattern}{bits}', stamp_ns=0, frame_id='', msg_cls=TS)
    out = to_rgb_or_mono(cdr_round_trip(msg))
    assert out.shape == (h, w, 3)
    np.testing.assert_array_equal(out[4:-4, 4:-4], np.broadcast_to(colour, (h - 8, w - 8, 3)))


@pytest.mark.parametrize('encoding,order', [('yuv422', 'uyvy'), ('uyvy', 'uyvy'),
                                            ('yuv422_yuy2', 'yuyv'), ('yuyv', 'yuyv')])
def test_yuv422_to_rgb(encoding: str, order: str) -> None:
    h, w = 4, 8
    # left half grey (U = V = 128), right half strongly red (V high, U low)
    y = np.full((h, w), 120, np.uint8)
    u = np.where(np.arange(w // 2) < w // 4, 128, 90).astype(np.uint8)
    v = np.where(np.arange(w // 2) < w // 4, 128, 220).astype(np.uint8)
    packed = np.zeros((h, w, 2), np.uint8)
    packed[:, :, 1 if order == 'uyvy' else 0] = y
    chroma = np.zeros((h, w), np.uint8)
    chroma[:, 0::2], chroma[:, 1::2] = u, v
    packed[:, :, 0 if order == 'uyvy' else 1] = chroma
    msg = numpy_to_image(packed, encoding, stamp_ns=0, frame_id='', msg_cls=TS)
    out = to_rgb_or_mono(msg).astype(int)
    grey = out[:, : w // 2]
    assert np.ptp(grey) <= 2 and abs(grey.mean() - 120) < 25  # limited/full range both fine
    red = out[:, w // 2:]
    assert (red[..., 0] > red[..., 1] + 60).all() and (red[..., 0] > red[..., 2] + 60).all()
    odd = numpy_to_image(np.zeros((2, 3, 2), np.uint8), encoding, stamp_ns=0, frame_id='',
                         msg_cls=TS)
    with pytest.raises(ImageSizeError, match='even width'):
        to_rgb_or_mono(odd)


@pytest.mark.parametrize('encoding,dtype,channels', [('32FC1', np.float32, 1),
                                                     ('8UC3', np.uint8, 3),
                                                     ('64FC1', np.float64, 1)])
def test_to_rgb_or_mono_rejects_non_intensity(encoding: str, dtype: Any, channels: int) -> None:
    arr = np.zeros((2, 2) if channels == 1 else (2, 2, channels), dtype)
    msg = numpy_to_image(arr, encoding, stamp_ns=0, frame_id='', msg_cls=TS)
    with pytest.raises(UnsupportedEncodingError, match=encoding):
        to_rgb_or_mono(msg)


def test_to_rgb_or_mono_rejects_other_messages() -> None:
    with pytest.raises(WrongMessageTypeError):
        to_rgb_or_mono(sensor_msgs.msg.CameraInfo())


def test_large_frame_is_fast() -> None:
    """A real 1920x1536 rgb8 frame: build, round trip and view in well under a second."""
    rgb = np.random.default_rng(0).integers(0, 256, (1536, 1920, 3), dtype=np.uint8)
    t0 = time.perf_counter()
    for cls in FLAVOURS.values():
        msg = cdr_round_trip(numpy_to_image(rgb, 'bgr8', stamp_ns=0, frame_id='', msg_cls=cls))
        out = to_rgb_or_mono(msg)
        assert out.shape == (1536, 1920, 3)
        np.testing.assert_array_equal(out[::97, ::89], rgb[::97, ::89, ::-1])
    assert time.perf_counter() - t0 < 3.0


def test_depth_to_metres_millimetres_metres_and_no_depth() -> None:
    mm = np.array([[0, 1500], [65535, 250]], np.uint16)
    d = depth_to_metres(mm, '16UC1')
    assert d.dtype == np.float32 and np.isnan(d[0, 0])
    np.testing.assert_allclose(d[~np.isnan(d)], [1.5, 65.535, 0.25], rtol=1e-6)
    m = np.array([[np.inf, 2.5]], np.float64)
    np.testing.assert_array_equal(depth_to_metres(m, '64FC1'), m.astype(np.float32))
    with pytest.raises(UnsupportedEncodingError, match='rgb8'):
        depth_to_metres(np.zeros((2, 2, 3), np.uint8), 'rgb8')
