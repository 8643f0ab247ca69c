"""Exceptions of the mapping core (all name the offending field and the expected value)."""
from __future__ import annotations


class MappingError(ValueError):
    """Base class of the mapping core's input and configuration errors."""


class MapperConfigError(MappingError):
    """An unknown configuration key or a value outside its valid range."""


class MapperInputError(MappingError):
    """A per-frame input (tracks, odometry, GNSS fix) has the wrong shape, type or values."""


class StampOrderError(MapperInputError):
    """A frame's stamp is not later than the previous frame's stamp."""


class PlyFormatError(MappingError):
    """A PLY file cannot be written or parsed (missing property, bad header, truncated body)."""


class TumFormatError(MappingError):
    """A TUM trajectory file is malformed (wrong column count, non-numeric value)."""


class AlignmentError(MappingError):
    """Trajectories cannot be aligned (shape mismatch, too few or degenerate points)."""


class MapWriteError(MappingError, OSError):
    """A map file cannot be written safely: the target is a symlink, a name would leave the
    output directory, or the file system refused the write (read-only, full)."""
