"""Exceptions of the command-line tools (bag replay and recording, the results report).

Every message is a single line, so a CLI can print ``<prog>: error: <message>`` on stderr and
exit non-zero without a traceback.
"""
from __future__ import annotations


class BagToolError(Exception):
    """Base class of the errors raised by the bag replay and record tools."""


class BagNotFoundError(BagToolError, FileNotFoundError):
    """The bag path does not exist, or is a directory without a rosbag2 ``metadata.yaml``."""


class BagFormatError(BagToolError, ValueError):
    """The bag exists but cannot be read: bad metadata, truncated MCAP, corrupt SQLite file."""


class BagConfigError(BagToolError, ValueError):
    """An option of the play or record tools is invalid (rate, remap rule, QoS name, topics)."""


class UnknownMessageTypeError(BagToolError, ValueError):
    """A message type name (e.g. ``sensor_msgs/msg/Image``) cannot be resolved to a class."""


class BagWriteError(BagToolError, RuntimeError):
    """The output bag cannot be created or written (path exists, disk full, writer failure)."""


class ReportError(Exception):
    """Base class of the errors of ``semfeat-report`` (results tables of the docs)."""


class ReportManifestError(ReportError, ValueError):
    """The report manifest or the document's marker blocks are malformed or do not match."""


class ReportInputError(ReportError, FileNotFoundError):
    """A result directory, its JSON file or a value the manifest names is missing."""


class ReportOutputError(ReportError, OSError):
    """The document cannot be written where asked (a symbolic link)."""
