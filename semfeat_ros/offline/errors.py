"""Exceptions of the offline batch tools (``semfeat-features``, ``semfeat-map``, COLMAP peer).

Every message is a single line naming the path, topic or option and what was expected, so a CLI
prints ``<prog>: error: <message>`` on stderr and exits non-zero without a traceback.
"""
from __future__ import annotations


class OfflineError(Exception):
    """Base class of the offline tool errors."""


class BagNotFoundError(OfflineError, FileNotFoundError):
    """The bag path does not exist or is not a rosbag2 directory / storage file."""


class BagFormatError(OfflineError, ValueError):
    """The bag exists but cannot be read (bad metadata, truncated or corrupt storage)."""


class TopicNotFoundError(OfflineError, ValueError):
    """A required topic is missing from the bag or has an unexpected message type."""


class OutputPathError(OfflineError, ValueError):
    """An output path escapes the output directory, or the output already exists."""


class OfflineConfigError(OfflineError, ValueError):
    """An option or a configuration file of an offline tool is invalid."""


class EvaluationError(OfflineError, ValueError):
    """Ground truth and estimate cannot be compared (too few common stamps, no motion)."""


class NoFramesError(OfflineError, ValueError):
    """Every frame read from the bag was rejected (e.g. no image decodes): no output."""
