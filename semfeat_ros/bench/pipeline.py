"""The in-process pipeline of ``semfeat-map`` (decode -> front end -> matcher -> mapping
session) over a bag: the end-to-end rate, the soak, and the iSAM2 update time against the
keyframe count."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
import time
from typing import Any

import numpy as np
from tqdm import tqdm

from msg_adapters import navsatfix_to_numpy, odometry_to_numpy, stamp_to_ns, to_rgb_or_mono
from msg_adapters.errors import MessageError
from semfeat_ros.bench.machine import ProcSampler
from semfeat_ros.bench.stats import linear_slope, rolling_median, summarize
from semfeat_ros.offline.bag import BagSource

IMAGE_DELAY_NS = 50_000_000  # soak: a frame is mapped once odometry 50 ms past it is read
NETWORK_LABELS = ('xfeat',)  # end-to-end front ends whose keypoints take the network's classes


@dataclass
class _Event:
    key_ns: int
    order: int
    kind: str
    stamp_ns: int
    payload: Any


@dataclass
class Replay:
    """The bag's frames, odometry and GNSS deserialised in memory, in processing order, and
    its CameraInfo models (:class:`~semfeat_ros.offline.mapping_run.CameraTimeline`)."""

    events: list[_Event]
    cameras: Any
    image_topic: str

    @property
    def n_frames(self) -> int:
        return sum(e.kind == 'image' for e in self.events)


def read_replay(bag: Path, mc: Any) -> Replay:
    """Camera frames, odometry and GNSS of ``bag``, ordered so that each frame comes after the
    odometry that brackets its stamp (frames and fixes delayed by ``IMAGE_DELAY_NS``)."""
    from semfeat_ros.offline.bag import NAVSATFIX_TYPE, ODOMETRY_TYPE
    from semfeat_ros.offline.mapping_run import read_cameras

    names = mc.topics.absolute()  # as recorded in the bag
    with BagSource(bag) as source:
        image_topic = source.image_topic(names.image, names.image_default)
        cameras = read_cameras(source, names.camera_info, mc.fov_deg)
        topics = [image_topic]
        if mc.use_odometry and source.has(names.odometry, (ODOMETRY_TYPE,)):
            topics.append(names.odometry)
        if mc.use_gnss and source.has(names.gnss, (NAVSATFIX_TYPE,)):
            topics.append(names.gnss)
        events = []
        for m in source.messages(topics):
            try:
                if m.topic == image_topic:
                    s = stamp_to_ns(m.msg)
                    events.append(_Event(s + IMAGE_DELAY_NS, 2, 'image', s, m.msg))
                elif m.topic == names.odometry:
                    od = odometry_to_numpy(m.msg)
                    events.append(_Event(od.stamp_ns, 0, 'odom', od.stamp_ns, od.T))
                else:
                    fix = navsatfix_to_numpy(m.msg)
                    if fix.has_fix:
                        events.append(_Event(fix.stamp_ns + IMAGE_DELAY_NS, 1, 'gnss',
                                             fix.stamp_ns,
                                             ((fix.latitude, fix.longitude, fix.altitude),
                                              fix.covariance)))
            except MessageError:
                continue
    events.sort(key=lambda e: (e.key_ns, e.order))
    return Replay(events, cameras, image_topic)


class ReplayPipeline:
    """decode -> front end -> sequential matcher -> mapping session in one process, with the
    objects kept across passes (as the three nodes keep them).

    ``kind`` is 'semfeat' (the network, feature_node's code), 'orb' / 'sift' (OpenCV front
    ends of ``semfeat-map``, unlabelled keypoints, ORB through the matcher's binary mode) or
    'xfeat' (XFeat with its keypoints labelled by the network's segmentation, one network pass
    a frame, as feature_node runs it: the kinds of :data:`NETWORK_LABELS`).
    Per-frame wall times (ms) are appended to :attr:`times`.
    """

    def __init__(self, replay: Replay, mc: Any, kind: str) -> None:
        from semfeat_ros.mapping.session import MappingSession
        from semfeat_ros.matching.sequential import SequentialMatcher
        from semfeat_ros.offline.frontends import make_frontend

        self.replay = replay
        self.mc = mc
        self.frontend = make_frontend(kind, mc.frontend_conf, mc.max_features,
                                      network_labels=kind in NETWORK_LABELS)
        matcher_conf = dict(mc.matcher_conf)
        matcher_conf['matching'] = {**matcher_conf.get('matching', {}),
                                    'descriptor_type': self.frontend.descriptor_type}
        self.matcher = SequentialMatcher(matcher_conf)
        mapper_conf = {**mc.mapper_conf, 'use_odometry': bool(mc.use_odometry),
                       'use_gnss': bool(mc.use_gnss)}
        self.session = MappingSession(replay.cameras.models[0], mc.T_base_cam, mapper_conf,
                                      mc.session_conf)
        self.times: dict[str, list[float]] = {
            'decode': [], 'frontend': [], 'matcher': [], 'mapping_update': [], 'frame': []}
        self.frame_done: list[float] = []  # perf_counter at the end of every frame
        self.frames = 0
        self.rejected = 0
        self.keyframes = 0
        self.states: dict[str, int] = {}  # mapper state -> frames

    def _frame(self, ev: _Event) -> None:
        from semfeat_ros.mapping import MappingError
        from semfeat_ros.matching.errors import MatchingError
        from semfeat_ros.offline.frontends import matcher_frame
        from semfeat_ros.offline.mapping_run import tracks_for_mapper

        camera, frame_id = self.replay.cameras.at(ev.stamp_ns)
        t0 = time.perf_counter()
        try:
            image = np.ascontiguousarray(to_rgb_or_mono(ev.payload,
                                                        max_pixels=self.mc.max_image_pixels))
            t1 = time.perf_counter()
            out = self.frontend.process(image, camera, None)
            t2 = time.perf_counter()
            tr = self.matcher.process(matcher_frame(ev.stamp_ns, out, camera, frame_id))
            t3 = time.perf_counter()
            result = self.session.process(tracks_for_mapper(ev.stamp_ns, tr.columns()))
            t4 = time.perf_counter()
        except (MessageError, MatchingError, MappingError, ValueError):
            self.rejected += 1
            return
        finally:
            self.frames += 1
            self.frame_done.append(time.perf_counter())
        self.keyframes += int(result.keyframe)
        self.states[result.state] = self.states.get(result.state, 0) + 1
        for key, a, b in (('decode', t0, t1), ('frontend', t1, t2), ('matcher', t2, t3),
                          ('mapping_update', t3, t4), ('frame', t0, t4)):
            self.times[key].append((b - a) * 1e3)

    def play(self, max_frames: int | None = None, deadline: float | None = None,
             on_frame: Callable[[], None] | None = None) -> bool:
        """One pass over the bag (stops after ``max_frames`` frames or at the perf_counter
        ``deadline``); returns True when the pass completed. The next pass starts the map
        again (its stamps restart), as mapping_node does when time goes backwards."""
        done = 0
        for ev in self.replay.events:
            if ev.kind == 'odom':
                self.session.add_odometry(ev.stamp_ns, ev.payload)
            elif ev.kind == 'gnss':
                self.session.add_gnss(ev.stamp_ns, ev.payload[0], ev.payload[1])
            else:
                if (max_frames is not None and done >= max_frames) or (
                        deadline is not None and time.perf_counter() >= deadline):
                    return False
                self._frame(ev)
                done += 1
                if on_frame is not None:
                    on_frame()
        self.session.reset()
        return True


def measure_end_to_end(replay: Replay, mc: Any, kind: str, max_frames: int | None,
                       progress: bool) -> dict[str, Any]:
    """One pass of :class:`ReplayPipeline` with front end ``kind``; the sustained rate is the
    frames after the first one over the wall time from the end of the first frame (Hz)."""
    pipe = ReplayPipeline(replay, mc, kind)
    total = min(replay.n_frames, max_frames or replay.n_frames)
    with tqdm(total=total, desc=f'end-to-end {kind}', unit='frame',
              disable=not progress) as bar:
        pipe.play(max_frames, on_frame=lambda: bar.update(1))
    done = pipe.frame_done
    hz = (len(done) - 1) / (done[-1] - done[0]) if len(done) >= 2 and done[-1] > done[0] \
        else None
    return {
        'frontend': kind, 'description': pipe.frontend.describe(), 'frames': pipe.frames,
        'frames_mapped': len(pipe.times['frame']), 'frames_rejected': pipe.rejected,
        'keyframes': pipe.keyframes, 'sustained_hz': hz, 'mapper_states': pipe.states,
        'stats': {k: summarize(v) for k, v in pipe.times.items()},
    }


def soak(replay: Replay, mc: Any, minutes: float, progress: bool,
         period_s: float | None = None) -> dict[str, Any]:
    """Replay the bag in a loop through one persistent network pipeline for ``minutes`` of
    wall time, sampling the process's CPU % and RSS (``/proc/self``) and recording every
    mapped frame's time; reports the linear slopes of RSS (MB/min) and frame time (ms/min),
    over the whole soak and after the warm-up."""
    pipe = ReplayPipeline(replay, mc, 'semfeat')
    duration = minutes * 60.0
    period = period_s if period_s is not None else min(1.0, max(0.05, duration / 30.0))
    loops = 0
    bar = tqdm(total=round(duration), desc='soak', unit='s', disable=not progress)
    shown = 0
    frame_t: list[float] = []  # min since the start, of each mapped frame
    frame_ms: list[float] = []

    def tick() -> None:
        nonlocal shown
        times = pipe.times['frame']
        while len(frame_ms) < len(times):
            frame_ms.append(times[len(frame_ms)])
            frame_t.append((time.perf_counter() - t_start) / 60.0)
        elapsed = min(int(time.perf_counter() - t_start), round(duration))
        if elapsed > shown:
            bar.update(elapsed - shown)
            shown = elapsed

    with ProcSampler(period_s=period) as sampler:
        t_start = time.perf_counter()
        deadline = t_start + duration
        while pipe.play(deadline=deadline, on_frame=tick):
            loops += 1
        wall = time.perf_counter() - t_start
    bar.close()
    t = np.asarray(sampler.t_s) / 60.0
    rss = np.asarray(sampler.rss_mb)
    cpu = np.asarray(sampler.cpu_pct)
    warm = min(1.0, 0.2 * minutes)
    late = t >= warm
    ft, fms = np.asarray(frame_t), np.asarray(frame_ms)
    return {
        'minutes': minutes, 'wall_s': wall, 'frames': pipe.frames, 'loops_completed': loops,
        'frames_rejected': pipe.rejected, 'keyframes': pipe.keyframes,
        'sustained_hz': pipe.frames / wall if wall > 0 else None,
        'frame_ms': summarize(pipe.times['frame']), 'sample_period_s': period,
        'samples': int(t.size),
        'cpu_pct': summarize(cpu.tolist()),
        'rss_mb': {'start': float(rss[0]) if rss.size else None,
                   'end': float(rss[-1]) if rss.size else None,
                   'max': float(rss.max()) if rss.size else None},
        'rss_slope_mb_per_min': linear_slope(t, rss),
        'rss_slope_after_warmup_mb_per_min': linear_slope(t[late], rss[late]),
        'frame_ms_slope_per_min': linear_slope(ft, fms),
        'frame_ms_slope_after_warmup_per_min': linear_slope(ft[ft >= warm], fms[ft >= warm]),
        'warmup_min': warm,
        'series': {'t_min': t.tolist(), 'rss_mb': rss.tolist(), 'cpu_pct': cpu.tolist(),
                   'frame_t_min': ft.tolist(), 'frame_ms': fms.tolist()},
    }


def measure_isam2(keyframes: int, mapper_conf: dict[str, Any], progress: bool
                  ) -> dict[str, Any]:
    """Update time (ms) of every keyframe of the synthetic long drive of
    :func:`benchmark_update_time` (fixed-lag iSAM2) up to ``keyframes`` keyframes."""
    from semfeat_ros.mapping.benchmark import benchmark_update_time

    # the synthetic tracks have their own keypoint noise (benchmark_update_time's default)
    conf = {k: v for k, v in mapper_conf.items() if k != 'bearing_sigma_px'}
    t0 = time.perf_counter()
    res = benchmark_update_time(keyframes, odometry=True, seed=0, conf=conf, progress=progress)
    wall = time.perf_counter() - t0
    size = max(10, int(round(keyframes / 10.0, -1)) if keyframes >= 100 else keyframes)
    return {
        'keyframes': int(res.keyframe.size), 'wall_s': wall, 'ate_sim3_m': res.ate_sim3_m,
        'update_ms': summarize(res.update_ms), 'update_cpu_ms': summarize(res.update_cpu_ms),
        'frame_ms': summarize(res.frame_ms),
        'buckets': [{'first': a, 'last': b, 'p50_ms': med, 'p90_ms': p90, 'cpu_p50_ms': cpu}
                    for a, b, med, p90, cpu in res.buckets(size)],
        'slope_ms_per_1000_kf': (None if res.keyframe.size < 2 else 1000.0 * linear_slope(
            res.keyframe, rolling_median(res.update_ms, 51))),
        'stats': res.stats,
        'series': {'keyframe': res.keyframe.tolist(), 'update_ms': res.update_ms.tolist(),
                   'update_cpu_ms': res.update_cpu_ms.tolist()},
    }
