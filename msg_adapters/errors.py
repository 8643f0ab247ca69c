"""Exceptions of the message adapters.

Every error raised for a malformed or unsupported message (or a bad argument of a builder) is a
:class:`MessageError`, itself a ``ValueError``: a node can reject any bad input with one
``except MessageError`` clause, log the message and count it in its diagnostics. The messages
name the offending field and give the expected and the actual value.
"""
from __future__ import annotations


class MessageError(ValueError):
    """Base class: a message (or builder input) cannot be converted."""


class WrongMessageTypeError(MessageError):
    """A message or message class is not of the expected type or flavour (rclpy / rosbags)."""


class StampError(MessageError):
    """A time stamp is out of range (``sec`` outside int32, ``nanosec`` >= 1e9, ...)."""


class UnsupportedEncodingError(MessageError):
    """Unknown or unsupported ``Image.encoding`` (or one this operation cannot handle)."""


class UnsupportedFormatError(UnsupportedEncodingError):
    """Unknown or unsupported ``CompressedImage.format`` (codec other than jpeg / png)."""


class StepMismatchError(MessageError):
    """A row stride (``Image.step``, ``PointCloud2.row_step``) is too small for the width."""


class DataLengthError(MessageError):
    """``data`` is shorter than the header (``step * height``, ``row_step * height``) says."""


class ImageSizeError(MessageError):
    """An image has an unusable size (zero, or not matching what is expected)."""


class ImageTooLargeError(ImageSizeError):
    """``width * height`` exceeds the configured limit (protects from forged headers)."""


class ArrayShapeError(MessageError):
    """A numpy array given to a builder has the wrong shape or dtype."""


class ValueRangeError(MessageError):
    """A value is outside its allowed range (a label > 255 for a uint8 field, quality 0...)."""


class CompressedDecodeError(MessageError):
    """The bytes of a ``CompressedImage`` cannot be decoded (corrupt, truncated, wrong codec)."""


class CameraInfoError(MessageError):
    """Inconsistent or unusable ``CameraInfo`` (K, D, size, binning, ROI)."""


class UnsupportedDistortionError(CameraInfoError):
    """``CameraInfo.distortion_model`` is none of the supported models."""


class PointFieldError(MessageError):
    """Bad ``PointCloud2.fields``: unknown datatype, overlap, beyond ``point_step``, duplicates."""


class LayoutMismatchError(PointFieldError):
    """A PointCloud2 lacks a field of a product layout or has it with another datatype/count."""


class NonFiniteError(MessageError):
    """NaN or inf where a finite value is required."""


class NonFiniteCameraInfoError(CameraInfoError, NonFiniteError):
    """NaN or inf in ``CameraInfo.k`` or ``CameraInfo.d``."""
