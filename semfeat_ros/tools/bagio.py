"""Helpers shared by ``semfeat-play`` and ``semfeat-record``: bags, types, QoS, raw CDR.

Messages stay serialized CDR ``bytes`` end to end: the recorded bytes are published with
``Publisher.publish(bytes)`` and received with ``create_subscription(..., raw=True)``, so any
message type replays without per-type conversion. Only the type *name* must be importable as a
Python message class (rclpy needs it to create the publisher or subscription).
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
import importlib
import importlib.util
import os
from pathlib import Path
import re
import struct
import sys
from typing import Any

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rosbags.interfaces import (
    Connection,
    Nodetype,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from semfeat_ros.tools.errors import (
    BagConfigError,
    BagFormatError,
    BagNotFoundError,
    UnknownMessageTypeError,
)

#: Reliability names accepted by ``--qos``.
RELIABILITY_NAMES: dict[str, ReliabilityPolicy] = {
    'reliable': ReliabilityPolicy.RELIABLE,
    'best_effort': ReliabilityPolicy.BEST_EFFORT,
}
#: Depth of a replay publisher when the bag does not record one (rosbag2's default).
DEFAULT_DEPTH = 10


def one_line(text: object) -> str:
    """Collapse an error text (possibly multi-line, e.g. a YAML parser error) into one line."""
    return ' '.join(str(text).split())


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split a command line into ``(tool arguments, ROS arguments)``.

    ROS arguments are the ``--ros-args ... [--]`` sections; only they go to ``rclpy.init``.
    (rclpy's ``remove_ros_args`` would also take a bare ``a:=b`` as a deprecated remap rule,
    which is the syntax of ``--remap a:=b``.)
    """
    ours: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == '--ros-args':
            inside = True
            ros.append(arg)
        elif inside and arg == '--':
            inside = False
            ros.append(arg)
        else:
            (ros if inside else ours).append(arg)
    return ours, ros


def resolve_bag_path(path: str | os.PathLike[str]) -> Path:
    """Check that ``path`` names a rosbag2 bag and return the path to open.

    Accepted: a rosbag2 directory with ``metadata.yaml``, that ``metadata.yaml`` itself (its
    directory is returned), or a single ``.mcap`` / ``.db3`` storage file.

    Raises:
        BagNotFoundError: the path does not exist, or is a directory without ``metadata.yaml``.
        BagFormatError: the path is a file of another kind.
    """
    from semfeat_ros.offline import bag as offline_bag
    from semfeat_ros.offline import errors as offline_errors

    try:
        return offline_bag.resolve_bag_path(path)
    except offline_errors.BagNotFoundError as exc:
        raise BagNotFoundError(str(exc)) from None
    except offline_errors.BagFormatError as exc:
        raise BagFormatError(str(exc)) from None


@contextmanager
def open_bag(path: str | os.PathLike[str]) -> Iterator[Reader]:
    """Open a rosbag2 bag (directory or storage file) for reading.

    Raises:
        BagNotFoundError: see :func:`resolve_bag_path`.
        BagFormatError: the metadata or a storage file is unreadable (one-line message).
    """
    bag = resolve_bag_path(path)
    reader = Reader(bag)
    try:
        reader.open()
    except (BagNotFoundError, BagFormatError):
        raise
    except FileNotFoundError as exc:
        raise BagNotFoundError(f'cannot open bag {str(bag)!r}: {one_line(exc)}') from exc
    except Exception as exc:  # rosbags raises ReaderError, but also OSError, KeyError, ...
        raise BagFormatError(
            f'cannot open bag {str(bag)!r} (broken or truncated?): {one_line(exc)}') from exc
    try:
        yield reader
    finally:
        reader.close()


def iter_bag_messages(reader: Reader, connections: Sequence[Connection]
                      ) -> Iterator[tuple[Connection, int, bytes]]:
    """Yield ``(connection, timestamp ns, serialized CDR bytes)`` in bag order.

    Raises:
        BagFormatError: a storage file is corrupt or truncated part-way (one-line message).
    """
    stream = reader.messages(connections=list(connections))
    while True:
        try:
            item = next(stream)
        except StopIteration:
            return
        except Exception as exc:  # any failure inside the storage plugin means a broken bag
            raise BagFormatError(
                f'cannot read bag {str(reader.path)!r} (broken or truncated?): '
                f'{one_line(exc) or type(exc).__name__}') from exc
        conn, stamp, data = item
        yield conn, stamp, data if isinstance(data, bytes) else bytes(data)


