"""Exceptions of the sequential matcher (all subclass :class:`MatchingError`)."""
from __future__ import annotations


class MatchingError(ValueError):
    """Base class of every input/configuration error raised by ``semfeat_ros.matching``."""


class MatchingConfigError(MatchingError):
    """A configuration key is unknown or its value is out of range."""


class FeatureInputError(MatchingError):
    """Keypoints, descriptors, bearings, labels or scores have a wrong shape, dtype or value."""


class FrameOrderError(MatchingError):
    """A frame repeats the time stamp of the previous frame (duplicate message)."""


class TrackIdOverflowError(RuntimeError):
    """All 2**32 track ids have been used; ids are never reused, so tracking cannot go on."""
