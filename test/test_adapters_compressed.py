"""msg_adapters.image: sensor_msgs/CompressedImage (jpeg, png) <-> numpy, both flavours."""
from __future__ import annotations

import dataclasses
import time
from typing import Any

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
import sensor_msgs.msg

from msg_adapters import (
    ArrayShapeError,
    CompressedDecodeError,
    ImageSizeError,
    ImageTooLargeError,
    UnsupportedFormatError,
    ValueRangeError,
    compressed_size,
    compressed_to_numpy,
    numpy_to_compressed,
    parse_compressed_format,
    stamp_to_ns,
    to_rgb_or_mono,
)
from msg_adapters.image import CompressedFormat

TS = get_typestore(Stores.ROS2_JAZZY)
COMPRESSED = 'sensor_msgs/msg/CompressedImage'
FLAVOURS = {'rclpy': sensor_msgs.msg.CompressedImage, 'rosbags': TS.types[COMPRESSED]}


def cdr_round_trip(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return TS.deserialize_cdr(bytes(TS.serialize_cdr(msg, COMPRESSED)), COMPRESSED)
    return deserialize_message(serialize_message(msg), type(msg))


def cross(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return deserialize_message(bytes(TS.serialize_cdr(msg, COMPRESSED)),
                                   sensor_msgs.msg.CompressedImage)
    return TS.deserialize_cdr(serialize_message(msg), COMPRESSED)


def make_msg(flavour: str, data: bytes, fmt: str) -> Any:
    """A CompressedImage built directly (as another producer would), not by the adapter."""
    cls = FLAVOURS[flavour]
    template = numpy_to_compressed(np.zeros((2, 2), np.uint8), 'png', stamp_ns=5, frame_id='c',
                                   msg_cls=cls)
    if flavour == 'rosbags':
        return dataclasses.replace(template, format=fmt,
                                   data=np.frombuffer(data, np.uint8).copy())
    template.format = fmt
    template.data = data
    return template


def smooth_rgb(h: int = 48, w: int = 64) -> np.ndarray:
    """A smooth colour image (JPEG-friendly), RGB uint8."""
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([xx * 255 // (w - 1), yy * 255 // (h - 1),
                     np.full((h, w), 90)], axis=2).astype(np.uint8)


def noisy_rgb(h: int = 30, w: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_png_lossless_round_trips(flavour: str) -> None:
    cls = FLAVOURS[flavour]
    kw = {'stamp_ns': 1_234_000_000_567, 'frame_id': 'camera_front_optical', 'msg_cls': cls}
    rgb = noisy_rgb()
    rng = np.random.default_rng(4)
    cases = [
        (rgb, 'rgb8; png compressed bgr8', rgb),
        (rgb[..., 0], 'mono8; png compressed ', rgb[..., 0]),
        (np.dstack([rgb, rgb[..., :1]]), 'rgba8; png compressed bgra8', rgb),
        (rng.integers(0, 65536, (9, 7), dtype=np.uint16), 'mono16; png compressed ', None),
        (rng.integers(0, 65536, (9, 7, 3), dtype=np.uint16), 'rgb16; png compressed bgr16',
         None),
    ]
    for arr, fmt, expected in cases:
        expected = arr if expected is None else expected
        msg = numpy_to_compressed(arr, 'png', **kw)
        assert msg.format == fmt
        for received in (cdr_round_trip(msg), cross(msg)):
            out = compressed_to_numpy(received)
            assert out.dtype == arr.dtype
            np.testing.assert_array_equal(out, expected, err_msg=fmt)
            assert stamp_to_ns(received) == 1_234_000_000_567
            assert received.header.frame_id == 'camera_front_optical'


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_jpeg_round_trip_and_channel_order(flavour: str) -> None:
    cls = FLAVOURS[flavour]
    rgb = smooth_rgb()
    msg = numpy_to_compressed(rgb, 'jpeg', stamp_ns=0, frame_id='c', msg_cls=cls, quality=95)
    assert msg.format == 'rgb8; jpeg compressed bgr8'
    assert bytes(np.frombuffer(msg.data, np.uint8)[:3]) == b'\xff\xd8\xff'
    for received in (cdr_round_trip(msg), cross(msg)):
        out = compressed_to_numpy(received)
        assert out.shape == rgb.shape and out.dtype == np.uint8
        assert np.abs(out.astype(int) - rgb).mean() < 3.0
    red = np.zeros((16, 16, 3), np.uint8)
    red[..., 0] = 230
    out = compressed_to_numpy(numpy_to_compressed(red, 'jpg', stamp_ns=0, frame_id='',
                                                  msg_cls=cls))
    assert out[..., 0].min() > 200 and out[..., 2].max() < 30
    mono = numpy_to_compressed(rgb[..., 1], 'jpeg', stamp_ns=0, frame_id='', msg_cls=cls)
    assert mono.format == 'mono8; jpeg compressed mono8'
    out = compressed_to_numpy(cdr_round_trip(mono))
    assert out.shape == rgb.shape[:2]
    assert np.abs(out.astype(int) - rgb[..., 1]).mean() < 3.0
    rgba = numpy_to_compressed(np.dstack([rgb, rgb[..., :1]]), 'jpeg', stamp_ns=0,
                               frame_id='', msg_cls=cls)
    assert rgba.format == 'rgba8; jpeg compressed bgr8'
    assert compressed_to_numpy(rgba).shape == rgb.shape


def test_quality_changes_size() -> None:
    rgb = noisy_rgb(64, 64)
    low = numpy_to_compressed(rgb, 'jpeg', stamp_ns=0, frame_id='', msg_cls=TS, quality=20)
    high = numpy_to_compressed(rgb, 'jpeg', stamp_ns=0, frame_id='', msg_cls=TS, quality=98)
    assert low.data.size < high.data.size


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_decode_foreign_producers(flavour: str) -> None:
    """Messages as image_transport and older drivers write them."""
    rgb = smooth_rgb()
    bgr_png = cv2.imencode('.png', rgb[..., ::-1].copy())[1].tobytes()
    rgb_png = cv2.imencode('.png', rgb)[1].tobytes()  # RGB stored as is (format says so)
    gray_png = cv2.imencode('.png', rgb[..., 0].copy())[1].tobytes()
    for data, fmt in [(bgr_png, 'bgr8; png compressed bgr8'), (bgr_png, 'png'),
                      (bgr_png, 'PNG'), (bgr_png, ''), (bgr_png, 'bgr8'),
                      (rgb_png, 'rgb8; png compressed rgb8'),
                      (bgr_png, 'jpeg')]:  # a mislabelled codec: the magic bytes decide
        out = compressed_to_numpy(cdr_round_trip(make_msg(flavour, data, fmt)))
        np.testing.assert_array_equal(out, rgb, err_msg=fmt)
    out = compressed_to_numpy(make_msg(flavour, gray_png, 'mono8; png compressed '))
    np.testing.assert_array_equal(out, rgb[..., 0])
    jpg = cv2.imencode('.jpg', rgb[..., ::-1].copy(), [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
    out = compressed_to_numpy(make_msg(flavour, jpg.tobytes(), 'bgr8; jpeg compressed bgr8'))
    assert np.abs(out.astype(int) - rgb).mean() < 3.0
    assert compressed_size(make_msg(flavour, jpg.tobytes(), 'jpeg')) == ('jpeg', 64, 48)
    assert compressed_size(make_msg(flavour, bgr_png, 'png')) == ('png', 64, 48)


def test_parse_compressed_format() -> None:
    assert parse_compressed_format('rgb8; jpeg compressed bgr8') == CompressedFormat(
        'jpeg', 'rgb8', 'bgr8')
    assert parse_compressed_format('mono8; png compressed ') == CompressedFormat(
        'png', 'mono8', None)
    assert parse_compressed_format('jpeg') == CompressedFormat('jpeg', None, None)
    assert parse_compressed_format('JPG') == CompressedFormat('jpeg', None, None)
    assert parse_compressed_format('') == CompressedFormat(None, None, None)
    assert parse_compressed_format('bgr8') == CompressedFormat(None, 'bgr8', None)
    for bad in ['16UC1; compressedDepth png', '16UC1; compressedDepth', 'tiff',
                'rgb8; tiff compressed ', 'h264', 'bgr8; qoi compressed bgr8']:
        with pytest.raises(UnsupportedFormatError, match='not supported'):
            parse_compressed_format(bad)


# ----------------------------------------------------------------------------- bad input

@pytest.mark.parametrize('flavour', FLAVOURS)
def test_corrupt_jpeg_rejected(flavour: str) -> None:
    jpg = numpy_to_compressed(noisy_rgb(120, 160), 'jpeg', stamp_ns=0, frame_id='',
                              msg_cls=TS).data.tobytes()
    fmt = 'rgb8; jpeg compressed bgr8'
    rng = np.random.default_rng(9)
    corrupt = [
        jpg[: len(jpg) // 2],  # truncated inside the scan
        jpg[:100],  # truncated inside the headers
        b'\x00\x00' + jpg[2:],  # SOI destroyed
        b'\xff\xd8\xff' + rng.integers(0, 256, 500, dtype=np.uint8).tobytes(),  # garbage
        b'',
        b'\xff\xd8',
        jpg[:-2],  # end-of-image marker missing
        jpg[:-2] + b'\x00' * 10,
    ]
    for data in corrupt:
        with pytest.raises(CompressedDecodeError):
            compressed_to_numpy(cdr_round_trip(make_msg(flavour, data, fmt)))


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_corrupt_png_rejected(flavour: str) -> None:
    png = numpy_to_compressed(noisy_rgb(), 'png', stamp_ns=0, frame_id='',
                              msg_cls=TS).data.tobytes()
    for data in [png[: len(png) // 2], png[:20], png[:8] + b'\x00' * 40]:
        with pytest.raises(CompressedDecodeError):
            compressed_to_numpy(make_msg(flavour, data, 'rgb8; png compressed bgr8'))


def _patch_jpeg_size(jpg: bytes, width: int, height: int) -> bytes:
    i = jpg.index(b'\xff\xc0')
    return (jpg[: i + 5] + height.to_bytes(2, 'big') + width.to_bytes(2, 'big')
            + jpg[i + 9:])


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_decompression_bomb_rejected_before_decoding(flavour: str) -> None:
    jpg = numpy_to_compressed(smooth_rgb(), 'jpeg', stamp_ns=0, frame_id='',
                              msg_cls=TS).data.tobytes()
    bomb = make_msg(flavour, _patch_jpeg_size(jpg, 65000, 65000), 'jpeg')
    assert compressed_size(bomb) == ('jpeg', 65000, 65000)
    t0 = time.perf_counter()
    with pytest.raises(ImageTooLargeError, match=r'65000\*65000'):
        compressed_to_numpy(bomb)
    assert time.perf_counter() - t0 < 0.5
    png = numpy_to_compressed(smooth_rgb(), 'png', stamp_ns=0, frame_id='',
                              msg_cls=TS).data.tobytes()
    forged = png[:16] + (100_000).to_bytes(4, 'big') + (90_000).to_bytes(4, 'big') + png[24:]
    with pytest.raises(ImageTooLargeError, match=r'100000\*90000'):
        compressed_to_numpy(make_msg(flavour, forged, 'png'))
    small = make_msg(flavour, jpg, 'jpeg')
    with pytest.raises(ImageTooLargeError):
        compressed_to_numpy(small, max_pixels=64 * 48 - 1)
    assert compressed_to_numpy(small, max_pixels=64 * 48).shape == (48, 64, 3)


def test_unsupported_format_rejected() -> None:
    png = numpy_to_compressed(noisy_rgb(), 'png', stamp_ns=0, frame_id='',
                              msg_cls=TS).data.tobytes()
    with pytest.raises(UnsupportedFormatError):
        compressed_to_numpy(make_msg('rosbags', png, '16UC1; compressedDepth png'))


def test_builder_rejects_bad_arguments() -> None:
    kw = {'stamp_ns': 0, 'frame_id': '', 'msg_cls': TS}
    with pytest.raises(ValueRangeError, match='quality'):
        numpy_to_compressed(noisy_rgb(), 'jpeg', quality=0, **kw)
    with pytest.raises(ValueRangeError, match='png_level'):
        numpy_to_compressed(noisy_rgb(), 'png', png_level=10, **kw)
    with pytest.raises(UnsupportedFormatError, match='bmp'):
        numpy_to_compressed(noisy_rgb(), 'bmp', **kw)
    with pytest.raises(ArrayShapeError, match='float32'):
        numpy_to_compressed(noisy_rgb().astype(np.float32), 'png', **kw)
    with pytest.raises(ArrayShapeError, match='jpeg needs uint8'):
        numpy_to_compressed(np.zeros((4, 4), np.uint16), 'jpeg', **kw)
    with pytest.raises(ArrayShapeError):
        numpy_to_compressed(np.zeros((4, 4, 2), np.uint8), 'png', **kw)
    with pytest.raises(ImageSizeError, match='empty'):
        numpy_to_compressed(np.zeros((0, 4, 3), np.uint8), 'png', **kw)


def test_cdr_byte_identical_across_flavours() -> None:
    rgb = smooth_rgb()
    rc = numpy_to_compressed(rgb, 'jpeg', stamp_ns=77, frame_id='cam',
                             msg_cls=sensor_msgs.msg.CompressedImage)
    rb = numpy_to_compressed(rgb, 'jpeg', stamp_ns=77, frame_id='cam', msg_cls=TS)
    raw_rc, raw_rb = serialize_message(rc), bytes(TS.serialize_cdr(rb, COMPRESSED))
    a, b = np.frombuffer(raw_rc, np.uint8), np.frombuffer(raw_rb, np.uint8)
    assert a.shape == b.shape
    assert np.all(b[a != b] == 0)  # only alignment padding may differ
    assert bytes(TS.serialize_cdr(TS.deserialize_cdr(raw_rc, COMPRESSED), COMPRESSED)) == raw_rb


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_to_rgb_or_mono_accepts_compressed(flavour: str) -> None:
    cls = FLAVOURS[flavour]
    rgb = noisy_rgb()
    out = to_rgb_or_mono(cdr_round_trip(numpy_to_compressed(rgb, 'png', stamp_ns=0,
                                                            frame_id='', msg_cls=cls)))
    np.testing.assert_array_equal(out, rgb)
    mono16 = (rgb[..., 0].astype(np.uint16) << 8) | 0x7F
    out = to_rgb_or_mono(numpy_to_compressed(mono16, 'png', stamp_ns=0, frame_id='',
                                             msg_cls=cls))
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, rgb[..., 0])
    with pytest.raises(CompressedDecodeError):
        to_rgb_or_mono(make_msg(flavour, b'\x01\x02\x03', 'jpeg'))
