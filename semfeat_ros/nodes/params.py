"""Typed node configuration declared as ROS parameters with descriptors.

Each node has one dataclass of parameters. Every field carries its documentation and constraints
in ``field(metadata=...)`` (built with :func:`param`): a description, an optional numeric range,
an optional set of allowed strings, and whether it is read-only after start-up. The same
dataclass is the source of the node's ``config/<node>.yaml`` and of the parameter tables in the
README, so the three cannot drift apart.
"""
from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields
import typing
from typing import Any, TypeVar

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

C = TypeVar('C')

_TYPES = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
    list[str]: ParameterType.PARAMETER_STRING_ARRAY,
    list[int]: ParameterType.PARAMETER_INTEGER_ARRAY,
    list[float]: ParameterType.PARAMETER_DOUBLE_ARRAY,
}


def param(default: Any, description: str, *, range: tuple[float, float] | None = None,
          choices: tuple[str, ...] | None = None, read_only: bool = False) -> Any:
    """A dataclass field for a node parameter (see module docstring)."""
    meta = dict(description=description, range=range, choices=choices, read_only=read_only)
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class ParamInfo:
    """One parameter as documented: name, type name, default, constraints."""

    name: str
    type_name: str
    default: Any
    description: str
    range: tuple[float, float] | None
    choices: tuple[str, ...] | None
    read_only: bool


def describe(cls: type) -> list[ParamInfo]:
    """Parameters of a config dataclass, in declaration order."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in fields(cls):
        default = f.default if f.default is not MISSING else f.default_factory()  # type: ignore
        typ = hints[f.name]
        out.append(ParamInfo(f.name, getattr(typ, '__name__', str(typ)) if typ in (
            bool, int, float, str) else str(typ), default, f.metadata.get('description', ''),
            f.metadata.get('range'), f.metadata.get('choices'),
            bool(f.metadata.get('read_only', False))))
    return out


def _descriptor(info: ParamInfo, ptype: int) -> ParameterDescriptor:
    desc = ParameterDescriptor(type=ptype, description=info.description,
                               read_only=info.read_only)
    if info.range is not None:
        lo, hi = info.range
        if ptype == ParameterType.PARAMETER_INTEGER:
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
    if info.choices:
        desc.additional_constraints = 'one of: ' + ', '.join(info.choices)
    return desc


def check_value(info: ParamInfo, value: Any) -> str | None:
    """Why ``value`` is not acceptable for ``info`` (None when it is)."""
    if info.range is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
        lo, hi = info.range
        if not lo <= value <= hi:
            return f'{info.name}={value} outside [{lo}, {hi}]'
    if info.choices and value not in info.choices:
        return f'{info.name}={value!r} not one of {", ".join(info.choices)}'
    return None


def declare_config(node: Node, cls: type[C]) -> C:
    """Declare every field of ``cls`` on ``node`` and return the values the node starts with.

    Values come from the parameter file / command line overrides; out-of-range or unknown-choice
    values raise ``ValueError`` at start-up with the parameter's name.
    """
    hints = typing.get_type_hints(cls)
    for info in describe(cls):
        ptype = _TYPES[hints[info.name]]
        node.declare_parameter(info.name, info.default, _descriptor(info, ptype))
    return read_config(node, cls)


def read_config(node: Node, cls: type[C]) -> C:
    """The current values of the (declared) parameters of ``cls``, checked as at start-up
    (``ValueError`` names the parameter); a managed node's configure reads them anew."""
    hints = typing.get_type_hints(cls)
    values = {}
    for info in describe(cls):
        value = node.get_parameter(info.name).value
        if hints[info.name] is float and isinstance(value, int):
            value = float(value)
        problem = check_value(info, value)
        if problem:
            raise ValueError(f'parameter {problem}')
        values[info.name] = value
    return cls(**values)


def guard_updates(node: Node, cls: type) -> None:
    """Reject run-time parameter changes that violate ranges/choices (read-only is enforced by
    rclpy from the descriptor)."""
    infos = {i.name: i for i in describe(cls)}

    def on_set(params: list[Parameter]) -> SetParametersResult:
        for p in params:
            info = infos.get(p.name)
            problem = check_value(info, p.value) if info else None
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)


def to_yaml_dict(node_name: str, cls: type) -> dict:
    """The ``config/<node>.yaml`` content for a config dataclass's defaults."""
    return {node_name: {'ros__parameters': {i.name: i.default for i in describe(cls)}}}
