"""Training shards: rendered frames with labels, depth, poses, intrinsics and correspondences.

A shard is one ``.npz`` file (written with ``numpy.savez_compressed``, loadable without pickle)
holding ``N`` frames of one world (one seed) and ``P`` frame pairs:

* ``rgb`` (N, H, W, 3) uint8: rendered image (after exposure, noise, vignetting);
* ``label`` (N, H, W) uint8: class id 0..18, 255 outside the image circle;
* ``depth`` (N, H, W) float16 (or float32): range along the ray (m), inf sky, NaN outside;
* ``instance`` (N, H, W) uint16: object instance id (0 sky / outside);
* ``T_map_cam`` (N, 4, 4) float64: camera pose (optical frame -> map);
* ``T_map_base`` (N, 4, 4) float64: vehicle pose (base_link -> map);
* ``time_s`` (N,) float64: simulation time of the frame (s);
* ``frame_index`` (N,) int32: index of the frame in the shard's render order;
* ``seed`` () int64: world seed;
* ``camera`` () str: JSON camera parameters (:func:`camera_to_json`);
* ``pairs`` (P, 2) int32: frame indices (a, b) of each pair;
* ``corr_uv_a`` / ``corr_uv_b`` (P, M, 2) float32: pixel centres in ``a`` (px) and their
  occlusion-checked positions in ``b`` (px); the first ``corr_count`` rows are valid, the rest
  NaN;
* ``corr_count`` (P,) int32; ``pair_overlap`` (P,) float32: fraction of ``a``'s usable pixels
  visible in ``b``;
* ``moving_instances`` (K,) int64: instance ids of the moving agents (cars, pedestrians);
* ``format`` () str: ``semfeat_sim_shard/1``.

Correspondences exclude the moving agents (``moving_instances``: they move between the two frames;
parked cars do not and keep their correspondences) and pixels outside the image circle; use
:func:`semfeat_ros.sim.groundtruth.warp_dense` with the stored depth and poses for dense ones.
"""
from __future__ import annotations

from dataclasses import dataclass
import json
from pathlib import Path
import zipfile

import numpy as np

from semfeat_ros.camera import CameraModel, FisheyeCamera, PinholeCamera
from semfeat_ros.sim.errors import ShardError

SHARD_FORMAT = 'semfeat_sim_shard/1'

_REQUIRED = {
    'rgb': 4, 'label': 3, 'depth': 3, 'instance': 3, 'T_map_cam': 3, 'T_map_base': 3,
    'time_s': 1, 'frame_index': 1, 'seed': 0, 'camera': 0, 'pairs': 2, 'corr_uv_a': 3,
    'corr_uv_b': 3, 'corr_count': 1, 'pair_overlap': 1, 'moving_instances': 1, 'format': 0,
}


def camera_to_json(camera: CameraModel) -> str:
    """JSON string of a camera model's parameters (px, deg)."""
    data: dict[str, object] = {
        'distortion_model': camera.distortion_model, 'width': camera.width,
        'height': camera.height, 'fx': camera.fx, 'fy': camera.fy, 'cx': camera.cx,
        'cy': camera.cy, 'D': [float(x) for x in camera.D]}
    if isinstance(camera, FisheyeCamera):
        data['fov_deg'] = camera.fov_deg
    return json.dumps(data, sort_keys=True)


def camera_from_json(text: str) -> CameraModel:
    """Inverse of :func:`camera_to_json`."""
    try:
        d = json.loads(text)
        common = dict(width=int(d['width']), height=int(d['height']), fx=float(d['fx']),
                      fy=float(d['fy']), cx=float(d['cx']), cy=float(d['cy']))
        model = str(d['distortion_model'])
        coeffs = tuple(float(x) for x in d['D'])
    except (KeyError, TypeError, ValueError) as exc:
        raise ShardError(f'malformed camera JSON: {exc}') from exc
    if model == 'equidistant':
        return FisheyeCamera(**common, k=coeffs, fov_deg=float(d.get('fov_deg', 190.0)))
    if model in ('plumb_bob', 'rational_polynomial'):
        return PinholeCamera(**common, d=coeffs, model=model)
    raise ShardError(f'camera JSON: unknown distortion_model {model!r}')


