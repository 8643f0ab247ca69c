"""Odometry / PoseStamped / Path / NavSatFix adapters, rclpy and rosbags flavours."""
from __future__ import annotations

from nav_msgs.msg import Odometry, Path
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import NavSatFix

from msg_adapters import (
    matrix_to_quaternion,
    navsatfix_to_numpy,
    odometry_from_numpy,
    odometry_to_numpy,
    path_from_numpy,
    path_to_numpy,
    quaternion_to_matrix,
)
from msg_adapters.errors import NonFiniteError, ValueRangeError
from semfeat_ros.rotations import rpy_to_matrix

TS = get_typestore(Stores.ROS2_JAZZY)


def pose(rpy: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(*rpy)
    T[:3, 3] = t
    return T


@pytest.mark.parametrize('rpy', [(0, 0, 0), (0.1, -0.2, 3.1), (np.pi, 0, 0), (0, np.pi / 2, 0),
                                 (0.3, 0.2, -2.9)])
def test_quaternion_round_trip(rpy: tuple[float, float, float]) -> None:
    R = rpy_to_matrix(*rpy)
    q = matrix_to_quaternion(R)
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
    np.testing.assert_allclose(quaternion_to_matrix(*q), R, atol=1e-12)


@pytest.mark.parametrize('flavour', ['rclpy', 'rosbags'])
def test_odometry_round_trip_through_cdr(flavour: str) -> None:
    T = pose((0.01, -0.02, 1.2), (10.0, -3.0, 3.6))
    cov = np.diag([0.01, 0.02, 0.03, 0.001, 0.002, 0.003])
    cls = Odometry if flavour == 'rclpy' else TS.types['nav_msgs/msg/Odometry']
    msg = odometry_from_numpy(T, cov, stamp_ns=1_234_567_890_123, frame_id='map',
                              child_frame_id='base_link', msg_cls=cls)
    if flavour == 'rclpy':
        back = deserialize_message(serialize_message(msg), Odometry)
        other = TS.deserialize_cdr(serialize_message(msg), 'nav_msgs/msg/Odometry')
    else:
        raw = TS.serialize_cdr(msg, 'nav_msgs/msg/Odometry')
        back = TS.deserialize_cdr(raw, 'nav_msgs/msg/Odometry')
        other = deserialize_message(bytes(raw), Odometry)
    for m in (back, other):
        s = odometry_to_numpy(m)
        assert (s.stamp_ns, s.frame_id, s.child_frame_id) == (1_234_567_890_123, 'map',
                                                               'base_link')
        np.testing.assert_allclose(s.T, T, atol=1e-12)
        np.testing.assert_allclose(s.covariance, cov)


def test_unknown_covariance_is_never_all_zero() -> None:
    msg = odometry_from_numpy(np.eye(4), None, stamp_ns=0, frame_id='map',
                              child_frame_id='base_link', msg_cls=Odometry)
    assert odometry_to_numpy(msg).covariance[0, 0] == -1.0


def test_bad_odometry() -> None:
    msg = Odometry()
    msg.pose.pose.orientation.w = 0.0  # zero quaternion
    with pytest.raises(NonFiniteError, match='quaternion'):
        odometry_to_numpy(msg)
    msg.pose.pose.orientation.w = 1.0
    msg.pose.pose.position.x = float('nan')
    with pytest.raises(NonFiniteError, match='position'):
        odometry_to_numpy(msg)
    with pytest.raises(ValueRangeError, match='covariance'):
        odometry_from_numpy(np.eye(4), np.eye(3), stamp_ns=0, frame_id='m', child_frame_id='b',
                            msg_cls=Odometry)


@pytest.mark.parametrize('flavour', ['rclpy', 'rosbags'])
def test_path(flavour: str) -> None:
    cls = Path if flavour == 'rclpy' else TS.types['nav_msgs/msg/Path']
    poses = np.stack([pose((0, 0, 0.1 * i), (i, 0, 0.2 * i)) for i in range(4)])
    msg = path_from_numpy(np.arange(4) * 10**8, poses, frame_id='map', msg_cls=cls)
    assert len(msg.poses) == 4 and msg.header.frame_id == 'map'
    assert msg.poses[2].pose.position.z == pytest.approx(0.4)
    assert msg.header.stamp.nanosec == 3 * 10**8
    stamps, back = path_to_numpy(msg)
    np.testing.assert_array_equal(stamps, np.arange(4) * 10**8)
    np.testing.assert_allclose(back, poses, atol=1e-12)
    with pytest.raises(ValueRangeError):
        path_from_numpy(np.arange(3), poses, frame_id='map', msg_cls=cls)


def test_navsatfix() -> None:
    msg = NavSatFix(latitude=48.1, longitude=11.5, altitude=520.0)
    msg.position_covariance = [0.0004, 0, 0, 0, 0.0004, 0, 0, 0, 0.0016]
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    msg.status.status = 2
    s = navsatfix_to_numpy(deserialize_message(serialize_message(msg), NavSatFix))
    assert s.has_fix and s.covariance[2, 2] == pytest.approx(0.0016)
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_UNKNOWN
    assert navsatfix_to_numpy(msg).covariance is None
    msg.status.status = -1
    assert not navsatfix_to_numpy(msg).has_fix
    msg.latitude = 123.0
    with pytest.raises(ValueRangeError, match='latitude'):
        navsatfix_to_numpy(msg)
