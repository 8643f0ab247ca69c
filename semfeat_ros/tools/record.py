"""``semfeat-record``: record live topics into a rosbag2 bag (MCAP or SQLite3) with rosbags.

A stand-in for ``ros2 bag record`` where rosbag2 is not installable. Subscriptions are raw
(serialized CDR bytes in, the same bytes written), so any installed message type records
without conversion. A topic is subscribed as soon as a publisher for it appears on the graph
(its type is taken from the graph); reliability and durability follow the publishers'
offered QoS as ``ros2 bag record`` does, so a latched (transient_local) topic such as
``/semantic_cloud`` is received even when it was published before the recorder started. The
publishers' offered QoS is stored in the bag, so a replay reproduces it.

Timestamps are the reception time (middleware receive time, ns), the node's ROS time with
``--use-sim-time`` (driven by ``/clock``), or the message's ``header.stamp`` with
``--stamp header`` (falls back to reception time for types without a header).

The payloads are stored exactly as the middleware delivers them, like ``ros2 bag record``:
Fast DDS pads a serialized message with zero bytes to a multiple of 4, which every CDR reader
(rclpy, rosbags) ignores. Ctrl-C / SIGTERM stop cleanly: the bag is closed (metadata.yaml)
and the per-topic report printed; exit status 0.

Examples::

    semfeat-record out/run1 --topics /semantic_cloud /semfeat/odometry --duration 30
    semfeat-record out/run2 --format sqlite3 --topics /camera/front/image_raw --qos best_effort

Python API: :func:`record` (``record(out, conf, stop_event) -> RecordStats``).
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
import os
from pathlib import Path
import queue
import sys
import threading
import time
from typing import Any

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, ShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from tqdm import tqdm

from semfeat_ros.tools.bagio import (
    has_header_first,
    header_stamp_ns,
    message_definition,
    one_line,
    profile_to_bag_qos,
    reliability_from_name,
    resolve_message_class,
    split_ros_args,
    subscription_qos,
)
from semfeat_ros.tools.errors import (
    BagConfigError,
    BagFormatError,
    BagToolError,
    BagWriteError,
)

PROG = 'semfeat-record'
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
QOS_MODES = ('auto', 'reliable', 'best_effort')
STAMP_MODES = ('receive', 'header')
#: Longest single wait (s) of the spin loop: stop conditions are checked this often.
_POLL_S = 0.1


@dataclass
class RecordConfig:
    """Options of :func:`record` (the CLI flags of ``semfeat-record``).

    Attributes:
        topics: topics to record (relative names are resolved against the node namespace /).
        storage: ``mcap`` (default) or ``sqlite3``.
        duration: stop after this many seconds (0 = until stopped: signal or stop event).
        qos: ``auto`` (follow the publishers: reliable only if all are), ``reliable`` or
            ``best_effort``; durability always follows the publishers (transient_local when
            all offer it).
        stamp: ``receive`` (reception time, or ROS time with ``use_sim_time``) or ``header``
            (``header.stamp`` of messages that have one).
        use_sim_time: stamp with the node's ROS time, driven by ``/clock``.
        bag_version: rosbag2 metadata version written: 9 (what Jazzy writes) or 8.
        depth: subscription queue depth (messages).
        discovery_period: how often the graph is checked for new publishers (s).
        progress: show a tqdm message counter (on a terminal).
        node_name: name of the recorder node.
    """

    topics: tuple[str, ...] = ()
    storage: str = 'mcap'
    duration: float = 0.0
    qos: str = 'auto'
    stamp: str = 'receive'
    use_sim_time: bool = False
    bag_version: int = 9
    depth: int = 50
    discovery_period: float = 0.1
    progress: bool = True
    node_name: str = 'semfeat_recorder'

    @classmethod
    def coerce(cls, conf: RecordConfig | Mapping[str, Any] | None) -> RecordConfig:
        """A validated config from a :class:`RecordConfig`, a dict of its fields, or None."""
        if conf is None:
            conf = cls()
        elif isinstance(conf, Mapping):
            known = {f.name for f in fields(cls)}
            unknown = sorted(set(conf) - known)
            if unknown:
                raise BagConfigError(f'record config: unknown keys {unknown}; expected a '
                                     f'subset of {sorted(known)}')
            conf = cls(**{k: tuple(v) if k == 'topics' else v for k, v in conf.items()})
        conf.validate()
        return conf

    def validate(self) -> None:
        """Raise :class:`BagConfigError` naming the first invalid field."""
        if not self.topics or not all(isinstance(t, str) and t for t in self.topics):
            raise BagConfigError(f'topics: expected one or more topic names, got '
                                 f'{list(self.topics)}')
        if self.storage not in STORAGES:
            raise BagConfigError(f'storage: expected one of {sorted(STORAGES)}, got '
                                 f'{self.storage!r}')
        if not self.duration >= 0:
            raise BagConfigError(f'duration: expected >= 0 s (0 = until stopped), got '
                                 f'{self.duration}')
        if self.qos not in QOS_MODES:
            raise BagConfigError(f'qos: expected one of {list(QOS_MODES)}, got {self.qos!r}')
        if self.stamp not in STAMP_MODES:
            raise BagConfigError(f'stamp: expected one of {list(STAMP_MODES)}, got '
                                 f'{self.stamp!r}')
        if self.bag_version not in (8, 9):
            raise BagConfigError(f'bag_version: expected 8 or 9, got {self.bag_version}')
        if self.depth < 1:
            raise BagConfigError(f'depth: expected >= 1 message, got {self.depth}')
        if not self.discovery_period > 0:
            raise BagConfigError(f'discovery_period: expected > 0 s, got '
                                 f'{self.discovery_period}')


@dataclass
class RecordStats:
    """What :func:`record` wrote.

    Attributes:
        path: the bag directory.
        recorded: messages written per topic.
        types: message type per subscribed topic.
        qos: ``reliability/durability`` of each subscription.
        never_seen: requested topics that never had a publisher.
        skipped: topics not recorded, with the reason (type not installed, ...).
        header_fallback: messages stamped with reception time although ``stamp='header'``.
        interrupted: stopped by a signal, the stop event or a ROS shutdown (not the duration).
        wall_s: recording time (s).
        bytes: payload bytes written.
    """

    path: Path = Path()
    recorded: dict[str, int] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    qos: dict[str, str] = field(default_factory=dict)
    never_seen: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    header_fallback: int = 0
    interrupted: bool = False
    wall_s: float = 0.0
    bytes: int = 0

    def report(self) -> str:
        """Multi-line human-readable summary (one line per topic)."""
        lines = [f'{PROG}: wrote {sum(self.recorded.values())} messages '
                 f'({self.bytes / 1e6:.1f} MB) in {self.wall_s:.2f} s to {self.path}']
        for topic in sorted(self.recorded):
            lines.append(f'  {topic}: {self.recorded[topic]} messages '
                         f'[{self.types[topic]}, {self.qos[topic]}]')
        for topic in self.never_seen:
            lines.append(f'  {topic}: no publisher appeared, nothing recorded')
        for topic, reason in sorted(self.skipped.items()):
            lines.append(f'  skipped {topic}: {reason}')
        return '\n'.join(lines)


@dataclass
class _Item:
    topic: str
    sim_ns: int | None
    receive_ns: int
    data: bytes


@dataclass
class _NewTopic:
    topic: str
    type_name: str
    msgdef: str
    digest: str
    offered: list[Any]


class _BagSink(threading.Thread):
    """Owns the rosbags Writer: opens, writes and closes it in this one thread (SQLite objects
    must stay in their thread; the executor is never blocked by disk I/O). Messages stamped
    with sim time before the first ``/clock`` (ROS time 0) are held and written with the first
    valid stamp; if none ever comes they keep their reception time."""

    def __init__(self, out: Path, conf: RecordConfig,
                 on_written: Callable[[str, int], None]) -> None:
        super().__init__(name='semfeat-record-writer', daemon=True)
        self.out = out
        self.conf = conf
        self.items: queue.Queue[_Item | _NewTopic] = queue.Queue()
        self.error: BaseException | None = None
        self.ready = threading.Event()
        self._done = threading.Event()
        self._on_written = on_written
        self._conns: dict[str, Connection] = {}
        self._pending: list[_Item] = []

    def open(self) -> None:
        """Start the thread and wait until the bag is created.

        Raises:
            BagWriteError: the bag cannot be created (``out`` exists, no permission, ...).
        """
        self.start()
        self.ready.wait()
        if self.error is not None:
            self.join()
            raise BagWriteError(f'cannot create bag {str(self.out)!r}: '
                                f'{" ".join(str(self.error).split())}') from self.error

    def add_topic(self, topic: str, type_name: str, msgdef: str, digest: str,
                  offered: list[Any]) -> None:
        """Declare a topic (bag connection) before its first message."""
        self.items.put(_NewTopic(topic, type_name, msgdef, digest, offered))

    def _write(self, writer: Writer, item: _Item, stamp: int) -> None:
        writer.write(self._conns[item.topic], stamp, item.data)
        self._on_written(item.topic, len(item.data))

    def _handle(self, writer: Writer, item: _Item | _NewTopic) -> None:
        if isinstance(item, _NewTopic):
            self._conns[item.topic] = writer.add_connection(
                item.topic, item.type_name, msgdef=item.msgdef, rihs01=item.digest,
                offered_qos_profiles=item.offered)
        elif item.sim_ns is None:
            self._pending.append(item)
        else:
            for held in self._pending:
                self._write(writer, held, item.sim_ns)
            self._pending.clear()
            self._write(writer, item, item.sim_ns)

    def run(self) -> None:
        try:
            writer = Writer(self.out, version=self.conf.bag_version,
                            storage_plugin=STORAGES[self.conf.storage])
            writer.set_custom_data('recorded_by', PROG)
            writer.open()
        except BaseException as exc:  # WriterError (exists), PermissionError, ...
            self.error = exc
            self.ready.set()
            return
        self.ready.set()
        try:
            while not (self._done.is_set() and self.items.empty()):
                try:
                    item = self.items.get(timeout=_POLL_S)
                except queue.Empty:
                    continue
                self._handle(writer, item)
            for held in self._pending:
                self._write(writer, held, held.receive_ns)
            self._pending.clear()
        except BaseException as exc:  # reported by record(); recording stops
            self.error = exc
        finally:
            try:
                writer.close()
            except BaseException as exc:
                self.error = self.error or exc

    def finish(self) -> None:
        """Write what is queued, close the bag (metadata.yaml), stop the thread."""
        self._done.set()
        self.join()


class BagRecorder(Node):
    """Subscribes (raw) to the requested topics as their publishers appear."""

    def __init__(self, conf: RecordConfig, sink: _BagSink, stats: RecordStats,
                 context: Context | None = None) -> None:
        overrides = [Parameter('use_sim_time', value=True)] if conf.use_sim_time else []
        super().__init__(conf.node_name, context=context, parameter_overrides=overrides)
        self.conf = conf
        self.sink = sink
        self.stats = stats
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.wanted = {self.resolve_topic_name(t): t for t in conf.topics}
        self.subscribed: dict[str, Any] = {}
        # --use-sim-time or --ros-args -p use_sim_time:=true
        self.sim_time = bool(self.get_parameter('use_sim_time').value)
        self._forced = None if conf.qos == 'auto' else reliability_from_name(conf.qos)
        # Steady clock: with use_sim_time a ROS-time timer would wait for /clock, which may
        # only start once this recorder is subscribed (semfeat-play --wait-for-subscribers).
        self.create_timer(conf.discovery_period, self.discover,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'recording to {sink.out}: waiting for publishers on '
                               f'{sorted(self.wanted)}')
        self.discover()

    def discover(self) -> None:
        """Subscribe to every wanted topic that now has a publisher."""
        todo = [t for t in self.wanted if t not in self.subscribed and t not in
                self.stats.skipped]
        if not todo:
            return
        graph = dict(self.get_topic_names_and_types())
        for topic in todo:
            if topic not in graph:
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue  # only subscribers so far: nothing to record, QoS unknown
            try:
                self._subscribe(topic, graph[topic], infos)
            except BagToolError as exc:
                self.stats.skipped[topic] = str(exc)
                self.get_logger().warning(f'not recording {topic}: {exc}')

    def _subscribe(self, topic: str, types: Sequence[str], infos: Sequence[Any]) -> None:
        type_name = types[0]
        if len(types) > 1:
            self.get_logger().warning(f'{topic} has several types {list(types)}; recording '
                                      f'{type_name}')
        msg_cls = resolve_message_class(type_name)
        infos = [i for i in infos if i.topic_type == type_name] or list(infos)
        offered = [i.qos_profile for i in infos]
        qos = subscription_qos(offered, self._forced, self.conf.depth)
        msgdef, digest = message_definition(type_name, self.typestore,
                                            str(infos[0].topic_type_hash).replace('INVALID', ''))
        self.sink.add_topic(topic, type_name, msgdef, digest,
                            [profile_to_bag_qos(p) for p in offered])
        header = self.conf.stamp == 'header' and has_header_first(msg_cls)
        if self.conf.stamp == 'header' and not header:
            self.get_logger().warning(f'{topic} [{type_name}] has no header: stamping with '
                                      'reception time')
        self.subscribed[topic] = self.create_subscription(
            msg_cls, topic, self._callback(topic, header), qos, raw=True)
        self.stats.recorded.setdefault(topic, 0)
        self.stats.types[topic] = type_name
        rel = 'reliable' if qos.reliability == ReliabilityPolicy.RELIABLE else 'best_effort'
        self.stats.qos[topic] = f'{rel}/{qos.durability.name.lower()}'
        self.get_logger().info(f'recording {topic} [{type_name}] ({self.stats.qos[topic]})')

    def _callback(self, topic: str, header: bool) -> Callable[[bytes, dict], None]:
        sim = self.sim_time
        clock = self.get_clock()
        stats = self.stats

        def on_message(data: bytes, info: dict) -> None:
            receive_ns = int(info.get('received_timestamp') or 0) or time.time_ns()
            stamp: int | None = receive_ns
            if header:
                try:
                    stamp = header_stamp_ns(data)
                except BagFormatError:
                    stats.header_fallback += 1
            elif sim:
                now = clock.now().nanoseconds
                stamp = now if now > 0 else None
            elif self.conf.stamp == 'header':
                stats.header_fallback += 1
            self.sink.items.put(_Item(topic, stamp, receive_ns, data))

        return on_message


def record(out: str | os.PathLike[str], conf: RecordConfig | Mapping[str, Any],
           stop_event: threading.Event | None = None, context: Context | None = None,
           on_written: Callable[[str, int], None] | None = None) -> RecordStats:
    """Record ``conf.topics`` into a new bag directory ``out``; return what was written.

    Stops after ``conf.duration`` seconds, when ``stop_event`` is set, or when the ROS context
    shuts down (SIGINT / SIGTERM with rclpy's signal handlers); the bag is always closed with
    its metadata.yaml.

    Args:
        out: bag directory to create (must not exist; parents are created).
        conf: :class:`RecordConfig` or a dict of its fields (``topics`` required).
        stop_event: set it (from another thread) to stop recording.
        context: rclpy context; default: the global one, initialised (and shut down again
            afterwards) here if the caller has not done it.
        on_written: called as ``on_written(topic, payload bytes)`` from the writer thread after
            each message is written (progress display, or setting ``stop_event``).

    Raises:
        BagConfigError: invalid option. BagWriteError: ``out`` exists or writing failed.
    """
    conf = RecordConfig.coerce(conf)
    stop_event = stop_event or threading.Event()
    ctx = context or rclpy.get_default_context()
    own_init = not ctx.ok() and context is None
    out = Path(out)
    stats = RecordStats(path=out)
    counter = tqdm(unit='msg', desc=PROG, disable=None if conf.progress else True, leave=False)

    def written(topic: str, size: int) -> None:
        stats.recorded[topic] += 1
        stats.bytes += size
        counter.update(1)
        if on_written is not None:
            on_written(topic, size)

    sink = _BagSink(out, conf, written)
    try:
        sink.open()
    except BagWriteError:
        counter.close()
        raise
    recorder: BagRecorder | None = None
    executor: SingleThreadedExecutor | None = None
    start = time.monotonic()
    try:
        if own_init:
            rclpy.init(context=ctx)
        if ctx.ok():
            recorder = BagRecorder(conf, sink, stats, context=ctx)
            executor = SingleThreadedExecutor(context=ctx)
            executor.add_node(recorder)
            deadline = start + conf.duration if conf.duration else float('inf')
            try:
                while not stop_event.is_set() and ctx.ok() and sink.error is None:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    executor.spin_once(timeout_sec=min(_POLL_S, left))
            except (KeyboardInterrupt, ExternalShutdownException, ShutdownException):
                stop_event.set()  # Ctrl-C / shutdown: stop recording, keep what was received
            stats.interrupted = stop_event.is_set() or not ctx.ok()
            stats.never_seen = sorted(t for t in recorder.wanted if t not in recorder.subscribed
                                      and t not in stats.skipped)
    finally:
        stats.wall_s = time.monotonic() - start
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if recorder is not None:
            recorder.destroy_node()
        if own_init:
            rclpy.try_shutdown(context=ctx)
        sink.finish()
        counter.close()
    if sink.error is not None:
        raise BagWriteError(f'writing bag {str(out)!r} failed: '
                            f'{" ".join(str(sink.error).split()) or type(sink.error).__name__}'
                            ) from sink.error
    return stats


def build_parser() -> argparse.ArgumentParser:
    """Argument parser of ``semfeat-record`` (ROS arguments after ``--ros-args`` pass through)."""
    parser = argparse.ArgumentParser(
        prog=PROG, description='Record live topics into a rosbag2 bag with rosbags; raw '
                               'subscriptions: payloads stored as delivered, no conversion.')
    parser.add_argument('out', help='bag directory to create (must not exist)')
    parser.add_argument('--topics', nargs='+', required=True, metavar='TOPIC',
                        help='topics to record (subscribed when a publisher appears)')
    parser.add_argument('--format', '--storage', '-s', dest='storage', choices=sorted(STORAGES),
                        default='mcap', help='storage plugin (default mcap)')
    parser.add_argument('--duration', '-d', type=float, default=0.0, metavar='S',
                        help='stop after S seconds (default: until Ctrl-C / SIGTERM)')
    parser.add_argument('--qos', choices=QOS_MODES, default='auto',
                        help='subscription reliability (default auto: follow the publishers)')
    parser.add_argument('--stamp', choices=STAMP_MODES, default='receive',
                        help='bag timestamps: reception time (default) or header.stamp')
    parser.add_argument('--use-sim-time', action='store_true',
                        help='stamp with ROS time from /clock (same as -p use_sim_time:=true)')
    parser.add_argument('--bag-version', type=int, choices=(8, 9), default=9,
                        help='rosbag2 metadata version (default 9, as Jazzy writes; 8 for '
                             'older readers)')
    parser.add_argument('--no-progress', action='store_true', help='no progress counter')
    return parser


def config_from_args(args: argparse.Namespace) -> RecordConfig:
    """:class:`RecordConfig` from parsed ``semfeat-record`` arguments (validated)."""
    return RecordConfig.coerce(dict(
        topics=tuple(args.topics), storage=args.storage, duration=args.duration, qos=args.qos,
        stamp=args.stamp, use_sim_time=args.use_sim_time, bag_version=args.bag_version,
        progress=not args.no_progress))


def _init_ros(ros_args: Sequence[str]) -> None:
    try:
        rclpy.init(args=[PROG, *ros_args])
    except Exception as exc:  # rclpy's UnknownROSArgsError, RCLError, ...
        raise BagConfigError(f'invalid ROS arguments {list(ros_args)}: {one_line(exc)}'
                             ) from exc


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``semfeat-record``; returns the exit status.

    0: recorded (stopped by the duration, Ctrl-C or SIGTERM); 1: output exists, write failure
    or bad option (one line on stderr); 2: command-line syntax error (argparse).
    """
    ours, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(ours)
    stats: RecordStats | None = None
    try:
        conf = config_from_args(args)
        if Path(args.out).exists():
            raise BagWriteError(f'cannot create bag {args.out!r}: it exists already, not '
                                'overwriting')
        _init_ros(ros_args)
        stats = record(args.out, conf)
    except BagToolError as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
    if stats is not None:
        print(stats.report(), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(cli())
