"""Readers of the evaluation harness: image folders, Oxford/HPatches sequences, bags."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from semfeat_ros.evaluation.datasets import (
    bag_image_count,
    find_homography_sequences,
    iter_bag_images,
    list_images,
    read_homography_file,
    read_image,
    read_keypoint_file,
    read_label_image,
    select_indices,
)
from semfeat_ros.evaluation.errors import (
    DatasetError,
    HomographyFileError,
    ImageReadError,
    TopicError,
)


def _write(path: Path, img: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), img)
    return path


def _h_text(H: np.ndarray) -> str:
    return '\n'.join(' '.join(f'{v:.10e}' for v in row) for row in H) + '\n'


def test_read_image_variants(tmp_path: Path) -> None:
    gray = np.arange(64 * 48, dtype=np.uint32).reshape(48, 64).astype(np.uint8)
    rgb = read_image(_write(tmp_path / 'g.pgm', gray))
    assert rgb.shape == (48, 64, 3) and (rgb[:, :, 0] == gray).all()
    bgr = np.zeros((20, 30, 3), np.uint8)
    bgr[:, :, 0] = 200  # blue in OpenCV order
    assert (read_image(_write(tmp_path / 'c.png', bgr))[:, :, 2] == 200).all()
    deep = (np.ones((20, 30)) * 40000).astype(np.uint16)
    assert (read_image(_write(tmp_path / 'd.png', deep)) == 40000 >> 8).all()
    (tmp_path / 'bad.jpg').write_bytes(b'\xff\xd8\xff' + b'garbage' * 10)
    with pytest.raises(ImageReadError, match='bad.jpg'):
        read_image(tmp_path / 'bad.jpg')
    with pytest.raises(ImageReadError, match='not found'):
        read_image(tmp_path / 'missing.png')


def test_list_images(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match='no images'):
        list_images(tmp_path)
    with pytest.raises(DatasetError, match='not found'):
        list_images(tmp_path / 'nope')
    img = np.full((16, 16), 9, np.uint8)
    _write(tmp_path / 'b.PNG', img)
    _write(tmp_path / 'a.ppm', np.dstack([img] * 3))
    (tmp_path / 'notes.txt').write_text('x')
    assert [p.name for p in list_images(tmp_path)] == ['a.ppm', 'b.PNG']
    (tmp_path / 'c.jpg').write_bytes(b'not an image at all')
    with pytest.raises(ImageReadError, match='c.jpg'):
        list_images(tmp_path)


def test_select_indices() -> None:
    assert select_indices(10, 3) == [0, 3, 6]
    assert select_indices(3, 7) == [0, 1, 2, 0, 1, 2, 0]
    assert select_indices(5, 5) == [0, 1, 2, 3, 4]
    with pytest.raises(DatasetError):
        select_indices(0, 2)


def test_oxford_and_hpatches_layouts(tmp_path: Path) -> None:
    img = np.random.default_rng(0).integers(0, 255, (40, 50, 3)).astype(np.uint8)
    H2 = np.array([[1.0, 0.1, 3.0], [0.0, 0.9, -2.0], [1e-4, 0.0, 1.0]])
    ox = tmp_path / 'graf'
    ox.mkdir()
    for k in (1, 2, 3):
        _write(ox / f'img{k}.ppm', img)
    (ox / 'H1to2p').write_text(_h_text(H2 * 2.0))  # scale is normalised away
    (ox / 'H1to3p').write_text(_h_text(np.eye(3)))
    seqs = find_homography_sequences(ox)
    assert len(seqs) == 1 and seqs[0].reference.name == 'img1.ppm'
    assert [t.name for t, _ in seqs[0].targets] == ['img2.ppm', 'img3.ppm']
    np.testing.assert_allclose(seqs[0].targets[0][1], H2)

    hp = tmp_path / 'v_wall'
    hp.mkdir()
    _write(hp / '1.ppm', img)
    _write(hp / '2.ppm', img)
    (hp / 'H_1_2').write_text(_h_text(H2))
    both = find_homography_sequences(tmp_path)
    assert [s.name for s in both] == ['graf', 'v_wall']

    (ox / 'H1to3p').unlink()
    with pytest.raises(HomographyFileError, match='missing homography file .*H1to3p'):
        find_homography_sequences(ox)
    (ox / 'H1to3p').write_text('1 0 0\n0 1 0\n')
    with pytest.raises(HomographyFileError, match='9 finite numbers'):
        find_homography_sequences(ox)
    (ox / 'H1to3p').write_text('1 0 0 0 1 0 0 0 x')
    with pytest.raises(HomographyFileError, match='non-numeric'):
        read_homography_file(ox / 'H1to3p')
    (ox / 'H1to3p').write_text('0 0 0 0 0 0 0 0 1')
    with pytest.raises(HomographyFileError, match='singular'):
        read_homography_file(ox / 'H1to3p')
    empty = tmp_path / 'empty'
    empty.mkdir()
    with pytest.raises(DatasetError, match='no Oxford/HPatches sequence'):
        find_homography_sequences(empty)


def test_keypoint_and_label_files(tmp_path: Path) -> None:
    np.save(tmp_path / 'k.npy', np.array([[1.0, 2.0], [3.5, 4.0]]))
    (tmp_path / 'k.txt').write_text('1 2\n3.5 4\n')
    np.testing.assert_allclose(read_keypoint_file(tmp_path / 'k.npy'),
                               read_keypoint_file(tmp_path / 'k.txt'))
    (tmp_path / 'bad.txt').write_text('1 nan\n')
    with pytest.raises(DatasetError, match='finite'):
        read_keypoint_file(tmp_path / 'bad.txt')
    lab = np.full((10, 12), 3, np.uint8)
    _write(tmp_path / 'l.png', lab)
    assert (read_label_image(tmp_path / 'l.png', (10, 12)) == 3).all()
    with pytest.raises(ImageReadError, match='does not match'):
        read_label_image(tmp_path / 'l.png', (12, 10))


def write_image_bag(path: Path, topic: str, images: list[np.ndarray],
                    compressed: bool = False) -> Path:
    """A rosbag2 (sqlite3) with one Image (rgb8) or CompressedImage (png) topic."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from msg_adapters.image import numpy_to_compressed, numpy_to_image

    ts = get_typestore(Stores.ROS2_JAZZY)
    msgtype = 'sensor_msgs/msg/CompressedImage' if compressed else 'sensor_msgs/msg/Image'
    with Writer(path, version=9) as w:
        conn = w.add_connection(topic, msgtype, typestore=ts)
        for k, img in enumerate(images):
            stamp = (k + 1) * 100_000_000
            if compressed:
                msg = numpy_to_compressed(img, 'png', stamp_ns=stamp, frame_id='cam', msg_cls=ts)
            else:
                msg = numpy_to_image(img, 'rgb8', stamp_ns=stamp, frame_id='cam', msg_cls=ts)
            w.write(conn, stamp, ts.serialize_cdr(msg, msgtype))
    return path


@pytest.mark.parametrize('compressed', [False, True])
def test_bag_images(tmp_path: Path, compressed: bool) -> None:
    imgs = [np.full((24, 32, 3), 10 * k, np.uint8) for k in range(4)]
    imgs[2][:, :, 0] = 255  # red channel marks frame 2
    bag = write_image_bag(tmp_path / 'bag', '/cam/image', imgs, compressed)
    assert bag_image_count(bag, None) == ('/cam/image', 4)
    got = list(iter_bag_images(bag, '/cam/image', [2, 0]))
    assert [k for k, _, _ in got] == [0, 2]
    assert got[1][1] == 300_000_000
    assert (got[1][2][:, :, 0] == 255).all() and (got[1][2][:, :, 2] == 20).all()
    with pytest.raises(TopicError, match='topic /other not in bag.*/cam/image'):
        bag_image_count(bag, '/other')
    with pytest.raises(DatasetError, match='bag not found'):
        bag_image_count(tmp_path / 'missing', None)