def resolve_message_class(type_name: str) -> type:
    """Python message class of a ROS type name (``pkg/msg/Name`` or ``pkg/Name``).

    Uses ``rosidl_runtime_py.utilities.get_message`` when installed, else imports ``pkg.msg``.
    Only a ROS interface package is imported (see :func:`is_message_package`): the type names
    come from the bag, and importing an arbitrary module would run its code.

    Raises:
        UnknownMessageTypeError: the name is malformed or not a message of an installed ROS
            interface package.
    """
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or parts[1] != 'msg' or not all(parts):
        raise UnknownMessageTypeError(
            f'message type {type_name!r} is malformed: expected "package/msg/Name"')
    pkg, _, name = parts
    if not (_PACKAGE_NAME.fullmatch(pkg) and _TYPE_NAME.fullmatch(name)):
        raise UnknownMessageTypeError(
            f'message type {type_name!r} is malformed: expected a lower-case package name and '
            'a CamelCase type name')
    if not is_message_package(pkg):
        raise UnknownMessageTypeError(
            f'message type {type_name!r} is not installed: {pkg} is not a ROS interface '
            'package')
    try:
        from rosidl_runtime_py.utilities import get_message
    except ImportError:
        get_message = None
    if get_message is not None:
        try:
            return get_message(f'{pkg}/msg/{name}')
        except (AttributeError, ModuleNotFoundError, ValueError) as exc:
            raise UnknownMessageTypeError(
                f'message type {type_name!r} is not installed: {one_line(exc)}') from exc
    try:
        module = importlib.import_module(f'{pkg}.msg')
    except ImportError as exc:
        raise UnknownMessageTypeError(
            f'message type {type_name!r} is not installed: no Python package {pkg}.msg') from exc
    cls = getattr(module, name, None)
    if not isinstance(cls, type):
        raise UnknownMessageTypeError(
            f'message type {type_name!r} is not installed: {pkg}.msg has no class {name}')
    return cls


_PACKAGE_NAME = re.compile(r'[a-z][a-z0-9_]*')
_TYPE_NAME = re.compile(r'[A-Z][A-Za-z0-9]*')


def is_message_package(pkg: str) -> bool:
    """True when ``pkg`` is an installed ROS interface package, found without importing it: a
    top-level package directory with a ``msg`` sub-package and the rosidl type support library
    ``<pkg>_s__rosidl_typesupport_c*.so`` that rosidl generates."""
    try:
        spec = importlib.util.find_spec(pkg)  # a top-level name: nothing is executed
    except (ImportError, ValueError):
        return False
    if spec is None or not spec.submodule_search_locations:
        return False
    for location in spec.submodule_search_locations:
        d = Path(location)
        if (d / 'msg' / '__init__.py').is_file() and any(
                d.glob(f'{pkg}_s__rosidl_typesupport_c*.so')):
            return True
    return False


def has_header_first(msg_cls: type) -> bool:
    """True when the first field of a message class is a ``std_msgs/Header`` (CDR offset 4)."""
    fields = getattr(msg_cls, 'get_fields_and_field_types', None)
    if fields is None:
        return False
    items = list(fields().items())
    return bool(items) and items[0][1] == 'std_msgs/Header'


def header_stamp_ns(data: bytes) -> int:
    """Header stamp (ns) of a serialized message whose first field is ``std_msgs/Header``.

    CDR layout: 4-byte encapsulation header (``00 01`` little endian, ``00 00`` big endian),
    then ``int32 sec``, ``uint32 nanosec`` at offsets 4 and 8 (no padding needed).

    Raises:
        BagFormatError: fewer than 12 bytes or an unknown encapsulation kind.
    """
    if len(data) < 12:
        raise BagFormatError(f'message of {len(data)} bytes is too short for a header (>= 12)')
    kind = data[1]
    if data[0] != 0 or kind not in (0, 1):
        raise BagFormatError(
            f'unknown CDR encapsulation {data[:2].hex()}: expected 0000 (BE) or 0001 (LE)')
    sec, nanosec = struct.unpack_from('<iI' if kind == 1 else '>iI', data, 4)
    return sec * 1_000_000_000 + nanosec


def reliability_from_name(name: str) -> ReliabilityPolicy:
    """``reliable`` / ``best_effort`` -> rclpy policy (ValueError subclass on other names)."""
    try:
        return RELIABILITY_NAMES[name]
    except KeyError:
        raise BagConfigError(
            f'qos: expected one of {sorted(RELIABILITY_NAMES)}, got {name!r}') from None


