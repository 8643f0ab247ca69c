"""Exceptions of the synthetic parking-garage simulator."""
from __future__ import annotations


class SimError(ValueError):
    """Base class of the simulator's input errors."""


class SimConfigError(SimError):
    """A world, trajectory or render configuration value is out of range or malformed."""


class ShapeError(SimError):
    """An array argument has the wrong shape or dtype."""


class ShardError(SimError):
    """A dataset shard is missing, truncated or lacks a required array."""


class BagWriteError(RuntimeError):
    """Writing a rosbag2 recording failed (target exists, message conversion failed)."""