def save_shard(path: str | Path, arrays: dict[str, np.ndarray]) -> Path:
    """Validate and write a shard (``.npz``); returns the path written."""
    arrays = dict(arrays)
    arrays.setdefault('format', np.array(SHARD_FORMAT))
    _validate(arrays, str(path))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + '.tmp.npz')
    np.savez_compressed(tmp, **arrays)
    tmp.replace(p)
    return p


def _validate(data: dict[str, np.ndarray], source: str) -> None:
    missing = sorted(set(_REQUIRED) - set(data))
    if missing:
        raise ShardError(f'{source}: missing arrays {missing}')
    for key, ndim in _REQUIRED.items():
        if np.ndim(data[key]) != ndim:
            raise ShardError(
                f'{source}: {key!r} must have {ndim} dimensions, got shape '
                f'{np.shape(data[key])}')
    fmt = str(data['format'])
    if fmt != SHARD_FORMAT:
        raise ShardError(f'{source}: format is {fmt!r}, expected {SHARD_FORMAT!r}')
    n, h, w, c = data['rgb'].shape
    if c != 3 or data['rgb'].dtype != np.uint8:
        raise ShardError(f'{source}: rgb must be (N, H, W, 3) uint8, got {data["rgb"].shape} '
                         f'{data["rgb"].dtype}')
    for key in ('label', 'depth', 'instance'):
        if data[key].shape != (n, h, w):
            raise ShardError(f'{source}: {key!r} must have shape {(n, h, w)}, '
                             f'got {data[key].shape}')
    for key in ('T_map_cam', 'T_map_base'):
        if data[key].shape != (n, 4, 4):
            raise ShardError(f'{source}: {key!r} must have shape {(n, 4, 4)}, '
                             f'got {data[key].shape}')
    for key in ('time_s', 'frame_index'):
        if data[key].shape != (n,):
            raise ShardError(f'{source}: {key!r} must have shape ({n},), got {data[key].shape}')
    p = data['pairs'].shape[0]
    if data['pairs'].shape != (p, 2):
        raise ShardError(f'{source}: pairs must have shape (P, 2), got {data["pairs"].shape}')
    if p and (data['pairs'].min() < 0 or data['pairs'].max() >= n):
        raise ShardError(f'{source}: pair indices must lie in 0..{n - 1}')
    m = data['corr_uv_a'].shape[1] if data['corr_uv_a'].ndim == 3 else 0
    for key in ('corr_uv_a', 'corr_uv_b'):
        if data[key].shape != (p, m, 2):
            raise ShardError(f'{source}: {key!r} must have shape {(p, m, 2)}, '
                             f'got {data[key].shape}')
    for key in ('corr_count', 'pair_overlap'):
        if data[key].shape != (p,):
            raise ShardError(f'{source}: {key!r} must have shape ({p},), got {data[key].shape}')
    cam = camera_from_json(str(data['camera']))
    if (cam.width, cam.height) != (w, h):
        raise ShardError(f'{source}: camera is {cam.width}x{cam.height} but images are {w}x{h}')


