"""``semfeat-play``: replay a rosbag2 recording (MCAP or SQLite3) with its original timing.

A stand-in for ``ros2 bag play`` where rosbag2 is not installable (on a full ROS machine users
keep using ``ros2 bag play``). The recorded CDR bytes are published untouched
(``Publisher.publish(bytes)``), so any installed message type replays. Type names and QoS come
from the bag (``offered_qos_profiles``); ``--clock`` also publishes ``/clock``
(``rosgraph_msgs/Clock``) at a steady rate between messages and with every message.

The player waits at the end until reliable subscribers acknowledged everything (up to 5 s), so
the last large frames are not lost when the process exits. ``--loop`` restarts bag time at
each pass (``/clock`` jumps back, as with ``ros2 bag play --loop``). Ctrl-C / SIGTERM stop
cleanly (node destroyed, context shut down) and print the per-topic report; exit status 0.

Examples::

    semfeat-play bags/garage_short --clock --wait-for-subscribers 1 \
        --wait-topics /camera/front/image_raw
    semfeat-play run.mcap --rate 0.5 --topics /camera/front/image_raw --remap \
        /camera/front/image_raw:=/cam/image --qos best_effort --qos-override

Python API: :func:`play` (``play(bag, conf) -> PlayStats``).
"""
from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
import os
import queue
import sys
import threading
import time
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Connection, ConnectionExtRosbag2, Qos
from rosbags.rosbag2 import Reader
from rosgraph_msgs.msg import Clock
from tqdm import tqdm

from semfeat_ros.tools.bagio import (
    iter_bag_messages,
    one_line,
    open_bag,
    reliability_from_name,
    replay_qos,
    resolve_message_class,
    split_ros_args,
)
from semfeat_ros.tools.errors import BagConfigError, BagToolError, UnknownMessageTypeError

PROG = 'semfeat-play'
_NS = 1_000_000_000
#: Longest single sleep (s): the stop event and the ROS context are checked at least this often.
_POLL_S = 0.05


@dataclass
class PlayConfig:
    """Options of :func:`play` (the CLI flags of ``semfeat-play``).

    Attributes:
        rate: playback speed factor (2.0 = twice as fast); > 0.
        loop: replay the bag again and again until stopped.
        clock_hz: publish ``/clock`` at this rate (Hz) between messages and with each message;
            0 disables ``/clock``.
        topics: bag topics to play (empty = all).
        remap: bag topic -> published topic name.
        qos: reliability for topics without recorded QoS: ``reliable`` or ``best_effort``.
        qos_override: ignore the recorded QoS and use ``qos`` (volatile, depth 10) everywhere.
        wait_for_subscribers: before playing, wait until every topic of ``wait_topics`` has at
            least this many matched subscriptions (0 = do not wait).
        wait_topics: topics to wait on (bag or published names; empty = every played topic).
        wait_timeout: give up waiting after this many seconds and play anyway (warning).
        start_delay: extra pause (s) before the first message, after the subscriber wait.
        read_ahead: messages read ahead of the publishing clock by a reader thread.
        ack_timeout: at the end, wait up to this long (s) until reliable subscribers have
            acknowledged everything (else the last large messages die with the publisher).
        progress: show a tqdm progress bar (on a terminal).
        node_name: name of the player node.
    """

    rate: float = 1.0
    loop: bool = False
    clock_hz: float = 0.0
    topics: tuple[str, ...] = ()
    remap: dict[str, str] = field(default_factory=dict)
    qos: str = 'reliable'
    qos_override: bool = False
    wait_for_subscribers: int = 0
    wait_topics: tuple[str, ...] = ()
    wait_timeout: float = 30.0
    start_delay: float = 0.0
    read_ahead: int = 32
    ack_timeout: float = 5.0
    progress: bool = True
    node_name: str = 'semfeat_player'

    @classmethod
    def coerce(cls, conf: PlayConfig | Mapping[str, Any] | None) -> PlayConfig:
        """A validated config from a :class:`PlayConfig`, a dict of its fields, or None."""
        if conf is None:
            conf = cls()
        elif isinstance(conf, Mapping):
            known = {f.name for f in fields(cls)}
            unknown = sorted(set(conf) - known)
            if unknown:
                raise BagConfigError(
                    f'play config: unknown keys {unknown}; expected a subset of {sorted(known)}')
            conf = cls(**conf)
        conf.validate()
        return conf

    def validate(self) -> None:
        """Raise :class:`BagConfigError` naming the first invalid field."""
        if not self.rate > 0 or self.rate == float('inf'):
            raise BagConfigError(f'rate: expected a finite factor > 0, got {self.rate}')
        if not 0 <= self.clock_hz <= 10_000:
            raise BagConfigError(f'clock_hz: expected 0 (off) or 0 < Hz <= 10000, got '
                                 f'{self.clock_hz}')
        reliability_from_name(self.qos)
        if self.wait_for_subscribers < 0:
            raise BagConfigError(
                f'wait_for_subscribers: expected >= 0, got {self.wait_for_subscribers}')
        if not self.wait_timeout >= 0:
            raise BagConfigError(f'wait_timeout: expected >= 0 s, got {self.wait_timeout}')
        if not self.start_delay >= 0:
            raise BagConfigError(f'start_delay: expected >= 0 s, got {self.start_delay}')
        if not self.ack_timeout >= 0:
            raise BagConfigError(f'ack_timeout: expected >= 0 s, got {self.ack_timeout}')
        if self.read_ahead < 1:
            raise BagConfigError(f'read_ahead: expected >= 1 message, got {self.read_ahead}')
        for src, dst in self.remap.items():
            if not src or not dst:
                raise BagConfigError(f'remap: expected non-empty "from:=to" names, got '
                                     f'{src!r}:={dst!r}')


