"""Mode ``sequence``: frame pairs ``(i, i + stride)`` of a rendered drive, or of a real image
sequence without ground truth (``--images``, :mod:`.run_real_sequence`).

For rendered drives, ground truth comes from the rendered range images and camera poses through
the simulator's occlusion-checked ``semfeat_ros.sim.groundtruth.warp_pixels``; dynamic classes
(from the GT labels, when present) never count as visible. Two rendered sources:

* a rosbag2 bag (``--bag``) with an image topic, a range-image topic (``32FC1`` m, or ``16UC1``
  mm with 0 = invalid), a pose topic (``PoseStamped``, ``PoseWithCovarianceStamped``,
  ``Odometry`` or ``TransformStamped``: ``T_map_base`` by default, composed with the camera
  YAML's extrinsic, or directly ``T_map_cam``), optionally a GT label topic (mono8) and a
  ``CameraInfo`` topic (else the camera YAML). Messages are associated by header stamp.
* a simulator shard (``--shard``, :mod:`semfeat_ros.sim.dataset`), frames in time order.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
import struct

import numpy as np

from semfeat_ros.evaluation.datasets import (
    as_rgb8,
    decode_image_msg,
    open_bag,
    topic_connections,
)
from semfeat_ros.evaluation.errors import ConfigError, DatasetError
from semfeat_ros.evaluation.groundtruth import DepthGroundTruth, Pair
from semfeat_ros.evaluation.pipeline import EvalConf, evaluate
from semfeat_ros.evaluation.transforms import erode_mask

POSE_MSGTYPES: tuple[str, ...] = (
    'geometry_msgs/msg/PoseStamped', 'geometry_msgs/msg/PoseWithCovarianceStamped',
    'nav_msgs/msg/Odometry', 'geometry_msgs/msg/TransformStamped')


@dataclass(frozen=True)
class SequenceTopics:
    """Topic names of a rendered-drive bag (the simulator's defaults)."""

    image: str = '/camera/front/image_raw'
    depth: str = '/ground_truth/depth'
    pose: str = '/ground_truth/pose'
    labels: str | None = '/ground_truth/semantic'
    """Optional: used when the bag has it."""
    camera_info: str | None = '/camera/front/camera_info'
    """Optional: used when the bag has it, else the camera YAML."""


@dataclass(frozen=True)
class SequencePaths:
    """Exactly one source: ``bag``, ``shard`` (rendered drives) or ``images`` (a real sequence)."""

    out: Path
    bag: Path | None = None
    shard: Path | None = None
    camera: Path | None = None
    """Camera YAML: intrinsics when the bag has no CameraInfo, and the base_link -> camera
    extrinsic (default: the shipped config/camera_front.yaml); with ``images``, the frames'
    intrinsics (optional)."""
    gt_keypoints: Path | str | None = 'rendered'
    """``'rendered'`` (:func:`rendered_keypoints`), None / ``'none'``, or a folder of
    ``<frame index>.npy`` / ``.txt`` GT keypoint sets (K, 2) px (rendered drives only)."""
    images: Path | None = None
    """Folder of the frames of a real sequence (no ground truth)."""
    pattern: str = '*'
    """Glob on the file names of ``images`` that selects the frames."""
    camera_xml: Path | None = None
    """ViSP XML file with the intrinsics of ``images`` (``<camera>``: px, py, u0, v0)."""
    pinhole: tuple[float, ...] | None = None
    """Pinhole intrinsics ``(fx, fy, cx, cy)`` px of ``images``."""


@dataclass(frozen=True)
class SequenceConf:
    eval: EvalConf = field(default_factory=EvalConf)
    stride: int = 1
    max_pairs: int | None = None
    topics: SequenceTopics = field(default_factory=SequenceTopics)
    pose_frame: str = 'base_link'
    """``'base_link'`` (pose is T_map_base) or ``'camera'`` (pose is T_map_cam)."""
    pose_tolerance_ns: int = 1_000_000
    mask_margin_px: int = 8
    fov_deg: float | None = 190.0
    """Lens field of view (deg) of fisheye models; None: the calibration file's own (real
    sequences) or 190 (rendered drives)."""

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ConfigError(f'--stride must be >= 1, got {self.stride}')
        if self.max_pairs is not None and self.max_pairs < 1:
            raise ConfigError(f'--max-pairs must be >= 1, got {self.max_pairs}')
        if self.pose_frame not in ('base_link', 'camera'):
            raise ConfigError(f'pose frame must be base_link or camera, got {self.pose_frame!r}')


@dataclass
class Frame:
    """One rendered frame: RGB (H, W, 3) uint8, range image (H, W) m, optional labels, pose."""

    index: int
    stamp_ns: int
    rgb: np.ndarray
    depth: np.ndarray
    T_map_cam: np.ndarray
    labels: np.ndarray | None = None
    instance: np.ndarray | None = None


def rendered_keypoints(kp_max: int = 500) -> tuple[Callable[[Frame, np.ndarray], np.ndarray]
                                                   | None, str]:
    """The GT keypoint rule of the training targets (``semfeat_ros.model.data.
    keypoint_candidates``: image corners plus corners/junctions of the rendered label, instance
    and depth edges) as ``fn(frame, valid_mask) -> (K, 2) px``, at most ``kp_max`` per frame.
    Returns ``(None, reason)`` when the model package is not importable."""
    try:
        from semfeat_ros.model.data import default_data_conf, keypoint_candidates
    except ImportError as exc:
        return None, f'GT keypoints of the rendered geometry unavailable ({exc})'
    conf = {**default_data_conf, 'kp_max': int(kp_max)}

    def fn(frame: Frame, valid: np.ndarray) -> np.ndarray:
        labels = frame.labels if frame.labels is not None else np.where(valid, 0, 255)
        view: dict[str, np.ndarray] = {
            'rgb': frame.rgb, 'label': np.where(valid, labels, 255).astype(np.uint8),
            'depth': np.asarray(frame.depth, np.float32),
            'coverage': valid.astype(np.uint8)}
        if frame.instance is not None:
            view['instance'] = frame.instance
        return np.asarray(keypoint_candidates(view, conf), dtype=np.float64).reshape(-1, 2)

    return fn, ('GT keypoints: semfeat_ros.model.data.keypoint_candidates of the rendered frame '
                f'(image + label/instance/depth-edge corners, at most {kp_max})')


def pair_indices(n_frames: int, stride: int, max_pairs: int | None = None) -> list[tuple[int,
                                                                                         int]]:
    """``(i, i + stride)`` for ``i = 0, stride, 2 stride, ...`` (a chain, each frame used at most
    twice), at most ``max_pairs``."""
    pairs = [(i, i + stride) for i in range(0, n_frames - stride, stride)]
    return pairs[:max_pairs] if max_pairs is not None else pairs


def _warp_fn() -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    try:
        from semfeat_ros.sim.groundtruth import warp_pixels
    except ImportError as exc:
        raise DatasetError(f'sequence mode needs semfeat_ros.sim.groundtruth.warp_pixels '
                           f'({exc})') from exc
    return warp_pixels


def make_depth_pair(name: str, fa: Frame, fb: Frame, camera: object, valid: np.ndarray,
                    margin_px: int, warp: Callable[..., tuple[np.ndarray, np.ndarray]],
                    dynamic: np.ndarray | None = None,
                    gt_keypoints_a: np.ndarray | None = None) -> Pair:
    """A pair of rendered frames; ``valid`` is the camera's image-circle mask, ``dynamic`` the
    (256,) bool table of dynamic class ids (their pixels are never GT-visible)."""
    mask_a = erode_mask(valid, margin_px)
    mask_b = erode_mask(valid, margin_px)
    static_a, static_b = mask_a.copy(), mask_b.copy()
    if dynamic is not None:
        if fa.labels is not None:
            static_a &= ~dynamic[fa.labels]
        if fb.labels is not None:
            static_b &= ~dynamic[fb.labels]
    gt = DepthGroundTruth(fa.depth, fb.depth, fa.T_map_cam, fb.T_map_cam, camera, warp,
                          mask_a=static_a, mask_b=static_b)
    return Pair(name, fa.rgb, fb.rgb, mask_a, mask_b, gt, labels_a=fa.labels,
                labels_b=fb.labels, gt_keypoints_a=gt_keypoints_a, camera=camera,
                meta={'stamps_ns': [fa.stamp_ns, fb.stamp_ns]})


# ------------------------------------------------------------------------------ bag source

def header_stamp_ns(raw: bytes) -> int:
    """Header stamp (ns) of a serialized CDR message whose first field is a std_msgs/Header."""
    if len(raw) < 12:
        raise DatasetError(f'CDR message too short ({len(raw)} bytes) to hold a header')
    endian = '<' if raw[1] & 1 else '>'
    sec, nsec = struct.unpack_from(f'{endian}iI', raw, 4)
    return sec * 1_000_000_000 + nsec


def _pose_matrix(msg: object, msgtype: str) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    if msgtype == 'geometry_msgs/msg/TransformStamped':
        t, q = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose if msgtype == 'geometry_msgs/msg/PoseStamped' else msg.pose.pose
        t, q = pose.position, pose.orientation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    if not np.isfinite(quat).all() or np.linalg.norm(quat) < 1e-9:
        raise DatasetError(f'{msgtype}: invalid orientation quaternion {quat.tolist()}')
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quat / np.linalg.norm(quat)).as_matrix()
    T[:3, 3] = [t.x, t.y, t.z]
    return T


