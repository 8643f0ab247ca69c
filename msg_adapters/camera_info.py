"""``sensor_msgs/CameraInfo`` <-> camera models of :mod:`semfeat_ros.camera`.

Distortion models: ``equidistant`` (also accepted: ``fisheye``, ``kannala_brandt``; D = k1..k4,
OpenCV ``cv2.fisheye``) -> :class:`FisheyeCamera`; ``plumb_bob`` (D = k1 k2 p1 p2 k3) and
``rational_polynomial`` (D = k1 k2 p1 p2 k3 k4 k5 k6) -> :class:`PinholeCamera`. An empty
``distortion_model`` is accepted only with an all-zero D (a pinhole without distortion).

Validation (all :class:`~msg_adapters.errors.CameraInfoError`): width, height > 0; K has 9
finite values (NaN / inf -> :class:`~msg_adapters.errors.NonFiniteCameraInfoError`), fx, fy > 0
(an uncalibrated driver publishes K = 0), no skew (``K[0,1] == 0``, ``K[1,0] == 0``),
``K[2] == [0, 0, 1]``; the principal point lies inside the image; D has the model's length
(extra trailing zeros tolerated, an empty D means no distortion for the pinhole models) and is
finite; the lens model is monotonic up to ``fov_deg / 2`` (fisheye).

Binning and ROI (choice: **applied**, as ``image_geometry`` does). In ROS, ``width``, ``height``,
K and D describe the full-resolution calibration; ``binning_x/y`` (0 = 1 = none) and ``roi``
(all zero = full image) describe the image actually published. The returned model is the one
of the published image: size ``roi.width // binning_x`` x ``roi.height // binning_y`` and
``fx' = fx / bx``, ``cx' = (cx - roi.x_offset + 0.5) / bx - 0.5`` (pixel-centre exact; this
differs from ``image_geometry``'s ``(cx - x_offset) / bx`` by ``(bx - 1) / (2 bx)`` px). A ROI
that does not fit in the calibrated image, a binned size of 0 or a principal point outside the
result is rejected. ``apply_binning_roi=False`` rejects any binning / ROI instead. ``R`` and
``P`` (rectification) do not affect the raw image's model and are not used.

The lens field of view is not part of CameraInfo: pass ``fov_deg`` (full cone, deg).
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from msg_adapters._flavour import construct, float64_seq, resolve_class, sibling_class
from msg_adapters.errors import (
    CameraInfoError,
    ImageSizeError,
    NonFiniteCameraInfoError,
    UnsupportedDistortionError,
)
from msg_adapters.stamp import make_header
from semfeat_ros.camera.errors import CameraModelError
from semfeat_ros.camera.models import CameraModel, FisheyeCamera, PinholeCamera

CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'
ROI_TYPE = 'sensor_msgs/msg/RegionOfInterest'

_MODEL_ALIASES = {
    'equidistant': 'equidistant', 'fisheye': 'equidistant', 'kannala_brandt': 'equidistant',
    'plumb_bob': 'plumb_bob', 'rational_polynomial': 'rational_polynomial',
}
_N_COEFFS = {'equidistant': 4, 'plumb_bob': 5, 'rational_polynomial': 8}


def _finite(values: np.ndarray, field: str) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise NonFiniteCameraInfoError(
            f'CameraInfo.{field}: expected finite values, got {values[bad].tolist()} at '
            f'index {bad.tolist()}')


def _normalise_distortion(name: str, d: np.ndarray) -> tuple[str, np.ndarray]:
    key = name.strip().lower()
    if key == '':
        if np.any(d != 0.0):
            raise UnsupportedDistortionError(
                f'CameraInfo.distortion_model is empty but D = {d.tolist()} is not zero')
        return 'plumb_bob', np.zeros(5)
    kind = _MODEL_ALIASES.get(key)
    if kind is None:
        raise UnsupportedDistortionError(
            f'CameraInfo.distortion_model: unsupported {name!r}; expected equidistant, '
            f'plumb_bob or rational_polynomial')
    n = _N_COEFFS[kind]
    if kind != 'equidistant' and d.size == 0:
        return kind, np.zeros(n)
    if d.size < n or np.any(d[n:] != 0.0):
        hint = ''
        if kind == 'plumb_bob' and d.size == 4:
            hint = (' (a 4-coefficient D labelled plumb_bob is often an OpenCV fisheye k1..k4 '
                    "calibration: pass distortion_model='equidistant' if so)")
        raise CameraInfoError(
            f'CameraInfo.d: {kind} needs {n} coefficients, got {d.size}: {d.tolist()}{hint}')
    return kind, d[:n]


def camera_info_to_model(msg: Any, fov_deg: float = 190.0, *,
                         distortion_model: str | None = None,
                         apply_binning_roi: bool = True) -> CameraModel:
    """The camera model of a ``sensor_msgs/CameraInfo`` (rclpy or rosbags).

    ``fov_deg`` (deg, full cone) bounds the fisheye model's valid region. ``distortion_model``
    overrides the message's field (for mislabelled calibrations). See the module docstring for
    the checks and the binning / ROI handling.
    """
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise CameraInfoError(
            f'CameraInfo.width/height: expected > 0, got {width}x{height} (uncalibrated?)')
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9:
        raise CameraInfoError(f'CameraInfo.k: expected 9 values, got {k.size}')
    _finite(k, 'k')
    d = np.asarray(msg.d, dtype=np.float64).reshape(-1)
    _finite(d, 'd')
    name = str(msg.distortion_model) if distortion_model is None else str(distortion_model)
    kind, d = _normalise_distortion(name, d)
    fx, fy, cx, cy = float(k[0]), float(k[4]), float(k[2]), float(k[5])
    if fx <= 0.0 or fy <= 0.0:
        raise CameraInfoError(
            f'CameraInfo.k: focal lengths must be > 0 px, got fx={fx} fy={fy} (uncalibrated '
            f'camera?)')
    if abs(k[1]) > 1e-9 * fx or abs(k[3]) > 1e-9 * fy:
        raise CameraInfoError(
            f'CameraInfo.k: expected K[0,1] = K[1,0] = 0 (no skew), got {k[1]} and {k[3]}')
    if not np.allclose(k[6:], [0.0, 0.0, 1.0], rtol=0.0, atol=1e-12):
        raise CameraInfoError(f'CameraInfo.k: expected last row [0, 0, 1], got {k[6:].tolist()}')
    if not (0.0 <= cx < width and 0.0 <= cy < height):
        raise CameraInfoError(
            f'CameraInfo.k: principal point ({cx}, {cy}) px lies outside the {width}x{height} '
            f'image')

    bx, by = max(1, int(msg.binning_x)), max(1, int(msg.binning_y))
    roi = msg.roi
    x0, y0 = int(roi.x_offset), int(roi.y_offset)
    rw, rh = int(roi.width), int(roi.height)
    full_roi = x0 == 0 and y0 == 0 and rw == 0 and rh == 0
    if not apply_binning_roi and (bx != 1 or by != 1 or not full_roi):
        raise CameraInfoError(
            f'CameraInfo: binning {bx}x{by} / roi (x={x0}, y={y0}, {rw}x{rh}) given but '
            f'apply_binning_roi=False')
    if full_roi:
        rw, rh = width, height
    elif rw <= 0 or rh <= 0 or x0 + rw > width or y0 + rh > height:
        raise CameraInfoError(
            f'CameraInfo.roi: (x_offset={x0}, y_offset={y0}, width={rw}, height={rh}) does not '
            f'fit in the calibrated {width}x{height} image')
    out_w, out_h = rw // bx, rh // by
    if out_w <= 0 or out_h <= 0:
        raise CameraInfoError(
            f'CameraInfo.binning: {bx}x{by} binning of a {rw}x{rh} image leaves {out_w}x{out_h}')
    fx_b, fy_b = fx / bx, fy / by
    cx_b = (cx - x0 + 0.5) / bx - 0.5
    cy_b = (cy - y0 + 0.5) / by - 0.5
    try:
        if kind == 'equidistant':
            return FisheyeCamera(out_w, out_h, fx_b, fy_b, cx_b, cy_b,
                                 k=tuple(float(x) for x in d), fov_deg=float(fov_deg))
        return PinholeCamera(out_w, out_h, fx_b, fy_b, cx_b, cy_b,
                             d=tuple(float(x) for x in d), model=kind)
    except CameraModelError as exc:
        raise CameraInfoError(
            f'CameraInfo ({kind}, {out_w}x{out_h} after binning {bx}x{by} / roi, '
            f'fov_deg={fov_deg}): {exc}') from exc


def model_to_camera_info(model: CameraModel, *, stamp_ns: int, frame_id: str, msg_cls: Any,
                         typestore: Any | None = None) -> Any:
    """A ``sensor_msgs/CameraInfo`` of the flavour of ``msg_cls`` for a camera model.

    Fills width, height, distortion_model, D, K; R = identity, P = [K | 0]; no binning, full ROI.
    """
    cls = resolve_class(msg_cls, CAMERA_INFO_TYPE, typestore)
    roi_cls = sibling_class(cls, ROI_TYPE, typestore)
    K = np.asarray(model.K, dtype=np.float64)
    P = np.hstack([K, np.zeros((3, 1))])
    roi = construct(roi_cls, x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return construct(
        cls, header=make_header(stamp_ns, frame_id, cls, typestore=typestore),
        height=int(model.height), width=int(model.width),
        distortion_model=str(model.distortion_model), d=float64_seq(cls, model.D),
        k=K.reshape(9).copy(), r=np.eye(3).reshape(9), p=P.reshape(12).copy(),
        binning_x=0, binning_y=0, roi=roi)


def _matrix(calib: Mapping[str, Any], key: str, size: int | None,
            required: bool = True) -> np.ndarray | None:
    entry = calib.get(key)
    if entry is None:
        if required:
            raise CameraInfoError(f'calibration: missing key {key!r}')
        return None
    data = entry.get('data') if isinstance(entry, Mapping) else entry
    try:
        arr = np.asarray(data, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise CameraInfoError(f'calibration: {key}.data is not a list of numbers') from exc
    if size is not None and arr.size != size:
        raise CameraInfoError(f'calibration: {key}.data needs {size} values, got {arr.size}')
    return arr


def camera_info_from_calibration(calib: Mapping[str, Any], *, msg_cls: Any, stamp_ns: int = 0,
                                 frame_id: str | None = None,
                                 distortion_model: str | None = None,
                                 typestore: Any | None = None) -> Any:
    """A ``CameraInfo`` from a ``camera_calibration`` / ``camera_info_manager`` YAML mapping.

    Keys: ``image_width``, ``image_height``, ``camera_matrix``, ``distortion_model``,
    ``distortion_coefficients``, optional ``rectification_matrix``, ``projection_matrix`` and
    ``frame_id`` (used when ``frame_id`` is None). ``distortion_model`` overrides the file's.
    No validation of the values beyond their count: use :func:`camera_info_to_model`.
    """
    try:
        width, height = int(calib['image_width']), int(calib['image_height'])
    except (KeyError, TypeError, ValueError) as exc:
        raise CameraInfoError(f'calibration: image_width / image_height missing or not integers '
                              f'({exc})') from exc
    k = _matrix(calib, 'camera_matrix', 9)
    d = _matrix(calib, 'distortion_coefficients', None)
    r = _matrix(calib, 'rectification_matrix', 9, required=False)
    p = _matrix(calib, 'projection_matrix', 12, required=False)
    if p is None:
        p = np.hstack([k.reshape(3, 3), np.zeros((3, 1))]).reshape(12)
    model = distortion_model if distortion_model is not None else calib.get('distortion_model')
    if model is None:
        raise CameraInfoError("calibration: missing key 'distortion_model'")
    frame = frame_id if frame_id is not None else str(calib.get('frame_id', ''))
    cls = resolve_class(msg_cls, CAMERA_INFO_TYPE, typestore)
    roi = construct(sibling_class(cls, ROI_TYPE, typestore), x_offset=0, y_offset=0, height=0,
                    width=0, do_rectify=False)
    return construct(
        cls, header=make_header(stamp_ns, frame, cls, typestore=typestore), height=height,
        width=width, distortion_model=str(model), d=float64_seq(cls, d), k=k,
        r=np.eye(3).reshape(9) if r is None else r, p=p, binning_x=0, binning_y=0, roi=roi)


def load_camera_info_yaml(path: str | Path, *, msg_cls: Any, stamp_ns: int = 0,
                          frame_id: str | None = None, distortion_model: str | None = None,
                          typestore: Any | None = None) -> Any:
    """:func:`camera_info_from_calibration` of a YAML file (read with ``yaml.safe_load``)."""
    text = Path(path).read_text(encoding='utf-8')
    try:
        calib = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CameraInfoError(f'{path}: not valid YAML ({exc})') from exc
    if not isinstance(calib, Mapping):
        raise CameraInfoError(f'{path}: expected a YAML mapping, got {type(calib).__name__}')
    return camera_info_from_calibration(calib, msg_cls=msg_cls, stamp_ns=stamp_ns,
                                        frame_id=frame_id, distortion_model=distortion_model,
                                        typestore=typestore)


def check_image_size(model: CameraModel, width: int, height: int) -> None:
    """Raise :class:`ImageSizeError` unless an image of ``width x height`` px fits ``model``."""
    if (int(width), int(height)) != (int(model.width), int(model.height)):
        raise ImageSizeError(
            f'image is {width}x{height} px but the CameraInfo (after binning / roi) describes '
            f'{model.width}x{model.height} px')
