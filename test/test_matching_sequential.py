"""SequentialMatcher on a synthetic fisheye sequence: tracks, resets, stops, re-acquisition."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from semfeat_ros.camera import FisheyeCamera
from semfeat_ros.labels import load_labels
from semfeat_ros.matching import draw
from semfeat_ros.matching.errors import (
    FeatureInputError,
    FrameOrderError,
    MatchingConfigError,
    TrackIdOverflowError,
)
from semfeat_ros.matching.sequential import FrameFeatures, SequentialMatcher, TrackResult
from semfeat_ros.matching.tracks import MAX_TRACK_ID, TrackManager
from semfeat_ros.rotations import so3_exp

CAM = FisheyeCamera(640, 512, 186.7, 186.7, 320, 256, k=(0.02, -0.004, 0.0005, -0.0001),
                    fov_deg=190)
LABELS = load_labels()
CAR = LABELS.id_of('car')
STEP_NS = 100_000_000  # 10 Hz


class World:
    """Static labelled 3-D points with one descriptor each; a camera driving forward (+z)."""

    def __init__(self, seed: int = 0, n: int = 2500, dim: int = 64, car_frac: float = 0.0):
        rng = np.random.default_rng(seed)
        self.rng = rng
        pts = np.stack([rng.uniform(-8, 8, n), rng.uniform(-2.5, 1.4, n),
                        rng.uniform(-6, 30, n)], axis=1)
        near = np.hypot(pts[:, 0], pts[:, 1]) < 1.0
        pts[near, 0] += np.sign(pts[near, 0] + 1e-9) * 1.5
        self.points = pts
        self.dim = dim
        d = rng.normal(size=(n, dim))
        self.desc = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
        static_ids = np.flatnonzero(LABELS.static)
        self.labels = rng.choice(static_ids, n).astype(np.uint8)
        self.labels[rng.random(n) < car_frac] = CAR

    def pose(self, k: float, *, speed: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
        """World -> camera rotation and camera centre at frame k (slow yaw while driving)."""
        R = so3_exp(np.array([0.0, 0.01 * k, 0.0]))
        return R, np.array([0.0, 0.0, speed * k])

    def frame(self, k: int, *, stamp_k: int | None = None, pose_k: float | None = None,
              hide: np.ndarray | None = None, clutter: float = 0.15, noise_px: float = 0.5,
              with_bearings: bool = True, camera_id: str = 'front',
              ) -> tuple[FrameFeatures, np.ndarray]:
        """Features of frame k and the world point id of each keypoint (-1 for clutter)."""
        rng = self.rng
        R, c = self.pose(k if pose_k is None else pose_k)
        Xc = (self.points - c) @ R.T
        px, valid = CAM.project(Xc)
        vis = valid & CAM.in_image(px, border=2) & (np.linalg.norm(Xc, axis=1) > 0.5)
        if hide is not None:
            vis &= ~hide
        ids = np.flatnonzero(vis)
        kp = px[ids] + rng.normal(0, noise_px, (ids.size, 2))
        desc = self.desc[ids] + rng.normal(0, 0.03, (ids.size, self.dim)).astype(np.float32)
        labels = self.labels[ids]
        n_cl = int(clutter * ids.size)
        if n_cl:
            r = np.sqrt(rng.uniform(0, 1, n_cl)) * 250
            a = rng.uniform(0, 2 * np.pi, n_cl)
            kp_cl = np.stack([320 + r * np.cos(a), 256 + 0.9 * r * np.sin(a)], axis=1)
            kp = np.concatenate([kp, kp_cl])
            desc = np.concatenate([desc, rng.normal(size=(n_cl, self.dim)).astype(np.float32)])
            labels = np.concatenate([labels, rng.choice(np.flatnonzero(LABELS.static), n_cl)
                                     .astype(np.uint8)])
            ids = np.concatenate([ids, np.full(n_cl, -1)])
        order = rng.permutation(ids.size)
        kp, desc, labels, ids = kp[order], desc[order], labels[order], ids[order]
        bear = CAM.unproject(kp, check=False) if with_bearings else None
        stamp = (k if stamp_k is None else stamp_k) * STEP_NS + 1_000_000_000
        return FrameFeatures(stamp_ns=stamp, keypoints=kp, descriptors=desc, labels=labels,
                             scores=np.ones(ids.size, np.float32), bearings=bear,
                             camera_id=camera_id), ids


def gt_of(res: TrackResult, ids: np.ndarray) -> np.ndarray:
    return ids[res.indices]


class Ledger:
    """Checks across frames: one world point per track id, no id ever reused."""

    def __init__(self) -> None:
        self.point_of: dict[int, int] = {}
        self.last_age: dict[int, int] = {}
        self.bad = 0
        self.total = 0

    def add(self, res: TrackResult, ids: np.ndarray) -> None:
        for tid, pid, age in zip(res.track_ids.tolist(), gt_of(res, ids).tolist(),
                                 res.ages.tolist()):
            self.total += 1
            if self.point_of.setdefault(tid, pid) != pid or pid < 0:
                self.bad += 1
            self.last_age[tid] = age


def test_tracks_persist_over_a_sequence() -> None:
    world = World(seed=1)
    m = SequentialMatcher()
    ledger = Ledger()
    prev: dict[int, int] = {}  # world point -> track id in the previous frame
    prev_age: dict[int, int] = {}  # track id -> age in the previous frame
    continued = possible = 0
    for k in range(8):
        f, ids = world.frame(k)
        res = m.process(f)
        assert res.reset == ('first frame' if k == 0 else '')
        ledger.add(res, ids)
        if k:
            assert res.verified and res.model == 'essential'
            assert res.inlier_ratio > 0.5 and res.n_tracks > 300
            cur = dict(zip(gt_of(res, ids).tolist(), res.track_ids.tolist()))
            for pid, tid in prev.items():
                if pid in set(ids.tolist()):
                    possible += 1
                    continued += cur.get(pid) == tid
            # ages grow by one along continuing tracks; new tracks start at 2
            for tid, age, pi in zip(res.track_ids.tolist(), res.ages.tolist(),
                                    res.prev_indices.tolist()):
                if pi >= 0:  # matched to the previous frame (else re-acquired from older)
                    assert age == prev_age.get(tid, 1) + 1
        prev = dict(zip(gt_of(res, ids).tolist(), res.track_ids.tolist()))
        prev_age = dict(zip(res.track_ids.tolist(), res.ages.tolist()))
    assert ledger.bad <= 0.002 * ledger.total
    assert continued >= 0.95 * possible
    assert max(ledger.last_age.values()) == 8  # tracked in all 8 frames
    assert res.track_ids.dtype == np.uint32 and res.ages.dtype == np.uint16


def test_time_going_backwards_resets_with_new_ids() -> None:
    world = World(seed=2)
    m = SequentialMatcher()
    seen: set[int] = set()
    for k in range(4):
        res = m.process(world.frame(k)[0])
        seen |= set(res.track_ids.tolist())
    alive = set(res.track_ids.tolist())
    res = m.process(world.frame(1, stamp_k=0)[0])  # bag loop: back to the start
    assert 'backwards' in res.reset and res.n_tracks == 0 and res.n_matches == 0
    assert alive <= set(res.terminated_ids.tolist())
    res = m.process(world.frame(2, stamp_k=1)[0])
    assert res.n_tracks > 300 and res.n_new == res.n_tracks
    assert min(res.track_ids.tolist()) > max(seen)


def test_termination_then_new_id_and_reacquisition_within_window() -> None:
    world = World(seed=3)
    conf = {'tracking': {'max_missed': 1, 'reacquire_window': 2}}
    m = SequentialMatcher(conf)
    ledger = Ledger()
    hide = world.rng.random(len(world.points)) < 0.4
    tid_before: dict[int, int] = {}
    for k in range(3):
        f, ids = world.frame(k)
        res = m.process(f)
        ledger.add(res, ids)
    tid_before = dict(zip(gt_of(res, ids).tolist(), res.track_ids.tolist()))
    # Frame 3: 40 % of the points are hidden (occlusion) -> their tracks miss one frame.
    f, ids = world.frame(3, hide=hide)
    res = m.process(f)
    ledger.add(res, ids)
    # Frame 4: they are back; lost 1 frame <= max_missed -> re-acquired with the same ids.
    f, ids = world.frame(4)
    res = m.process(f)
    ledger.add(res, ids)
    assert res.n_reacquired > 100
    back = [(pid, tid) for pid, tid in zip(gt_of(res, ids).tolist(), res.track_ids.tolist())
            if pid in tid_before and hide[pid]]
    assert len(back) > 100
    assert sum(tid_before[pid] == tid for pid, tid in back) >= 0.95 * len(back)
    # Hide them for 2 frames (> max_missed): their tracks end, they come back with new ids.
    for k in (5, 6):
        f, ids = world.frame(k, hide=hide)
        res = m.process(f)
        ledger.add(res, ids)
    ended = set(res.terminated_ids.tolist())
    assert len(ended) > 100
    for k in (7, 8):  # a new track needs a match between two frames
        f, ids = world.frame(k)
        res = m.process(f)
        ledger.add(res, ids)
    back = {pid: tid for pid, tid in zip(gt_of(res, ids).tolist(), res.track_ids.tolist())
            if pid >= 0 and hide[pid]}
    assert len(back) > 100 and not set(back.values()) & ended
    assert set(res.ages[np.isin(res.track_ids, list(back.values()))].tolist()) == {2}
    assert not set(back.values()) & set(tid_before.values())
    assert ledger.bad <= 0.002 * ledger.total  # also: no id was ever given to two points


def test_reacquisition_disabled_gives_new_ids() -> None:
    world = World(seed=3)
    m = SequentialMatcher({'tracking': {'max_missed': 1, 'reacquire_window': 0}})
    hide = world.rng.random(len(world.points)) < 0.4
    for k in range(3):
        f, ids = world.frame(k)
        res = m.process(f)
    before = set(res.track_ids.tolist())
    m.process(world.frame(3, hide=hide)[0])
    f, ids = world.frame(4)
    res = m.process(f)
    assert res.n_reacquired == 0
    assert not (hide[ids[res.indices][ids[res.indices] >= 0]]).any()  # not in the previous frame
    f, ids = world.frame(5)
    res = m.process(f)
    hidden_back = [tid for pid, tid in zip(gt_of(res, ids).tolist(), res.track_ids.tolist())
                   if pid >= 0 and hide[pid]]
    assert hidden_back and not set(hidden_back) & before


def test_frame_with_too_few_features_does_not_crash_and_tracks_come_back() -> None:
    world = World(seed=4)
    m = SequentialMatcher()
    for k in range(3):
        res = m.process(world.frame(k)[0])
    tracks_k2 = set(res.track_ids.tolist())
    f, _ = world.frame(3)
    tiny = replace(f, keypoints=f.keypoints[:3], descriptors=f.descriptors[:3],
                   labels=f.labels[:3], scores=f.scores[:3], bearings=f.bearings[:3])
    res = m.process(tiny)
    assert res.n_tracks == 0 and not res.verified and res.model == 'none'
    empty = replace(f, stamp_ns=f.stamp_ns + 1, keypoints=np.zeros((0, 2)),
                    descriptors=np.zeros((0, 64), np.float32), labels=np.zeros(0, np.uint8),
                    scores=np.zeros(0, np.float32), bearings=np.zeros((0, 3)))
    res = m.process(empty)
    assert res.n_tracks == 0 and res.n_features == 0
    f, ids = world.frame(4)
    res = m.process(f)  # lost for 2 frames (= max_missed): re-acquired from frame 2
    assert res.n_reacquired > 300
    assert len(set(res.track_ids.tolist()) & tracks_k2) > 300


def test_stopped_vehicle_keeps_tracks() -> None:
    world = World(seed=5)
    m = SequentialMatcher()
    m.process(world.frame(0)[0])
    res = m.process(world.frame(1)[0])
    ids_moving = set(res.track_ids.tolist())
    ages = []
    for k in range(2, 6):  # the vehicle stands at the pose of frame 1
        res = m.process(world.frame(k, pose_k=1)[0])
        assert res.verified and res.model == 'rotation'
        assert res.n_tracks > 0.9 * len(ids_moving)
        ages.append(int(np.median(res.ages)))
    assert ages == [3, 4, 5, 6]
    assert len(set(res.track_ids.tolist()) & ids_moving) > 0.9 * len(ids_moving)
    res = m.process(world.frame(6, pose_k=2)[0])  # drives on
    assert res.model == 'essential' and res.n_tracks > 0.8 * len(ids_moving)


def test_dynamic_classes_are_never_tracked() -> None:
    world = World(seed=6, car_frac=0.3)
    m = SequentialMatcher()
    for k in range(3):
        f, ids = world.frame(k)
        res = m.process(f)
        assert not (res.labels == CAR).any()
        assert res.n_eligible == int((f.labels != CAR).sum())
    assert res.n_tracks > 300
    m_dyn = SequentialMatcher({'semantic': {'track_dynamic': True}})
    for k in range(2):
        res = m_dyn.process(world.frame(k)[0])
    assert (res.labels == CAR).sum() > 50


def test_camera_change_gap_and_duplicate_stamp() -> None:
    world = World(seed=7)
    m = SequentialMatcher()
    m.process(world.frame(0)[0])
    res = m.process(world.frame(1)[0])
    n_before = res.n_tracks
    with pytest.raises(FrameOrderError, match='repeats'):
        m.process(world.frame(1)[0])
    res = m.process(world.frame(2)[0])  # the rejected duplicate did not disturb anything
    assert res.reset == '' and res.n_tracks > 0.9 * n_before
    res = m.process(world.frame(3, camera_id='rear')[0])
    assert 'camera changed' in res.reset and res.n_tracks == 0
    res = m.process(world.frame(4, camera_id='rear', stamp_k=40)[0])  # 3.6 s later
    assert 'time gap' in res.reset and res.n_tracks == 0
    res = m.process(world.frame(5, camera_id='rear', stamp_k=41)[0])
    assert res.reset == '' and res.n_tracks > 300


def test_bearings_from_camera_and_columns_contract() -> None:
    world = World(seed=8)
    m = SequentialMatcher(camera=CAM)
    m.process(world.frame(0, with_bearings=False)[0])
    f, ids = world.frame(1, with_bearings=False)
    res = m.process(f)
    assert res.n_tracks > 300
    cols = res.columns()
    assert list(cols) == ['u', 'v', 'bx', 'by', 'bz', 'label', 'track_id', 'age', 'score']
    dtypes = {k: v.dtype for k, v in cols.items()}
    assert dtypes == {'u': np.float32, 'v': np.float32, 'bx': np.float32, 'by': np.float32,
                      'bz': np.float32, 'label': np.uint8, 'track_id': np.uint32,
                      'age': np.uint16, 'score': np.float32}
    b = np.stack([cols['bx'], cols['by'], cols['bz']], axis=1)
    assert np.allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-5)
    assert np.allclose(np.stack([cols['u'], cols['v']], 1), f.keypoints[res.indices], atol=1e-3)
    assert ((cols['score'] > 0.5) & (cols['score'] <= 1.0)).all()
    assert (res.prev_indices >= 0).all()
    st = res.stats()
    assert st['n_inliers'] == res.n_inliers and 0 < st['inlier_ratio'] <= 1
    assert res.inlier_matches.shape[0] + res.rejected_matches.shape[0] == res.n_matches


def test_binary_descriptors() -> None:
    world = World(seed=9)
    bits = world.rng.integers(0, 256, (len(world.points), 32), dtype=np.uint8)
    m = SequentialMatcher({'matching': {'descriptor_type': 'binary', 'ratio_threshold': 0.8}})
    for k in range(3):
        f, ids = world.frame(k, clutter=0.0)
        flips = (world.rng.random((ids.size, 32, 8)) < 0.03)
        noise = np.packbits(flips, axis=2)[:, :, 0]
        res = m.process(replace(f, descriptors=bits[ids] ^ noise))
    assert res.verified and res.n_tracks > 300
    assert (ids[res.indices] >= 0).all()


def test_input_and_config_errors() -> None:
    world = World(seed=10)
    f, _ = world.frame(0)
    m = SequentialMatcher()
    with pytest.raises(FeatureInputError, match='descriptors'):
        m.process(replace(f, descriptors=f.descriptors[:-1]))
    with pytest.raises(FeatureInputError, match='keypoints'):
        m.process(replace(f, keypoints=f.keypoints[:, :1]))
    with pytest.raises(FeatureInputError, match='labels'):
        m.process(replace(f, labels=f.labels[:-2]))
    with pytest.raises(FeatureInputError, match='stamp_ns'):
        m.process(replace(f, stamp_ns=1.5))
    with pytest.raises(FeatureInputError, match='no camera'):
        m.process(replace(f, bearings=None))
    with pytest.raises(MatchingConfigError, match='descriptor_type'):
        SequentialMatcher({'matching': {'descriptor_type': 'sift'}})
    with pytest.raises(MatchingConfigError, match=r'conf\.tracking\.max_mised'):
        SequentialMatcher({'tracking': {'max_mised': 3}})
    with pytest.raises(MatchingConfigError, match='unknown class'):
        SequentialMatcher({'semantic': {'compatible_groups': [['road', 'asphalt']]}})
    res = m.process(f)  # errors above left the matcher untouched
    assert res.reset == 'first frame'


def test_debug_image() -> None:
    world = World(seed=11)
    m = SequentialMatcher()
    m.process(world.frame(0)[0])
    res = m.process(world.frame(1, clutter=0.4)[0])
    assert res.n_inliers > 0 and res.rejected_matches.shape[0] > 0
    img = draw.draw_track_result(res, size=(640, 512))
    assert img.shape == (512, 1280, 3) and img.dtype == np.uint8
    green = (img[..., 1] > 150) & (img[..., 0] < 80)
    red = (img[..., 0] > 150) & (img[..., 1] < 80)
    assert green.sum() > 1000 and red.sum() > 50
    mono = np.full((512, 640), 100, np.uint8)
    half = draw.draw_track_result(res, mono, mono, scale=0.5)
    assert half.shape == (256, 640, 3)
    with pytest.raises(FeatureInputError, match='image size'):
        draw.draw_track_result(res)
    with pytest.raises(FeatureInputError, match='indices'):
        draw.draw_matches(None, None, np.zeros((2, 2)), np.zeros((2, 2)), [[0, 5]],
                          size=(10, 10))


def test_id_overflow_is_reported_and_leaves_a_clean_state() -> None:
    world = World(seed=12)
    m = SequentialMatcher()
    m.tracks = TrackManager(first_id=MAX_TRACK_ID)  # as if 2**32 - 1 ids had been used
    m.process(world.frame(0)[0])
    with pytest.raises(TrackIdOverflowError):
        m.process(world.frame(1)[0])
    res = m.process(world.frame(2)[0])  # the matcher restarted cleanly
    assert res.reset == 'first frame' and res.n_tracks == 0


def test_motion_gate_uses_the_image_width() -> None:
    # the second frame is the first one shifted by 0.3 image widths: beyond the default gate
    # (0.15 widths per frame step), so nothing continues; without the gate everything does
    world = World(seed=5)
    f0, _ = world.frame(0, clutter=0.0)
    shifted = f0.keypoints + np.array([0.3 * CAM.width, 0.0])
    f1 = replace(f0, stamp_ns=f0.stamp_ns + STEP_NS, keypoints=shifted,
                 bearings=f0.bearings.copy())
    gated = SequentialMatcher(camera=CAM)
    gated.process(f0)
    assert gated.process(f1).matches.shape[0] == 0
    # the width comes from the frame when the matcher has no camera
    no_cam = SequentialMatcher()
    no_cam.process(replace(f0, image_width=CAM.width))
    assert no_cam.process(replace(f1, image_width=CAM.width)).matches.shape[0] == 0
    free = SequentialMatcher({'matching': {'max_displacement': 0.0}}, camera=CAM)
    free.process(f0)
    assert free.process(f1).matches.shape[0] > 0.9 * len(f0.keypoints)
