"""ROS 2 message <-> numpy adapters for rclpy and rosbags messages alike (no rclpy import).

Readers take a message of either flavour (rclpy objects as received by a node, rosbags
dataclasses as read from a bag); builders take ``msg_cls`` (the message class of the wanted
flavour, or a rosbags typestore) and build the header from ``stamp_ns`` (int, ns) and
``frame_id``. Every rejection of bad input raises a :class:`MessageError` (a ``ValueError``)
naming the field and the expected vs actual value.

Modules: :mod:`~msg_adapters.image` (Image, CompressedImage), :mod:`~msg_adapters.camera_info`,
:mod:`~msg_adapters.point_cloud2` (any layout), :mod:`~msg_adapters.layouts` (the product
layouts of the topic contract), :mod:`~msg_adapters.stamp`, :mod:`~msg_adapters.nav`
(Odometry, PoseStamped, Path, NavSatFix), :mod:`~msg_adapters.errors`.
"""
from __future__ import annotations

from msg_adapters.camera_info import (
    camera_info_from_calibration,
    camera_info_to_model,
    check_image_size,
    load_camera_info_yaml,
    model_to_camera_info,
)
from msg_adapters.errors import (
    ArrayShapeError,
    CameraInfoError,
    CompressedDecodeError,
    DataLengthError,
    ImageSizeError,
    ImageTooLargeError,
    LayoutMismatchError,
    MessageError,
    NonFiniteCameraInfoError,
    NonFiniteError,
    PointFieldError,
    StampError,
    StepMismatchError,
    UnsupportedDistortionError,
    UnsupportedEncodingError,
    UnsupportedFormatError,
    ValueRangeError,
    WrongMessageTypeError,
)
from msg_adapters.image import (
    DEFAULT_MAX_PIXELS,
    compressed_size,
    compressed_to_numpy,
    depth_to_metres,
    encoding_info,
    image_to_numpy,
    numpy_to_compressed,
    numpy_to_image,
    parse_compressed_format,
    to_rgb_or_mono,
)
from msg_adapters.layouts import (
    SEMANTIC_CLOUD_DTYPE,
    TRACKS_DTYPE,
    Features,
    SemanticCloud,
    Tracks,
    features_dtype,
    features_from_msg,
    features_to_msg,
    pack_rgb,
    semantic_cloud_from_msg,
    semantic_cloud_to_msg,
    tracks_from_msg,
    tracks_to_msg,
    unpack_rgb,
)
from msg_adapters.nav import (
    GnssSample,
    OdometrySample,
    matrix_to_pose,
    matrix_to_quaternion,
    navsatfix_to_numpy,
    odometry_from_numpy,
    odometry_to_numpy,
    path_from_numpy,
    path_to_numpy,
    pose_stamped_to_numpy,
    pose_to_matrix,
    quaternion_to_matrix,
)
from msg_adapters.point_cloud2 import (
    DATATYPES,
    array_to_pointcloud2,
    dtype_to_fields,
    fields_to_dtype,
    pointcloud2_to_array,
)
from msg_adapters.stamp import header_info, make_header, ns_to_stamp, split_ns, stamp_to_ns

__all__ = [
    'GnssSample', 'OdometrySample', 'matrix_to_pose', 'matrix_to_quaternion',
    'navsatfix_to_numpy', 'odometry_from_numpy', 'odometry_to_numpy', 'path_from_numpy',
    'path_to_numpy', 'pose_stamped_to_numpy', 'pose_to_matrix', 'quaternion_to_matrix',
    'DATATYPES', 'DEFAULT_MAX_PIXELS', 'SEMANTIC_CLOUD_DTYPE', 'TRACKS_DTYPE',
    'ArrayShapeError', 'CameraInfoError', 'CompressedDecodeError', 'DataLengthError',
    'Features', 'ImageSizeError', 'ImageTooLargeError', 'LayoutMismatchError', 'MessageError',
    'NonFiniteCameraInfoError', 'NonFiniteError', 'PointFieldError', 'SemanticCloud',
    'StampError', 'StepMismatchError', 'Tracks', 'UnsupportedDistortionError',
    'UnsupportedEncodingError', 'UnsupportedFormatError', 'ValueRangeError',
    'WrongMessageTypeError',
    'array_to_pointcloud2', 'camera_info_from_calibration', 'camera_info_to_model',
    'check_image_size', 'compressed_size', 'compressed_to_numpy', 'depth_to_metres',
    'dtype_to_fields',
    'encoding_info', 'features_dtype', 'features_from_msg', 'features_to_msg',
    'fields_to_dtype', 'header_info', 'image_to_numpy', 'load_camera_info_yaml', 'make_header',
    'model_to_camera_info', 'ns_to_stamp', 'numpy_to_compressed', 'numpy_to_image',
    'pack_rgb', 'parse_compressed_format', 'pointcloud2_to_array', 'semantic_cloud_from_msg',
    'semantic_cloud_to_msg', 'split_ns', 'stamp_to_ns', 'to_rgb_or_mono', 'tracks_from_msg',
    'tracks_to_msg', 'unpack_rgb',
]
