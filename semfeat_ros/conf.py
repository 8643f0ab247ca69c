"""Configuration dictionaries: ``default_conf`` plus overrides, and the common value checks.

Every package keeps a ``default_conf`` (one comment per key) and its own exception classes
(``errors.py``); the functions here take that class as ``error`` and raise it, so a caller
reports a bad key or value as its package's error. Names in messages are dotted paths
(``verification.threshold_rad``). Pure Python, so any module may import it.
"""
from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
import copy
from typing import Any


def _dotted(name: str, key: str) -> str:
    return f'{name}.{key}' if name else key


def merge_conf(default: Mapping[str, Any], conf: Mapping[str, Any] | None,
               error: type[Exception], *, name: str = '', what: str = 'config key',
               opaque: Collection[str] = ()) -> dict[str, Any]:
    """Deep copy of ``default`` updated with ``conf``; neither argument is modified.

    A key whose default is a mapping is merged recursively, unless its dotted path (relative to
    ``default``, e.g. ``pair_mix`` or ``matching.weights``) is in ``opaque``: then the override
    replaces the whole value (a mapping whose keys are data, not options). ``None`` for ``conf``
    or for a nested section keeps the defaults.

    Args:
        default: the defaults; a mapping value is a nested section.
        conf: overrides, or None.
        error: the exception class raised (the caller's package error).
        name: dotted prefix of the keys in messages (e.g. ``data``); '' for none.
        what: noun of the message, ``unknown {what} {dotted names}; known keys: ...``.
        opaque: dotted paths of mapping values replaced, not merged.

    Raises:
        error: a key not in ``default`` (every unknown key of the section, dotted), or a
            section that is not a mapping.
    """
    return _merge(default, conf, error, name, what, frozenset(opaque), '')


def _merge(default: Mapping[str, Any], conf: Any, error: type[Exception], name: str,
           what: str, opaque: frozenset[str], path: str) -> dict[str, Any]:
    out = copy.deepcopy(dict(default))
    if conf is None:
        return out
    if not isinstance(conf, Mapping):
        raise error(f'{name or "config"}: expected a mapping, got {type(conf).__name__}')
    unknown = sorted(str(key) for key in conf if key not in default)
    if unknown:
        names = ', '.join(_dotted(name, key) for key in unknown)
        raise error(f'unknown {what} {names}; known keys: {", ".join(sorted(default))}')
    for key, value in conf.items():
        sub = _dotted(path, key)
        if isinstance(default[key], Mapping) and sub not in opaque:
            out[key] = _merge(default[key], value, error, _dotted(name, key), what, opaque,
                              sub)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _is_number(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float)


def check_number(value: Any, name: str, error: type[Exception], lo: float | None = None,
                 hi: float | None = None, *, lo_open: bool = False,
                 integer: bool = False) -> None:
    """Raise ``error`` unless ``value`` is a number (not a bool, not NaN) in ``[lo, hi]``.

    ``None`` for a bound leaves that side unbounded; with ``lo_open`` the lower bound is
    exclusive; with ``integer`` the value must be integral (``3`` or ``3.0``). ``name`` is the
    dotted key in the message.
    """
    if not _is_number(value):
        raise error(f'{name} must be a number, got {value!r}')
    if integer and int(value) != value:
        raise error(f'{name} must be an integer, got {value!r}')
    bad_lo = lo is not None and (value <= lo if lo_open else value < lo)
    bad_hi = hi is not None and value > hi
    if bad_lo or bad_hi or value != value:
        lo_s = '-inf' if lo is None else f'{lo}'
        hi_s = 'inf' if hi is None else f'{hi}'
        raise error(f'{name} must be a number in {"(" if lo_open else "["}{lo_s}, {hi_s}], '
                    f'got {value!r}')


def check_int_min(value: Any, name: str, error: type[Exception], lo: int) -> None:
    """Raise ``error`` unless ``value`` is an ``int`` (not a bool, not a float) ``>= lo``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise error(f'{name} must be an integer >= {lo}, got {value!r}')


def check_choice(value: Any, name: str, error: type[Exception], choices: Sequence[Any]) -> None:
    """Raise ``error`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise error(f'{name} must be one of {tuple(choices)}, got {value!r}')


def check_fraction(value: Any, name: str, error: type[Exception]) -> None:
    """Raise ``error`` unless ``value`` is a number in ``[0, 1]``."""
    if not _is_number(value) or not 0.0 <= value <= 1.0:
        raise error(f'{name} must be a number in [0, 1], got {value!r}')
