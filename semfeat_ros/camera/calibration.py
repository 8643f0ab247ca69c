"""Load a camera calibration YAML (CameraInfo layout, as camera_calibration writes) + extrinsic."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from semfeat_ros.camera.errors import CameraModelError
from semfeat_ros.camera.models import CameraModel, FisheyeCamera, PinholeCamera
from semfeat_ros.rotations import rpy_to_matrix

# Optical frame (z forward, x right, y down) expressed in the camera body frame (x forward, y left,
# z up): the columns are the optical axes.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class Extrinsic:
    """Pose of ``camera_front_optical`` in ``base_link``.

    ``translation`` in m, ``rpy`` (rad) of the camera body frame (x forward) in base_link; a
    positive pitch tilts the camera down.
    """

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def T_base_cam(self) -> np.ndarray:  # noqa: N802
        """4x4 transform mapping optical-frame points (m) into base_link."""
        T = np.eye(4)
        T[:3, :3] = rpy_to_matrix(*self.rpy) @ R_BODY_OPTICAL
        T[:3, 3] = self.translation
        return T

    @property
    def height(self) -> float:
        """Mounting height of the camera above the base_link origin (m)."""
        return float(self.translation[2])


def _matrix(node: object, rows: int, cols: int, name: str) -> np.ndarray:
    data = node.get('data') if isinstance(node, dict) else node
    arr = np.asarray(data, dtype=np.float64).ravel()
    if arr.size != rows * cols:
        raise CameraModelError(f'{name}: expected {rows * cols} values, got {arr.size}')
    return arr.reshape(rows, cols)


def camera_from_dict(data: dict, *, fov_deg: float | None = None,
                     distortion_model: str | None = None) -> CameraModel:
    """Build a camera model from a parsed calibration YAML.

    ``distortion_model`` overrides the file's label (some tools write ``plumb_bob`` for fisheye
    k1..k4 coefficients).
    """
    try:
        width, height = int(data['image_width']), int(data['image_height'])
        K = _matrix(data['camera_matrix'], 3, 3, 'camera_matrix')
        dist = np.asarray(
            (data.get('distortion_coefficients') or {}).get('data', []), dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise CameraModelError(f'malformed calibration: {exc}') from exc
    model = distortion_model or str(data.get('distortion_model', 'plumb_bob'))
    fov = float(fov_deg if fov_deg is not None else data.get('fov_deg', 190.0))
    common = dict(width=width, height=height, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    if model in ('equidistant', 'fisheye', 'kannala_brandt'):
        if dist.size != 4:
            raise CameraModelError(f'equidistant model needs 4 coefficients, got {dist.size}')
        return FisheyeCamera(**common, k=tuple(dist), fov_deg=fov)
    if model in ('plumb_bob', 'rational_polynomial'):
        return PinholeCamera(**common, d=tuple(dist), model=model)
    raise CameraModelError(f'unsupported distortion_model {model!r}')


def load_camera_yaml(path: str | Path | None = None, *, fov_deg: float | None = None,
                     distortion_model: str | None = None) -> tuple[CameraModel, Extrinsic]:
    """Load a calibration YAML (default: the shipped ``config/camera_front.yaml``).

    Returns the camera model and the base_link -> camera extrinsic (identity if the file has none).
    """
    if path is None:
        from semfeat_ros.paths import config_path
        path = config_path('camera_front.yaml')
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f'camera calibration not found: {p}')
    with open(p, encoding='utf-8') as f:
        data = yaml.safe_load(f)
    if not isinstance(data, dict):
        raise CameraModelError(f'{p}: expected a mapping')
    camera = camera_from_dict(data, fov_deg=fov_deg, distortion_model=distortion_model)
    ext = data.get('extrinsic') or {}
    try:
        extrinsic = Extrinsic(
            translation=tuple(float(x) for x in ext.get('translation', (0.0, 0.0, 0.0))),
            rpy=tuple(float(x) for x in ext.get('rpy', (0.0, 0.0, 0.0))))
    except (TypeError, ValueError) as exc:
        raise CameraModelError(f'{p}: malformed extrinsic: {exc}') from exc
    if len(extrinsic.translation) != 3 or len(extrinsic.rpy) != 3:
        raise CameraModelError(f'{p}: extrinsic translation and rpy need 3 values each')
    return camera, extrinsic
