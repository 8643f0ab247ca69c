"""Fisheye (Kannala-Brandt / equidistant) and pinhole camera models, calibration loading."""
from __future__ import annotations

from semfeat_ros.camera.calibration import Extrinsic, camera_from_dict, load_camera_yaml
from semfeat_ros.camera.errors import CameraModelError, OutsideImageCircleError
from semfeat_ros.camera.models import CameraModel, FisheyeCamera, PinholeCamera

__all__ = [
    'CameraModel', 'CameraModelError', 'Extrinsic', 'FisheyeCamera', 'OutsideImageCircleError',
    'PinholeCamera', 'camera_from_dict', 'load_camera_yaml',
]
