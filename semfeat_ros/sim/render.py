"""Fisheye renderer of a :class:`~semfeat_ros.sim.world.World` and the camera sensor model.

:class:`Renderer` casts one exact ray per pixel centre through the project's camera model
(``camera.unproject``) and returns linear radiance, class labels, range (m along the ray) and
instance ids. :class:`SensorModel` turns radiance into an 8-bit image: auto-exposure with lag and
per-frame jitter, a little optical blur, vignetting, shot + read noise, tone curve and gamma.

Outputs outside the lens's image circle: RGB 0, label 255 (ignore), depth NaN, instance 0.
Sky: label ``sky``, depth +inf, instance 0.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from semfeat_ros.camera import CameraModel, FisheyeCamera
from semfeat_ros.sim import materials as mt
from semfeat_ros.sim.errors import SimConfigError
from semfeat_ros.sim.groundtruth import pixel_bearings
from semfeat_ros.sim.primitives import concat_boxes, concat_ellipsoids
from semfeat_ros.sim.raycast import SUB, SceneArrays, make_layout, trace
from semfeat_ros.sim.shade import PlaneTable, shade
from semfeat_ros.sim.world import World


@dataclass
class Frame:
    """One rendered frame (H, W images)."""

    radiance: np.ndarray  # (H, W, 3) float32 linear
    label: np.ndarray  # (H, W) uint8
    depth: np.ndarray  # (H, W) float32 range along the ray (m)
    instance: np.ndarray  # (H, W) int32
    T_map_cam: np.ndarray  # (4, 4)
    time_s: float


_BASE_EXPOSURE = 0.3  # exposure at unit sensor gain (about a sunlit deck)
_LUT_SCALE = 2048.0  # LUT entries per unit of exposed linear signal


def _tone_lut() -> np.ndarray:
    """8-bit tone curve: extended Reinhard (white point 2.5) then gamma 1/2.2."""
    x = (np.arange(int(_LUT_SCALE * 2.5) + 1) + 0.5) / _LUT_SCALE
    y = x * (1.0 + x / 6.25) / (1.0 + x)
    y = np.power(np.minimum(y, 1.0), 1.0 / 2.2)
    return (y * 255.0 + 0.5).astype(np.uint8)


_TONE_LUT = _tone_lut()


def _rotate(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (N, 3) rotated by ``R`` (explicit: numpy's (N, 3) @ (3, 3) is slow)."""
    out = np.empty(v.shape, np.float32)
    for k in range(3):
        out[:, k] = v[:, 0] * R[k, 0] + v[:, 1] * R[k, 1] + v[:, 2] * R[k, 2]
    return out


