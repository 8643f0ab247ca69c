"""msg_adapters.layouts: the product PointCloud2 layouts of the topic contract."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
import sensor_msgs.msg

from msg_adapters import (
    SEMANTIC_CLOUD_DTYPE,
    TRACKS_DTYPE,
    ArrayShapeError,
    LayoutMismatchError,
    NonFiniteError,
    ValueRangeError,
    array_to_pointcloud2,
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

TS = get_typestore(Stores.ROS2_JAZZY)
PC2 = 'sensor_msgs/msg/PointCloud2'
FLAVOURS = {'rclpy': sensor_msgs.msg.PointCloud2, 'rosbags': TS.types[PC2]}
F32, U8, U16, U32 = 7, 2, 4, 6


def cdr_round_trip(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return TS.deserialize_cdr(bytes(TS.serialize_cdr(msg, PC2)), PC2)
    return deserialize_message(serialize_message(msg), type(msg))


def cross(msg: Any) -> Any:
    if hasattr(msg, '__msgtype__'):
        return deserialize_message(bytes(TS.serialize_cdr(msg, PC2)),
                                   sensor_msgs.msg.PointCloud2)
    return TS.deserialize_cdr(serialize_message(msg), PC2)


def field_list(msg: Any) -> list[tuple[str, int, int, int]]:
    return [(str(f.name), int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]


def test_documented_offsets() -> None:
    dt = features_dtype(64)
    assert [dt.fields[n][1] for n in dt.names] == [0, 4, 8, 12, 16]
    assert dt.itemsize == 16 + 4 * 64
    assert features_dtype(1).itemsize == 20
    assert [TRACKS_DTYPE.fields[n][1] for n in TRACKS_DTYPE.names] == [
        0, 4, 8, 12, 16, 20, 24, 28, 32]
    assert TRACKS_DTYPE.itemsize == 36
    assert [SEMANTIC_CLOUD_DTYPE.fields[n][1] for n in SEMANTIC_CLOUD_DTYPE.names] == [
        0, 4, 8, 12, 16, 17, 20, 24]
    assert SEMANTIC_CLOUD_DTYPE.itemsize == 28
    with pytest.raises(ArrayShapeError):
        features_dtype(0)


def _features(n: int, dim: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    kp = rng.uniform(0, 1900, (n, 2))
    desc = rng.normal(size=(n, dim))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    return kp, rng.uniform(0, 1, n), rng.integers(0, 19, n), desc


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('n,dim', [(50, 64), (1, 1), (0, 32)])
def test_features_round_trip(flavour: str, n: int, dim: int) -> None:
    kp, scores, labels, desc = _features(n, dim)
    msg = features_to_msg(kp, scores, labels, desc, stamp_ns=1_700_000_000_000_000_042,
                          frame_id='camera_front_optical', msg_cls=FLAVOURS[flavour])
    assert field_list(msg) == [('u', 0, F32, 1), ('v', 4, F32, 1), ('score', 8, F32, 1),
                               ('label', 12, U8, 1), ('descriptor', 16, F32, dim)]
    assert (msg.height, msg.width, msg.point_step) == (1, n, 16 + 4 * dim)
    assert msg.is_dense and not msg.is_bigendian
    for received in (cdr_round_trip(msg), cross(msg)):
        out = features_from_msg(received)
        assert out.stamp_ns == 1_700_000_000_000_000_042
        assert out.frame_id == 'camera_front_optical'
        assert out.keypoints.dtype == np.float32 and out.keypoints.shape == (n, 2)
        np.testing.assert_array_equal(out.keypoints, kp.astype(np.float32))
        np.testing.assert_array_equal(out.scores, scores.astype(np.float32))
        np.testing.assert_array_equal(out.labels, labels.astype(np.uint8))
        assert out.descriptors.shape == (n, dim) and out.descriptors.flags.c_contiguous
        np.testing.assert_array_equal(out.descriptors, desc.astype(np.float32))


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_tracks_round_trip(flavour: str) -> None:
    rng = np.random.default_rng(1)
    n = 30
    uv = rng.uniform(0, 1500, (n, 2))
    rays = rng.normal(size=(n, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    labels = rng.integers(0, 19, n)
    ids = rng.integers(0, 2 ** 32, n, dtype=np.uint64)
    ids[0] = 2 ** 32 - 1
    ages = rng.integers(1, 1000, n)
    ages[1] = 70_000  # saturates
    scores = rng.uniform(0, 1, n)
    msg = tracks_to_msg(uv, rays, labels, ids, ages, scores, stamp_ns=9, frame_id='cam',
                        msg_cls=FLAVOURS[flavour])
    assert field_list(msg) == [
        ('u', 0, F32, 1), ('v', 4, F32, 1), ('bx', 8, F32, 1), ('by', 12, F32, 1),
        ('bz', 16, F32, 1), ('label', 20, U8, 1), ('track_id', 24, U32, 1),
        ('age', 28, U16, 1), ('score', 32, F32, 1)]
    assert msg.point_step == 36
    for received in (cdr_round_trip(msg), cross(msg)):
        out = tracks_from_msg(received)
        np.testing.assert_array_equal(out.uv, uv.astype(np.float32))
        np.testing.assert_array_equal(out.bearings, rays.astype(np.float32))
        np.testing.assert_array_equal(out.labels, labels)
        assert out.track_ids.dtype == np.uint32
        np.testing.assert_array_equal(out.track_ids, ids)
        np.testing.assert_array_equal(out.ages, np.minimum(ages, 65535))
        np.testing.assert_array_equal(out.scores, scores.astype(np.float32))
        assert (out.stamp_ns, out.frame_id) == (9, 'cam')


def test_pack_rgb_pcl_convention() -> None:
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [0, 0, 1], [255, 255, 255],
                    [12, 34, 56]], np.uint8)
    packed = pack_rgb(rgb)
    assert packed.dtype == np.float32
    assert packed.view(np.uint32).tolist() == [0xFF0000, 0x00FF00, 0x0000FF, 0x000001,
                                                0xFFFFFF, 0x0C2238]
    assert np.isfinite(packed).all()
    np.testing.assert_array_equal(unpack_rgb(packed), rgb)
    np.testing.assert_array_equal(unpack_rgb(packed.view(np.uint32)), rgb)
    np.testing.assert_array_equal(unpack_rgb(packed.astype('>f4')), rgb)
    with pytest.raises(ValueRangeError, match='256'):
        pack_rgb(np.array([[256, 0, 0]]))
    with pytest.raises(ArrayShapeError):
        pack_rgb(np.zeros((3, 4), np.uint8))
    with pytest.raises(ArrayShapeError):
        unpack_rgb(np.zeros(3, np.float64))


def _cloud(n: int, seed: int = 2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {'xyz': rng.normal(0, 20, (n, 3)),
            'rgb': rng.integers(0, 256, (n, 3), dtype=np.uint8),
            'label': rng.integers(0, 19, n), 'floor': rng.integers(0, 4, n),
            'landmark_id': rng.integers(0, 2 ** 32, n, dtype=np.uint64),
            'n_obs': rng.integers(2, 100_000, n)}


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_semantic_cloud_round_trip(flavour: str) -> None:
    c = _cloud(200)
    c['rgb'][0] = [0, 0, 1]  # a denormal float32 when packed: must survive bit-exactly
    msg = semantic_cloud_to_msg(c['xyz'], c['rgb'], c['label'], c['floor'], c['landmark_id'],
                                c['n_obs'], stamp_ns=11, frame_id='map',
                                msg_cls=FLAVOURS[flavour])
    assert field_list(msg) == [
        ('x', 0, F32, 1), ('y', 4, F32, 1), ('z', 8, F32, 1), ('rgb', 12, F32, 1),
        ('label', 16, U8, 1), ('floor', 17, U8, 1), ('landmark_id', 20, U32, 1),
        ('n_obs', 24, U16, 1)]
    raw = np.frombuffer(msg.data, np.uint8).reshape(200, 28)
    assert raw[0, 12:16].tolist() == [1, 0, 0, 0]  # little-endian 0x00000001: B, G, R, 0
    assert not raw[:, 18:20].any() and not raw[:, 26:28].any()
    for received in (cdr_round_trip(msg), cross(msg)):
        out = semantic_cloud_from_msg(received)
        np.testing.assert_array_equal(out.xyz, c['xyz'].astype(np.float32))
        np.testing.assert_array_equal(out.rgb, c['rgb'])
        np.testing.assert_array_equal(out.labels, c['label'])
        np.testing.assert_array_equal(out.floors, c['floor'])
        np.testing.assert_array_equal(out.landmark_ids, c['landmark_id'])
        np.testing.assert_array_equal(out.n_obs, np.minimum(c['n_obs'], 65535))
        assert (out.stamp_ns, out.frame_id) == (11, 'map')


def test_semantic_cloud_cdr_identical_across_flavours() -> None:
    c = _cloud(20)
    args = (c['xyz'], c['rgb'], c['label'], c['floor'], c['landmark_id'], c['n_obs'])
    rc = semantic_cloud_to_msg(*args, stamp_ns=3, frame_id='map',
                               msg_cls=sensor_msgs.msg.PointCloud2)
    rb = semantic_cloud_to_msg(*args, stamp_ns=3, frame_id='map', msg_cls=TS)
    raw_rc, raw_rb = serialize_message(rc), bytes(TS.serialize_cdr(rb, PC2))
    a, b = np.frombuffer(raw_rc, np.uint8), np.frombuffer(raw_rb, np.uint8)
    assert a.shape == b.shape and np.all(b[a != b] == 0)
    assert bytes(TS.serialize_cdr(TS.deserialize_cdr(raw_rc, PC2), PC2)) == raw_rb


def test_nonfinite_policy() -> None:
    c = _cloud(5)
    c['xyz'][3, 1] = np.nan
    args = (c['xyz'], c['rgb'], c['label'], c['floor'], c['landmark_id'], c['n_obs'])
    with pytest.raises(NonFiniteError, match='xyz: 1 row.*index 3'):
        semantic_cloud_to_msg(*args, stamp_ns=0, frame_id='map', msg_cls=TS)
    msg = semantic_cloud_to_msg(*args, stamp_ns=0, frame_id='map', msg_cls=TS,
                                allow_nonfinite=True)
    assert not msg.is_dense
    assert np.isnan(semantic_cloud_from_msg(msg).xyz[3, 1])
    kp, scores, labels, desc = _features(4, 8)
    kw = {'stamp_ns': 0, 'frame_id': 'c', 'msg_cls': TS}
    for column, index in (('keypoints', 0), ('scores', 1), ('descriptors', 3)):
        bad = [kp.copy(), scores.copy(), labels, desc.copy()]
        bad[index][2] = np.inf
        with pytest.raises(NonFiniteError, match=column):
            features_to_msg(*bad, **kw)
    uv = np.zeros((2, 2))
    rays = np.array([[0, 0, 1], [np.nan, 0, 1]], float)
    with pytest.raises(NonFiniteError, match='bearings'):
        tracks_to_msg(uv, rays, [0, 1], [1, 2], [1, 1], [0.5, 0.5], **kw)


def test_value_ranges_and_shapes() -> None:
    kp, scores, labels, desc = _features(3, 4)
    kw = {'stamp_ns': 0, 'frame_id': 'c', 'msg_cls': TS}
    with pytest.raises(ValueRangeError, match=r'labels: value 256 outside \[0, 255\]'):
        features_to_msg(kp, scores, [0, 1, 256], desc, **kw)
    with pytest.raises(ValueRangeError, match='value -1'):
        features_to_msg(kp, scores, [0, -1, 2], desc, **kw)
    with pytest.raises(ArrayShapeError, match=r'keypoints: .*\(3, 2\)'):
        features_to_msg(kp[:, :1], scores, labels, desc, **kw)
    with pytest.raises(ArrayShapeError, match='scores'):
        features_to_msg(kp, scores[:2], labels, desc, **kw)
    with pytest.raises(ArrayShapeError, match='descriptors'):
        features_to_msg(kp, scores, labels, desc[:, 0], **kw)
    with pytest.raises(ArrayShapeError, match='labels: expected integers'):
        features_to_msg(kp, scores, [0.5, 1, 2], desc, **kw)
    uv, rays = np.zeros((2, 2)), np.tile([0.0, 0.0, 1.0], (2, 1))
    with pytest.raises(ValueRangeError, match='track_ids'):
        tracks_to_msg(uv, rays, [0, 1], [0, 2 ** 32], [1, 1], [0.5, 0.5], **kw)
    with pytest.raises(ValueRangeError, match='ages'):
        tracks_to_msg(uv, rays, [0, 1], [0, 1], [-1, 1], [0.5, 0.5], **kw)
    with pytest.raises(ArrayShapeError, match='bearings'):
        tracks_to_msg(uv, rays[:, :2], [0, 1], [0, 1], [1, 1], [0.5, 0.5], **kw)
    c = _cloud(2)
    with pytest.raises(ValueRangeError, match='floor'):
        semantic_cloud_to_msg(c['xyz'], c['rgb'], c['label'], [0, 300], c['landmark_id'],
                              c['n_obs'], **kw)
    with pytest.raises(ValueRangeError, match='rgb'):
        semantic_cloud_to_msg(c['xyz'], c['rgb'].astype(int) + 200, c['label'], c['floor'],
                              c['landmark_id'], c['n_obs'], **kw)


def test_readers_accept_foreign_producers() -> None:
    """Same names and datatypes, other offsets / order / byte order / extra fields."""
    dt = np.dtype({'names': ['extra', 'label', 'descriptor', 'v', 'u', 'score'],
                   'formats': ['>f8', 'u1', ('>f4', (3,)), '>f4', '>f4', '>f4'],
                   'offsets': [0, 8, 9, 21, 25, 29], 'itemsize': 40})
    arr = np.zeros(4, dtype=dt)
    arr['u'], arr['v'], arr['score'] = [1, 2, 3, 4], [5, 6, 7, 8], 0.25
    arr['label'] = [3, 4, 5, 6]
    arr['descriptor'] = np.arange(12).reshape(4, 3)
    for cls in FLAVOURS.values():
        msg = cdr_round_trip(array_to_pointcloud2(arr, stamp_ns=1, frame_id='c', msg_cls=cls))
        assert msg.is_bigendian
        out = features_from_msg(msg)
        np.testing.assert_array_equal(out.keypoints, [[1, 5], [2, 6], [3, 7], [4, 8]])
        np.testing.assert_array_equal(out.descriptors, np.arange(12).reshape(4, 3))
        np.testing.assert_array_equal(out.labels, [3, 4, 5, 6])
        assert out.keypoints.dtype.isnative and out.descriptors.dtype.isnative


def test_readers_reject_other_layouts() -> None:
    kp, scores, labels, desc = _features(3, 4)
    features = features_to_msg(kp, scores, labels, desc, stamp_ns=0, frame_id='c', msg_cls=TS)
    with pytest.raises(LayoutMismatchError, match="field 'bx'.*missing"):
        tracks_from_msg(features)
    with pytest.raises(LayoutMismatchError, match="'x'"):
        semantic_cloud_from_msg(features)
    wrong = np.zeros(2, dtype=[('u', '<f4'), ('v', '<f4'), ('score', '<f4'), ('label', '<u2'),
                               ('descriptor', '<f4', (4,))])
    msg = array_to_pointcloud2(wrong, stamp_ns=0, frame_id='c', msg_cls=TS)
    with pytest.raises(LayoutMismatchError, match="'label' needs datatype 2.*datatype 4"):
        features_from_msg(msg)
    doubles = np.zeros(2, dtype=[('u', '<f4'), ('v', '<f4'), ('score', '<f4'), ('label', 'u1'),
                                 ('descriptor', '<f8', (4,))])
    with pytest.raises(LayoutMismatchError, match='descriptor'):
        features_from_msg(array_to_pointcloud2(doubles, stamp_ns=0, frame_id='c', msg_cls=TS))


@pytest.mark.parametrize('bad', ['descriptors', 'keypoints', 'scores', 'labels'])
def test_ragged_or_one_dimensional_inputs_raise_array_shape_errors(bad: str) -> None:
    cols: dict[str, Any] = {'keypoints': np.zeros((2, 2)), 'scores': np.ones(2),
                            'labels': np.zeros(2, np.uint8), 'descriptors': np.zeros((2, 4))}
    for value in ([[1.0, 2.0], [3.0]], np.zeros(8)):  # ragged, 1-D
        with pytest.raises(ArrayShapeError, match=bad):
            features_to_msg(**{**cols, bad: value}, stamp_ns=1, frame_id='c',
                            msg_cls=sensor_msgs.msg.PointCloud2)
    with pytest.raises(ArrayShapeError, match='bearings'):
        tracks_to_msg(np.zeros((2, 2)), [[1.0, 0.0, 0.0], [1.0]], np.zeros(2, np.uint8),
                      np.zeros(2, np.uint32), np.zeros(2, np.uint16), np.ones(2), stamp_ns=1,
                      frame_id='c', msg_cls=sensor_msgs.msg.PointCloud2)