@dataclass
class PlayStats:
    """What :func:`play` did.

    Attributes:
        published: messages published per (published) topic name.
        types: message type per published topic.
        qos: ``reliability/durability/depth`` used per published topic.
        skipped: bag topics not played, with the reason (unknown type, ...).
        clock_messages: ``/clock`` messages published.
        passes: complete passes over the bag (more than 1 with ``loop``).
        interrupted: stopped by a signal, the stop event or a ROS shutdown.
        wall_s: time spent publishing (s), without the subscriber wait and start delay.
        bag_span_s: bag time between the first and last played message of one pass (s).
        lateness_mean_ms: mean of (publish time - scheduled time) (ms).
        lateness_max_ms: maximum of (publish time - scheduled time) (ms).
    """

    published: dict[str, int] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    qos: dict[str, str] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    clock_messages: int = 0
    passes: int = 0
    interrupted: bool = False
    wall_s: float = 0.0
    bag_span_s: float = 0.0
    lateness_mean_ms: float = 0.0
    lateness_max_ms: float = 0.0

    def report(self) -> str:
        """Multi-line human-readable summary (one line per topic)."""
        lines = [f'{PROG}: {"interrupted" if self.interrupted else "done"}: '
                 f'{sum(self.published.values())} messages in {self.wall_s:.2f} s '
                 f'({self.passes} complete pass(es), bag span {self.bag_span_s:.2f} s, '
                 f'lateness mean {self.lateness_mean_ms:.2f} ms max '
                 f'{self.lateness_max_ms:.2f} ms)']
        for topic in sorted(self.published):
            lines.append(f'  {topic}: {self.published[topic]} messages '
                         f'[{self.types[topic]}, {self.qos[topic]}]')
        if self.clock_messages:
            lines.append(f'  /clock: {self.clock_messages} messages')
        for topic, reason in sorted(self.skipped.items()):
            lines.append(f'  skipped {topic}: {reason}')
        return '\n'.join(lines)


@dataclass
class _TopicPlan:
    bag_topic: str
    out_topic: str
    type_name: str
    msg_cls: type
    qos: QoSProfile
    connections: list[Connection]


def _offered(conns: Sequence[Connection]) -> list[Qos]:
    out: list[Qos] = []
    for conn in conns:
        if isinstance(conn.ext, ConnectionExtRosbag2):
            out.extend(conn.ext.offered_qos_profiles)
    return out


