"""Reading rosbag2 recordings for the offline tools (rosbags ``AnyReader``, no rclpy, no DDS).

:class:`BagSource` opens a bag directory (with ``metadata.yaml``) or a single ``.mcap`` /
``.db3`` file, lists its topics, checks that required topics exist with the expected message
types and yields deserialised messages of several topics merged in recording-time order. Every
failure is a one-line :mod:`semfeat_ros.offline.errors` exception.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
import os
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from msg_adapters import pose_stamped_to_numpy
from msg_adapters.errors import MessageError
from semfeat_ros.offline.errors import BagFormatError, BagNotFoundError, TopicNotFoundError

#: Storage files rosbags opens directly, without a metadata.yaml.
STORAGE_SUFFIXES = ('.mcap', '.db3')
IMAGE_TYPE = 'sensor_msgs/msg/Image'
COMPRESSED_TYPE = 'sensor_msgs/msg/CompressedImage'
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)
CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'
ODOMETRY_TYPE = 'nav_msgs/msg/Odometry'
NAVSATFIX_TYPE = 'sensor_msgs/msg/NavSatFix'
POSE_STAMPED_TYPE = 'geometry_msgs/msg/PoseStamped'
POINTCLOUD2_TYPE = 'sensor_msgs/msg/PointCloud2'


def one_line(text: object) -> str:
    """Collapse a (possibly multi-line) error text into one line."""
    return ' '.join(str(text).split())


def typestore() -> Any:
    """The rosbags ROS 2 Jazzy typestore used to read and write bags."""
    return get_typestore(Stores.ROS2_JAZZY)


def resolve_bag_path(path: str | os.PathLike[str]) -> Path:
    """The path to open for ``path``: a rosbag2 directory, its ``metadata.yaml`` or a storage
    file (``.mcap`` / ``.db3``).

    Raises:
        BagNotFoundError: the path does not exist or is a directory without ``metadata.yaml``.
        BagFormatError: the path is a file of another kind.
    """
    bag = Path(path)
    if not bag.exists():
        raise BagNotFoundError(f'bag {str(bag)!r} does not exist')
    if bag.is_file() and bag.name == 'metadata.yaml':
        return bag.parent
    if bag.is_dir():
        if not (bag / 'metadata.yaml').is_file():
            storage = sorted(p.name for p in bag.iterdir() if p.suffix in STORAGE_SUFFIXES)
            hint = f' (it holds {storage[0]!r}: pass that file instead)' if storage else ''
            raise BagNotFoundError(
                f'{str(bag)!r} is not a rosbag2 directory: no metadata.yaml in it{hint}')
        return bag
    if bag.suffix not in STORAGE_SUFFIXES:
        raise BagFormatError(
            f'{str(bag)!r} is not a bag: expected a rosbag2 directory or a '
            f'{"/".join(STORAGE_SUFFIXES)} file, got a {bag.suffix or "suffix-less"} file')
    return bag


def absolute_topic(topic: str) -> str:
    """A topic name as recorded in a bag: relative names (the nodes' parameters) resolve in the
    root namespace, as for nodes started without one (``'camera/info'`` -> ``'/camera/info'``)."""
    return topic if topic.startswith('/') else '/' + topic


@dataclass(frozen=True)
class BagMessage:
    """One deserialised message: ``topic``, recording time ``log_ns`` (ns), ``msgtype``,
    the rosbags message object ``msg`` and its serialized CDR bytes ``raw``."""

    topic: str
    log_ns: int
    msgtype: str
    msg: Any
    raw: bytes


class BagSource:
    """A rosbag2 bag opened for reading (use as a context manager)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = resolve_bag_path(path)
        self.typestore = typestore()
        self._reader = AnyReader([self.path], default_typestore=self.typestore)
        try:
            self._reader.open()
        except Exception as exc:  # AnyReaderError, OSError, KeyError, ... from the plugins
            raise BagFormatError(
                f'cannot open bag {str(self.path)!r} (broken or truncated?): '
                f'{one_line(exc) or type(exc).__name__}') from exc
        self.topics: dict[str, str] = {}
        self._counts: dict[str, int] = {}
        for conn in self._reader.connections:
            self.topics.setdefault(conn.topic, conn.msgtype)
            self._counts[conn.topic] = self._counts.get(conn.topic, 0) + int(conn.msgcount)

    def __enter__(self) -> BagSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        try:
            self._reader.close()
        except Exception:  # closing a half-broken reader must not hide the original error
            pass

    def has(self, topic: str, msgtypes: Sequence[str] | None = None) -> bool:
        """True when ``topic`` is in the bag (with one of ``msgtypes`` if given)."""
        topic = absolute_topic(topic)
        return topic in self.topics and (msgtypes is None or self.topics[topic] in msgtypes)

    def message_count(self, topic: str) -> int:
        """Messages recorded on ``topic`` (0 when absent)."""
        return self._counts.get(absolute_topic(topic), 0)

    def describe_topics(self, msgtypes: Sequence[str] | None = None) -> str:
        """``'topic (type), ...'`` of the bag's topics (of ``msgtypes`` only, if given)."""
        items = [f'{t} ({m})' for t, m in sorted(self.topics.items())
                 if msgtypes is None or m in msgtypes]
        return ', '.join(items) if items else 'none'

    def require(self, topic: str, msgtypes: Sequence[str], what: str) -> str:
        """The message type of ``topic``; raises :class:`TopicNotFoundError` when it is missing,
        empty or of another type (``what`` names the role, e.g. ``'camera images'``)."""
        topic = absolute_topic(topic)
        if topic not in self.topics:
            raise TopicNotFoundError(
                f'bag {str(self.path)!r} has no topic {topic!r} ({what}); topics of the '
                f'expected type {"/".join(msgtypes)}: {self.describe_topics(msgtypes)}')
        if self.topics[topic] not in msgtypes:
            raise TopicNotFoundError(
                f'topic {topic!r} ({what}) has type {self.topics[topic]}, expected '
                f'{" or ".join(msgtypes)}')
        if self.message_count(topic) == 0:
            raise TopicNotFoundError(f'topic {topic!r} ({what}) has no messages in the bag')
        return self.topics[topic]

    def image_topic(self, topic: str | None, default: str) -> str:
        """The camera topic to read: ``topic`` when given (must be an image topic), else
        ``default`` (raw ``Image``) or ``default + '/compressed'`` whichever the bag has."""
        if topic:
            self.require(topic, IMAGE_TYPES, 'camera images')
            return absolute_topic(topic)
        default = absolute_topic(default)
        for cand in (default, default.rstrip('/') + '/compressed'):
            if self.has(cand, IMAGE_TYPES) and self.message_count(cand):
                return cand
        raise TopicNotFoundError(
            f'bag {str(self.path)!r} has no camera topic {default!r} or '
            f'{default.rstrip("/") + "/compressed"!r} (pass --topic); image topics in the bag: '
            f'{self.describe_topics(IMAGE_TYPES)}')

    @property
    def start_ns(self) -> int:
        """Recording time of the first message (ns)."""
        return int(self._reader.start_time)

    def messages(self, topics: Iterable[str], *, deserialize: bool = True,
                 start_ns: int | None = None) -> Iterator[BagMessage]:
        """Messages of ``topics`` (absent ones are skipped) in recording-time order, from
        recording time ``start_ns`` (ns) on when given.

        Raises:
            BagFormatError: the storage is corrupt part-way, or a message cannot be decoded.
        """
        wanted = {absolute_topic(t) for t in topics}
        conns = [c for c in self._reader.connections if c.topic in wanted]
        if not conns:
            return
        stream = self._reader.messages(connections=conns, start=start_ns)
        while True:
            try:
                conn, log_ns, raw = next(stream)
            except StopIteration:
                return
            except Exception as exc:  # any failure inside the storage plugin: broken bag
                raise BagFormatError(
                    f'cannot read bag {str(self.path)!r} (broken or truncated?): '
                    f'{one_line(exc) or type(exc).__name__}') from exc
            data = raw if isinstance(raw, bytes) else bytes(raw)
            msg = None
            if deserialize:
                try:
                    msg = self._reader.deserialize(data, conn.msgtype)
                except Exception as exc:
                    raise BagFormatError(
                        f'cannot decode a {conn.msgtype} message on {conn.topic!r} at '
                        f'{log_ns} ns: {one_line(exc) or type(exc).__name__}') from exc
            yield BagMessage(conn.topic, int(log_ns), conn.msgtype, msg, data)


def read_poses(source: BagSource, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """All ``PoseStamped`` of ``topic``: ``(stamps_ns (K,) int64 sorted, poses (K, 4, 4))``
    (header stamps; m). Empty arrays when the topic is absent."""
    if not source.has(topic, (POSE_STAMPED_TYPE,)):
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    stamps, poses = [], []
    for m in source.messages([topic]):
        try:
            stamp, _, T = pose_stamped_to_numpy(m.msg)
        except MessageError as exc:
            raise BagFormatError(f'{topic}: bad pose at {m.log_ns} ns: {exc}') from exc
        stamps.append(stamp)
        poses.append(T)
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind='stable')
    return (np.asarray(stamps, dtype=np.int64)[order],
            np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[order])


def read_depth_views(source: BagSource, topic: str, gt: tuple[np.ndarray, np.ndarray],
                     T_base_cam: np.ndarray, camera: Any) -> list[Any]:
    """Ground-truth range images of ``topic`` (``32FC1`` m or ``16UC1`` mm along the ray) as
    :class:`semfeat_ros.offline.metrics.DepthView`, posed by the ground truth ``gt`` =
    ``(stamps_ns, T_map_base)`` at their stamps and ``T_base_cam`` (4, 4); ``camera`` is scaled
    to each image's size. Empty when the topic is absent."""
    from msg_adapters import depth_to_metres, image_to_numpy, stamp_to_ns
    from semfeat_ros.offline.metrics import DepthView, associate

    if not source.has(topic, (IMAGE_TYPE,)) or len(gt[0]) == 0:
        return []
    views = []
    for m in source.messages([topic]):
        try:
            stamp = stamp_to_ns(m.msg)
            depth = depth_to_metres(image_to_numpy(m.msg), str(m.msg.encoding))
        except MessageError as exc:
            raise BagFormatError(f'{topic}: bad range image at {m.log_ns} ns: {exc}') from exc
        idx, poses = associate(np.array([stamp]), gt[0], gt[1])
        if len(idx) == 0:
            continue
        h, w = depth.shape
        cam = camera if (camera.width, camera.height) == (w, h) else camera.scaled(w, h)
        views.append(DepthView(depth, poses[0] @ np.asarray(T_base_cam, float), cam, stamp))
    return views
