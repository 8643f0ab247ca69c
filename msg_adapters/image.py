"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` <-> numpy.

Raw images (:func:`image_to_numpy`)
    Supported encodings: ``rgb8 bgr8 rgba8 bgra8 rgb16 bgr16 rgba16 bgra16 mono8 mono16``,
    ``bayer_{rggb,bggr,gbrg,grbg}{8,16}``, ``yuv422``/``uyvy``, ``yuv422_yuy2``/``yuyv`` and the
    OpenCV type encodings ``{8,16}{U,S}C<n>``, ``32SC<n>``, ``32FC<n>``, ``64FC<n>``.
    The result is a zero-copy strided view of the message's ``data`` (rows ``step`` bytes apart,
    so row padding is skipped without copying); it is read-only when the message buffer is
    (rosbags deserialisation). Only big-endian multi-byte data (``is_bigendian``) is copied, to
    native byte order. One-channel encodings give ``(height, width)``, others
    ``(height, width, channels)``.

Checks (all raise a :class:`~msg_adapters.errors.MessageError` subclass): unknown encoding,
``width * height`` above ``max_pixels`` (checked before anything is touched, so a forged header
never causes a large allocation), ``step < width * bytes_per_pixel``, ``len(data) < step *
height``. Trailing bytes beyond ``step * height`` are ignored.

Compressed images (:func:`compressed_to_numpy`)
    jpeg and png, decoded with ``cv2.imdecode``. ``format`` is parsed the way
    ``compressed_image_transport`` writes it (``'<encoding>; <codec> compressed <target>'``,
    e.g. ``'rgb8; jpeg compressed bgr8'``, ``'mono8; png compressed '``), plain ``'jpeg'`` /
    ``'png'`` or empty (the codec is then recognised from the magic bytes). The image size is
    read from the JPEG frame header / PNG IHDR and checked against ``max_pixels`` before
    decoding (decompression bombs). Colour results are in RGB order.