def _camera_from_yaml(path: Path | None, fov_deg: float) -> tuple[object, np.ndarray]:
    from semfeat_ros.camera import load_camera_yaml

    camera, extrinsic = load_camera_yaml(path, fov_deg=fov_deg)
    return camera, extrinsic.T_base_cam


class BagSequence:
    """Index of a rendered-drive bag: frames (image + depth + pose [+ labels]) by stamp."""

    def __init__(self, bag: Path, conf: SequenceConf, camera_yaml: Path | None) -> None:
        self.bag = bag
        self.conf = conf
        t = conf.topics
        with open_bag(bag) as reader:
            self.image_conns = topic_connections(
                reader, t.image, ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage'))
            self.depth_conns = topic_connections(reader, t.depth, ('sensor_msgs/msg/Image',))
            pose_conns = topic_connections(reader, t.pose, POSE_MSGTYPES)
            present = {c.topic for c in reader.connections}
            self.label_conns = (topic_connections(reader, t.labels, ('sensor_msgs/msg/Image',))
                                if t.labels and t.labels in present else [])
            info_conns = (topic_connections(reader, t.camera_info,
                                            ('sensor_msgs/msg/CameraInfo',))
                          if t.camera_info and t.camera_info in present else [])
            stamps: dict[str, list[int]] = {'image': [], 'depth': [], 'labels': []}
            kinds = {c.id: 'image' for c in self.image_conns}
            kinds.update({c.id: 'depth' for c in self.depth_conns})
            kinds.update({c.id: 'labels' for c in self.label_conns})
            poses: list[tuple[int, np.ndarray]] = []
            info_msg = None
            conns = [*self.image_conns, *self.depth_conns, *self.label_conns, *pose_conns,
                     *info_conns]
            for conn, _, raw in reader.messages(connections=conns):
                if conn.id in kinds:
                    stamps[kinds[conn.id]].append(header_stamp_ns(raw))
                elif conn.msgtype in POSE_MSGTYPES:
                    msg = reader.deserialize(raw, conn.msgtype)
                    st = msg.header.stamp
                    poses.append((int(st.sec) * 1_000_000_000 + int(st.nanosec),
                                  _pose_matrix(msg, conn.msgtype)))
                elif info_msg is None:
                    info_msg = reader.deserialize(raw, conn.msgtype)
        if not stamps['image']:
            raise DatasetError(f'topic {t.image} in bag {bag} has no messages')
        if not poses:
            raise DatasetError(f'pose topic {t.pose} in bag {bag} has no messages')
        yaml_camera, T_base_cam = _camera_from_yaml(camera_yaml, conf.fov_deg)
        if info_msg is not None:
            from msg_adapters.camera_info import camera_info_to_model

            self.camera = camera_info_to_model(info_msg, fov_deg=conf.fov_deg)
            self.camera_source = f'CameraInfo {t.camera_info}'
        else:
            self.camera = yaml_camera
            self.camera_source = f'camera YAML {camera_yaml or "config/camera_front.yaml"}'
        T_extr = T_base_cam if conf.pose_frame == 'base_link' else np.eye(4)
        pose_stamps = np.array([s for s, _ in poses], dtype=np.int64)
        depth_set, label_set = set(stamps['depth']), set(stamps['labels'])
        self.frames: list[tuple[int, np.ndarray]] = []  # (stamp, T_map_cam) in image order
        for s in sorted(set(stamps['image'])):
            if s not in depth_set:
                continue
            k = int(np.argmin(np.abs(pose_stamps - s)))
            if abs(int(pose_stamps[k]) - s) > conf.pose_tolerance_ns:
                continue
            self.frames.append((s, poses[k][1] @ T_extr))
        self.has_labels = bool(label_set) and all(s in label_set for s, _ in self.frames)
        if len(self.frames) < 2:
            raise DatasetError(
                f'bag {bag}: {len(self.frames)} frame(s) have an image ({t.image}), a depth '
                f'image ({t.depth}) with the same stamp and a pose ({t.pose}) within '
                f'{conf.pose_tolerance_ns / 1e6:g} ms; need at least 2')

    def iter_frame_pairs(self, pairs: list[tuple[int, int]]) -> Iterator[tuple[Frame, Frame]]:
        """The frames of ``pairs`` (indices into :attr:`frames`), reading the bag once."""
        index_of = {s: k for k, (s, _) in enumerate(self.frames)}
        needed = {k for p in pairs for k in p}
        parts: dict[int, dict[str, np.ndarray]] = {}
        kinds = {c.id: 'image' for c in self.image_conns}
        kinds.update({c.id: 'depth' for c in self.depth_conns})
        if self.has_labels:
            kinds.update({c.id: 'labels' for c in self.label_conns})
        want = {'image', 'depth', 'labels'} if self.has_labels else {'image', 'depth'}
        nxt = 0
        from msg_adapters.errors import UnsupportedEncodingError
        from msg_adapters.image import depth_to_metres

        with open_bag(self.bag) as reader:
            conns = [c for c in reader.connections if c.id in kinds]
            for conn, _, raw in reader.messages(connections=conns):
                k = index_of.get(header_stamp_ns(raw))
                if k is None or k not in needed:
                    continue
                msg = reader.deserialize(raw, conn.msgtype)
                kind = kinds[conn.id]
                arr = decode_image_msg(msg, conn.msgtype, raw=kind != 'image')
                if kind == 'image':
                    val = as_rgb8(arr, f'{conn.topic} frame {k}')
                elif kind == 'depth':
                    try:
                        val = depth_to_metres(arr, str(msg.encoding))
                    except UnsupportedEncodingError as exc:
                        raise DatasetError(f'{conn.topic}: {exc}') from exc
                else:
                    val = np.asarray(arr, dtype=np.uint8)
                parts.setdefault(k, {})[kind] = val
                while nxt < len(pairs) and all(want <= set(parts.get(i, {})) for i in pairs[nxt]):
                    a, b = pairs[nxt]
                    yield self._frame(a, parts[a]), self._frame(b, parts[b])
                    nxt += 1
                    keep = {i for p in pairs[nxt:] for i in p}
                    for i in [i for i in parts if i not in keep]:
                        del parts[i]
        if nxt < len(pairs):
            raise DatasetError(f'bag {self.bag}: frames of pair {pairs[nxt]} are incomplete')

    def _frame(self, k: int, parts: dict[str, np.ndarray]) -> Frame:
        stamp, T = self.frames[k]
        return Frame(k, stamp, parts['image'], parts['depth'], T, parts.get('labels'))


# ---------------------------------------------------------------------------- shard source

def shard_frames(path: Path) -> tuple[list[Frame], object]:
    """All frames of a simulator shard in time order, and its camera model."""
    try:
        from semfeat_ros.sim.dataset import load_shard
    except ImportError as exc:
        raise DatasetError(f'reading shards needs semfeat_ros.sim.dataset ({exc})') from exc
    data = load_shard(path)
    order = np.argsort(np.asarray(data['time_s']), kind='stable')
    frames = [Frame(int(i), int(round(float(data['time_s'][i]) * 1e9)), data['rgb'][i],
                    np.asarray(data['depth'][i], dtype=np.float32), data['T_map_cam'][i],
                    data['label'][i], data['instance'][i]) for i in order]
    return frames, data['camera_model']


# ------------------------------------------------------------------------------------ main

def _gt_keypoints(folder: Path | None, index: int) -> np.ndarray | None:
    if folder is None:
        return None
    from semfeat_ros.evaluation.datasets import read_keypoint_file

    for suffix in ('.npy', '.txt'):
        p = Path(folder) / f'{index}{suffix}'
        if p.is_file():
            return read_keypoint_file(p)
    return None


def main(conf: SequenceConf, paths: SequencePaths) -> dict:
    """Evaluate every method on the pairs of a rendered drive or, with ``paths.images``, of a
    real image sequence (:func:`.run_real_sequence.main`); outputs go to ``paths.out``."""
    if sum(p is not None for p in (paths.bag, paths.shard, paths.images)) != 1:
        raise ConfigError('sequence: give exactly one of --bag BAG, --shard NPZ and --images DIR')
    if paths.images is not None:
        from semfeat_ros.evaluation import run_real_sequence

        return run_real_sequence.main(conf, paths)
    if paths.camera_xml is not None or paths.pinhole is not None or paths.pattern != '*':
        raise ConfigError('sequence: --camera-xml, --pinhole and --glob apply to --images only')
    if conf.fov_deg is None:
        conf = replace(conf, fov_deg=190.0)
    warp = _warp_fn()
    from semfeat_ros.labels import load_labels

    dynamic = np.zeros(256, dtype=bool)
    dyn = load_labels().dynamic
    dynamic[: len(dyn)] = dyn
    notes: list[str] = []
    if paths.bag is not None:
        seq = BagSequence(Path(paths.bag), conf, paths.camera)
        camera = seq.camera
        pairs = pair_indices(len(seq.frames), conf.stride, conf.max_pairs)
        frame_pairs: Iterator[tuple[Frame, Frame]] = seq.iter_frame_pairs(pairs)
        source = f'{len(seq.frames)} frames of {conf.topics.image} in {paths.bag}'
        notes.append(f'camera: {seq.camera_source}; poses: {conf.topics.pose} '
                     f'({conf.pose_frame}); GT labels: '
                     + ('yes' if seq.has_labels else 'no'))
    else:
        frames, camera = shard_frames(Path(paths.shard))
        pairs = pair_indices(len(frames), conf.stride, conf.max_pairs)
        frame_pairs = ((frames[a], frames[b]) for a, b in pairs)
        source = f'{len(frames)} frames of shard {paths.shard}'
    if not pairs:
        raise DatasetError(f'{source}: too few frames for stride {conf.stride}')
    valid = camera.valid_mask()
    gt_dir: Path | None = None
    gt_fn = None
    if isinstance(paths.gt_keypoints, str) and paths.gt_keypoints in ('rendered', 'none'):
        if paths.gt_keypoints == 'rendered':
            gt_fn, note = rendered_keypoints()
            notes.append(note)
    elif paths.gt_keypoints is not None:
        gt_dir = Path(paths.gt_keypoints)
        if not gt_dir.is_dir():
            raise DatasetError(f'GT keypoint folder not found: {gt_dir}')
        notes.append(f'GT keypoints: files in {gt_dir}')

    def gt_keypoints(frame: Frame) -> np.ndarray | None:
        if gt_fn is not None:
            return gt_fn(frame, valid)
        return _gt_keypoints(gt_dir, frame.index)

    def gen() -> Iterator[Pair]:
        for fa, fb in frame_pairs:
            if fa.rgb.shape[:2] != (camera.height, camera.width):
                raise DatasetError(f'frame {fa.index}: image {fa.rgb.shape[1]}x'
                                   f'{fa.rgb.shape[0]} px does not match the camera '
                                   f'{camera.width}x{camera.height} px')
            yield make_depth_pair(f'{fa.index:05d}-{fb.index:05d}', fa, fb, camera, valid,
                                  conf.mask_margin_px, warp, dynamic, gt_keypoints(fa))

    notes.append(f'pairs (i, i + {conf.stride}); GT from range images + poses, '
                 'occlusion-checked (semfeat_ros.sim.groundtruth.warp_pixels); dynamic classes '
                 'never visible')
    return evaluate(gen(), conf.eval, paths.out, mode='sequence', source=source,
                    n_pairs=len(pairs),
                    mask_description=f'camera image circle, margin {conf.mask_margin_px} px',
                    notes=notes)
