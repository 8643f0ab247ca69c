"""Internal: tell rclpy and rosbags messages apart and build messages of either flavour.

Two flavours of message objects exist for the same ROS 2 type:

* **rclpy** classes (``sensor_msgs.msg.Image`` ...): default-constructible, ``uint8[]`` fields are
  ``array.array('B')``, fixed-size float arrays are numpy arrays, other sequences array.array or
  lists. The message packages are imported lazily, so using only the rosbags flavour never needs
  ROS 2 installed; ``rclpy`` itself is never imported here.
* **rosbags** classes (from a ``rosbags.typesys`` typestore): dataclasses that carry
  ``__msgtype__`` (e.g. ``'sensor_msgs/msg/Image'``), need every field in the constructor, and
  hold numeric sequences as numpy arrays.

A builder is given ``msg_cls``: the class of the message to build (either flavour) or a rosbags
``Typestore`` (then the class is looked up in it). The classes of nested messages (Header, Time,
PointField, RegionOfInterest) are derived from ``msg_cls``: for rosbags from the explicit
``typestore`` if given, else from the module ``msg_cls`` was generated in, else from the default
ROS 2 Jazzy typestore; for rclpy by importing ``<package>.msg``.
"""
from __future__ import annotations

import array
from functools import lru_cache
import importlib
import sys
from typing import Any

import numpy as np

from msg_adapters.errors import WrongMessageTypeError


def is_typestore(obj: Any) -> bool:
    """True for a rosbags ``Typestore`` (has ``types`` and ``serialize_cdr``)."""
    return hasattr(obj, 'types') and hasattr(obj, 'serialize_cdr') and not isinstance(obj, type)


def is_rosbags(obj: Any) -> bool:
    """True for a rosbags message class or instance (they carry ``__msgtype__``)."""
    return hasattr(obj, '__msgtype__')


@lru_cache(maxsize=1)
def default_typestore() -> Any:
    """The rosbags ROS 2 Jazzy typestore (created once)."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def msgtype_of(cls_or_msg: Any) -> str:
    """``'pkg/msg/Name'`` of a message class or instance of either flavour."""
    cls = cls_or_msg if isinstance(cls_or_msg, type) else type(cls_or_msg)
    if is_rosbags(cls):
        return str(cls.__msgtype__)
    parts = getattr(cls, '__module__', '').split('.')
    if len(parts) >= 2 and parts[1] == 'msg' and hasattr(cls, 'get_fields_and_field_types'):
        return f'{parts[0]}/msg/{cls.__name__}'
    raise WrongMessageTypeError(
        f'{cls!r} is neither an rclpy nor a rosbags message class')


def _rclpy_class(msgtype: str) -> type:
    pkg, kind, name = msgtype.split('/')
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
    except ImportError as exc:  # ROS 2 message package not installed
        raise WrongMessageTypeError(
            f'cannot import the rclpy message package {pkg}.{kind} for {msgtype}: {exc}') from exc
    return getattr(module, name)


def _rosbags_class(anchor: type | None, msgtype: str, typestore: Any | None) -> type:
    if typestore is not None:
        try:
            return typestore.types[msgtype]
        except KeyError as exc:
            raise WrongMessageTypeError(f'typestore has no type {msgtype}') from exc
    if anchor is not None:
        module = sys.modules.get(anchor.__module__)
        found = getattr(module, msgtype.replace('/', '__'), None) if module else None
        if isinstance(found, type) and getattr(found, '__msgtype__', None) == msgtype:
            return found
    return default_typestore().types[msgtype]


def resolve_class(msg_cls: Any, msgtype: str, typestore: Any | None = None) -> type:
    """The class of ``msgtype`` given ``msg_cls`` (a class of that type, or a typestore).

    Raises :class:`WrongMessageTypeError` if ``msg_cls`` is a class of another type.
    """
    if is_typestore(msg_cls):
        return _rosbags_class(None, msgtype, msg_cls)
    if not isinstance(msg_cls, type):
        raise WrongMessageTypeError(
            f'msg_cls: expected a {msgtype} class (rclpy or rosbags) or a rosbags typestore, '
            f'got {type(msg_cls).__name__}')
    actual = msgtype_of(msg_cls)
    if actual != msgtype:
        raise WrongMessageTypeError(f'msg_cls: expected a {msgtype} class, got {actual}')
    return msg_cls


def sibling_class(msg_cls: type, msgtype: str, typestore: Any | None = None) -> type:
    """The class of ``msgtype`` in the same flavour as ``msg_cls``."""
    if is_rosbags(msg_cls):
        return _rosbags_class(msg_cls, msgtype, typestore)
    return _rclpy_class(msgtype)


def flavour_class(msg_cls: Any, msgtype: str, typestore: Any | None = None) -> type:
    """The class of ``msgtype`` in the flavour selected by ``msg_cls``.

    ``msg_cls`` is any message class (rclpy or rosbags) or a rosbags typestore.
    """
    if not isinstance(msg_cls, type):
        return resolve_class(msg_cls, msgtype, typestore)
    msgtype_of(msg_cls)  # validates that it is a message class of either flavour
    return sibling_class(msg_cls, msgtype, typestore)


def construct(cls: type, **fields: Any) -> Any:
    """Build a message of either flavour from all its fields.

    rclpy constructors copy ``array.array`` arguments; setting attributes afterwards does not.
    """
    if is_rosbags(cls):
        return cls(**fields)
    msg = cls()
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


def byte_view(data: Any) -> np.ndarray:
    """``data`` of a ``uint8[]`` field as a 1-D uint8 numpy array, without copying if possible.

    Works for numpy arrays (rosbags), ``array.array`` (rclpy), bytes, bytearray and memoryview.
    The result shares memory with the message (read-only if the buffer is).
    """
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            data = data.astype(np.uint8) if data.dtype.kind in 'iub' else data.view(np.uint8)
        return np.ascontiguousarray(data.reshape(-1))
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(list(data), dtype=np.uint8)


def uint8_field(cls: type, payload: np.ndarray) -> Any:
    """A ``uint8[]`` field value for a message of ``cls``'s flavour from a 1-D uint8 array."""
    flat = np.ascontiguousarray(payload).reshape(-1)
    if flat.dtype != np.uint8:
        flat = flat.view(np.uint8)
    if is_rosbags(cls):
        return flat
    out = array.array('B')
    out.frombytes(flat)
    return out


def float64_seq(cls: type, values: Any) -> Any:
    """A ``float64[]`` (unbounded sequence) field value for ``cls``'s flavour."""
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if is_rosbags(cls):
        return arr.copy()
    return array.array('d', arr.tolist())