def replay_qos(offered: Sequence[Qos], default_reliability: ReliabilityPolicy,
               override: bool = False) -> QoSProfile:
    """Publisher QoS for replaying a topic recorded with the ``offered`` profiles.

    As ``ros2 bag play``: reliable only if every recorded publisher was reliable (best effort if
    any was), transient_local only if every one was; depth from the recording when it was
    known (keep_last, depth > 0), else 1 for transient_local (latched) and 10 otherwise.
    No offered profile, unknown policies, or ``override`` -> ``default_reliability``, volatile.
    """
    if override or not offered:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=DEFAULT_DEPTH,
                          reliability=default_reliability, durability=DurabilityPolicy.VOLATILE)
    rel = {q.reliability for q in offered}
    if rel == {QosReliability.RELIABLE}:
        reliability = ReliabilityPolicy.RELIABLE
    elif QosReliability.BEST_EFFORT in rel:
        reliability = ReliabilityPolicy.BEST_EFFORT
    else:
        reliability = default_reliability
    latched = {q.durability for q in offered} == {QosDurability.TRANSIENT_LOCAL}
    durability = DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE
    depths = [q.depth for q in offered if q.history == QosHistory.KEEP_LAST and q.depth > 0]
    depth = max(depths) if depths else (1 if latched else DEFAULT_DEPTH)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                      durability=durability)


def _qos_time(duration: Any) -> QosTime:
    sec, nsec = divmod(int(duration.nanoseconds), 1_000_000_000)
    return QosTime(sec, nsec)


def profile_to_bag_qos(profile: QoSProfile) -> Qos:
    """rclpy QoS profile (e.g. a publisher's offered profile from the graph) -> rosbags Qos.

    The policy enums share the rmw values; durations are split into (sec, nsec), the infinite
    duration giving (9223372036, 854775807) as rosbag2 on Jazzy writes it.
    """
    return Qos(
        history=QosHistory(int(profile.history)),
        depth=int(profile.depth),
        reliability=QosReliability(int(profile.reliability)),
        durability=QosDurability(int(profile.durability)),
        deadline=_qos_time(profile.deadline),
        lifespan=_qos_time(profile.lifespan),
        liveliness=QosLiveliness(int(profile.liveliness)),
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def subscription_qos(offered: Sequence[QoSProfile], forced: ReliabilityPolicy | None,
                     depth: int) -> QoSProfile:
    """Subscription QoS matching the publishers' ``offered`` profiles (``ros2 bag record``).

    Reliable only if every publisher is reliable (``forced`` overrides), transient_local only
    if every publisher offers it (so latched data such as ``/semantic_cloud`` is received).
    """
    if forced is not None:
        reliability = forced
    elif offered and all(p.reliability == ReliabilityPolicy.RELIABLE for p in offered):
        reliability = ReliabilityPolicy.RELIABLE
    else:
        reliability = ReliabilityPolicy.BEST_EFFORT
    latched = bool(offered) and all(
        p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in offered)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE,
                      liveliness=LivelinessPolicy.AUTOMATIC)


def _msg_search_dirs() -> list[Path]:
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    return [Path(p) / 'share' for p in prefixes]


def _referenced_types(fields: Sequence[tuple[str, Any]]) -> Iterator[str]:
    for _, desc in fields:
        while desc[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            desc = desc[1][0]
        if desc[0] == Nodetype.NAME:
            yield desc[1]


def message_definition(type_name: str, typestore: Any = None, type_hash: str = ''
                       ) -> tuple[str, str]:
    """``(msgdef text, RIHS01 hash)`` of a type, for a bag connection (MCAP schema, metadata).

    Looks the type up in ``typestore`` (default: rosbags' ROS 2 Jazzy store), else parses the
    installed ``share/<pkg>/msg/<Name>.msg`` files (``AMENT_PREFIX_PATH`` and this Python
    prefix) and registers them in the store. When no definition exists anywhere, returns an
    empty definition with ``type_hash`` (what rosbag2 does for an unknown definition).

    Raises:
        UnknownMessageTypeError: no definition is found and ``type_hash`` is empty.
    """
    store = typestore if typestore is not None else get_typestore(Stores.ROS2_JAZZY)
    missing: dict[str, Any] = {}
    pending = [type_name]
    while pending:
        name = pending.pop()
        if name in store.fielddefs or name in missing:
            continue
        pkg, _, short = name.partition('/msg/')
        files = [d / pkg / 'msg' / f'{short}.msg' for d in _msg_search_dirs()]
        found = next((f for f in files if f.is_file()), None)
        if found is None:
            if type_hash:
                return '', type_hash
            raise UnknownMessageTypeError(
                f'no message definition for {name!r} (needed by {type_name!r}) in the typestore '
                f'or in any share/{pkg}/msg directory')
        types = get_types_from_msg(found.read_text(), name)
        missing.update(types)
        for _, (_, fields) in types.items():
            pending.extend(_referenced_types(fields))
    if missing:
        store.register(missing)
    msgdef, _ = store.generate_msgdef(type_name, ros_version=2)
    return msgdef, store.hash_rihs01(type_name)