"""
from __future__ import annotations

from dataclasses import dataclass
import re
from typing import Any

import cv2
import numpy as np

from msg_adapters._flavour import byte_view, construct, resolve_class, uint8_field
from msg_adapters.errors import (
    ArrayShapeError,
    CompressedDecodeError,
    DataLengthError,
    ImageSizeError,
    ImageTooLargeError,
    StepMismatchError,
    UnsupportedEncodingError,
    UnsupportedFormatError,
    ValueRangeError,
    WrongMessageTypeError,
)
from msg_adapters.stamp import make_header

IMAGE_TYPE = 'sensor_msgs/msg/Image'
COMPRESSED_TYPE = 'sensor_msgs/msg/CompressedImage'

#: Default limit on ``width * height`` (px): 50 megapixels.
DEFAULT_MAX_PIXELS = 50_000_000

_U8, _U16 = np.dtype(np.uint8), np.dtype(np.uint16)
_NAMED_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    'mono8': (_U8, 1), 'mono16': (_U16, 1),
    'rgb8': (_U8, 3), 'bgr8': (_U8, 3), 'rgba8': (_U8, 4), 'bgra8': (_U8, 4),
    'rgb16': (_U16, 3), 'bgr16': (_U16, 3), 'rgba16': (_U16, 4), 'bgra16': (_U16, 4),
    'yuv422': (_U8, 2), 'uyvy': (_U8, 2), 'yuv422_yuy2': (_U8, 2), 'yuyv': (_U8, 2),
}
for _pattern in ('rggb', 'bggr', 'gbrg', 'grbg'):
    _NAMED_ENCODINGS[f'bayer_{_pattern}8'] = (_U8, 1)
    _NAMED_ENCODINGS[f'bayer_{_pattern}16'] = (_U16, 1)
_TYPE_ENCODING = re.compile(r'^(8U|8S|16U|16S|32S|32F|64F)C([1-9][0-9]{0,2})$')
_TYPE_DTYPES = {'8U': 'u1', '8S': 'i1', '16U': 'u2', '16S': 'i2', '32S': 'i4', '32F': 'f4',
                '64F': 'f8'}

# ROS bayer pattern (first 2x2 block) -> OpenCV code (OpenCV names the pattern one pixel later).
_BAYER_TO_RGB = {'rggb': cv2.COLOR_BayerBG2RGB, 'bggr': cv2.COLOR_BayerRG2RGB,
                 'gbrg': cv2.COLOR_BayerGR2RGB, 'grbg': cv2.COLOR_BayerGB2RGB}
_YUV_TO_RGB = {'yuv422': cv2.COLOR_YUV2RGB_UYVY, 'uyvy': cv2.COLOR_YUV2RGB_UYVY,
               'yuv422_yuy2': cv2.COLOR_YUV2RGB_YUY2, 'yuyv': cv2.COLOR_YUV2RGB_YUY2}


def encoding_info(encoding: str) -> tuple[np.dtype, int]:
    """``(native element dtype, channels)`` of an ``Image.encoding``.

    Raises :class:`UnsupportedEncodingError` for unknown encodings.
    """
    if encoding in _NAMED_ENCODINGS:
        return _NAMED_ENCODINGS[encoding]
    match = _TYPE_ENCODING.match(encoding)
    if match:
        return np.dtype(_TYPE_DTYPES[match.group(1)]), int(match.group(2))
    raise UnsupportedEncodingError(
        f'Image.encoding: unsupported {encoding!r}; expected one of '
        f'{", ".join(sorted(_NAMED_ENCODINGS))} or an OpenCV type such as 8UC3, 16UC1, 32FC1')


def check_size(width: int, height: int, max_pixels: int | None, what: str = 'Image') -> None:
    """Raise :class:`ImageTooLargeError` if ``width * height`` exceeds ``max_pixels`` (px)."""
    if width < 0 or height < 0:
        raise ImageSizeError(f'{what}: negative size {width}x{height}')
    if max_pixels is not None and width * height > max_pixels:
        raise ImageTooLargeError(
            f'{what}: width*height = {width}*{height} = {width * height} px exceeds the limit '
            f'of {max_pixels} px (max_pixels)')


def depth_to_metres(arr: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W) float32 range in metres of a depth image's pixels: ``16UC1`` / ``mono16`` in
    millimetres (0 = no depth -> NaN) or ``32FC1`` / ``64FC1`` in metres.

    Raises :class:`UnsupportedEncodingError` for any other encoding.
    """
    if encoding in ('16UC1', 'mono16'):
        d = arr.astype(np.float32) / 1000.0
        d[arr == 0] = np.nan
        return d
    if encoding in ('32FC1', '64FC1'):
        return np.asarray(arr, dtype=np.float32)
    raise UnsupportedEncodingError(
        f'depth image encoding {encoding!r} not supported (32FC1 m or 16UC1 mm)')


