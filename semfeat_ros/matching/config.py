"""Configuration of the matcher: LightGlue / hloc style ``default_conf`` plus overrides.

The merge and the range check of :mod:`semfeat_ros.conf`, raising
:class:`MatchingConfigError`.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from semfeat_ros import conf as common_conf
from semfeat_ros.matching.errors import MatchingConfigError


def merge_conf(default: Mapping[str, Any], conf: Mapping[str, Any] | None,
               name: str = 'conf') -> dict[str, Any]:
    """Deep copy of ``default`` updated with ``conf``; unknown keys raise.

    Nested dictionaries are merged recursively. ``name`` prefixes the key in error messages,
    e.g. ``conf.verification.threshold_rad``.
    """
    return common_conf.merge_conf(default, conf, MatchingConfigError, name=name)


def check_range(conf: Mapping[str, Any], key: str, lo: float | None, hi: float | None,
                name: str = 'conf', *, integer: bool = False, lo_open: bool = False) -> None:
    """Raise :class:`MatchingConfigError` unless ``lo <= conf[key] <= hi`` (None: unbounded).

    With ``lo_open`` the lower bound is exclusive. With ``integer`` the value must be integral.
    """
    common_conf.check_number(conf[key], f'{name}.{key}', MatchingConfigError, lo, hi,
                             lo_open=lo_open, integer=integer)