def _qos_text(qos: QoSProfile) -> str:
    rel = 'reliable' if qos.reliability == ReliabilityPolicy.RELIABLE else 'best_effort'
    dur = qos.durability.name.lower()
    return f'{rel}/{dur}/depth {qos.depth}'


def plan_topics(reader: Reader, conf: PlayConfig) -> tuple[list[_TopicPlan], dict[str, str]]:
    """Publishers to create: ``(plans, skipped bag topic -> reason)``.

    Raises:
        BagConfigError: a requested topic is not in the bag, or nothing is left to play.
    """
    by_topic: dict[str, list[Connection]] = {}
    for conn in reader.connections:
        by_topic.setdefault(conn.topic, []).append(conn)
    missing = [t for t in conf.topics if t not in by_topic]
    if missing:
        raise BagConfigError(f'topics: {missing} not in the bag; it has {sorted(by_topic)}')
    unused_remaps = sorted(set(conf.remap) - set(by_topic))
    if unused_remaps:
        raise BagConfigError(f'remap: {unused_remaps} not in the bag; it has {sorted(by_topic)}')
    default_rel = reliability_from_name(conf.qos)
    plans: list[_TopicPlan] = []
    skipped: dict[str, str] = {}
    for topic in sorted(by_topic):
        if conf.topics and topic not in conf.topics:
            continue
        conns = by_topic[topic]
        type_name = conns[0].msgtype
        others = sorted({c.msgtype for c in conns} - {type_name})
        if others:
            skipped[f'{topic} [{", ".join(others)}]'] = (
                f'a topic has one type; playing it as {type_name} only')
        try:
            msg_cls = resolve_message_class(type_name)
        except UnknownMessageTypeError as exc:
            skipped[topic] = str(exc)
            continue
        same = [c for c in conns if c.msgtype == type_name]
        plans.append(_TopicPlan(topic, conf.remap.get(topic, topic), type_name, msg_cls,
                                replay_qos(_offered(same), default_rel, conf.qos_override),
                                same))
    if not plans:
        raise BagConfigError(f'nothing to play: no playable topic in the bag (skipped: '
                             f'{"; ".join(f"{k}: {v}" for k, v in skipped.items()) or "none"})')
    outs = [p.out_topic for p in plans]
    dup = sorted({t for t in outs if outs.count(t) > 1})
    if dup:
        raise BagConfigError(f'remap: several bag topics would publish on {dup}')
    return plans, skipped


_END = object()


class _ReadAhead(threading.Thread):
    """Reads ``(connection, stamp ns, bytes)`` into a bounded queue ahead of the publisher."""

    def __init__(self, reader: Reader, connections: Sequence[Connection], depth: int,
                 stop: threading.Event) -> None:
        super().__init__(name='semfeat-play-reader', daemon=True)
        self.items: queue.Queue[Any] = queue.Queue(maxsize=depth)
        self._reader = reader
        self._connections = list(connections)
        self._halt = stop

    def _put(self, item: Any) -> bool:
        while not self._halt.is_set():
            try:
                self.items.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def run(self) -> None:
        try:
            for item in iter_bag_messages(self._reader, self._connections):
                if not self._put(item):
                    return
        except BaseException as exc:  # handed to the publishing thread, raised there
            self._put(exc)
            return
        self._put(_END)


