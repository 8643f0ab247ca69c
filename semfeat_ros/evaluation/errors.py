"""Exceptions of the evaluation harness (all carry a one-line message naming the input)."""
from __future__ import annotations


class EvalError(ValueError):
    """Base class: bad input to the evaluation (path, file contents, option value)."""


class DatasetError(EvalError):
    """A dataset folder or bag is unusable (empty, wrong layout, missing topic)."""


class ImageReadError(EvalError):
    """An image file (or bag message) could not be decoded into pixels."""


class HomographyFileError(DatasetError):
    """A homography text file of an Oxford/HPatches sequence is missing or malformed."""


class CameraFileError(DatasetError):
    """A camera intrinsics file (e.g. a ViSP XML configuration) is missing or malformed."""


class TopicError(DatasetError):
    """A requested topic is absent from a bag or has an unexpected message type."""


class ConfigError(EvalError):
    """An option value is out of range or inconsistent (e.g. unknown method name)."""


class MethodUnavailableError(RuntimeError):
    """A method cannot run here (missing weights, missing optional module); it is skipped."""