class Renderer:
    """Ray-casting renderer of one world through one camera model.

    The image is always cut into two halves (left, right) rendered independently, in
    ``workers`` threads (numpy releases the GIL in its loops); the result does not depend on
    ``workers``.
    """

    def __init__(self, world: World, camera: CameraModel, workers: int = 2) -> None:
        self.world = world
        self.camera = camera
        bearings = pixel_bearings(camera)
        self.valid = np.isfinite(bearings[..., 0])
        if not self.valid.any():
            raise SimConfigError('camera has no pixel inside its image circle')
        rays = np.nan_to_num(bearings)
        split = max(SUB, (camera.width // 2) // SUB * SUB)
        left = np.zeros_like(self.valid)
        left[:, :split] = True
        self.parts = []
        for mask in (left, ~left):
            part = self.valid & mask
            if part.any():
                lay = make_layout(rays, part)
                real = np.flatnonzero(lay.slot_real)
                self.parts.append((lay, real, lay.slot_pixel[real]))
        self.pixel_angle = 1.0 / max(camera.fx, camera.fy)
        self._static_scene = SceneArrays(world.boxes, world.ellipsoids, world.cylinders,
                                         world.planes)
        self._planes = PlaneTable(self._static_scene)
        self.workers = max(1, int(workers))
        self._pool: ThreadPoolExecutor | None = None

    def close(self) -> None:
        """Stop the worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __del__(self) -> None:
        self.close()

    def scene_at(self, time_s: float) -> SceneArrays:
        """Static primitives plus the agents at ``time_s`` (s)."""
        if not self.world.agents:
            return self._static_scene
        dyn_b, dyn_e = self.world.dynamic_primitives(time_s)
        w = self.world
        return SceneArrays(concat_boxes(w.boxes, dyn_b), concat_ellipsoids(w.ellipsoids, dyn_e),
                           w.cylinders, w.planes)

    def _render_part(self, part, R: np.ndarray, origin: np.ndarray, scene: SceneArrays,
                     planes: PlaneTable, out: tuple[np.ndarray, ...]) -> None:
        lay, real, pix = part
        dirs = _rotate(lay.bearings, R)
        axes = (_rotate(lay.blocks.axis, R), _rotate(lay.tiles.axis, R),
                _rotate(lay.subs.axis, R))
        hits = trace(scene, lay, dirs, origin, axes)
        sh = shade(self.world, scene, planes, hits, dirs, origin, self.pixel_angle)
        radiance, label, depth, instance = out
        radiance[pix] = sh.radiance[real]
        label[pix] = sh.label[real]
        depth[pix] = hits.t[real]
        instance[pix] = sh.instance[real]

    def render(self, T_map_cam: np.ndarray, time_s: float = 0.0) -> Frame:
        """Render the view of camera pose ``T_map_cam`` (optical frame -> map) at ``time_s``."""
        T = np.asarray(T_map_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise SimConfigError(f'T_map_cam must be a finite 4x4 matrix, got {T.shape}')
        R = T[:3, :3].astype(np.float32)
        origin = T[:3, 3]
        scene = self.scene_at(time_s)
        planes = self._planes if scene is self._static_scene else PlaneTable(scene)
        h, w = self.camera.height, self.camera.width
        out = (np.zeros((h * w, 3), np.float32), np.full(h * w, mt.IGNORE, np.uint8),
               np.full(h * w, np.nan, np.float32), np.zeros(h * w, np.int32))
        if self.workers > 1 and len(self.parts) > 1:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=self.workers,
                                                thread_name_prefix='semfeat-render')
            futures = [self._pool.submit(self._render_part, part, R, origin, scene, planes, out)
                       for part in self.parts]
            for f in futures:
                f.result()
        else:
            for part in self.parts:
                self._render_part(part, R, origin, scene, planes, out)
        radiance, label, depth, instance = out
        return Frame(radiance.reshape(h, w, 3), label.reshape(h, w), depth.reshape(h, w),
                     instance.reshape(h, w), T, float(time_s))


@dataclass
class SensorModel:
    """Auto-exposure, optics and noise of the camera (deterministic per seed and frame index).

    Attributes:
        key: target mean (geometric) exposure of the scene (linear).
        ae_speed: fraction of the log-exposure error corrected per frame (auto-exposure lag).
        ae_jitter: std of a per-frame log2 exposure jitter (EV).
        exposure_range: min/max exposure (linear gain), the indoor limit keeps dark scenes dark.
        read_noise, shot_noise: noise std at unit gain (linear units); the gain is the
            exposure relative to a sunlit scene, so dark scenes get noisier.
        vignetting: relative brightness loss at the rim of the image circle.
        blur_sigma: optical blur (px).
    """

    key: float = 0.2
    ae_speed: float = 0.35
    ae_jitter: float = 0.06
    exposure_range: tuple[float, float] = (0.12, 1.4)
    read_noise: float = 0.0025
    shot_noise: float = 0.010
    vignetting: float = 0.45
    blur_sigma: float = 0.55
    seed: int = 0

    def __post_init__(self) -> None:
        self._log_exposure: float | None = None
        self._vignette: np.ndarray | None = None

    def reset(self) -> None:
        """Forget the auto-exposure state (next frame starts converged)."""
        self._log_exposure = None

    def _vignette_for(self, camera: CameraModel, valid: np.ndarray) -> np.ndarray:
        if self._vignette is None or self._vignette.shape != valid.shape:
            rays = pixel_bearings(camera)
            theta = np.arccos(np.clip(np.nan_to_num(rays[..., 2], nan=1.0), -1.0, 1.0))
            tmax = camera.theta_max if isinstance(camera, FisheyeCamera) else float(theta.max())
            v = 1.0 - self.vignetting * (theta / max(tmax, 1e-6)) ** 3
            self._vignette = np.where(valid, v, 0.0).astype(np.float32)
        return self._vignette

    def metered_exposure(self, radiance: np.ndarray, valid: np.ndarray) -> float:
        """The exposure that maps the frame's geometric-mean luminance to ``key``."""
        idx = np.flatnonzero(valid.ravel())[::7]  # a subsample, like a real AE's coarse grid
        rgb = radiance.reshape(-1, 3)[idx]
        lum = 0.2126 * rgb[:, 0] + 0.7152 * rgb[:, 1] + 0.0722 * rgb[:, 2]
        geo = float(np.exp(np.mean(np.log(lum + 1e-3))))
        lo, hi = self.exposure_range
        return float(np.clip(self.key / geo, lo, hi))

    def expose(self, frame: Frame, camera: CameraModel, frame_index: int,
               valid: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """8-bit RGB image (H, W, 3) and the exposure used (linear gain) for a frame."""
        valid = frame.label != mt.IGNORE if valid is None else valid
        target = np.log(self.metered_exposure(frame.radiance, valid))
        rng = np.random.default_rng([self.seed, frame_index, 0xE7])
        if self._log_exposure is None:
            log_e = target
        else:
            log_e = self._log_exposure + self.ae_speed * (target - self._log_exposure)
        self._log_exposure = log_e
        exposure = float(np.exp(log_e + rng.normal(0.0, self.ae_jitter) * np.log(2.0)))
        img = frame.radiance * np.float32(exposure)
        if self.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
        img *= self._vignette_for(camera, valid)[..., None]
        gain = exposure / _BASE_EXPOSURE
        sigma = np.sqrt(np.maximum(img, 0.0) * np.float32(self.shot_noise ** 2 * gain)
                        + np.float32((self.read_noise * gain) ** 2))
        img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
        # tone curve (extended Reinhard, white point 2.5) and sRGB-like gamma through a LUT
        code = np.clip(img * np.float32(_LUT_SCALE), 0, len(_TONE_LUT) - 1).astype(np.int32)
        out = _TONE_LUT[code]
        out[~valid] = 0
        return out, exposure