class BagPlayer(Node):
    """Publish-only node: one raw publisher per played topic, plus ``/clock`` if asked."""

    def __init__(self, plans: Sequence[_TopicPlan], conf: PlayConfig,
                 context: Context | None = None) -> None:
        super().__init__(conf.node_name, context=context)
        self.conf = conf
        self.plans = list(plans)
        self.pubs: dict[tuple[str, str], tuple[str, Publisher]] = {}
        for plan in self.plans:
            try:
                pub = self.create_publisher(plan.msg_cls, plan.out_topic, plan.qos)
            except Exception as exc:  # invalid topic name from a remap rule
                raise BagConfigError(
                    f'cannot publish {plan.bag_topic!r} as {plan.out_topic!r}: {exc}') from exc
            self.pubs[(plan.bag_topic, plan.type_name)] = (pub.topic_name, pub)
        self.clock_pub: Publisher | None = None
        if conf.clock_hz > 0:
            # rclcpp::ClockQoS, as ros2 bag play: keep_last 1, best effort.
            self.clock_pub = self.create_publisher(
                Clock, '/clock', QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                                            reliability=ReliabilityPolicy.BEST_EFFORT))
        self.last_clock_ns = -1
        self.clock_count = 0

    def publish_clock(self, stamp_ns: int) -> None:
        """Publish ``/clock`` = ``stamp_ns`` (bag time, ns) unless it would go backwards."""
        if self.clock_pub is None or stamp_ns <= self.last_clock_ns:
            return
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(stamp_ns, _NS)
        self.clock_pub.publish(msg)
        self.last_clock_ns = stamp_ns
        self.clock_count += 1

    def wait_for_acks(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` (s, shared) until reliable subscribers acknowledged all
        data; False (and a warning) on timeout."""
        end = time.monotonic() + timeout_s
        for out_topic, pub in self.pubs.values():
            left = max(0.0, end - time.monotonic())
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * _NS))):
                self.get_logger().warning(f'{out_topic}: not all messages acknowledged by '
                                          f'subscribers within {timeout_s} s')
                return False
        return True

    def subscriber_shortfall(self, wanted: int, topics: Sequence[str]) -> list[str]:
        """Played topics (of ``topics``, bag or published names) with < ``wanted`` readers."""
        short = []
        for (bag_topic, _), (out_topic, pub) in self.pubs.items():
            if topics and bag_topic not in topics and out_topic not in topics:
                continue
            if pub.get_subscription_count() < wanted:
                short.append(out_topic)
        return short


class _Stopper:
    """Stop condition: the caller's event, or the ROS context shut down (SIGINT, SIGTERM)."""

    def __init__(self, event: threading.Event, context: Context) -> None:
        self.event = event
        self.context = context

    def __call__(self) -> bool:
        return self.event.is_set() or not self.context.ok()

    def sleep(self, seconds: float) -> bool:
        """Sleep up to ``seconds``; False if stopped meanwhile."""
        end = time.monotonic() + seconds
        while not self():
            left = end - time.monotonic()
            if left <= 0:
                return True
            self.event.wait(min(left, _POLL_S))
        return False


def _play_pass(player: BagPlayer, reader: Reader, conf: PlayConfig, stopped: _Stopper,
               stats: PlayStats, bar: tqdm, lateness: list[float]) -> bool:
    """Publish the bag once; True when the pass completed, False if stopped."""
    connections = [c for p in player.plans for c in p.connections]
    halt = threading.Event()
    ahead = _ReadAhead(reader, connections, conf.read_ahead, halt)
    ahead.start()
    player.last_clock_ns = -1  # a new pass restarts bag time (/clock jumps back, as rosbag2)
    clock_period_ns = int(_NS / conf.clock_hz) if conf.clock_hz > 0 else 0
    first_ns = last_ns = -1
    wall0 = next_clock = 0
    try:
        while True:
            try:
                item = ahead.items.get(timeout=_POLL_S)
            except queue.Empty:
                if stopped():
                    return False
                continue
            if item is _END:
                stats.bag_span_s = max(stats.bag_span_s, (last_ns - first_ns) / _NS)
                return True
            if isinstance(item, BaseException):
                raise item
            conn, stamp, data = item
            if first_ns < 0:
                first_ns, wall0 = stamp, time.monotonic_ns()
                next_clock = wall0
            target = wall0 + int((stamp - first_ns) / conf.rate)
            while True:  # sleep until the message is due, ticking /clock meanwhile
                if stopped():
                    return False
                now = time.monotonic_ns()
                if clock_period_ns and now >= next_clock:
                    bag_now = first_ns + int((now - wall0) * conf.rate)
                    player.publish_clock(min(bag_now, stamp))
                    next_clock += clock_period_ns * ((now - next_clock) // clock_period_ns + 1)
                if now >= target:
                    break
                wake = min(target, next_clock) if clock_period_ns else target
                stopped.event.wait(min((wake - now) / _NS, _POLL_S))
            out_topic, pub = player.pubs[(conn.topic, conn.msgtype)]
            try:
                player.publish_clock(stamp)
                pub.publish(data)
            except Exception:
                if stopped():  # the context was shut down between the check and the call
                    return False
                raise
            lateness.append((time.monotonic_ns() - target) / 1e6)
            stats.published[out_topic] += 1
            last_ns = stamp
            bar.update(1)
    finally:
        halt.set()
        ahead.join()


def _wait_for_start(player: BagPlayer, conf: PlayConfig, stopped: _Stopper) -> None:
    """The subscriber wait (``wait_for_subscribers``, up to ``wait_timeout``), then
    ``start_delay``."""
    if conf.wait_for_subscribers:
        deadline = time.monotonic() + conf.wait_timeout
        while short := player.subscriber_shortfall(conf.wait_for_subscribers, conf.wait_topics):
            if time.monotonic() >= deadline:
                player.get_logger().warning(
                    f'still fewer than {conf.wait_for_subscribers} subscriber(s) on {short} '
                    f'after {conf.wait_timeout} s; playing anyway')
                break
            if not stopped.sleep(_POLL_S):
                return
    if conf.start_delay:
        stopped.sleep(conf.start_delay)


def play(bag: str | os.PathLike[str], conf: PlayConfig | Mapping[str, Any] | None = None,
         stop_event: threading.Event | None = None, context: Context | None = None
         ) -> PlayStats:
    """Publish the messages of ``bag`` with their recorded timing; return what was published.

    Args:
        bag: rosbag2 directory (or its metadata.yaml), or a single ``.mcap`` / ``.db3`` file.
        conf: :class:`PlayConfig` or a dict of its fields (defaults for the rest).
        stop_event: set it (from another thread) to stop playback early.
        context: rclpy context to use; default: the global one, initialised (and shut down
            again afterwards) here if the caller has not done it.

    Raises:
        BagNotFoundError, BagFormatError: wrong path, broken or truncated bag.
        BagConfigError: invalid option, requested topic not in the bag, nothing playable.
    """
    conf = PlayConfig.coerce(conf)
    stop_event = stop_event or threading.Event()
    ctx = context or rclpy.get_default_context()
    own_init = not ctx.ok() and context is None
    stats = PlayStats()
    with open_bag(bag) as reader:
        plans, stats.skipped = plan_topics(reader, conf)
        if own_init:
            rclpy.init(context=ctx)
        player: BagPlayer | None = None
        try:
            stopped = _Stopper(stop_event, ctx)
            if stopped():
                stats.interrupted = True
                return stats
            player = BagPlayer(plans, conf, context=ctx)
            for _, (out_topic, _) in player.pubs.items():
                stats.published[out_topic] = 0
            for plan in plans:
                out_topic = player.pubs[(plan.bag_topic, plan.type_name)][0]
                stats.types[out_topic] = plan.type_name
                stats.qos[out_topic] = _qos_text(plan.qos)
            log = player.get_logger()
            for topic, reason in stats.skipped.items():
                log.warning(f'skipping {topic}: {reason}')
            lateness: list[float] = []
            start = time.monotonic()
            try:  # Ctrl-C (KeyboardInterrupt) anywhere here: stop, report what was published
                _wait_for_start(player, conf, stopped)
                total = sum(c.msgcount for p in plans for c in p.connections)
                if not stopped():
                    log.info(f'playing {total} messages on {len(plans)} topic(s) from {bag} '
                             f'at rate {conf.rate:g}{" (loop)" if conf.loop else ""}')
                start = time.monotonic()
                with tqdm(total=None if conf.loop else total, unit='msg', desc=PROG,
                          disable=None if conf.progress else True, leave=False) as bar:
                    while not stopped():
                        if not _play_pass(player, reader, conf, stopped, stats, bar, lateness):
                            break
                        stats.passes += 1
                        if not conf.loop:
                            break
                if not stopped():
                    player.wait_for_acks(conf.ack_timeout)
            except KeyboardInterrupt:
                stop_event.set()
            stats.wall_s = time.monotonic() - start
            stats.interrupted = stopped()
            stats.clock_messages = player.clock_count
            if lateness:
                stats.lateness_mean_ms = sum(lateness) / len(lateness)
                stats.lateness_max_ms = max(lateness)
            return stats
        finally:
            if player is not None:
                player.destroy_node()
            if own_init:
                rclpy.try_shutdown(context=ctx)


def _remap_rule(text: str) -> tuple[str, str]:
    src, sep, dst = text.partition(':=')
    if not sep or not src or not dst:
        raise argparse.ArgumentTypeError(f'expected FROM:=TO, got {text!r}')
    return src, dst


def build_parser() -> argparse.ArgumentParser:
    """Argument parser of ``semfeat-play`` (ROS arguments after ``--ros-args`` pass through)."""
    parser = argparse.ArgumentParser(
        prog=PROG, description='Replay a rosbag2 bag (MCAP or SQLite3) with its original '
                               'timing over rclpy; recorded bytes are published untouched.')
    parser.add_argument('bag', help='rosbag2 directory, its metadata.yaml, or a .mcap/.db3 file')
    parser.add_argument('--rate', '-r', type=float, default=1.0,
                        help='playback speed factor (default 1.0)')
    parser.add_argument('--loop', '-l', action='store_true', help='replay until interrupted')
    parser.add_argument('--clock', nargs='?', type=float, const=100.0, default=0.0,
                        metavar='HZ', help='publish /clock at HZ (100 when given without a '
                                           'value; put it after BAG) and with every message')
    parser.add_argument('--topics', nargs='+', default=[], metavar='TOPIC',
                        help='play only these bag topics')
    parser.add_argument('--remap', '-m', nargs='+', type=_remap_rule, default=[],
                        metavar='FROM:=TO', help='publish bag topic FROM as TO')
    parser.add_argument('--qos', choices=sorted(('reliable', 'best_effort')),
                        default='reliable', help='reliability of topics the bag has no QoS '
                                                 'for (default reliable)')
    parser.add_argument('--qos-override', action='store_true',
                        help='ignore the recorded QoS: use --qos, volatile, depth 10')
    parser.add_argument('--wait-for-subscribers', type=int, default=0, metavar='N',
                        help='wait until each waited-on topic has N subscriptions')
    parser.add_argument('--wait-topics', nargs='+', default=[], metavar='TOPIC',
                        help='topics to wait on (default: all played topics)')
    parser.add_argument('--wait-timeout', type=float, default=30.0, metavar='S',
                        help='play anyway after S seconds of waiting (default 30)')
    parser.add_argument('--start-delay', '--delay', type=float, default=0.0, metavar='S',
                        help='pause S seconds before the first message')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    return parser


def config_from_args(args: argparse.Namespace) -> PlayConfig:
    """:class:`PlayConfig` from parsed ``semfeat-play`` arguments (validated)."""
    return PlayConfig.coerce(dict(
        rate=args.rate, loop=args.loop, clock_hz=args.clock, topics=tuple(args.topics),
        remap=dict(args.remap), qos=args.qos, qos_override=args.qos_override,
        wait_for_subscribers=args.wait_for_subscribers, wait_topics=tuple(args.wait_topics),
        wait_timeout=args.wait_timeout, start_delay=args.start_delay,
        progress=not args.no_progress))


def _init_ros(ros_args: Sequence[str]) -> None:
    try:
        rclpy.init(args=[PROG, *ros_args])
    except Exception as exc:  # rclpy's UnknownROSArgsError, RCLError, ...
        raise BagConfigError(f'invalid ROS arguments {list(ros_args)}: {one_line(exc)}'
                             ) from exc


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``semfeat-play``; returns the exit status.

    0: played (or stopped by Ctrl-C / SIGTERM); 1: wrong path, broken bag or bad option (one
    line on stderr); 2: command-line syntax error (argparse).
    """
    ours, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(ours)
    stats: PlayStats | None = None
    try:
        conf = config_from_args(args)
        with open_bag(args.bag) as reader:  # report a wrong path / broken bag before ROS starts
            plan_topics(reader, conf)
        _init_ros(ros_args)
        stats = play(args.bag, conf)
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
