"""``semfeat-features`` core: run feature_node's front end over every frame of a bag.

The output is a new rosbag2 (MCAP, zstd chunks) with, per decoded camera frame,

* the features topic (``/semfeat/features``, PointCloud2 in the contract layout: u, v, score,
  label, descriptor[D]) and the mask topic (``/semfeat/semantic_mask``, mono8 class ids), both
  with the image's header stamp and frame_id, written at the image's recording time;
* the CameraInfo messages passed through unchanged (same bytes, same recording times).

As in feature_node, frames are rejected (counted, not written) when they cannot be decoded,
exceed ``max_image_pixels``, or disagree with the CameraInfo; the CameraInfo of a frame is the
latest one at or before its stamp (the first one for earlier frames, since a recording may
store a frame's CameraInfo just after the image).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import os
from pathlib import Path
import shutil
import time
from typing import Any

from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from tqdm import tqdm

from msg_adapters import features_to_msg, numpy_to_image, stamp_to_ns, to_rgb_or_mono
from msg_adapters.errors import MessageError
from semfeat_ros.frontend import FrontendError
from semfeat_ros.offline.bag import (
    CAMERA_INFO_TYPE,
    POINTCLOUD2_TYPE,
    BagSource,
    absolute_topic,
    one_line,
)
from semfeat_ros.offline.errors import NoFramesError, OutputPathError
from semfeat_ros.offline.frontends import NetworkFrontend
from semfeat_ros.offline.mapping_run import CameraTimeline, read_cameras

IMAGE_MSGTYPE = 'sensor_msgs/msg/Image'


@dataclass
class FeaturesBagConfig:
    """Topics and limits (feature_node's parameters; ``image_topic`` None = from the node's
    ``image_topic`` raw or compressed, whichever the bag has)."""

    image_topic: str | None = None
    default_image_topic: str = '/camera/front/image_raw'
    camera_info_topic: str = '/camera/front/camera_info'
    features_topic: str = '/semfeat/features'
    mask_topic: str = '/semfeat/semantic_mask'
    require_camera_info: bool = True
    fov_deg: float = 190.0
    max_image_pixels: int = 50_000_000
    max_frames: int | None = None

    def absolute(self) -> FeaturesBagConfig:
        """The same with topic names as recorded in a bag (relative ones resolved in the root
        namespace, as for nodes started without one)."""
        names = ('image_topic', 'default_image_topic', 'camera_info_topic', 'features_topic',
                 'mask_topic')
        return dataclasses.replace(self, **{k: absolute_topic(getattr(self, k))
                                            for k in names if getattr(self, k) is not None})


@dataclass
class FeaturesBagSummary:
    """What was written: counts per topic, rejected frames, timing (ms)."""

    out: Path
    image_topic: str
    frames_read: int = 0
    frames_written: int = 0
    frames_rejected: int = 0
    camera_infos: int = 0
    keypoints_total: int = 0
    frontend_ms: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    reject_reasons: dict[str, int] = field(default_factory=dict)


def check_new_output(out: str | os.PathLike[str]) -> Path:
    """The output bag path, which must not exist yet (rosbag2 writers never overwrite)."""
    p = Path(out)
    if p.exists() or p.is_symlink():
        raise OutputPathError(f'output bag {str(p)!r} already exists; choose a new --out')
    if not p.parent.exists():
        raise OutputPathError(f'parent directory of --out {str(p)!r} does not exist')
    return p


def write_features_bag(source: BagSource, out: str | os.PathLike[str],
                       frontend: NetworkFrontend, conf: FeaturesBagConfig,
                       progress: bool = True) -> FeaturesBagSummary:
    """Run ``frontend`` over the bag's frames and write the output bag (see module doc).

    Raises:
        TopicNotFoundError: no camera topic, or no CameraInfo while it is required.
        OutputPathError: ``out`` exists or cannot be written.
        BagFormatError: the input bag is broken part-way.
    """
    t0 = time.perf_counter()
    conf = conf.absolute()
    out_path = check_new_output(out)
    image_topic = source.image_topic(conf.image_topic, conf.default_image_topic)
    cameras: CameraTimeline | None = None
    if conf.require_camera_info or source.has(conf.camera_info_topic, (CAMERA_INFO_TYPE,)):
        cameras = read_cameras(source, conf.camera_info_topic, conf.fov_deg)
    ts = source.typestore
    summary = FeaturesBagSummary(out_path, image_topic)
    total = source.message_count(image_topic)
    if conf.max_frames is not None:
        total = min(total, conf.max_frames)
    writer = Writer(out_path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.set_custom_data('semfeat_features', f'source={source.path.name}; '
                           f'frontend={frontend.describe()}')
    try:
        writer.open()
    except Exception as exc:  # WriterError, PermissionError, ...
        raise OutputPathError(f'cannot create output bag {str(out_path)!r}: '
                              f'{one_line(exc)}') from exc
    ok = False
    bar = tqdm(total=total, desc='features', unit='frame', disable=not progress)
    try:
        c_feat = writer.add_connection(conf.features_topic, POINTCLOUD2_TYPE, typestore=ts)
        c_mask = writer.add_connection(conf.mask_topic, IMAGE_MSGTYPE, typestore=ts)
        c_info = (writer.add_connection(conf.camera_info_topic, CAMERA_INFO_TYPE, typestore=ts)
                  if cameras is not None else None)

        def reject(reason: str) -> None:
            summary.frames_rejected += 1
            summary.reject_reasons[reason] = summary.reject_reasons.get(reason, 0) + 1

        topics = [image_topic] + ([conf.camera_info_topic] if c_info is not None else [])
        for m in source.messages(topics):
            if m.topic == conf.camera_info_topic:
                writer.write(c_info, m.log_ns, m.raw)
                summary.camera_infos += 1
                continue
            if conf.max_frames is not None and summary.frames_read >= conf.max_frames:
                break
            summary.frames_read += 1
            bar.update(1)
            try:
                stamp = stamp_to_ns(m.msg)
                image = to_rgb_or_mono(m.msg, max_pixels=conf.max_image_pixels)
            except MessageError as exc:
                reject(f'image: {type(exc).__name__}')
                continue
            frame_id = str(m.msg.header.frame_id)
            camera = cameras.at(stamp)[0] if cameras is not None else None
            t1 = time.perf_counter()
            try:
                res = frontend.process(image, camera)
                msg = features_to_msg(res.keypoints, res.scores, res.labels, res.descriptors,
                                      stamp_ns=stamp, frame_id=frame_id, msg_cls=ts)
            except (FrontendError, MessageError) as exc:
                reject(f'features: {type(exc).__name__}')
                continue
            summary.frontend_ms.append((time.perf_counter() - t1) * 1e3)
            mask = numpy_to_image(res.mask, 'mono8', stamp_ns=stamp, frame_id=frame_id,
                                  msg_cls=ts)
            writer.write(c_feat, m.log_ns, ts.serialize_cdr(msg, POINTCLOUD2_TYPE))
            writer.write(c_mask, m.log_ns, ts.serialize_cdr(mask, IMAGE_MSGTYPE))
            summary.frames_written += 1
            summary.keypoints_total += len(res)
        if summary.frames_read and not summary.frames_written:
            reasons = ', '.join(f'{k} x{v}' for k, v in summary.reject_reasons.items())
            raise NoFramesError(f'no frame of {image_topic} could be processed: all '
                                f'{summary.frames_read} read were rejected ({reasons})')
        ok = True
    finally:
        bar.close()
        try:
            writer.close()
        except Exception as exc:
            if ok:
                raise OutputPathError(
                    f'cannot finish output bag {str(out_path)!r}: {one_line(exc)}') from exc
        if not ok:
            shutil.rmtree(out_path, ignore_errors=True)
    summary.wall_s = time.perf_counter() - t0
    return summary


def summary_dict(s: FeaturesBagSummary) -> dict[str, Any]:
    """JSON-friendly summary."""
    from semfeat_ros.offline.metrics import timing_stats

    return {'out': str(s.out), 'image_topic': s.image_topic, 'frames_read': s.frames_read,
            'frames_written': s.frames_written, 'frames_rejected': s.frames_rejected,
            'reject_reasons': dict(s.reject_reasons), 'camera_infos': s.camera_infos,
            'keypoints_per_frame': (s.keypoints_total / s.frames_written
                                    if s.frames_written else 0.0),
            'frontend_ms': timing_stats(s.frontend_ms), 'wall_s': round(s.wall_s, 3)}
