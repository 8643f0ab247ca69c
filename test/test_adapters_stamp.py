"""msg_adapters.stamp and the flavour machinery (rclpy vs rosbags classes)."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import builtin_interfaces.msg
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
import sensor_msgs.msg
import std_msgs.msg

from msg_adapters import (
    MessageError,
    StampError,
    WrongMessageTypeError,
    header_info,
    make_header,
    ns_to_stamp,
    split_ns,
    stamp_to_ns,
)
from msg_adapters._flavour import msgtype_of, resolve_class

TS = get_typestore(Stores.ROS2_JAZZY)
RB_TIME = TS.types['builtin_interfaces/msg/Time']
RB_HEADER = TS.types['std_msgs/msg/Header']
RB_IMAGE = TS.types['sensor_msgs/msg/Image']

STAMPS = [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1, -1_000_000_001,
          (2 ** 31 - 1) * 10 ** 9 + 999_999_999, -(2 ** 31) * 10 ** 9]


@pytest.mark.parametrize('ns', STAMPS)
@pytest.mark.parametrize('cls', [builtin_interfaces.msg.Time, RB_TIME, sensor_msgs.msg.Image,
                                 RB_IMAGE, TS])
def test_ns_stamp_round_trip(ns: int, cls: object) -> None:
    stamp = ns_to_stamp(ns, cls)
    assert 0 <= stamp.nanosec < 10 ** 9
    assert stamp_to_ns(stamp) == ns
    assert split_ns(ns) == (stamp.sec, stamp.nanosec)


def test_flavour_of_stamp_follows_msg_cls() -> None:
    assert isinstance(ns_to_stamp(5, sensor_msgs.msg.Image), builtin_interfaces.msg.Time)
    rb = ns_to_stamp(5, RB_IMAGE)
    assert rb.__msgtype__ == 'builtin_interfaces/msg/Time'
    assert isinstance(ns_to_stamp(5, TS), RB_TIME)


def test_negative_stamp_is_floor_split() -> None:
    stamp = ns_to_stamp(-1, builtin_interfaces.msg.Time)
    assert (stamp.sec, stamp.nanosec) == (-1, 999_999_999)


@pytest.mark.parametrize('ns', [2 ** 31 * 10 ** 9, -(2 ** 31) * 10 ** 9 - 1])
def test_stamp_outside_int32_rejected(ns: int) -> None:
    with pytest.raises(StampError, match='int32'):
        ns_to_stamp(ns, RB_TIME)


@pytest.mark.parametrize('bad', [1.5, '12', True, None])
def test_stamp_ns_must_be_integer(bad: object) -> None:
    with pytest.raises(StampError, match='stamp_ns'):
        ns_to_stamp(bad, RB_TIME)  # type: ignore[arg-type]


def test_numpy_integer_stamp_accepted() -> None:
    assert stamp_to_ns(ns_to_stamp(np.int64(12_345), RB_TIME)) == 12_345


def test_bad_nanosec_rejected() -> None:
    stamp = builtin_interfaces.msg.Time(sec=3, nanosec=1_000_000_000)
    with pytest.raises(StampError, match='nanosec'):
        stamp_to_ns(stamp)
    with pytest.raises(StampError, match='nanosec'):
        stamp_to_ns(RB_TIME(sec=3, nanosec=2_000_000_000))


def test_stamp_to_ns_accepts_header_and_message() -> None:
    header = make_header(1_234_567_890_123, 'cam', std_msgs.msg.Header)
    assert isinstance(header, std_msgs.msg.Header)
    assert stamp_to_ns(header) == 1_234_567_890_123
    img = sensor_msgs.msg.Image(header=header)
    assert stamp_to_ns(img) == 1_234_567_890_123
    assert header_info(img) == (1_234_567_890_123, 'cam')
    with pytest.raises(WrongMessageTypeError):
        stamp_to_ns(object())


@pytest.mark.parametrize('ns', STAMPS)
def test_header_cdr_identical_across_flavours(ns: int) -> None:
    rc = make_header(ns, 'camera_front_optical', std_msgs.msg.Header)
    rb = make_header(ns, 'camera_front_optical', RB_HEADER)
    raw_rc = serialize_message(rc)
    raw_rb = bytes(TS.serialize_cdr(rb, 'std_msgs/msg/Header'))
    assert raw_rc == raw_rb  # no alignment padding in a header: byte-identical
    assert stamp_to_ns(TS.deserialize_cdr(raw_rc, 'std_msgs/msg/Header')) == ns
    assert stamp_to_ns(deserialize_message(raw_rb, std_msgs.msg.Header)) == ns


def test_frame_id_must_be_str() -> None:
    with pytest.raises(WrongMessageTypeError, match='frame_id'):
        make_header(0, 5, RB_HEADER)  # type: ignore[arg-type]


def test_msgtype_and_class_resolution() -> None:
    assert msgtype_of(sensor_msgs.msg.Image) == 'sensor_msgs/msg/Image'
    assert msgtype_of(RB_IMAGE) == 'sensor_msgs/msg/Image'
    assert msgtype_of(sensor_msgs.msg.Image()) == 'sensor_msgs/msg/Image'
    assert resolve_class(TS, 'sensor_msgs/msg/Image') is RB_IMAGE
    with pytest.raises(WrongMessageTypeError, match='expected a sensor_msgs/msg/PointCloud2'):
        resolve_class(sensor_msgs.msg.Image, 'sensor_msgs/msg/PointCloud2')
    with pytest.raises(WrongMessageTypeError):
        resolve_class(dict, 'sensor_msgs/msg/Image')
    with pytest.raises(WrongMessageTypeError):
        resolve_class('sensor_msgs/msg/Image', 'sensor_msgs/msg/Image')
    assert issubclass(WrongMessageTypeError, MessageError)
    assert issubclass(MessageError, ValueError)


def test_package_imports_neither_rclpy_nor_ros_messages() -> None:
    """msg_adapters and its rosbags path work without rclpy or the ROS message packages."""
    code = textwrap.dedent("""
        import sys
        import numpy as np
        import msg_adapters
        from msg_adapters.layouts import semantic_cloud_to_msg, semantic_cloud_from_msg
        from rosbags.typesys import Stores, get_typestore
        ts = get_typestore(Stores.ROS2_JAZZY)
        msg = semantic_cloud_to_msg(np.zeros((2, 3)), np.zeros((2, 3), np.uint8), [0, 1],
                                    [0, 0], [5, 6], [1, 2], stamp_ns=1, frame_id='map',
                                    msg_cls=ts)
        assert semantic_cloud_from_msg(msg).landmark_ids.tolist() == [5, 6]
        bad = sorted(m for m in sys.modules
                     if m.split('.')[0] in ('rclpy', 'sensor_msgs', 'std_msgs', 'torch',
                                            'gtsam'))
        print(bad)
    """)
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=60, check=True)
    assert out.stdout.strip() == '[]', out.stdout + out.stderr