def image_to_numpy(msg: Any, *, max_pixels: int | None = DEFAULT_MAX_PIXELS,
                   copy: bool = False) -> np.ndarray:
    """Pixels of a ``sensor_msgs/Image`` (rclpy or rosbags) as a numpy array.

    Returns a zero-copy view (``copy=False``) honouring ``step``, or a C-contiguous writable
    copy (``copy=True``). Multi-byte big-endian data is always converted to native order.
    Shape ``(height, width)`` for one-channel encodings, else ``(height, width, channels)``.
    """
    encoding = str(msg.encoding)
    base, channels = encoding_info(encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    check_size(width, height, max_pixels)
    pixel_bytes = base.itemsize * channels
    row_bytes = width * pixel_bytes
    if step < row_bytes:
        raise StepMismatchError(
            f'Image.step: {step} bytes is less than width*bytes_per_pixel = {width}*'
            f'{pixel_bytes} = {row_bytes} bytes for encoding {encoding!r}')
    buf = byte_view(msg.data)
    needed = step * height
    if buf.size < needed:
        raise DataLengthError(
            f'Image.data: {buf.size} bytes, expected step*height = {step}*{height} = {needed} '
            f'bytes')
    dtype = base.newbyteorder('>' if msg.is_bigendian else '<') if base.itemsize > 1 else base
    shape = (height, width, channels)
    if height == 0 or width == 0:
        arr = np.zeros(shape, dtype=base)
    else:
        arr = np.ndarray(shape, dtype=dtype, buffer=buf, offset=0,
                         strides=(step, pixel_bytes, base.itemsize))
    if channels == 1:
        arr = arr[..., 0]
    if not arr.dtype.isnative:
        arr = arr.astype(base)
    elif copy:
        arr = np.array(arr, order='C', copy=True)
    return arr


def numpy_to_image(arr: np.ndarray, encoding: str, *, stamp_ns: int, frame_id: str,
                   msg_cls: Any, typestore: Any | None = None,
                   bigendian: bool = False) -> Any:
    """A ``sensor_msgs/Image`` of the flavour of ``msg_cls`` from a numpy array.

    ``arr`` is ``(height, width)`` (or ``(height, width, 1)``) for one-channel encodings and
    ``(height, width, channels)`` otherwise; its dtype must match the encoding (uint8 for
    ``rgb8``, uint16 for ``mono16``, float32 for ``32FC1`` ...). The message has no row padding
    (``step = width * bytes_per_pixel``) and little-endian data unless ``bigendian``.
    ``stamp_ns`` is the header stamp (ns), ``msg_cls`` the Image class (rclpy or rosbags) or a
    rosbags typestore.
    """
    base, channels = encoding_info(encoding)
    a = np.asarray(arr)
    if channels == 1 and a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    expected = (2,) if channels == 1 else (3,)
    if a.ndim not in expected or (channels > 1 and a.shape[2] != channels):
        want = '(height, width)' if channels == 1 else f'(height, width, {channels})'
        raise ArrayShapeError(f'numpy_to_image: encoding {encoding!r} needs shape {want}, '
                              f'got {a.shape}')
    if a.dtype.newbyteorder('=') != base:
        raise ArrayShapeError(f'numpy_to_image: encoding {encoding!r} needs dtype {base}, '
                              f'got {a.dtype}')
    order = '>' if bigendian else '<'
    data = np.ascontiguousarray(a, dtype=base.newbyteorder(order) if base.itemsize > 1 else base)
    height, width = int(a.shape[0]), int(a.shape[1])
    cls = resolve_class(msg_cls, IMAGE_TYPE, typestore)
    return construct(
        cls, header=make_header(stamp_ns, frame_id, cls, typestore=typestore),
        height=height, width=width, encoding=encoding, is_bigendian=int(bool(bigendian)),
        step=width * channels * base.itemsize,
        data=uint8_field(cls, data.view(np.uint8).reshape(-1)))


# ----------------------------------------------------------------------------- compressed

@dataclass(frozen=True)
class CompressedFormat:
    """Parsed ``CompressedImage.format``.

    ``codec`` is ``'jpeg'``, ``'png'`` or None (unknown: recognise from the data);
    ``encoding`` the original raw encoding if given; ``target`` the pixel format the codec
    stored (``'bgr8'``, ``'mono8'`` ...) if given.
    """

    codec: str | None
    encoding: str | None
    target: str | None


_CODECS = {'jpeg': 'jpeg', 'jpg': 'jpeg', 'png': 'png'}
_JPEG_MAGIC = b'\xff\xd8\xff'
_PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
_JPEG_SOF = frozenset((0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD,
                       0xCE, 0xCF))


def _codec(token: str, fmt: str) -> str:
    codec = _CODECS.get(token.lower())
    if codec is None:
        raise UnsupportedFormatError(
            f'CompressedImage.format: codec {token!r} in {fmt!r} is not supported; '
            f'expected jpeg or png')
    return codec


def parse_compressed_format(fmt: str) -> CompressedFormat:
    """Parse ``CompressedImage.format`` as written by ``compressed_image_transport``.

    Accepts ``'<enc>; <codec> compressed [<target>]'``, ``'<codec>'``, ``'<enc>'`` or ``''``.
    Raises :class:`UnsupportedFormatError` for other codecs (``compressedDepth``, tiff, qoi...).
    """
    text = str(fmt).strip()
    if ';' in text:
        enc_part, rest = text.split(';', 1)
        tokens = rest.split()
        if not tokens:
            return CompressedFormat(None, enc_part.strip() or None, None)
        codec = _codec(tokens[0], text)
        target = tokens[2] if len(tokens) >= 3 and tokens[1].lower() == 'compressed' else None
        return CompressedFormat(codec, enc_part.strip() or None, target)
    tokens = text.split()
    if not tokens:
        return CompressedFormat(None, None, None)
    if tokens[0].lower() in _CODECS:
        return CompressedFormat(_CODECS[tokens[0].lower()], None, None)
    if tokens[0] in _NAMED_ENCODINGS or _TYPE_ENCODING.match(tokens[0]):
        return CompressedFormat(None, tokens[0], None)  # old transports wrote the encoding only
    return CompressedFormat(_codec(tokens[0], text), None, None)


def _jpeg_size(buf: np.ndarray) -> tuple[int, int]:
    """``(width, height)`` px from the JPEG frame header (SOFn), without decoding."""
    view = memoryview(buf)
    n = len(view)
    i = 2
    while i < n:
        if view[i] != 0xFF:
            raise CompressedDecodeError(
                f'CompressedImage.data: corrupt JPEG, expected a marker (0xFF) at byte {i}, '
                f'got 0x{view[i]:02x}')
        while i < n and view[i] == 0xFF:
            i += 1
        if i >= n:
            break
        marker = view[i]
        i += 1
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:
            continue  # stand-alone markers
        if marker in (0xD9, 0xDA) or i + 2 > n:
            break  # end of image / start of scan before any frame header
        length = (view[i] << 8) | view[i + 1]
        if marker in _JPEG_SOF:
            if i + 7 > n:
                break
            height = (view[i + 3] << 8) | view[i + 4]
            width = (view[i + 5] << 8) | view[i + 6]
            if width == 0 or height == 0:
                raise CompressedDecodeError(
                    f'CompressedImage.data: JPEG frame header gives size {width}x{height} '
                    f'(a zero height needs a DNL marker, not supported)')
            return width, height
        if length < 2:
            raise CompressedDecodeError(
                f'CompressedImage.data: corrupt JPEG, segment 0x{marker:02x} has length '
                f'{length} < 2')
        i += length
    raise CompressedDecodeError(
        f'CompressedImage.data: corrupt or truncated JPEG ({n} bytes), no frame header (SOF) '
        f'before the image data')


def _png_size(buf: np.ndarray) -> tuple[int, int]:
    """``(width, height)`` px from the PNG IHDR chunk, without decoding."""
    head = buf[:24].tobytes()
    if len(head) < 24 or head[12:16] != b'IHDR':
        raise CompressedDecodeError(
            f'CompressedImage.data: corrupt or truncated PNG ({buf.size} bytes), no IHDR chunk')
    width = int.from_bytes(head[16:20], 'big')
    height = int.from_bytes(head[20:24], 'big')
    if width == 0 or height == 0:
        raise CompressedDecodeError(f'CompressedImage.data: PNG IHDR gives size {width}x{height}')
    return width, height


def _sniff(buf: np.ndarray) -> str:
    head = buf[:8].tobytes()
    if head.startswith(_JPEG_MAGIC):
        return 'jpeg'
    if head.startswith(_PNG_MAGIC):
        return 'png'
    raise CompressedDecodeError(
        f'CompressedImage.data: neither JPEG (ff d8 ff) nor PNG magic bytes, starts with '
        f'{head.hex(" ") or "<empty>"} ({buf.size} bytes)')


def _compressed_header(msg: Any) -> tuple[CompressedFormat, np.ndarray, str, int, int]:
    fmt = parse_compressed_format(msg.format)  # rejects unsupported codecs
    buf = byte_view(msg.data)
    codec = _sniff(buf)  # the bytes decide: a mislabelled jpeg/png format is tolerated
    width, height = _jpeg_size(buf) if codec == 'jpeg' else _png_size(buf)
    if codec == 'jpeg' and b'\xff\xd9' not in buf[-4096:].tobytes():
        # Entropy-coded data never contains ff d9 (0xff is stuffed), so its absence from the
        # tail means the end-of-image marker is missing: the stream was cut.
        raise CompressedDecodeError(
            f'CompressedImage.data: truncated JPEG ({buf.size} bytes), no end-of-image marker '
            f'(ff d9)')
    return fmt, buf, codec, width, height


def compressed_size(msg: Any) -> tuple[str, int, int]:
    """``(codec, width, height)`` of a ``CompressedImage`` from its headers, without decoding."""
    _, _, codec, width, height = _compressed_header(msg)
    return codec, width, height


def compressed_to_numpy(msg: Any, *, max_pixels: int | None = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` (jpeg / png; rclpy or rosbags).

    Returns ``(H, W, 3)`` RGB or ``(H, W)`` mono, uint8 (uint16 for 16-bit PNG). An alpha
    channel is dropped. The channel order stored by the codec is taken from ``format``
    (``'... compressed bgr8'`` -> BGR, ``'... compressed rgb8'`` -> RGB, none -> OpenCV's BGR).
    Raises :class:`CompressedDecodeError` for corrupt / truncated data,
    :class:`UnsupportedFormatError` for other codecs, :class:`ImageTooLargeError` if the header
    size exceeds ``max_pixels`` (checked before decoding).
    """
    fmt, buf, codec, width, height = _compressed_header(msg)
    check_size(width, height, max_pixels, what=f'CompressedImage ({codec})')
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise CompressedDecodeError(
            f'CompressedImage.data: cv2.imdecode failed on {buf.size} bytes of {codec} '
            f'(corrupt or truncated)')
    if img.shape[:2] != (height, width):
        raise CompressedDecodeError(
            f'CompressedImage.data: decoded size {img.shape[1]}x{img.shape[0]} differs from '
            f'the header size {width}x{height}')
    if img.ndim == 2:
        return img
    rgb_stored = fmt.target is not None and fmt.target.lower().startswith('rgb')
    if img.shape[2] == 4:
        return np.ascontiguousarray(img[..., :3] if rgb_stored else img[..., 2::-1])
    if img.shape[2] == 3:
        return img if rgb_stored else np.ascontiguousarray(img[..., ::-1])
    raise CompressedDecodeError(
        f'CompressedImage.data: decoded image has {img.shape[2]} channels, expected 1, 3 or 4')


def numpy_to_compressed(arr: np.ndarray, fmt: str = 'jpeg', *, stamp_ns: int, frame_id: str,
                        msg_cls: Any, quality: int = 90, png_level: int = 3,
                        typestore: Any | None = None) -> Any:
    """Encode an RGB / mono numpy image into a ``sensor_msgs/CompressedImage``.

    ``arr``: ``(H, W)`` mono or ``(H, W, 3)`` RGB uint8 (jpeg, png), ``(H, W, 4)`` RGBA uint8
    (png keeps alpha, jpeg drops it), uint16 mono / RGB (png only). ``fmt`` is ``'jpeg'`` (or
    ``'jpg'``) or ``'png'``; ``quality`` the JPEG quality 1..100, ``png_level`` the PNG
    compression level 0..9. ``format`` is written as ``compressed_image_transport`` does, e.g.
    ``'rgb8; jpeg compressed bgr8'``, ``'mono8; jpeg compressed mono8'``,
    ``'rgba8; png compressed bgra8'``, ``'mono16; png compressed '``.
    """
    codec = _CODECS.get(str(fmt).lower())
    if codec is None:
        raise UnsupportedFormatError(f'numpy_to_compressed: fmt {fmt!r} is not jpeg or png')
    a = np.asarray(arr)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.dtype not in (_U8, _U16) or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        raise ArrayShapeError(
            f'numpy_to_compressed: expected (H, W), (H, W, 3) or (H, W, 4) uint8/uint16, '
            f'got shape {a.shape} dtype {a.dtype}')
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageSizeError(f'numpy_to_compressed: empty image of shape {a.shape}')
    bits = 8 * a.dtype.itemsize
    if codec == 'jpeg' and bits != 8:
        raise ArrayShapeError(f'numpy_to_compressed: jpeg needs uint8, got {a.dtype}')
    if codec == 'jpeg':
        if not 1 <= int(quality) <= 100:
            raise ValueRangeError(f'quality: expected 1..100, got {quality}')
        params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
    else:
        if not 0 <= int(png_level) <= 9:
            raise ValueRangeError(f'png_level: expected 0..9, got {png_level}')
        params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)]
    if a.ndim == 2:
        encoding = f'mono{bits}'
        target = 'mono8' if codec == 'jpeg' else ''
        pixels = a
    elif a.shape[2] == 3 or codec == 'jpeg':
        encoding = f'rgb{bits}' if a.shape[2] == 3 else f'rgba{bits}'
        target = f'bgr{bits}'
        pixels = a[..., 2::-1]
    else:
        encoding, target = f'rgba{bits}', f'bgra{bits}'
        pixels = a[..., [2, 1, 0, 3]]
    ok, encoded = cv2.imencode('.jpg' if codec == 'jpeg' else '.png',
                               np.ascontiguousarray(pixels), params)
    if not ok:
        raise CompressedDecodeError(f'cv2.imencode failed for {codec} of shape {a.shape}')
    cls = resolve_class(msg_cls, COMPRESSED_TYPE, typestore)
    return construct(cls, header=make_header(stamp_ns, frame_id, cls, typestore=typestore),
                     format=f'{encoding}; {codec} compressed {target}',
                     data=uint8_field(cls, encoded.reshape(-1)))


# ----------------------------------------------------------------------------- both kinds

def _to_uint8(arr: np.ndarray, bit_depth: int) -> np.ndarray:
    if arr.dtype == _U8:
        return arr
    if not 8 < bit_depth <= 16:
        raise ValueRangeError(f'bit_depth: expected 9..16 for 16-bit data, got {bit_depth}')
    shift = bit_depth - 8
    return np.clip(arr >> shift, 0, 255).astype(np.uint8)


def to_rgb_or_mono(msg: Any, *, max_pixels: int | None = DEFAULT_MAX_PIXELS,
                   bit_depth: int = 16) -> np.ndarray:
    """What the feature node needs: uint8 ``(H, W, 3)`` RGB or ``(H, W)`` mono.

    Accepts a ``sensor_msgs/Image`` (mono8/16, rgb/bgr/rgba/bgra 8/16, bayer 8/16 demosaiced,
    yuv422 / yuyv, 8UC1, 16UC1) or a ``CompressedImage`` (jpeg, png), either flavour. 16-bit
    data is shifted right by ``bit_depth - 8`` (``bit_depth`` = significant bits, 16 by
    default, 12 for a 12-bit sensor publishing mono16) and saturated to uint8. The result may be
    a read-only view of the message data. Raises :class:`UnsupportedEncodingError` for
    encodings without a defined intensity / colour order (32FC1, 8UC3, ...) and
    :class:`ImageSizeError` for an empty image.
    """
    if hasattr(msg, 'format') and not hasattr(msg, 'encoding'):
        img = compressed_to_numpy(msg, max_pixels=max_pixels)
        return _to_uint8(img, bit_depth)
    if not hasattr(msg, 'encoding'):
        raise WrongMessageTypeError(
            f'to_rgb_or_mono: expected an Image or CompressedImage, got {type(msg).__name__}')
    encoding = str(msg.encoding)
    arr = image_to_numpy(msg, max_pixels=max_pixels)
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ImageSizeError(f'Image: empty image {arr.shape[1]}x{arr.shape[0]}')
    if encoding in ('mono8', '8UC1', 'mono16', '16UC1'):
        return _to_uint8(arr, bit_depth)
    if encoding.startswith('bayer_'):
        pattern = encoding[6:10]
        return cv2.cvtColor(np.ascontiguousarray(_to_uint8(arr, bit_depth)),
                            _BAYER_TO_RGB[pattern])
    if encoding in _YUV_TO_RGB:
        if arr.shape[1] % 2:
            raise ImageSizeError(f'Image: {encoding} needs an even width, got {arr.shape[1]}')
        return cv2.cvtColor(np.ascontiguousarray(arr), _YUV_TO_RGB[encoding])
    if encoding in ('rgb8', 'rgb16', 'rgba8', 'rgba16'):
        return _to_uint8(arr[..., :3], bit_depth)
    if encoding in ('bgr8', 'bgr16', 'bgra8', 'bgra16'):
        return np.ascontiguousarray(_to_uint8(arr[..., 2::-1], bit_depth))
    raise UnsupportedEncodingError(
        f'Image.encoding: {encoding!r} is not an intensity or colour image (expected mono8, '
        f'mono16, rgb8, bgr8, rgba8, bgra8, bayer_*, yuv422 ...)')
