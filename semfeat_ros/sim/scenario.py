"""A ready-to-render scenario: world + drive + camera (with its extrinsic) + renderer + sensor."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
import time

import numpy as np

from semfeat_ros.camera import CameraModel, load_camera_yaml
from semfeat_ros.sim.config import GarageConfig
from semfeat_ros.sim.errors import SimConfigError
from semfeat_ros.sim.geometry import camera_pose
from semfeat_ros.sim.render import Renderer, SensorModel
from semfeat_ros.sim.trajectory import Trajectory
from semfeat_ros.sim.world import World, build_world


@dataclass
class Scenario:
    """Everything needed to render the long drive of one seed at one image size."""

    seed: int
    world: World
    trajectory: Trajectory
    camera: CameraModel
    camera_full: CameraModel
    T_base_cam: np.ndarray
    renderer: Renderer
    sensor: SensorModel

    @classmethod
    def create(cls, seed: int = 0, size: tuple[int, int] = (640, 512),
               config: GarageConfig | None = None,
               camera_yaml: str | Path | None = None) -> Scenario:
        """Build the world of ``seed`` and a renderer at ``size = (width, height)`` px.

        The camera is ``load_camera_yaml(camera_yaml)[0].scaled(width, height)`` (default: the
        shipped ``config/camera_front.yaml``) with that file's base_link -> camera extrinsic.
        """
        w, h = (int(v) for v in size)
        if w < 16 or h < 16 or w > 4096 or h > 4096:
            raise SimConfigError(f'image size must be within 16..4096 px, got {w}x{h}')
        cam_full, extrinsic = load_camera_yaml(camera_yaml)
        camera = cam_full.scaled(w, h)
        world = build_world(seed, config)
        traj = Trajectory(world.layout)
        return cls(seed=int(seed), world=world, trajectory=traj, camera=camera,
                   camera_full=cam_full, T_base_cam=extrinsic.T_base_cam,
                   renderer=Renderer(world, camera), sensor=SensorModel(seed=int(seed)))

    def base_pose(self, t: float) -> np.ndarray:
        """``T_map_base`` (4x4) at time ``t`` (s)."""
        return self.trajectory.sample(t).T_map_base

    def camera_pose(self, t: float) -> np.ndarray:
        """``T_map_cam = T_map_base @ T_base_cam`` (4x4) at time ``t`` (s)."""
        return camera_pose(self.base_pose(t), self.T_base_cam)


def benchmark(width: int = 640, height: int = 512, n_frames: int = 10, seed: int = 0,
              sensor: bool = True, workers: int = 2) -> dict[str, float]:
    """Render ``n_frames`` frames along the long drive with ``workers`` render threads and
    return the speed (``fps``, ``ms_per_frame``) measured in this process."""
    sc = Scenario.create(seed=seed, size=(width, height))
    sc.renderer.workers = max(1, int(workers))
    times = np.linspace(0.0, sc.trajectory.duration * 0.95, n_frames)
    sc.renderer.render(sc.camera_pose(times[0]), times[0])  # warm-up (caches, threads)
    t0 = time.perf_counter()
    for k, t in enumerate(times):
        frame = sc.renderer.render(sc.camera_pose(t), t)
        if sensor:
            sc.sensor.expose(frame, sc.camera, k)
    dt = time.perf_counter() - t0
    sc.renderer.close()
    return {'fps': n_frames / dt, 'ms_per_frame': 1000.0 * dt / n_frames,
            'width': float(width), 'height': float(height), 'frames': float(n_frames)}
