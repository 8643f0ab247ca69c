"""Exceptions of the multi-task network, its training and its inference wrapper."""
from __future__ import annotations


class ModelConfigError(ValueError):
    """A network, extractor or training configuration value is missing, unknown or invalid."""


class ModelInputError(ValueError):
    """An image or tensor passed to the network or the extractor has the wrong shape or type."""


class WeightsNotFoundError(FileNotFoundError):
    """No trained weights exist where they were expected (e.g. shipped weights not trained yet)."""


class WeightsFormatError(ValueError):
    """A weights file or its JSON config is unreadable or does not match the network."""


class DatasetError(ValueError):
    """A training shard is missing, unreadable or does not follow the documented layout."""
