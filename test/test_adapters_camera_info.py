"""msg_adapters.camera_info against real calibrations and OpenCV's projection functions."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
import sensor_msgs.msg
import yaml

from msg_adapters import (
    CameraInfoError,
    ImageSizeError,
    NonFiniteCameraInfoError,
    NonFiniteError,
    UnsupportedDistortionError,
    camera_info_from_calibration,
    camera_info_to_model,
    check_image_size,
    load_camera_info_yaml,
    model_to_camera_info,
    stamp_to_ns,
)
from semfeat_ros.camera.models import FisheyeCamera, PinholeCamera

TS = get_typestore(Stores.ROS2_JAZZY)
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
FLAVOURS = {'rclpy': sensor_msgs.msg.CameraInfo, 'rosbags': TS.types[CAMERA_INFO]}
REPO = Path(__file__).resolve().parents[1]
REAL_CALIB = Path('/work/shared/data/real_fisheye_calib/ost.yaml')
FRONT_CALIB = REPO / 'config' / 'camera_front.yaml'


def cdr_round_trip(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return TS.deserialize_cdr(bytes(TS.serialize_cdr(msg, CAMERA_INFO)), CAMERA_INFO)
    return deserialize_message(serialize_message(msg), type(msg))


def cross(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return deserialize_message(bytes(TS.serialize_cdr(msg, CAMERA_INFO)),
                                   sensor_msgs.msg.CameraInfo)
    return TS.deserialize_cdr(serialize_message(msg), CAMERA_INFO)


def with_fields(msg: Any, **fields: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        for key in ('k', 'd'):
            if key in fields:
                fields[key] = np.asarray(fields[key], dtype=np.float64)
        return dataclasses.replace(msg, **fields)
    out = cdr_round_trip(msg)
    for name, value in fields.items():
        if name == 'k':
            value = np.asarray(value, dtype=np.float64)
        if name == 'd':
            value = [float(x) for x in value]
        setattr(out, name, value)
    return out


def with_roi(msg: Any, x: int, y: int, w: int, h: int) -> Any:
    out = cdr_round_trip(msg)
    out.roi.x_offset, out.roi.y_offset, out.roi.width, out.roi.height = x, y, w, h
    return out


def fisheye_points(rng: np.random.Generator, n: int, max_deg: float) -> np.ndarray:
    """Points (m) in front of the camera up to ``max_deg`` off-axis, various depths."""
    theta = np.radians(rng.uniform(0.0, max_deg, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                     np.cos(theta)], axis=1)
    return rays * rng.uniform(0.5, 30.0, (n, 1))


def cv_fisheye_project(model: FisheyeCamera, pts: np.ndarray) -> np.ndarray:
    out, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                       model.K, np.asarray(model.k, dtype=np.float64))
    return out.reshape(-1, 2)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_real_fisheye_calibration_matches_opencv(flavour: str) -> None:
    msg = load_camera_info_yaml(REAL_CALIB, msg_cls=FLAVOURS[flavour], stamp_ns=123,
                                frame_id='cam', distortion_model='equidistant')
    assert msg.distortion_model == 'equidistant'
    for received in (cdr_round_trip(msg), cross(msg)):
        model = camera_info_to_model(received, fov_deg=180.0)
        assert isinstance(model, FisheyeCamera)
        assert (model.width, model.height) == (800, 503)
        assert model.fx == pytest.approx(290.050152) and model.cy == pytest.approx(273.885669)
        assert model.k == pytest.approx((-0.030464, -0.019695, 0.002098, 0.001030))
        pts = fisheye_points(np.random.default_rng(0), 500, 85.0)
        ours, valid = model.project(pts)
        assert valid.all()
        np.testing.assert_allclose(ours, cv_fisheye_project(model, pts), atol=1e-6)
        assert stamp_to_ns(received) == 123 and received.header.frame_id == 'cam'


def test_real_calibration_mislabelled_plumb_bob_is_rejected_with_hint() -> None:
    msg = load_camera_info_yaml(REAL_CALIB, msg_cls=TS)
    assert msg.distortion_model == 'plumb_bob' and msg.d.size == 4
    with pytest.raises(CameraInfoError, match="plumb_bob needs 5 coefficients, got 4.*"
                                              "distortion_model='equidistant'"):
        camera_info_to_model(msg)
    model = camera_info_to_model(msg, distortion_model='equidistant', fov_deg=180.0)
    assert isinstance(model, FisheyeCamera)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_front_camera_calibration(flavour: str) -> None:
    calib = yaml.safe_load(FRONT_CALIB.read_text())
    msg = camera_info_from_calibration(calib, msg_cls=FLAVOURS[flavour], stamp_ns=5)
    assert msg.header.frame_id == 'camera_front_optical'
    model = camera_info_to_model(cdr_round_trip(msg), fov_deg=calib['fov_deg'])
    expected = FisheyeCamera(1920, 1536, 560.0, 560.0, 960.0, 768.0,
                             k=(0.02, -0.004, 0.0005, -0.0001), fov_deg=190.0)
    assert model == expected
    assert model.theta_max == pytest.approx(np.radians(95.0))
    pts = fisheye_points(np.random.default_rng(1), 400, 89.0)
    np.testing.assert_allclose(model.project(pts)[0], cv_fisheye_project(model, pts),
                               atol=1e-6)
    check_image_size(model, 1920, 1536)
    with pytest.raises(ImageSizeError, match='960x768'):
        check_image_size(model, 960, 768)


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('model', [
    FisheyeCamera(1920, 1536, 560.0, 561.0, 960.5, 767.25, k=(0.02, -0.004, 0.0005, -0.0001),
                  fov_deg=190.0),
    PinholeCamera(640, 480, 500.0, 502.0, 320.5, 240.25, d=(-0.2, 0.05, 0.001, -0.002, 0.01),
                  model='plumb_bob'),
    PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5,
                  d=(0.1, -0.05, 0.001, 0.0005, 0.002, 0.05, -0.01, 0.003),
                  model='rational_polynomial'),
], ids=['equidistant', 'plumb_bob', 'rational_polynomial'])
def test_model_round_trip(flavour: str, model: Any) -> None:
    msg = model_to_camera_info(model, stamp_ns=10 ** 18, frame_id='camera_front_optical',
                               msg_cls=FLAVOURS[flavour])
    assert msg.distortion_model == model.distortion_model
    np.testing.assert_array_equal(np.asarray(msg.r).reshape(3, 3), np.eye(3))
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4)[:, :3], model.K)
    for received in (cdr_round_trip(msg), cross(msg)):
        back = camera_info_to_model(received, fov_deg=getattr(model, 'fov_deg', 190.0))
        assert back == model
        assert stamp_to_ns(received) == 10 ** 18


@pytest.mark.parametrize('model', [
    PinholeCamera(640, 480, 500.0, 502.0, 320.5, 240.25, d=(-0.2, 0.05, 0.001, -0.002, 0.01),
                  model='plumb_bob'),
    PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5,
                  d=(0.1, -0.05, 0.001, 0.0005, 0.002, 0.05, -0.01, 0.003),
                  model='rational_polynomial'),
], ids=['plumb_bob', 'rational_polynomial'])
def test_pinhole_d_order_matches_opencv(model: PinholeCamera) -> None:
    msg = model_to_camera_info(model, stamp_ns=0, frame_id='c', msg_cls=TS)
    back = camera_info_to_model(cdr_round_trip(msg))
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-0.5, 0.5, (200, 2)), np.ones(200)]) * rng.uniform(
        1, 10, (200, 1))
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), back.K,
                               np.asarray(msg.d, dtype=np.float64))
    np.testing.assert_allclose(back.project(pts)[0], ref.reshape(-1, 2), atol=1e-6)


def test_cdr_byte_identical_across_flavours() -> None:
    model = FisheyeCamera(1920, 1536, 560.0, 560.0, 960.0, 768.0,
                          k=(0.02, -0.004, 0.0005, -0.0001))
    rc = model_to_camera_info(model, stamp_ns=99, frame_id='cam',
                              msg_cls=sensor_msgs.msg.CameraInfo)
    rb = model_to_camera_info(model, stamp_ns=99, frame_id='cam', msg_cls=TS)
    raw_rc, raw_rb = serialize_message(rc), bytes(TS.serialize_cdr(rb, CAMERA_INFO))
    a, b = np.frombuffer(raw_rc, np.uint8), np.frombuffer(raw_rb, np.uint8)
    assert a.shape == b.shape and np.all(b[a != b] == 0)
    assert bytes(TS.serialize_cdr(TS.deserialize_cdr(raw_rc, CAMERA_INFO), CAMERA_INFO)) == raw_rb


# ----------------------------------------------------------------------------- binning / roi

FULL = FisheyeCamera(1920, 1536, 560.0, 560.0, 960.0, 768.0, k=(0.02, -0.004, 0.0005, -0.0001))


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_binning_and_roi_are_applied(flavour: str) -> None:
    msg = model_to_camera_info(FULL, stamp_ns=0, frame_id='c', msg_cls=FLAVOURS[flavour])
    pts = fisheye_points(np.random.default_rng(3), 200, 60.0)
    full_px, _ = FULL.project(pts)
    binned = camera_info_to_model(with_fields(msg, binning_x=2, binning_y=4))
    assert (binned.width, binned.height) == (960, 384)
    np.testing.assert_allclose(binned.project(pts)[0][:, 0], (full_px[:, 0] + 0.5) / 2 - 0.5)
    np.testing.assert_allclose(binned.project(pts)[0][:, 1], (full_px[:, 1] + 0.5) / 4 - 0.5)
    cropped = camera_info_to_model(with_roi(msg, 400, 300, 1200, 1000))
    assert (cropped.width, cropped.height) == (1200, 1000)
    np.testing.assert_allclose(cropped.project(pts)[0], full_px - [400, 300], atol=1e-9)
    both = camera_info_to_model(with_roi(with_fields(msg, binning_x=2, binning_y=2),
                                         400, 300, 1200, 1000))
    assert (both.width, both.height) == (600, 500)
    np.testing.assert_allclose(both.project(pts)[0], (full_px - [400, 300] + 0.5) / 2 - 0.5,
                               atol=1e-9)
    unchanged = camera_info_to_model(with_fields(msg, binning_x=1, binning_y=0))
    assert unchanged == FULL


def test_binning_and_roi_rejections() -> None:
    msg = model_to_camera_info(FULL, stamp_ns=0, frame_id='c', msg_cls=TS)
    with pytest.raises(CameraInfoError, match='does not fit'):
        camera_info_to_model(with_roi(msg, 1000, 0, 1000, 100))
    with pytest.raises(CameraInfoError, match='does not fit'):
        camera_info_to_model(with_roi(msg, 10, 10, 0, 100))
    with pytest.raises(CameraInfoError, match='leaves 0x'):
        camera_info_to_model(with_fields(msg, binning_x=4000, binning_y=1))
    with pytest.raises(CameraInfoError, match='apply_binning_roi=False'):
        camera_info_to_model(with_fields(msg, binning_x=2), apply_binning_roi=False)
    with pytest.raises(CameraInfoError, match='apply_binning_roi=False'):
        camera_info_to_model(with_roi(msg, 0, 0, 100, 100), apply_binning_roi=False)
    with pytest.raises(CameraInfoError, match='principal point'):
        camera_info_to_model(with_roi(msg, 0, 0, 500, 500))  # crop away from the centre


# ----------------------------------------------------------------------------- bad input

K_GOOD = [560.0, 0.0, 960.0, 0.0, 560.0, 768.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_bad_camera_info_rejected(flavour: str) -> None:
    msg = model_to_camera_info(FULL, stamp_ns=0, frame_id='c', msg_cls=FLAVOURS[flavour])
    assert camera_info_to_model(msg) == FULL
    cases: list[tuple[dict[str, Any], type[Exception], str]] = [
        ({'k': [0.0] * 9}, CameraInfoError, 'focal lengths must be > 0'),
        ({'k': [560.0, 0, 960, 0, -560.0, 768, 0, 0, 1]}, CameraInfoError, 'fy=-560'),
        ({'k': [560.0, 1.5, 960, 0, 560, 768, 0, 0, 1]}, CameraInfoError, 'skew'),
        ({'k': [560.0, 0, 960, 0, 560, 768, 0, 0, 2]}, CameraInfoError, 'last row'),
        ({'k': [560.0, 0, 2000, 0, 560, 768, 0, 0, 1]}, CameraInfoError, 'principal point'),
        ({'k': [560.0, 0, 960, 0, 560, -1, 0, 0, 1]}, CameraInfoError, 'principal point'),
        ({'k': [np.nan] + K_GOOD[1:]}, NonFiniteCameraInfoError, r'CameraInfo\.k'),
        ({'k': K_GOOD[:4] + [np.inf] + K_GOOD[5:]}, NonFiniteError, 'index'),
        ({'d': [0.02, np.nan, 0.0, 0.0]}, NonFiniteCameraInfoError, r'CameraInfo\.d'),
        ({'d': [0.02, -0.004, 0.0005]}, CameraInfoError, 'equidistant needs 4'),
        ({'d': [0.02, -0.004, 0.0005, 0.0, 0.3]}, CameraInfoError, 'equidistant needs 4'),
        ({'d': [-1.0, 0.0, 0.0, 0.0]}, CameraInfoError, 'not monotonic'),
        ({'width': 0}, CameraInfoError, 'width/height'),
        ({'height': 0}, CameraInfoError, 'width/height'),
        ({'distortion_model': 'mei'}, UnsupportedDistortionError, "'mei'"),
        ({'distortion_model': ''}, UnsupportedDistortionError, 'empty'),
        ({'distortion_model': 'rational_polynomial'}, CameraInfoError, 'needs 8'),
    ]
    for fields, exc, pattern in cases:
        with pytest.raises(exc, match=pattern):
            camera_info_to_model(with_fields(msg, **fields))


def test_lenient_cases_accepted() -> None:
    msg = model_to_camera_info(FULL, stamp_ns=0, frame_id='c', msg_cls=TS)
    padded = camera_info_to_model(with_fields(msg, d=[0.02, -0.004, 0.0005, -0.0001, 0.0]))
    assert padded == FULL
    alias = camera_info_to_model(with_fields(msg, distortion_model='fisheye'))
    assert alias == FULL
    undistorted = camera_info_to_model(with_fields(msg, distortion_model='', d=[]))
    assert isinstance(undistorted, PinholeCamera) and undistorted.d == (0.0,) * 5
    no_d = camera_info_to_model(with_fields(msg, distortion_model='plumb_bob', d=[]))
    assert isinstance(no_d, PinholeCamera)
    narrower = camera_info_to_model(msg, fov_deg=120.0)
    assert narrower.theta_max == pytest.approx(np.radians(60.0))


def test_calibration_file_errors(tmp_path: Path) -> None:
    calib = yaml.safe_load(FRONT_CALIB.read_text())
    for key in ('camera_matrix', 'distortion_coefficients', 'image_width', 'distortion_model'):
        broken = {k: v for k, v in calib.items() if k != key}
        with pytest.raises(CameraInfoError, match=key.split('_')[0]):
            camera_info_from_calibration(broken, msg_cls=TS)
    short = dict(calib, camera_matrix={'rows': 3, 'cols': 3, 'data': [1.0, 2.0]})
    with pytest.raises(CameraInfoError, match='needs 9 values, got 2'):
        camera_info_from_calibration(short, msg_cls=TS)
    bad_yaml = tmp_path / 'bad.yaml'
    bad_yaml.write_text('image_width: [1, 2\n')
    with pytest.raises(CameraInfoError, match='not valid YAML'):
        load_camera_info_yaml(bad_yaml, msg_cls=TS)
    scalar = tmp_path / 'scalar.yaml'
    scalar.write_text('42\n')
    with pytest.raises(CameraInfoError, match='mapping'):
        load_camera_info_yaml(scalar, msg_cls=TS)