def load_shard(path: str | Path) -> dict:
    """Load and validate a shard.

    Returns a dict with every array of the table in the module docstring (numpy arrays; ``seed``
    as int, ``camera`` as the JSON string) plus ``camera_model``: the
    :class:`~semfeat_ros.camera.CameraModel` built from it.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ShardError: the file is not a readable shard of this format.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f'shard not found: {p}')
    try:
        with np.load(p, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise ShardError(f'{p}: not a readable .npz shard ({exc})') from exc
    _validate(data, str(p))
    out: dict = dict(data)
    out['seed'] = int(data['seed'])
    out['camera'] = str(data['camera'])
    out['format'] = str(data['format'])
    out['camera_model'] = camera_from_json(out['camera'])
    return out


# ------------------------------------------------------------------------------------ rendering


@dataclass(frozen=True)
class DatasetConfig:
    """How training shards are rendered.

    Attributes:
        frames: frames per seed (one shard per seed), a multiple of ``clip``.
        size: image size (width, height) px; the camera is the shipped one scaled to it.
        clip: consecutive frames per clip; clips start at random times of the drive and use a
            randomly perturbed camera rig (height, pitch, yaw, lateral offset).
        pairs: frame-index offsets within a clip that form training pairs.
        corr_per_pair: sampled correspondences stored per pair.
        randomize_world: draw the garage configuration from the seed
            (:func:`~semfeat_ros.sim.config.random_config`) instead of the default one.
        depth_dtype: ``float16`` or ``float32``.
    """

    frames: int = 64
    size: tuple[int, int] = (320, 256)
    clip: int = 4
    pairs: tuple[tuple[int, int], ...] = ((0, 1), (1, 2), (2, 3), (0, 2), (0, 3))
    corr_per_pair: int = 1024
    randomize_world: bool = True
    depth_dtype: str = 'float16'

    def __post_init__(self) -> None:
        if self.clip < 1 or self.frames < self.clip or self.frames % self.clip:
            raise ShardError(f'frames ({self.frames}) must be a positive multiple of clip '
                             f'({self.clip})')
        if any(not (0 <= a < self.clip and 0 <= b < self.clip and a != b)
               for a, b in self.pairs):
            raise ShardError(f'pairs {self.pairs} must index distinct frames of a clip of '
                             f'{self.clip}')
        if self.depth_dtype not in ('float16', 'float32'):
            raise ShardError(f'depth_dtype must be float16 or float32, got {self.depth_dtype}')
        if self.corr_per_pair < 0:
            raise ShardError(f'corr_per_pair must be >= 0, got {self.corr_per_pair}')


def _rig_perturbation(rng: np.random.Generator, T_base_cam: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """A perturbed extrinsic and a vehicle pose offset (lateral, yaw) for one clip."""
    from semfeat_ros.rotations import rpy_to_matrix
    from semfeat_ros.sim.geometry import make_transform

    d_rpy = rng.normal(0.0, [0.02, 0.05, 0.03])
    dz = rng.uniform(-0.12, 0.12)
    T_cam = T_base_cam.copy()
    # rotate the optical frame about the body axes (pre-multiply in base_link)
    T_cam[:3, :3] = rpy_to_matrix(*d_rpy) @ T_cam[:3, :3]
    T_cam[2, 3] += dz
    offset = make_transform(rpy_to_matrix(0.0, 0.0, rng.normal(0.0, 0.08)),
                            [0.0, rng.uniform(-0.7, 0.7), 0.0])
    return T_cam, offset


def render_shard(seed: int, cfg: DatasetConfig, progress: bool = False) -> dict[str, np.ndarray]:
    """Render the frames, pairs and correspondences of one seed (see the module docstring)."""
    from tqdm import tqdm

    from semfeat_ros.sim.config import GarageConfig, random_config
    from semfeat_ros.sim.groundtruth import sample_correspondences
    from semfeat_ros.sim.materials import IGNORE
    from semfeat_ros.sim.scenario import Scenario

    rng = np.random.default_rng([seed, 0xDA7A])
    gcfg = random_config(rng) if cfg.randomize_world else GarageConfig()
    sc = Scenario.create(seed=seed, size=cfg.size, config=gcfg)
    sensor = sc.sensor
    sensor.vignetting = float(rng.uniform(0.3, 0.6))
    sensor.blur_sigma = float(rng.uniform(0.4, 0.9))
    sensor.read_noise *= float(rng.uniform(0.6, 1.6))
    sensor.shot_noise *= float(rng.uniform(0.6, 1.6))
    sensor.ae_jitter = 0.2
    cam = sc.camera
    w, h = cfg.size
    n = cfg.frames
    rgb = np.zeros((n, h, w, 3), np.uint8)
    label = np.zeros((n, h, w), np.uint8)
    depth = np.zeros((n, h, w), np.dtype(cfg.depth_dtype))
    instance = np.zeros((n, h, w), np.uint16)
    T_cam_all = np.zeros((n, 4, 4))
    T_base_all = np.zeros((n, 4, 4))
    times = np.zeros(n)
    moving = np.array([a.inst for a in sc.world.agents], np.int64)
    depth32: list[np.ndarray] = []
    masks: list[np.ndarray] = []
    duration = sc.trajectory.duration
    bar = tqdm(total=n, desc=f'seed {seed}', unit='frame', disable=not progress, leave=False)
    for c0 in range(0, n, cfg.clip):
        T_cam_rig, offset = _rig_perturbation(rng, sc.T_base_cam)
        t = float(rng.uniform(0.0, max(duration - 4.0, 0.1)))
        sensor.reset()
        for k in range(c0, c0 + cfg.clip):
            T_base = sc.base_pose(t) @ offset
            T_cam = T_base @ T_cam_rig
            frame = sc.renderer.render(T_cam, t)
            img, _ = sensor.expose(frame, cam, k)
            rgb[k], label[k], instance[k] = img, frame.label, frame.instance.astype(np.uint16)
            depth[k] = frame.depth.astype(depth.dtype)
            depth32.append(frame.depth)
            masks.append((frame.label != IGNORE) & ~np.isin(frame.instance, moving))
            T_cam_all[k], T_base_all[k], times[k] = T_cam, T_base, t
            t += float(rng.uniform(0.1, 0.5))
            bar.update(1)
    bar.close()
    pairs = [(c0 + a, c0 + b) for c0 in range(0, n, cfg.clip) for a, b in cfg.pairs]
    m = cfg.corr_per_pair
    corr_a = np.full((len(pairs), m, 2), np.nan, np.float32)
    corr_b = np.full((len(pairs), m, 2), np.nan, np.float32)
    count = np.zeros(len(pairs), np.int32)
    overlap = np.zeros(len(pairs), np.float32)
    for i, (a, b) in enumerate(pairs):
        ua, ub, ov = sample_correspondences(depth32[a], depth32[b], T_cam_all[a], T_cam_all[b],
                                            cam, m, rng, mask_a=masks[a])
        corr_a[i, :len(ua)], corr_b[i, :len(ub)] = ua, ub
        count[i], overlap[i] = len(ua), ov
    return {
        'rgb': rgb, 'label': label, 'depth': depth, 'instance': instance,
        'T_map_cam': T_cam_all, 'T_map_base': T_base_all, 'time_s': times,
        'frame_index': np.arange(n, dtype=np.int32), 'seed': np.array(seed, np.int64),
        'camera': np.array(camera_to_json(cam)), 'pairs': np.array(pairs, np.int32).reshape(-1, 2),
        'corr_uv_a': corr_a, 'corr_uv_b': corr_b, 'corr_count': count, 'pair_overlap': overlap,
        'moving_instances': moving, 'format': np.array(SHARD_FORMAT),
    }


def parse_seeds(text: str) -> list[int]:
    """``'A-B'`` (inclusive), ``'A,B,C'`` or ``'A'`` -> list of seeds."""
    out: list[int] = []
    try:
        for part in str(text).split(','):
            part = part.strip()
            if '-' in part[1:]:
                a, b = part.split('-', 1) if not part.startswith('-') else (part, '')
                lo, hi = int(a), int(b)
                if hi < lo:
                    raise ValueError(f'{part}: end before start')
                out.extend(range(lo, hi + 1))
            else:
                out.append(int(part))
    except ValueError as exc:
        raise ShardError(f"seeds must look like 'A-B', 'A,B,C' or 'A', got {text!r} "
                         f'({exc})') from None
    if not out or min(out) < 0:
        raise ShardError(f'seeds must be non-negative integers, got {text!r}')
    return out


def write_dataset(out_dir: str | Path, seeds: list[int], cfg: DatasetConfig,
                  progress: bool = True) -> list[Path]:
    """Render one shard per seed into ``out_dir/shard_<seed>.npz``; returns the paths."""
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in tqdm(seeds, desc='shards', unit='seed', disable=not progress):
        data = render_shard(seed, cfg, progress=progress)
        paths.append(save_shard(out / f'shard_{seed:05d}.npz', data))
    return paths
