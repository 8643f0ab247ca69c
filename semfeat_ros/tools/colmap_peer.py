"""COLMAP peer of ``semfeat-map``: COLMAP's own SfM pipeline on the frames of a bag.

usage: python -m semfeat_ros.tools.colmap_peer BAG --out DIR [--topic T] [--max-frames N]
           [--start S] [--stride N] [--max-features N] [--overlap N] [--refine-intrinsics]
           [--threads N] [--no-figures] [--quiet] [--verbose]

Through pycolmap (4.2): the camera frames are written to ``DIR/images`` (JPEG bytes of
CompressedImage frames as recorded, other frames as PNG), named ``<header stamp ns>.<ext>``;
one shared camera (``OPENCV_FISHEYE`` with the bag's CameraInfo intrinsics for ``equidistant``,
``OPENCV`` for ``plumb_bob``; fixed unless ``--refine-intrinsics``) and a mask of the lens's
image circle; SIFT extraction (``pycolmap.extract_features``), sequential matching
(``pycolmap.match_sequential``), incremental mapping (``pycolmap.incremental_mapping``). The
largest reconstruction is evaluated like ``semfeat-map`` (Sim(3) alignment: COLMAP is scale
free; images registered to stamps by name): ``DIR/trajectory.tum`` (base_link poses through the
calibration's extrinsic), ``DIR/metrics.json`` (ATE, scale, ramp altitude error, registered
frames, wall time per stage), ``DIR/trajectory_top.png``, ``DIR/altitude.png``.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
import json
from pathlib import Path
import sys
import time
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from msg_adapters import stamp_to_ns, to_rgb_or_mono
from msg_adapters.errors import MessageError
from semfeat_ros.camera import CameraModel
from semfeat_ros.mapping import write_tum
from semfeat_ros.offline import figures
from semfeat_ros.offline.bag import COMPRESSED_TYPE, BagSource, one_line, read_poses
from semfeat_ros.offline.errors import OfflineConfigError, OfflineError, OutputPathError
from semfeat_ros.offline.mapping_run import read_cameras
from semfeat_ros.offline.metrics import (
    RAMP_PITCH_RAD,
    evaluate_trajectory,
    gt_levels,
    pitch_of,
    storey_of,
    travelled,
)
from semfeat_ros.offline.paths import confined, prepare_out_dir
from semfeat_ros.offline.report import json_safe

PROG = 'colmap_peer'


@dataclass
class ColmapPeerConfig:
    """Options of the COLMAP peer (topics: the nodes' defaults)."""

    topic: str | None = None
    default_image_topic: str = '/camera/front/image_raw'
    camera_info_topic: str = '/camera/front/camera_info'
    ground_truth_topic: str = '/ground_truth/pose'
    camera_config: Path | None = None
    fov_deg: float = 190.0
    max_frames: int | None = None
    start_s: float = 0.0
    stride: int = 1  # use every stride-th frame
    max_features: int = 8192  # COLMAP's default SIFT budget per image
    overlap: int = 10  # COLMAP's default sequential overlap (images)
    refine_intrinsics: bool = False
    num_threads: int = 1  # 1: deterministic (COLMAP's multi-threaded runs differ run to run)
    seed: int = 0
    figures: bool = True
    progress: bool = True
    verbose: bool = False  # COLMAP's own INFO log on stderr


@dataclass(frozen=True)
class ColmapPaths:
    """Input bag and output directory."""

    bag: Path
    out: Path


def colmap_camera(camera: CameraModel) -> tuple[str, str]:
    """``(COLMAP model name, comma-separated params)`` of a CameraInfo model.

    Raises:
        OfflineConfigError: a distortion model COLMAP cannot represent here.
    """
    k = [camera.fx, camera.fy, camera.cx, camera.cy]
    d = [float(x) for x in np.asarray(camera.D).ravel()]
    if camera.distortion_model == 'equidistant':
        return 'OPENCV_FISHEYE', ','.join(f'{v:.10g}' for v in k + (d + [0.0] * 4)[:4])
    if camera.distortion_model == 'plumb_bob':
        return 'OPENCV', ','.join(f'{v:.10g}' for v in k + (d + [0.0] * 4)[:4])
    raise OfflineConfigError(
        f'CameraInfo distortion_model {camera.distortion_model!r}: the COLMAP peer supports '
        f'equidistant (OPENCV_FISHEYE) and plumb_bob (OPENCV)')


def _image_bytes(msg: Any, msgtype: str) -> tuple[bytes, str]:
    """The frame as an image file: recorded JPEG/PNG bytes, else a lossless PNG."""
    if msgtype == COMPRESSED_TYPE:
        fmt = str(msg.format).lower()
        data = bytes(np.asarray(msg.data, dtype=np.uint8).tobytes())
        if 'jpeg' in fmt or 'jpg' in fmt:
            return data, '.jpg'
        if 'png' in fmt:
            return data, '.png'
    img = to_rgb_or_mono(msg)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode('.png', img)
    if not ok:
        raise OfflineConfigError('cannot encode a frame as PNG')
    return buf.tobytes(), '.png'


def export_frames(source: BagSource, image_topic: str, image_dir: Path, conf: ColmapPeerConfig
                  ) -> dict[str, int]:
    """Write the bag's frames to ``image_dir``; returns ``{image name: stamp ns}``."""
    names: dict[str, int] = {}
    total = source.message_count(image_topic)
    if conf.max_frames is not None:
        total = min(total, conf.max_frames)
    start = source.start_ns + int(conf.start_s * 1e9) if conf.start_s > 0 else None
    bar = tqdm(total=total, desc='frames', unit='frame', disable=not conf.progress)
    try:
        for i, m in enumerate(source.messages([image_topic], start_ns=start)):
            if conf.max_frames is not None and len(names) >= conf.max_frames:
                break
            if i % conf.stride:
                continue
            try:
                stamp = stamp_to_ns(m.msg)
                data, ext = _image_bytes(m.msg, m.msgtype)
            except MessageError:
                continue
            name = f'{stamp}{ext}'
            if name in names:
                continue
            confined(image_dir.parent, Path(image_dir.name) / name).write_bytes(data)
            names[name] = stamp
            bar.update(1)
    finally:
        bar.close()
    return names


def _pose_matrix(rigid: Any) -> np.ndarray:
    T = np.eye(4)
    T[:3, :] = np.asarray(rigid.matrix(), dtype=np.float64).reshape(3, 4)
    return T


def main(conf: ColmapPeerConfig, paths: ColmapPaths) -> dict[str, Any]:
    """Run COLMAP on the bag's frames and evaluate; returns the metrics (also written)."""
    import pycolmap

    from semfeat_ros.camera import load_camera_yaml

    if conf.max_frames is not None and conf.max_frames < 2:
        raise OfflineConfigError(f'--max-frames must be >= 2, got {conf.max_frames}')
    for name, v in (('--max-features', conf.max_features), ('--overlap', conf.overlap),
                    ('--stride', conf.stride)):
        if v < 1:
            raise OfflineConfigError(f'{name} must be >= 1, got {v}')
    try:
        _, extrinsic = load_camera_yaml(conf.camera_config)
    except (OSError, ValueError) as exc:
        raise OfflineConfigError(f'camera calibration: {one_line(exc)}') from exc
    T_base_cam = extrinsic.T_base_cam
    pycolmap.logging.minloglevel = 0 if conf.verbose else 2  # 2: errors only
    times: dict[str, float] = {}
    t_all = time.perf_counter()
    with BagSource(paths.bag) as source:
        image_topic = source.image_topic(conf.topic, conf.default_image_topic)
        cameras = read_cameras(source, conf.camera_info_topic, conf.fov_deg)
        camera = cameras.models[0]
        model, params = colmap_camera(camera)
        out = prepare_out_dir(paths.out)
        database = confined(out, 'database.db')
        if database.exists():
            raise OutputPathError(f'{str(database)!r} exists (an earlier run?): choose a new '
                                  f'--out')
        image_dir = confined(out, 'images')
        image_dir.mkdir(exist_ok=True)
        t0 = time.perf_counter()
        names = export_frames(source, image_topic, image_dir, conf)
        times['export_s'] = time.perf_counter() - t0
        gt_stamps, gt_poses = read_poses(source, conf.ground_truth_topic)
    if len(names) < 2:
        raise OfflineConfigError(f'only {len(names)} frame(s) exported: need at least 2')
    mask_path = confined(out, 'camera_mask.png')
    first = cv2.imread(str(image_dir / next(iter(names))), cv2.IMREAD_UNCHANGED)
    if first is None or first.shape[:2] != (camera.height, camera.width):
        got = 'unreadable' if first is None else f'{first.shape[1]}x{first.shape[0]} px'
        raise OfflineConfigError(f'frames are {got}, the CameraInfo describes '
                                 f'{camera.width}x{camera.height} px')
    cv2.imwrite(str(mask_path), camera.valid_mask().astype(np.uint8) * 255)

    reader = pycolmap.ImageReaderOptions(camera_model=model, camera_params=params,
                                         camera_mask_path=str(mask_path))
    extraction = pycolmap.FeatureExtractionOptions(num_threads=conf.num_threads)
    extraction.sift.max_num_features = conf.max_features
    t0 = time.perf_counter()
    pycolmap.extract_features(database, image_dir, image_names=sorted(names),
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    times['extract_s'] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_sequential(
        database, matching_options=pycolmap.FeatureMatchingOptions(num_threads=conf.num_threads),
        pairing_options=pycolmap.SequentialPairingOptions(overlap=conf.overlap),
        device=pycolmap.Device.cpu)
    times['match_s'] = time.perf_counter() - t0
    opts = pycolmap.IncrementalPipelineOptions(
        num_threads=conf.num_threads, random_seed=conf.seed,
        ba_refine_focal_length=conf.refine_intrinsics,
        ba_refine_extra_params=conf.refine_intrinsics)
    opts.mapper.random_seed = conf.seed
    opts.mapper.abs_pose_refine_focal_length = conf.refine_intrinsics
    opts.mapper.abs_pose_refine_extra_params = conf.refine_intrinsics
    sparse = confined(out, 'sparse')
    sparse.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(database, image_dir, sparse, options=opts)
    times['mapping_s'] = time.perf_counter() - t0
    times['total_s'] = time.perf_counter() - t_all
    times['colmap_s'] = times['extract_s'] + times['match_s'] + times['mapping_s']

    metrics: dict[str, Any] = {
        'bag': str(paths.bag), 'peer': f'COLMAP (pycolmap {pycolmap.__version__}): SIFT, '
        f'sequential matching (overlap {conf.overlap}), incremental mapping',
        'camera_model': model, 'camera_params': params, 'intrinsics_refined':
        conf.refine_intrinsics, 'frames': len(names), 'models': len(recs),
        'wall_time_s': {k: round(v, 3) for k, v in times.items()}}
    best = max(recs.values(), key=lambda r: r.num_reg_images(), default=None)
    if best is None or best.num_reg_images() < 3:
        metrics.update(registered_frames=0 if best is None else best.num_reg_images(),
                       ate_sim3_rmse_m=None, evaluation_error='COLMAP registered fewer than 3 '
                       'frames')
    else:
        T_cam_base = np.linalg.inv(T_base_cam)
        rows = sorted((names[img.name], np.linalg.inv(_pose_matrix(img.cam_from_world()))
                       @ T_cam_base) for img in best.images.values()
                      if img.has_pose and img.name in names)
        stamps = np.array([s for s, _ in rows], np.int64)
        poses = np.array([T for _, T in rows]).reshape(-1, 4, 4)
        write_tum(confined(out, 'trajectory.tum'), stamps, poses)
        metrics.update(registered_frames=len(rows),
                       registered_fraction=round(len(rows) / len(names), 4),
                       points3d=int(best.num_points3D()),
                       mean_reprojection_error_px=float(best.compute_mean_reprojection_error()))
        if len(gt_stamps):
            try:
                ev = evaluate_trajectory(stamps, poses, gt_stamps, gt_poses, metric=False)
            except OfflineError as exc:
                metrics['evaluation_error'] = str(exc)
            else:
                metrics.update({k: v for k, v in ev.metrics.items() if 'se3' not in k})
                if conf.figures:
                    _figures(out, ev, stamps, gt_stamps, gt_poses)
    with open(confined(out, 'metrics.json'), 'w', encoding='utf-8') as f:
        json.dump(json_safe(metrics), f, indent=2)
        f.write('\n')
    return json_safe(metrics)


def _figures(out: Path, ev: Any, stamps: np.ndarray, gt_stamps: np.ndarray,
             gt_poses: np.ndarray) -> None:
    gt_xyz = gt_poses[:, :3, 3]
    levels = gt_levels(gt_poses).altitudes
    est = ev.sim3.apply(ev.est[:, :3, 3])
    title = f'COLMAP, {len(est)} registered frames'
    figures.plot_trajectory_top(confined(out, 'trajectory_top.png'), gt_xyz,
                                storey_of(gt_xyz[:, 2], levels), est,
                                storey_of(est[:, 2], levels),
                                f'{title}: Sim(3)-aligned estimate vs ground truth',
                                est_label='estimate (registered frames)')
    gt_s = travelled(gt_xyz)
    est_s = np.interp(stamps[ev.est_index].astype(np.float64), gt_stamps.astype(np.float64),
                      gt_s)
    figures.plot_altitude(confined(out, 'altitude.png'), gt_s, gt_xyz[:, 2],
                          np.abs(pitch_of(gt_poses)) > RAMP_PITCH_RAD, est_s, est[:, 2],
                          f'{title}: altitude over distance', levels=levels.tolist(),
                          est_label='estimate (registered frames, aligned)')


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description='COLMAP (pycolmap) SfM on the frames of a bag, evaluated like '
        'semfeat-map.')
    p.add_argument('bag', type=Path, help='input rosbag2 directory or .mcap/.db3 file')
    p.add_argument('--out', type=Path, required=True, help='output directory (created)')
    p.add_argument('--topic', default=None, help='camera topic (default: '
                   '/camera/front/image_raw or its /compressed)')
    p.add_argument('--camera-config', type=Path, default=None,
                   help='calibration YAML with the base_link -> camera extrinsic')
    p.add_argument('--max-frames', type=int, default=None, help='use at most N frames')
    p.add_argument('--start', type=float, default=0.0, metavar='S',
                   help='skip the first S seconds of the recording')
    p.add_argument('--stride', type=int, default=1, help='use every N-th frame')
    p.add_argument('--max-features', type=int, default=8192, help='SIFT features per image')
    p.add_argument('--overlap', type=int, default=10, help='sequential matching overlap')
    p.add_argument('--refine-intrinsics', action='store_true',
                   help='let bundle adjustment refine focal length and distortion')
    p.add_argument('--threads', type=int, default=1,
                   help='COLMAP threads (1: deterministic; more threads give run-to-run '
                   'differences)')
    p.add_argument('--no-figures', action='store_true')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.add_argument('--verbose', action='store_true', help="COLMAP's INFO log on stderr")
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    conf = ColmapPeerConfig(topic=args.topic, camera_config=args.camera_config,
                            max_frames=args.max_frames, start_s=args.start,
                            stride=args.stride, max_features=args.max_features,
                            overlap=args.overlap,
                            refine_intrinsics=args.refine_intrinsics,
                            num_threads=max(1, args.threads), figures=not args.no_figures,
                            progress=not args.quiet, verbose=args.verbose)
    try:
        m = main(conf, ColmapPaths(args.bag, args.out))
    except (OfflineError, ValueError, OSError) as exc:
        print(f'{PROG}: error: {one_line(exc)}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    ate = m.get('ate_sim3_rmse_m')
    print(f'{PROG}: {m["registered_frames"]} of {m["frames"]} frames registered '
          f'({m["models"]} model(s)); ATE RMSE Sim(3) '
          f'{"n/a" if ate is None else f"{ate:.3f} m"}; COLMAP time '
          f'{m["wall_time_s"]["colmap_s"]:.1f} s; wrote {args.out}/metrics.json')
    return 0


if __name__ == '__main__':
    sys.exit(cli())
