"""The nodes' parameter YAML files read by the offline tools, so an offline run == a live run.

``config/<node>.yaml`` holds ``<node>: {ros__parameters: {...}}`` (flat keys). The tools read it
with ``yaml.safe_load`` and check it against the node's typed config dataclass (passed in by the
caller, which may import the node module): unknown keys, wrong types, values outside the
documented range or choices raise :class:`OfflineConfigError` naming the key.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, fields
import os
from pathlib import Path
import typing
from typing import Any, TypeVar

import yaml

from semfeat_ros.offline.errors import OfflineConfigError

C = TypeVar('C')

def read_node_params(path: str | os.PathLike[str], node: str) -> dict[str, Any]:
    """``ros__parameters`` of ``node`` in a parameter YAML file (``/**`` accepted too).

    Raises:
        OfflineConfigError: missing file, YAML error, or no parameters for ``node``.
    """
    p = Path(path)
    if not p.is_file():
        raise OfflineConfigError(f'parameter file {str(p)!r} does not exist')
    try:
        with open(p, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as exc:
        raise OfflineConfigError(
            f'cannot read parameter file {str(p)!r}: {" ".join(str(exc).split())}') from exc
    if not isinstance(data, dict):
        raise OfflineConfigError(f'{str(p)!r}: expected a mapping at the top level')
    for key in (node, f'/{node}', '/**'):
        section = data.get(key)
        if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
            return dict(section['ros__parameters'])
    raise OfflineConfigError(
        f'{str(p)!r}: no "{node}: ros__parameters:" section (top-level keys: '
        f'{", ".join(map(str, data)) or "none"})')


def _type_ok(value: Any, typ: Any) -> bool:
    if typ is bool:
        return isinstance(value, bool)
    if typ is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if typ is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if typ is str:
        return isinstance(value, str)
    origin = typing.get_origin(typ)
    if origin is list:
        (item,) = typing.get_args(typ) or (Any,)
        return isinstance(value, list) and (item is Any or all(_type_ok(v, item) for v in value))
    return True


def node_config(cls: type[C], params: Mapping[str, Any], source: str) -> C:
    """An instance of the node's config dataclass ``cls`` from YAML ``params``; missing keys
    keep their defaults. Raises :class:`OfflineConfigError` on unknown keys, wrong types and
    values outside the field's documented ``range`` / ``choices``."""
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise OfflineConfigError(
            f'{source}: unknown parameter(s) {", ".join(unknown)}; known: '
            f'{", ".join(sorted(known))}')
    values = {}
    for name, value in params.items():
        f, typ = known[name], hints[name]
        if not _type_ok(value, typ):
            default = f.default if f.default is not MISSING else f.default_factory()
            raise OfflineConfigError(
                f'{source}: parameter {name} must be of type {getattr(typ, "__name__", typ)} '
                f'(like the default {default!r}), got {value!r}')
        rng = f.metadata.get('range')
        if rng is not None and not rng[0] <= value <= rng[1]:
            raise OfflineConfigError(
                f'{source}: parameter {name} must be in [{rng[0]}, {rng[1]}], got {value!r}')
        choices = f.metadata.get('choices')
        if choices and value not in choices:
            raise OfflineConfigError(
                f'{source}: parameter {name} must be one of {", ".join(choices)}, got {value!r}')
        values[name] = float(value) if typ is float else value
    return cls(**values)


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``['key=value', ...]`` (values parsed as YAML: numbers, lists, true/false) -> dict."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition('=')
        if not sep or not key.strip():
            raise OfflineConfigError(f'--set expects KEY=VALUE, got {item!r}')
        try:
            out[key.strip()] = yaml.safe_load(text) if text.strip() else ''
        except yaml.YAMLError as exc:
            raise OfflineConfigError(
                f'--set {key.strip()}: cannot parse {text!r} ({" ".join(str(exc).split())})'
            ) from exc
    return out
