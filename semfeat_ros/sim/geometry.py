"""Rigid transforms and the camera pose convention of the simulator.

Frames (REP-103 / REP-105):

* ``map``: z up, metres; x east, y north (ENU).
* ``base_link``: the vehicle's rear-axle centre at road-surface height; x forward, y left, z up.
  ``/ground_truth/pose`` is ``T_map_base`` (the pose of base_link in map).
* ``camera_front_optical``: z forward, x right, y down.

Camera pose convention: ``T_map_cam = T_map_base @ T_base_cam`` where ``T_base_cam`` maps points
from the optical frame into base_link (the extrinsic of ``config/camera_front.yaml``). A 4x4
``T_a_b`` maps homogeneous points expressed in frame ``b`` into frame ``a``.
"""
from __future__ import annotations

import numpy as np

from semfeat_ros.sim.errors import ShapeError

__all__ = [
    'camera_pose', 'check_transform', 'invert_transform', 'make_transform', 'transform_points',
]


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation (m)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (no general matrix inverse)."""
    T = check_transform(T, 'T')
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def check_transform(T: np.ndarray, name: str) -> np.ndarray:
    """Validate a 4x4 rigid transform and return it as float64."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ShapeError(f'{name}: expected a 4x4 transform, got shape {arr.shape}')
    if not np.isfinite(arr).all():
        raise ShapeError(f'{name}: transform contains NaN or inf')
    return arr


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points (m)."""
    return points @ T[:3, :3].T + T[:3, 3]


def camera_pose(T_map_base: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """Camera pose ``T_map_cam = T_map_base @ T_base_cam`` (optical frame in map)."""
    return check_transform(T_map_base, 'T_map_base') @ check_transform(T_base_cam, 'T_base_cam')
