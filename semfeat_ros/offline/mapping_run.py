"""Front end -> matcher -> mapper over a recorded bag, without DDS (the code the nodes run).

:func:`run_mapping` reads the camera frames (or recorded ``/semfeat/tracks``), wheel odometry
and GNSS of a bag in recording order and feeds them through

* a front end (:mod:`semfeat_ros.offline.frontends`: the network as feature_node, XFeat, or
  an OpenCV baseline),
* :class:`~semfeat_ros.matching.sequential.SequentialMatcher` (matcher_node's core), with the
  features converted as they travel in ``/semfeat/features`` (float32 keypoints, bearings from
  the bag's CameraInfo),
* :class:`~semfeat_ros.mapping.session.MappingSession` (mapping_node's core), with the tracks
  converted as they travel in ``/semfeat/tracks`` (float32 bearings and pixels).

Stream timing (:class:`~semfeat_ros.mapping.session.FrameFeeder`, as in mapping_node): wheel
odometry is interpolated at each frame's stamp, so a frame is handed to the mapper once an
odometry sample at or after its stamp has been read (or ``odom_wait_s`` of bag time has passed,
or the bag ended). The session attaches to each frame the newest GNSS fix stamped at or before
it, within ``gnss_max_dt_s``. Frames whose decoding,
matching or mapping input is rejected are counted and skipped, as the nodes reject them.
"""
from __future__ import annotations

from bisect import bisect_right
from collections import deque
from collections.abc import Callable
import dataclasses
from dataclasses import dataclass, field
import time
from typing import Any

import numpy as np
from tqdm import tqdm

from msg_adapters import (
    camera_info_to_model,
    navsatfix_to_numpy,
    odometry_to_numpy,
    stamp_to_ns,
    to_rgb_or_mono,
    tracks_from_msg,
)
from msg_adapters.errors import MessageError
from msg_adapters.image import image_to_numpy
from semfeat_ros.camera import CameraModel
from semfeat_ros.frontend import FrontendConfig, FrontendError
from semfeat_ros.mapping import Mapper, MapperResult, MappingError, Tracks
from semfeat_ros.mapping.session import FrameFeeder, MappingSession, SessionConfig
from semfeat_ros.matching.errors import MatchingError
from semfeat_ros.matching.sequential import SequentialMatcher
from semfeat_ros.offline.bag import (
    CAMERA_INFO_TYPE,
    IMAGE_TYPE,
    NAVSATFIX_TYPE,
    ODOMETRY_TYPE,
    POINTCLOUD2_TYPE,
    BagSource,
    absolute_topic,
)
from semfeat_ros.offline.errors import BagFormatError, OfflineConfigError, TopicNotFoundError
from semfeat_ros.offline.frontends import (
    FRONTEND_KINDS,
    UNLABELED_CLASS,
    make_frontend,
    matcher_frame,
)

LABEL_SOURCES = ('auto', 'network', 'groundtruth', 'none')


@dataclass(frozen=True)
class Topics:
    """Topic names read from the bag (the nodes' defaults)."""

    image: str | None = None  # None: ``image_default`` (raw) or its /compressed, as present
    image_default: str = '/camera/front/image_raw'
    camera_info: str = '/camera/front/camera_info'
    odometry: str = '/vehicle/odom'
    gnss: str = '/gnss/fix'
    ground_truth: str = '/ground_truth/pose'
    gt_semantic: str = '/ground_truth/semantic'
    gt_depth: str = '/ground_truth/depth'

    def absolute(self) -> Topics:
        """The names as recorded in a bag (relative ones resolved in the root namespace)."""
        return Topics(**{k: v if v is None else absolute_topic(v)
                         for k, v in dataclasses.asdict(self).items()})


