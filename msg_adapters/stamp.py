"""Time stamps: ``builtin_interfaces/Time`` <-> integer nanoseconds, headers.

ROS 2 ``Time`` is ``sec`` (int32) + ``nanosec`` (uint32, < 1e9). Times before the epoch have a
negative ``sec`` and a non-negative ``nanosec`` (``-1 ns`` is ``sec=-1, nanosec=999999999``).
"""
from __future__ import annotations

import operator
from typing import Any

from msg_adapters._flavour import construct, flavour_class
from msg_adapters.errors import StampError, WrongMessageTypeError

NS_PER_S = 1_000_000_000
_INT32_MIN = -(2 ** 31)
_INT32_MAX = 2 ** 31 - 1

TIME_TYPE = 'builtin_interfaces/msg/Time'
HEADER_TYPE = 'std_msgs/msg/Header'


def split_ns(stamp_ns: int) -> tuple[int, int]:
    """``(sec, nanosec)`` of a time in ns; raises :class:`StampError` if sec leaves int32."""
    if isinstance(stamp_ns, bool):
        raise StampError(f'stamp_ns: expected an integer number of ns, got {stamp_ns!r}')
    try:
        ns = operator.index(stamp_ns)
    except TypeError as exc:
        raise StampError(
            f'stamp_ns: expected an integer number of ns, got {stamp_ns!r}') from exc
    sec, nanosec = divmod(ns, NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise StampError(
            f'stamp_ns={ns} gives sec={sec}, outside the int32 range of builtin_interfaces/Time')
    return sec, nanosec


def stamp_to_ns(obj: Any) -> int:
    """Nanoseconds of a ``Time``, a ``Header`` or any message with a ``header`` (either flavour).

    Raises :class:`StampError` if ``nanosec`` is not in [0, 1e9) or ``sec`` leaves int32.
    """
    stamp = obj
    if hasattr(stamp, 'header'):
        stamp = stamp.header
    if hasattr(stamp, 'stamp'):
        stamp = stamp.stamp
    if not (hasattr(stamp, 'sec') and hasattr(stamp, 'nanosec')):
        raise WrongMessageTypeError(
            f'expected a builtin_interfaces/Time, a Header or a message with a header, '
            f'got {type(obj).__name__}')
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if not 0 <= nanosec < NS_PER_S:
        raise StampError(f'Time.nanosec: expected 0 <= nanosec < 1e9, got {nanosec}')
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise StampError(f'Time.sec: expected an int32, got {sec}')
    return sec * NS_PER_S + nanosec


def ns_to_stamp(stamp_ns: int, msg_cls: Any, *, typestore: Any | None = None) -> Any:
    """A ``builtin_interfaces/Time`` for ``stamp_ns`` (ns).

    ``msg_cls`` selects the flavour: the Time class itself, any other message class of the
    wanted flavour (rclpy or rosbags), or a rosbags typestore.
    """
    sec, nanosec = split_ns(stamp_ns)
    cls = flavour_class(msg_cls, TIME_TYPE, typestore)
    return construct(cls, sec=sec, nanosec=nanosec)


def make_header(stamp_ns: int, frame_id: str, msg_cls: Any, *,
                typestore: Any | None = None) -> Any:
    """A ``std_msgs/Header`` (stamp from ``stamp_ns`` in ns) in the flavour of ``msg_cls``."""
    if not isinstance(frame_id, str):
        raise WrongMessageTypeError(f'frame_id: expected a str, got {type(frame_id).__name__}')
    header_cls = flavour_class(msg_cls, HEADER_TYPE, typestore)
    return construct(header_cls, stamp=ns_to_stamp(stamp_ns, header_cls, typestore=typestore),
                     frame_id=frame_id)


def header_info(msg: Any) -> tuple[int, str]:
    """``(stamp_ns, frame_id)`` of a message with a header (either flavour)."""
    return stamp_to_ns(msg), str(msg.header.frame_id)
