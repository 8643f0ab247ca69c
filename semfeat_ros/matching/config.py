"""Configuration of the matcher: LightGlue / hloc style ``default_conf`` plus overrides."""
from __future__ import annotations

from collections.abc import Mapping
import copy
from typing import Any

from semfeat_ros.matching.errors import MatchingConfigError


def merge_conf(default: Mapping[str, Any], conf: Mapping[str, Any] | None,
               name: str = 'conf') -> dict[str, Any]:
    """Deep copy of ``default`` updated with ``conf``; unknown keys raise.

    Nested dictionaries are merged recursively. ``name`` prefixes the key in error messages,
    e.g. ``conf.verification.threshold_rad``.
    """
    out = copy.deepcopy(dict(default))
    if conf is None:
        return out
    if not isinstance(conf, Mapping):
        raise MatchingConfigError(f'{name}: expected a mapping, got {type(conf).__name__}')
    for key, value in conf.items():
        if key not in out:
            raise MatchingConfigError(
                f'{name}.{key}: unknown key; known keys: {", ".join(sorted(out))}')
        if isinstance(out[key], dict):
            out[key] = merge_conf(out[key], value, f'{name}.{key}')
        else:
            out[key] = copy.deepcopy(value)
    return out


def check_range(conf: Mapping[str, Any], key: str, lo: float | None, hi: float | None,
                name: str = 'conf', *, integer: bool = False, lo_open: bool = False) -> None:
    """Raise :class:`MatchingConfigError` unless ``lo <= conf[key] <= hi`` (None: unbounded).

    With ``lo_open`` the lower bound is exclusive. With ``integer`` the value must be an int.
    """
    value = conf[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise MatchingConfigError(f'{name}.{key}: expected a number, got {value!r}')
    if integer and int(value) != value:
        raise MatchingConfigError(f'{name}.{key}: expected an integer, got {value!r}')
    bad_lo = lo is not None and (value <= lo if lo_open else value < lo)
    bad_hi = hi is not None and value > hi
    if bad_lo or bad_hi or value != value:
        lo_s = '-inf' if lo is None else f'{lo}'
        hi_s = 'inf' if hi is None else f'{hi}'
        bracket = '(' if lo_open else '['
        raise MatchingConfigError(
            f'{name}.{key}: expected a value in {bracket}{lo_s}, {hi_s}], got {value!r}')