@dataclass
class MapConfig:
    """What :func:`run_mapping` runs.

    ``frontend``: 'semfeat' | 'xfeat' | 'sift' | 'orb'; ``tracks_topic``: map recorded tracks
    instead (front end and matcher skipped); ``start_s``: skip the first seconds of the
    recording; ``labels`` (xfeat, sift, orb): 'network' = the network's segmentation (as
    feature_node), 'groundtruth' = the bag's ground-truth class masks, 'auto' = the network
    when its weights are found, else the ground truth when recorded, else none;
    ``matcher_conf`` / ``mapper_conf``: overrides of the cores' ``default_conf`` (the nodes'
    YAML); ``T_base_cam`` (4, 4) m.
    """

    T_base_cam: np.ndarray
    frontend: str = 'semfeat'
    frontend_conf: FrontendConfig = field(default_factory=FrontendConfig)
    max_features: int = 1000
    labels: str = 'auto'
    matcher_conf: dict[str, Any] = field(default_factory=dict)
    mapper_conf: dict[str, Any] = field(default_factory=dict)
    session_conf: SessionConfig = field(default_factory=SessionConfig)
    use_odometry: bool = True
    use_gnss: bool = True
    tracks_topic: str | None = None
    fov_deg: float = 190.0
    max_image_pixels: int = 50_000_000
    max_frames: int | None = None
    start_s: float = 0.0
    topics: Topics = field(default_factory=Topics)
    odom_wait_s: float = 0.5
    label_wait_s: float = 1.0


@dataclass
class FrameRecord:
    """Per-frame timings (ms) and the mapper's answer for one frame."""

    stamp_ns: int
    decode_ms: float = 0.0
    frontend_ms: float = 0.0
    matcher_ms: float = 0.0
    n_features: int = 0
    n_tracks: int = 0
    track_ids: np.ndarray | None = None  # (n_tracks,) ids of the tracks seen in this frame
    result: MapperResult | None = None


@dataclass
class MapRun:
    """Everything a mapping run produced (the mapper keeps the map and the trajectory)."""

    mapper: Mapper
    camera: CameraModel
    records: list[FrameRecord]
    frontend: str
    frontend_description: str
    labels_source: str
    image_topic: str | None
    counts: dict[str, int]
    wall_s: float
    used_odometry: bool
    used_gnss: bool

    @property
    def mapped(self) -> list[FrameRecord]:
        """Frames the mapper accepted."""
        return [r for r in self.records if r.result is not None]


@dataclass(frozen=True)
class CameraTimeline:
    """The CameraInfo models of a bag by header stamp (ns): :meth:`at` gives the latest one
    at or before a stamp (the first one for earlier frames) and its ``frame_id``."""

    stamps: np.ndarray
    models: tuple[CameraModel, ...]
    frame_ids: tuple[str, ...]

    def at(self, stamp_ns: int) -> tuple[CameraModel, str]:
        i = max(0, bisect_right(self.stamps.tolist(), int(stamp_ns)) - 1)
        return self.models[i], self.frame_ids[i]


def read_cameras(source: BagSource, topic: str, fov_deg: float) -> CameraTimeline:
    """All CameraInfo models of ``topic`` (one-line error when missing or all invalid)."""
    source.require(topic, (CAMERA_INFO_TYPE,), 'camera calibration')
    stamps, models, frames = [], [], []
    last_error = ''
    for m in source.messages([topic]):
        try:
            model = camera_info_to_model(m.msg, fov_deg=fov_deg)
        except MessageError as exc:
            last_error = str(exc)
            continue
        stamps.append(stamp_to_ns(m.msg))
        models.append(model)
        frames.append(str(m.msg.header.frame_id))
    if not models:
        raise TopicNotFoundError(f'{topic}: no usable CameraInfo in the bag ({last_error})')
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind='stable')
    return CameraTimeline(np.asarray(stamps, dtype=np.int64)[order],
                          tuple(models[i] for i in order), tuple(frames[i] for i in order))


def tracks_for_mapper(stamp_ns: int, columns: dict[str, np.ndarray]) -> Tracks:
    """Mapper input from ``/semfeat/tracks`` columns (float32 as in the message)."""
    return Tracks(int(stamp_ns), np.asarray(columns['track_id'], dtype=np.uint32),
                  np.stack([columns['bx'], columns['by'], columns['bz']], axis=1)
                  .astype(np.float32),
                  np.stack([columns['u'], columns['v']], axis=1).astype(np.float32),
                  np.asarray(columns['label'], dtype=np.uint8))


def _frame_image(msg: Any, max_pixels: int) -> np.ndarray:
    return np.ascontiguousarray(to_rgb_or_mono(msg, max_pixels=max_pixels))


