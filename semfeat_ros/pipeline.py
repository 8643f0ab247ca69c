"""Glue between the stages that the nodes and the offline tools share (no rclpy)."""
from __future__ import annotations

import hashlib

import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.matching.sequential import FrameFeatures


def camera_id(camera: CameraModel, frame_id: str = '') -> str:
    """Identity of a camera (frame, size, intrinsics): a change restarts tracking."""
    desc = (f'{frame_id}|{camera.distortion_model}|{camera.width}x{camera.height}|'
            f'{camera.K.round(6).tolist()}|{camera.D.round(9).tolist()}')
    return hashlib.sha1(desc.encode()).hexdigest()[:12]


def frame_features(stamp_ns: int, keypoints: np.ndarray, descriptors: np.ndarray,
                   labels: np.ndarray, scores: np.ndarray, camera: CameraModel,
                   frame_id: str = '') -> FrameFeatures:
    """A matcher input with unit bearings (N, 3) from ``camera``; keypoints without a bearing
    (outside the image circle, non-finite) and rows with non-finite descriptors are dropped.
    Binary (uint8) descriptors keep their type."""
    kp = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    bearings = camera.unproject(kp, check=False)
    desc = np.asarray(descriptors)
    if desc.dtype != np.uint8:
        desc = desc.astype(np.float32, copy=False)
    ok = np.isfinite(bearings).all(axis=1)
    if desc.dtype != np.uint8:
        ok &= np.isfinite(desc.reshape(len(desc), -1)).all(axis=1)
    return FrameFeatures(
        stamp_ns=int(stamp_ns), keypoints=kp[ok].astype(np.float32),
        descriptors=desc[ok],
        labels=np.asarray(labels, dtype=np.uint8)[ok],
        scores=np.asarray(scores, dtype=np.float32)[ok], bearings=bearings[ok],
        camera_id=camera_id(camera, frame_id), image_width=int(camera.width),
        image_height=int(camera.height))
