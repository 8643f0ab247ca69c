"""Helpers of the semfeat-play / semfeat-record tests (no tests here): small bags written with
rosbags, bag reading, and a subprocess wrapper that watches a tool's log output."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

from conftest import REPO, ros_env
import numpy as np
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

T0_NS = 1_700_000_000 * 1_000_000_000
NS = 1_000_000_000
IMAGE, CHATTER, ODOM = '/camera/front/image_raw', '/chatter', '/vehicle/odom'
STORE = get_typestore(Stores.ROS2_JAZZY)
T = STORE.types
PLUGINS = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}

# One message: (topic, type name, bag timestamp ns, rosbags message object).
Message = tuple[str, str, int, object]


def _header(stamp_ns: int, frame: str) -> object:
    sec, nsec = divmod(stamp_ns, NS)
    return T['std_msgs/msg/Header'](T['builtin_interfaces/msg/Time'](sec, nsec), frame)


def sample_messages(seed: int = 0) -> list[Message]:
    """~0.95 s of traffic: 10 Image (10 Hz, 128x96 rgb8), 20 Odometry (20 Hz), 5 String."""
    rng = np.random.default_rng(seed)
    msgs: list[Message] = []
    for i in range(10):
        t = T0_NS + i * 100_000_000
        pixels = rng.integers(0, 256, 96 * 128 * 3, dtype=np.uint8)
        msgs.append((IMAGE, 'sensor_msgs/msg/Image', t, T['sensor_msgs/msg/Image'](
            _header(t, 'camera_front_optical'), 96, 128, 'rgb8', 0, 384, pixels)))
    for i in range(20):
        t = T0_NS + 10_000_000 + i * 50_000_000
        pose = T['geometry_msgs/msg/Pose'](T['geometry_msgs/msg/Point'](0.1 * i, 0.0, 0.0),
                                           T['geometry_msgs/msg/Quaternion'](0.0, 0.0, 0.0, 1.0))
        twist = T['geometry_msgs/msg/Twist'](T['geometry_msgs/msg/Vector3'](2.0, 0.0, 0.0),
                                             T['geometry_msgs/msg/Vector3'](0.0, 0.0, 0.01 * i))
        msgs.append((ODOM, 'nav_msgs/msg/Odometry', t, T['nav_msgs/msg/Odometry'](
            _header(t, 'odom'), 'base_link',
            T['geometry_msgs/msg/PoseWithCovariance'](pose, rng.random(36)),
            T['geometry_msgs/msg/TwistWithCovariance'](twist, rng.random(36)))))
    for i, dt_ms in enumerate((30, 170, 420, 610, 930)):  # irregular spacing
        msgs.append((CHATTER, 'std_msgs/msg/String', T0_NS + dt_ms * 1_000_000,
                     T['std_msgs/msg/String']('hello' + '!' * i)))  # CDR sizes 4k + 0..3
    return sorted(msgs, key=lambda m: m[2])


def qos(reliability: QosReliability = QosReliability.RELIABLE,
        durability: QosDurability = QosDurability.VOLATILE, depth: int = 10) -> Qos:
    """An offered QoS profile as rosbag2 stores it."""
    inf = QosTime(9223372036, 854775807)
    return Qos(QosHistory.KEEP_LAST, depth, reliability, durability, inf, inf,
               QosLiveliness.AUTOMATIC, inf, False)


def write_bag(path: Path, messages: Sequence[Message], storage: str = 'mcap',
              offered: dict[str, Sequence[Qos]] | None = None, store: object = STORE
              ) -> dict[str, list[tuple[int, bytes]]]:
    """Write ``messages`` to a new bag; return topic -> [(stamp ns, CDR bytes)] written."""
    written: dict[str, list[tuple[int, bytes]]] = {}
    with Writer(path, version=9, storage_plugin=PLUGINS[storage]) as writer:
        conns = {}
        for topic, type_name, stamp, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(
                    topic, type_name, typestore=store,
                    offered_qos_profiles=(offered or {}).get(topic, ()))
            data = bytes(store.serialize_cdr(msg, type_name))
            writer.write(conns[topic], stamp, data)
            written.setdefault(topic, []).append((stamp, data))
    return written


def dds_padded(data: bytes) -> bytes:
    """``data`` as a subscriber receives it: Fast DDS pads a serialized payload with zeros to a
    multiple of 4 bytes (``ros2 bag record`` stores the same padded bytes; every CDR reader
    ignores the padding)."""
    return data + bytes(-len(data) % 4)


def payloads(msgs: Sequence[tuple[int, bytes]], padded: bool = False) -> list[bytes]:
    """The CDR bytes of ``[(stamp, bytes)]``, optionally as received over DDS."""
    return [dds_padded(d) if padded else d for _, d in msgs]


def read_bag(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> [(stamp ns, CDR bytes)] of every message of a bag."""
    out: dict[str, list[tuple[int, bytes]]] = {}
    with Reader(path) as reader:
        for conn, stamp, data in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, bytes(data)))
    return out


def timing_deviation_ms(played: dict[str, list[tuple[int, bytes]]],
                        recorded: dict[str, list[tuple[int, bytes]]], rate: float
                        ) -> np.ndarray:
    """Per message: recorded time - bag time / rate (ms), minus the median (constant delay)."""
    pairs = [(b[0], r[0]) for topic, msgs in played.items()
             for b, r in zip(msgs, recorded[topic], strict=True)]
    bag_t, rec_t = np.array(pairs, dtype=np.float64).T
    offset = rec_t - (bag_t - bag_t.min()) / rate
    return (offset - np.median(offset)) / 1e6


class Tool:
    """A ``python -m semfeat_ros.tools.<name>`` subprocess on an isolated ROS domain."""

    #: Every tool started, so a failed test can kill its processes (see :meth:`kill_all`).
    started: list[Tool] = []

    def __init__(self, name: str, args: Sequence[str], domain: int) -> None:
        Tool.started.append(self)
        self.proc = subprocess.Popen(
            [sys.executable, '-m', f'semfeat_ros.tools.{name}', '--no-progress', *map(str, args)],
            env=ros_env(domain), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True)
        self.out: list[str] = []
        self.err: list[str] = []
        self._readers = [threading.Thread(target=self._pump, args=(s, d), daemon=True)
                         for s, d in ((self.proc.stdout, self.out), (self.proc.stderr, self.err))]
        for reader in self._readers:
            reader.start()

    @staticmethod
    def _pump(stream: object, sink: list[str]) -> None:
        for line in stream:  # type: ignore[attr-defined]
            sink.append(line)

    def wait_for(self, text: str, timeout: float = 20.0) -> None:
        """Block until ``text`` appears in the tool's stderr (its ROS log)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if any(text in line for line in self.err):
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        self.kill()
        raise AssertionError(f'{text!r} not logged; stderr:\n{"".join(self.err)}')

    def finish(self, sig: int | None = None, timeout: float = 30.0) -> tuple[int, str, str]:
        """Send ``sig`` (if given), wait for exit; return (exit code, stdout, stderr)."""
        if sig is not None:
            self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise
        for reader in self._readers:
            reader.join(timeout=5)
        return code, ''.join(self.out), ''.join(self.err)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=10)

    @classmethod
    def kill_all(cls) -> None:
        """Kill the tools still running (a test failed before stopping them)."""
        for tool in cls.started:
            tool.kill()
        cls.started.clear()