def run_mapping(source: BagSource, conf: MapConfig, progress: bool = True,
                on_tracks: Callable[[int, str, dict[str, np.ndarray]], None] | None = None
                ) -> MapRun:
    """Run the front end, matcher and mapper over ``source`` (see the module doc).

    ``on_tracks(stamp_ns, frame_id, columns)`` receives every matched frame's
    ``/semfeat/tracks`` columns (:meth:`TrackResult.columns`), e.g. to record them.

    Raises:
        TopicNotFoundError: the camera / CameraInfo / tracks topic is missing.
        OfflineConfigError: an invalid option (e.g. labels='groundtruth' without the topic).
        BagFormatError: the bag is broken part-way.
        semfeat_ros.model.errors.WeightsNotFoundError: the network has no trained weights.
    """
    t_start = time.perf_counter()
    topics = conf.topics.absolute()
    if conf.labels not in LABEL_SOURCES:
        raise OfflineConfigError(f'labels: expected one of {LABEL_SOURCES}, got {conf.labels!r}')
    if conf.frontend not in FRONTEND_KINDS:
        raise OfflineConfigError(
            f'frontend: expected one of {", ".join(FRONTEND_KINDS)}, got {conf.frontend!r}')
    from_tracks = bool(conf.tracks_topic)
    image_topic = None
    if from_tracks:
        source.require(conf.tracks_topic, (POINTCLOUD2_TYPE,), 'recorded tracks')
    else:
        image_topic = source.image_topic(topics.image, topics.image_default)
    cameras = read_cameras(source, topics.camera_info, conf.fov_deg)
    camera0 = cameras.models[0]

    frontend = None
    labels_source = 'recorded tracks' if from_tracks else 'network'
    use_gt_labels = False
    matcher_conf = dict(conf.matcher_conf)
    if not from_tracks:
        network_labels = {'network': True, 'auto': None}.get(conf.labels, False)
        frontend = make_frontend(conf.frontend, conf.frontend_conf, conf.max_features,
                                 network_labels=network_labels)
        if conf.frontend != 'semfeat':
            has_gt = source.has(topics.gt_semantic, (IMAGE_TYPE,))
            if conf.labels == 'groundtruth' and not has_gt:
                raise OfflineConfigError(
                    f'labels=groundtruth needs the class-mask topic {topics.gt_semantic!r}, '
                    f'which the bag lacks')
            use_gt_labels = conf.labels == 'groundtruth' or (
                conf.labels == 'auto' and frontend.labeller is None and has_gt)
            labels_source = ('ground truth ' + topics.gt_semantic if use_gt_labels
                             else 'network' if frontend.labeller is not None
                             else f'none (every keypoint labelled {UNLABELED_CLASS})')
        matching = dict(matcher_conf.get('matching', {}))
        matching['descriptor_type'] = frontend.descriptor_type
        matcher_conf['matching'] = matching
    matcher = SequentialMatcher(matcher_conf) if not from_tracks else None

    used_odom = conf.use_odometry and source.has(topics.odometry, (ODOMETRY_TYPE,))
    used_gnss = conf.use_gnss and source.has(topics.gnss, (NAVSATFIX_TYPE,))
    mapper_conf = {**conf.mapper_conf, 'use_odometry': bool(conf.use_odometry),
                   'use_gnss': bool(conf.use_gnss)}
    session = MappingSession(camera0, conf.T_base_cam, mapper_conf, conf.session_conf)
    feeder = FrameFeeder(session, conf.odom_wait_s, expect_odometry=used_odom)

    frame_topic = conf.tracks_topic if from_tracks else image_topic
    total = source.message_count(frame_topic)
    if conf.max_frames is not None:
        total = min(total, conf.max_frames)
    stream_topics = [frame_topic]
    if used_odom:
        stream_topics.append(topics.odometry)
    if used_gnss:
        stream_topics.append(topics.gnss)
    if use_gt_labels:
        stream_topics.append(topics.gt_semantic)
    counts = dict(frames_read=0, frames_rejected=0, frames_without_labels=0,
                  odometry_messages=0, gnss_fixes=0, gnss_without_fix=0,
                  matcher_rejected=0)
    records: list[FrameRecord] = []
    waiting: deque[tuple[int, int, Any]] = deque()  # (stamp, log_ns, image msg) for labels
    masks: dict[int, np.ndarray] = {}
    label_wait_ns = int(conf.label_wait_s * 1e9)
    bar = tqdm(total=total, desc=f'map ({conf.frontend if not from_tracks else "tracks"})',
               unit='frame', disable=not progress)

    def process_frame(stamp: int, msg: Any, labels: np.ndarray | None) -> None:
        record = FrameRecord(stamp)
        records.append(record)
        bar.update(1)
        camera, frame_id = cameras.at(stamp)
        t0 = time.perf_counter()
        try:
            image = _frame_image(msg, conf.max_image_pixels)
        except MessageError:
            counts['frames_rejected'] += 1
            return
        t1 = time.perf_counter()
        try:
            out = frontend.process(image, camera, labels)
        except FrontendError:
            counts['frames_rejected'] += 1
            return
        t2 = time.perf_counter()
        try:
            tr = matcher.process(matcher_frame(stamp, out, camera, frame_id))
        except MatchingError:
            counts['matcher_rejected'] += 1
            return
        t3 = time.perf_counter()
        record.decode_ms = (t1 - t0) * 1e3
        record.frontend_ms = (t2 - t1) * 1e3
        record.matcher_ms = (t3 - t2) * 1e3
        record.n_features = len(out)
        record.n_tracks = tr.n_tracks
        cols = tr.columns()
        record.track_ids = cols['track_id']
        feeder.push(tracks_for_mapper(stamp, cols), record)
        if on_tracks is not None:
            on_tracks(stamp, str(msg.header.frame_id), cols)

    def release(now_ns: int | None) -> None:
        for fed in feeder.release(now_ns):
            fed.tag.result = fed.result

    def drain_waiting(now_ns: int | None) -> None:
        while waiting:
            stamp, log_ns, msg = waiting[0]
            if stamp in masks:
                waiting.popleft()
                process_frame(stamp, msg, masks.pop(stamp))
            elif now_ns is None or now_ns - log_ns > label_wait_ns:
                waiting.popleft()
                counts['frames_without_labels'] += 1
            else:
                return

    try:
        start = source.start_ns + int(conf.start_s * 1e9) if conf.start_s > 0 else None
        for m in source.messages(stream_topics, start_ns=start):
            if m.topic == frame_topic:
                if conf.max_frames is not None and counts['frames_read'] >= conf.max_frames:
                    break
                counts['frames_read'] += 1
                try:
                    stamp = stamp_to_ns(m.msg)
                except MessageError:
                    counts['frames_rejected'] += 1
                    continue
                if from_tracks:
                    record = FrameRecord(stamp)
                    records.append(record)
                    bar.update(1)
                    try:
                        cols = tracks_from_msg(m.msg)
                    except MessageError:
                        counts['frames_rejected'] += 1
                        continue
                    record.n_tracks = len(cols.track_ids)
                    record.track_ids = cols.track_ids
                    feeder.push(Tracks(stamp, cols.track_ids, cols.bearings, cols.uv,
                                       cols.labels), record)
                elif use_gt_labels:
                    waiting.append((stamp, m.log_ns, m.msg))
                else:
                    process_frame(stamp, m.msg, None)
            elif m.topic == topics.odometry:
                try:
                    odo = odometry_to_numpy(m.msg)
                    feeder.add_odometry(odo.stamp_ns, odo.T)
                except (MessageError, MappingError):
                    continue
                counts['odometry_messages'] += 1
            elif m.topic == topics.gnss:
                try:
                    fix = navsatfix_to_numpy(m.msg)
                except MessageError:
                    continue
                if not fix.has_fix:
                    counts['gnss_without_fix'] += 1
                    continue
                counts['gnss_fixes'] += 1
                feeder.add_fix(fix.stamp_ns, (fix.latitude, fix.longitude, fix.altitude),
                               fix.covariance)
            elif m.topic == topics.gt_semantic:
                try:
                    masks[stamp_to_ns(m.msg)] = image_to_numpy(m.msg)
                except MessageError:
                    continue
            if use_gt_labels:
                drain_waiting(m.log_ns)
            release(m.log_ns)
        if use_gt_labels:
            for stamp, _, msg in list(waiting):
                if stamp in masks:
                    process_frame(stamp, msg, masks.pop(stamp))
                else:
                    counts['frames_without_labels'] += 1
            waiting.clear()
        release(None)
    finally:
        bar.close()
    counts['mapper_rejected'] = feeder.rejected
    if not records:
        raise BagFormatError(f'no frames were read from {frame_topic!r}')
    return MapRun(
        mapper=session.mapper, camera=camera0, records=records,
        frontend='tracks' if from_tracks else conf.frontend,
        frontend_description=(f'recorded {conf.tracks_topic}' if from_tracks
                              else frontend.describe()),
        labels_source=labels_source, image_topic=image_topic, counts=counts,
        wall_s=time.perf_counter() - t_start, used_odometry=used_odom, used_gnss=used_gnss)
