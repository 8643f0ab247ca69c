"""Frames a benchmark measures on: the bag's compressed frames and frames rendered by the
simulator at a higher resolution (JPEG-encoded, cached on disk)."""
from __future__ import annotations

from dataclasses import dataclass
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msg_adapters import to_rgb_or_mono
from msg_adapters.stamp import make_header
from semfeat_ros.camera import CameraModel
from semfeat_ros.offline.bag import BagSource, typestore
from semfeat_ros.offline.errors import OfflineConfigError
from semfeat_ros.offline.paths import confined

JPEG_QUALITY = 80  # quality of the bundled bag's frames (semfeat-sim --jpeg-quality 80)
CAMERA_FRAME = 'camera_front_optical'
COMPRESSED_FORMAT = 'rgb8; jpeg compressed bgr8'
CACHE_VERSION = 1
FRAME_PERIOD_NS = 100_000_000  # 10 Hz, the bundled bag's rate


@dataclass
class FrameSet:
    """Compressed frames of one resolution (rosbags CompressedImage messages) and the camera
    model at that resolution."""

    name: str
    size: tuple[int, int]  # (W, H) px
    msgs: list[Any]
    camera: CameraModel
    source: str


def compressed_msg(data: bytes, stamp_ns: int) -> Any:
    """A rosbags ``sensor_msgs/CompressedImage`` holding the JPEG bytes ``data``."""
    ts = typestore()
    cls = ts.types['sensor_msgs/msg/CompressedImage']
    return cls(header=make_header(stamp_ns, CAMERA_FRAME, cls, typestore=ts),
               format=COMPRESSED_FORMAT, data=np.frombuffer(data, dtype=np.uint8).copy())


def bag_frames(source: BagSource, n: int, fov_deg: float,
               topics: Any) -> FrameSet:
    """The first ``n`` camera frames of the bag and its (first) CameraInfo model."""
    from semfeat_ros.offline.mapping_run import read_cameras

    topic = source.image_topic(topics.image, topics.image_default)
    camera = read_cameras(source, topics.camera_info, fov_deg).models[0]
    msgs = []
    for m in source.messages([topic]):
        msgs.append(m.msg)
        if len(msgs) >= n:
            break
    if len(msgs) < 2:
        raise OfflineConfigError(f'{topic}: the bag has {len(msgs)} frame(s), need at least 2')
    h, w = to_rgb_or_mono(msgs[0]).shape[:2]
    return FrameSet(f'{w}x{h}', (w, h), msgs, camera, f'{source.path.name} {topic}')


def rendered_frames(out: Path, n: int, size: tuple[int, int], seed: int,
                    progress: bool) -> FrameSet:
    """``n`` consecutive 10 Hz frames of the simulator's drive (seed ``seed``, starting where
    the bundled bag starts: 6 s before the ramp's top) rendered at ``size`` and JPEG-encoded
    (quality 80, as the bag); cached in ``<out>/frames_WxH/`` and reused when present."""
    from semfeat_ros.camera import load_camera_yaml

    w, h = size
    cache = confined(out, f'frames_{w}x{h}')
    meta_path = cache / 'frames.json'
    want = {'version': CACHE_VERSION, 'seed': seed, 'size': [w, h], 'frames': n,
            'jpeg_quality': JPEG_QUALITY}
    files = [cache / f'frame_{k:03d}.jpg' for k in range(n)]
    meta: dict[str, Any] = {}
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            meta = {}
    valid = ({k: meta.get(k) for k in want} == want and isinstance(meta.get('start_s'), float)
             and len(meta.get('stamps_ns') or ()) == n and all(f.is_file() for f in files))
    if not valid:
        meta = _render(cache, files, want, progress)
    msgs = [compressed_msg(f.read_bytes(), int(s)) for f, s in zip(files, meta['stamps_ns'])]
    camera = load_camera_yaml()[0].scaled(w, h)
    return FrameSet(f'{w}x{h}', (w, h), msgs, camera,
                    f'simulator seed {seed}, t = {meta["start_s"]:.2f} s + k / 10 Hz '
                    f'(cached in {cache.name}/)')


def _render(cache: Path, files: list[Path], want: dict[str, Any],
            progress: bool) -> dict[str, Any]:
    from msg_adapters import numpy_to_compressed
    from semfeat_ros.sim.bag import STAMP0_NS, resolve_start
    from semfeat_ros.sim.scenario import Scenario

    cache.mkdir(parents=True, exist_ok=True)
    sc = Scenario.create(seed=want['seed'], size=tuple(want['size']))
    try:
        t0 = resolve_start(sc, 'ramp')
        stamps = []
        ts = typestore()
        for k, path in enumerate(tqdm(files, desc=f'render {want["size"][0]}x'
                                      f'{want["size"][1]}', unit='frame', disable=not progress)):
            t = t0 + k * FRAME_PERIOD_NS * 1e-9
            stamp = STAMP0_NS + int(round(t * 1e9))
            frame = sc.renderer.render(sc.camera_pose(t), t)
            rgb, _ = sc.sensor.expose(frame, sc.camera, k)
            msg = numpy_to_compressed(rgb, 'jpeg', stamp_ns=stamp, frame_id=CAMERA_FRAME,
                                      msg_cls=ts, quality=JPEG_QUALITY)
            atomic_write(path, np.asarray(msg.data, dtype=np.uint8).tobytes())
            stamps.append(stamp)
    finally:
        sc.renderer.close()
    meta = {**want, 'start_s': t0, 'stamps_ns': stamps}
    atomic_write(cache / 'frames.json', (json.dumps(meta, indent=1) + '\n').encode())
    return meta


def atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f'.{path.name}.tmp{os.getpid()}')
    tmp.write_bytes(data)
    os.replace(tmp, path)
