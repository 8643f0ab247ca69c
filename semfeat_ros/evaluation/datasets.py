"""Readers: image folders, Oxford/HPatches homography sequences, images from rosbag2 bags."""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path
import re
from typing import Any
from xml.etree import ElementTree

import cv2
import numpy as np

from semfeat_ros.evaluation.errors import (
    CameraFileError,
    DatasetError,
    HomographyFileError,
    ImageReadError,
    TopicError,
)

IMAGE_EXTENSIONS: tuple[str, ...] = ('.jpg', '.jpeg', '.png', '.ppm', '.pgm')
"""Image files recognised in folders (case-insensitive)."""
IMAGE_MSGTYPES: tuple[str, ...] = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')


# --------------------------------------------------------------------------- image files

def as_rgb8(arr: np.ndarray, source: str = 'image') -> np.ndarray:
    """(H, W, 3) uint8 RGB from a mono or RGB array of uint8/uint16 (16-bit scaled down)."""
    a = np.asarray(arr)
    if a.dtype == np.uint16:
        a = (a >> 8).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise ImageReadError(f'{source}: expected 8- or 16-bit pixels, got dtype {a.dtype}')
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 8 or a.shape[1] < 8:
        raise ImageReadError(f'{source}: expected an (H, W) or (H, W, 3) image of at least '
                             f'8x8 px, got shape {a.shape}')
    return np.ascontiguousarray(a)


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB; :class:`ImageReadError` if undecodable."""
    p = Path(path)
    if not p.is_file():
        raise ImageReadError(f'image not found: {p}')
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageReadError(f'cannot decode image {p} (corrupt or unsupported format)')
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return as_rgb8(img, str(p))


def read_label_image(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """Read a mono8 class-id PNG (255 = ignore) that must be ``shape = (H, W)``."""
    p = Path(path)
    lab = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if lab is None:
        raise ImageReadError(f'cannot decode label image {p}')
    if lab.ndim != 2 or lab.dtype != np.uint8:
        raise ImageReadError(f'label image {p}: expected mono8 class ids, got shape '
                             f'{lab.shape} dtype {lab.dtype}')
    if lab.shape != tuple(shape):
        raise ImageReadError(f'label image {p}: size {lab.shape[1]}x{lab.shape[0]} px does not '
                             f'match its image ({shape[1]}x{shape[0]} px)')
    return lab


def read_keypoint_file(path: str | Path) -> np.ndarray:
    """A GT keypoint set: ``.npy`` (K, 2) or text with two columns ``u v`` (px) per line."""
    p = Path(path)
    try:
        arr = np.load(p, allow_pickle=False) if p.suffix == '.npy' else np.loadtxt(p, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DatasetError(f'cannot read GT keypoints {p}: {exc}') from exc
    arr = np.asarray(arr, dtype=np.float64)
    if arr.size == 0:
        return arr.reshape(0, 2)
    if arr.ndim != 2 or arr.shape[1] < 2 or not np.isfinite(arr[:, :2]).all():
        raise DatasetError(f'GT keypoints {p}: expected (K, 2) finite u v px, got {arr.shape}')
    return arr[:, :2]


def natural_key(name: str) -> tuple[tuple[int, int | str], ...]:
    """Sort key of a file name with its digit runs compared as numbers (``frame_2`` before
    ``frame_10``; ``image.0002`` before ``image.0010`` as in plain sorting)."""
    return tuple((0, int(part)) if part.isdigit() else (1, part.lower())
                 for part in re.split(r'(\d+)', name) if part)


@dataclass(frozen=True)
class PinholeIntrinsics:
    """Pinhole intrinsics (px) with an optional radial coefficient ``k1`` (OpenCV plumb_bob
    order, on normalised undistorted coordinates: ``u = cx + fx x (1 + k1 r^2)``)."""

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    source: str = ''

    def camera(self, width: int, height: int) -> object:
        """The ``semfeat_ros.camera.PinholeCamera`` of these intrinsics on ``width x height``
        px images (``CameraModelError`` when the principal point lies outside them)."""
        from semfeat_ros.camera import PinholeCamera

        return PinholeCamera(width, height, self.fx, self.fy, self.cx, self.cy, d=(self.k1,))


_VISP_KEYS: tuple[str, ...] = ('px', 'py', 'u0', 'v0')


def read_visp_camera_xml(path: str | Path) -> PinholeIntrinsics:
    """Intrinsics of a ViSP XML file: the first element (document order) with ``px``, ``py``,
    ``u0``, ``v0`` children (px), i.e. the ``<camera>`` block of a model-based tracker
    configuration (``mbt-depth/castel/chateau.xml``) or a ``<camera><model>`` block of
    ``vpXmlParserCamera``. ViSP's ``kud`` (distortion applied to undistorted coordinates,
    ``u = u0 + px x (1 + kud r^2)``) becomes ``k1`` when present.

    Raises:
        CameraFileError: missing or unparsable file, no such element, or non-numeric values.
    """
    p = Path(path)
    if not p.is_file():
        raise CameraFileError(f'camera XML not found: {p}')
    try:
        root = ElementTree.parse(p).getroot()
    except (ElementTree.ParseError, OSError) as exc:
        raise CameraFileError(f'camera XML {p}: cannot parse ({exc})') from exc
    for node in root.iter():
        children = {c.tag: (c.text or '').strip() for c in node}
        if not all(k in children for k in _VISP_KEYS):
            continue
        try:
            vals = [float(children[k]) for k in (*_VISP_KEYS, 'kud') if k in children]
        except ValueError as exc:
            raise CameraFileError(f'camera XML {p}: <{node.tag}> has a non-numeric value '
                                  f'({exc})') from exc
        if not np.isfinite(vals).all():
            raise CameraFileError(f'camera XML {p}: <{node.tag}> has a non-finite value')
        return PinholeIntrinsics(*vals[:4], k1=vals[4] if len(vals) > 4 else 0.0,
                                 source=f'{p} <{node.tag}>')
    raise CameraFileError(f'camera XML {p}: no element with <px>, <py>, <u0>, <v0> children')


def list_images(folder: str | Path, *, pattern: str = '*', natural: bool = False) -> list[Path]:
    """Image files of ``folder`` (not recursive) whose name matches the glob ``pattern``, sorted
    by name (``natural``: digit runs as numbers, :func:`natural_key`); :class:`DatasetError` if
    there is none. Files with other extensions (e.g. ``depth_*.bin``) are never listed."""
    d = Path(folder)
    if not d.is_dir():
        raise DatasetError(f'image folder not found: {d}')
    files = sorted((p for p in d.iterdir()
                    if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                    and fnmatchcase(p.name, pattern)),
                   key=(lambda p: natural_key(p.name)) if natural else None)
    if not files:
        which = '' if pattern == '*' else f' matching {pattern!r}'
        raise DatasetError(f'no images ({", ".join(IMAGE_EXTENSIONS)}){which} in folder {d}')
    unreadable = [p for p in files if not cv2.haveImageReader(str(p))]
    if unreadable:
        raise ImageReadError(f'unreadable image {unreadable[0]} (no decoder recognises it'
                             + (f'; {len(unreadable) - 1} more' if len(unreadable) > 1 else '')
                             + ')')
    return files


def find_companion(folder: str | Path | None, image: Path,
                   suffixes: Sequence[str]) -> Path | None:
    """``folder/<image stem><suffix>`` for the first suffix that exists, else None."""
    if folder is None:
        return None
    for s in suffixes:
        p = Path(folder) / f'{image.stem}{s}'
        if p.is_file():
            return p
    return None


# --------------------------------------------------------------- Oxford / HPatches layout

@dataclass(frozen=True)
class HomographySequence:
    """One planar sequence: the reference image and, for each other image, the GT ``H``
    (reference px -> that image's px)."""

    name: str
    reference: Path
    targets: tuple[tuple[Path, np.ndarray], ...]


_OXFORD_IMG = re.compile(r'^img(\d+)$', re.IGNORECASE)
_HPATCHES_IMG = re.compile(r'^(\d+)$')


def read_homography_file(path: str | Path) -> np.ndarray:
    """Parse a 3x3 homography text file (9 numbers, whitespace separated)."""
    p = Path(path)
    if not p.is_file():
        raise HomographyFileError(f'missing homography file {p}')
    try:
        vals = np.array(p.read_text(encoding='utf-8').split(), dtype=np.float64)
    except ValueError as exc:
        raise HomographyFileError(f'homography file {p}: non-numeric content ({exc})') from exc
    if vals.size != 9 or not np.isfinite(vals).all():
        raise HomographyFileError(f'homography file {p}: expected 9 finite numbers, '
                                  f'got {vals.size}')
    H = vals.reshape(3, 3)
    if abs(np.linalg.det(H)) < 1e-12 or abs(H[2, 2]) < 1e-12:
        raise HomographyFileError(f'homography file {p}: matrix is singular')
    return H / H[2, 2]


def _numbered_images(folder: Path) -> tuple[dict[int, Path], str]:
    oxford: dict[int, Path] = {}
    hpatches: dict[int, Path] = {}
    for p in folder.iterdir():
        if not (p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS):
            continue
        if m := _OXFORD_IMG.match(p.stem):
            oxford[int(m.group(1))] = p
        elif m := _HPATCHES_IMG.match(p.stem):
            hpatches[int(m.group(1))] = p
    if oxford:
        return oxford, 'oxford'
    return hpatches, 'hpatches'


def read_homography_sequence(folder: str | Path) -> HomographySequence:
    """Read one sequence in the Oxford layout (``img1..imgN`` + ``H1to{k}p``) or the HPatches
    layout (``1..N`` + ``H_1_{k}``). Every image k >= 2 needs its homography file."""
    d = Path(folder)
    images, layout = _numbered_images(d)
    if 1 not in images or len(images) < 2:
        raise DatasetError(
            f'{d}: not an Oxford/HPatches sequence (need img1 and img2.. or 1 and 2.. images '
            f'with extension {"/".join(IMAGE_EXTENSIONS)}; found {len(images)} numbered)')
    targets = []
    for k in sorted(images):
        if k == 1:
            continue
        hname = f'H1to{k}p' if layout == 'oxford' else f'H_1_{k}'
        targets.append((images[k], read_homography_file(d / hname)))
    return HomographySequence(d.name, images[1], tuple(targets))


def find_homography_sequences(root: str | Path) -> list[HomographySequence]:
    """``root`` itself if it is a sequence, else each sub-folder that is one (sorted)."""
    d = Path(root)
    if not d.is_dir():
        raise DatasetError(f'dataset folder not found: {d}')
    images, _ = _numbered_images(d)
    if images:
        return [read_homography_sequence(d)]
    subs = sorted(p for p in d.iterdir() if p.is_dir() and _numbered_images(p)[0])
    if not subs:
        raise DatasetError(f'{d}: no Oxford/HPatches sequence (img1.ppm + H1to2p ..., or '
                           '1.ppm + H_1_2 ...) in it or its sub-folders')
    return [read_homography_sequence(p) for p in subs]


# ------------------------------------------------------------------------------- bags

@contextmanager
def open_bag(bag: str | Path) -> Iterator[Any]:
    """A rosbags ``AnyReader`` opened on a rosbag2 folder or rosbag1 file (a context manager).

    Raises:
        DatasetError: the path does not exist, or the bag cannot be read (bad metadata, a
            truncated or foreign storage file), when opening it or while reading its messages.
    """
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as Rosbag1Error
    from rosbags.rosbag2 import ReaderError as Rosbag2Error
    from rosbags.serde import SerdeError
    from rosbags.typesys import Stores, get_typestore

    p = Path(bag)
    if not p.exists():
        raise DatasetError(f'bag not found: {p}')
    reader = AnyReader([p], default_typestore=get_typestore(Stores.ROS2_JAZZY))
    broken = (AnyReaderError, Rosbag1Error, Rosbag2Error, SerdeError)
    try:
        reader.open()
    except (*broken, OSError, KeyError) as exc:
        raise DatasetError(f'cannot read bag {p} (broken or truncated?): '
                           f'{" ".join(str(exc).split()) or type(exc).__name__}') from exc
    try:
        yield reader
    except broken as exc:
        raise DatasetError(f'cannot read bag {p} (broken or truncated?): '
                           f'{" ".join(str(exc).split()) or type(exc).__name__}') from exc
    finally:
        reader.close()


def topic_connections(reader, topic: str, msgtypes: Sequence[str] | None = None) -> list:  # noqa: ANN001
    """Connections of ``topic`` in an open reader; :class:`TopicError` if absent or of another
    message type (the message names the topics that are present)."""
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        present = sorted({f'{c.topic} ({c.msgtype})' for c in reader.connections})
        raise TopicError(f'topic {topic} not in bag {reader.paths[0]}; present: '
                         + (', '.join(present) or 'none'))
    if msgtypes is not None and any(c.msgtype not in msgtypes for c in conns):
        raise TopicError(f'topic {topic} has type {conns[0].msgtype}, expected one of '
                         + ', '.join(msgtypes))
    return conns


def image_topics(reader) -> list[str]:  # noqa: ANN001
    """Topics of an open reader carrying Image or CompressedImage messages."""
    return sorted({c.topic for c in reader.connections if c.msgtype in IMAGE_MSGTYPES})


def decode_image_msg(msg: object, msgtype: str, *, raw: bool = False) -> np.ndarray:
    """Pixels of a rosbags Image / CompressedImage message via ``msg_adapters.image``: uint8 RGB
    or mono (``to_rgb_or_mono``), or with ``raw`` the message's own values (depth, labels)."""
    try:
        from msg_adapters.image import compressed_to_numpy, image_to_numpy, to_rgb_or_mono
    except ImportError as exc:
        raise DatasetError(f'msg_adapters.image is not available to decode {msgtype}: '
                           f'{exc}') from exc
    try:
        if not raw:
            return to_rgb_or_mono(msg)
        if msgtype.endswith('CompressedImage'):
            return compressed_to_numpy(msg)
        return image_to_numpy(msg)
    except ValueError as exc:
        raise ImageReadError(f'cannot decode {msgtype} message: {exc}') from exc


def select_indices(n_available: int, n_wanted: int) -> list[int]:
    """``n_wanted`` indices spread evenly over ``range(n_available)`` (cycling if more are
    wanted than available): ``floor(k * n / N)`` for N <= n, else ``k mod n``."""
    if n_available <= 0:
        raise DatasetError('no frames available')
    if n_wanted <= n_available:
        return [(k * n_available) // n_wanted for k in range(n_wanted)]
    return [k % n_available for k in range(n_wanted)]


def bag_image_count(bag: str | Path, topic: str | None) -> tuple[str, int]:
    """Resolve the image topic (the only image topic if ``topic`` is None) and count messages."""
    with open_bag(bag) as reader:
        if topic is None:
            topics = image_topics(reader)
            if len(topics) != 1:
                raise TopicError(f'bag {bag}: give --topic; image topics present: '
                                 + (', '.join(topics) or 'none'))
            topic = topics[0]
        conns = topic_connections(reader, topic, IMAGE_MSGTYPES)
        count = sum(int(c.msgcount) for c in conns)
    if count == 0:
        raise DatasetError(f'topic {topic} in bag {bag} has no messages')
    return topic, count


def iter_bag_images(bag: str | Path, topic: str,
                    indices: Sequence[int]) -> Iterator[tuple[int, int, np.ndarray]]:
    """Yield ``(index, stamp_ns, rgb)`` for the messages of ``topic`` whose 0-based position in
    the bag is in ``indices`` (each at most once, in bag order)."""
    wanted = set(int(i) for i in indices)
    with open_bag(bag) as reader:
        conns = topic_connections(reader, topic, IMAGE_MSGTYPES)
        for k, (conn, t_ns, raw) in enumerate(reader.messages(connections=conns)):
            if k not in wanted:
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            yield k, int(t_ns), as_rgb8(decode_image_msg(msg, conn.msgtype),
                                        f'{topic} message {k}')
