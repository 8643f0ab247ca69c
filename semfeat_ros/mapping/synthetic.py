"""A small synthetic parking structure for tests and benchmarks of the mapper (no rendering).

The world is a corridor of a parking garage built around a driven path: a ground surface that
follows the path's altitude (level stretches joined by ramps), walls, pillars, a ceiling, painted
lines, parked cars (dynamic class, static geometry) and walking pedestrians (moving). Frames are
the tracks a perfect matcher would produce: every visible point keeps its track id while it
stays visible; bearings go through the real camera model with pixel noise, so fisheye
observations beyond 90 degrees off-axis occur. Wheel odometry and GNSS are simulated from the
ground truth.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from semfeat_ros.camera import CameraModel
from semfeat_ros.labels import load_labels
from semfeat_ros.mapping.geometry import se3_inv, unit, yaw_of
from semfeat_ros.mapping.types import GnssFix, OdometryDelta, Tracks


@dataclass(frozen=True)
class PathSegment:
    """A stretch of the drive: ``length`` (m) with ``turn`` (rad, left positive) of heading and
    ``rise`` (m) of altitude spread evenly over it."""

    length: float
    turn: float = 0.0
    rise: float = 0.0


GARAGE_SEGMENTS = (
    PathSegment(16.0, 0.15), PathSegment(20.0, -0.15, 3.0), PathSegment(22.0, 0.2),
)
"""Level 0 (16 m), a 15 % ramp up 3 m, level 1 (22 m): about 58 m in total."""


def long_drive_segments(length_m: float) -> tuple[PathSegment, ...]:
    """A serpentine drive of about ``length_m`` with a 3 m ramp up and down every 120 m."""
    segs: list[PathSegment] = []
    total, i = 0.0, 0
    pattern = (PathSegment(30.0, 0.3), PathSegment(20.0, 0.0, 3.0), PathSegment(30.0, -0.6),
               PathSegment(20.0, 0.0, -3.0), PathSegment(20.0, 0.3))
    while total < length_m:
        seg = pattern[i % len(pattern)]
        segs.append(seg)
        total += seg.length
        i += 1
    return tuple(segs)


@dataclass(frozen=True)
class GroundTruthPath:
    """Base poses along the path sampled every ``step`` metres (m, map frame, z up)."""

    s: np.ndarray  # (K,) travelled distance (m)
    poses: np.ndarray  # (K, 4, 4) T_map_base


def make_path(segments: tuple[PathSegment, ...] = GARAGE_SEGMENTS, step: float = 0.05,
              smooth_m: float = 1.5) -> GroundTruthPath:
    """Integrate heading and altitude along ``segments``; ramp ends are smoothed (Gaussian,
    ``smooth_m``) so pitch changes continuously. The first pose is the identity (level)."""
    n = [max(1, int(round(seg.length / step))) for seg in segments]
    dpsi = np.concatenate([np.full(k, seg.turn / k) for k, seg in zip(n, segments)])
    dz = np.concatenate([np.full(k, seg.rise / k) for k, seg in zip(n, segments)])
    if smooth_m > 0:
        half = int(3 * smooth_m / step)
        kern = np.exp(-0.5 * (np.arange(-half, half + 1) * step / smooth_m) ** 2)
        kern /= kern.sum()
        dz = np.convolve(np.concatenate([np.zeros(half), dz, np.zeros(half)]), kern, 'valid')
        dpsi = np.convolve(np.concatenate([np.zeros(half), dpsi, np.zeros(half)]), kern,
                           'valid')
    psi = np.concatenate([[0.0], np.cumsum(dpsi)])
    dh = np.sqrt(np.maximum(step**2 - dz**2, 1e-12))
    x = np.concatenate([[0.0], np.cumsum(dh * np.cos(psi[:-1]))])
    y = np.concatenate([[0.0], np.cumsum(dh * np.sin(psi[:-1]))])
    z = np.concatenate([[0.0], np.cumsum(dz)])
    P = np.stack([x, y, z], axis=1)
    tangent = unit(np.gradient(P, axis=0))
    zw = np.array([0.0, 0.0, 1.0])
    poses = np.tile(np.eye(4), (len(P), 1, 1))
    for i in range(len(P)):
        xb = tangent[i]
        yb = unit(np.cross(zw, xb))
        poses[i, :3, :3] = np.stack([xb, yb, np.cross(xb, yb)], axis=1)
        poses[i, :3, 3] = P[i]
    # Start exactly level at the origin (the mapper's map frame is the first base pose).
    poses = np.einsum('ij,kjl->kil', se3_inv(poses[0]), poses)
    return GroundTruthPath(np.arange(len(P)) * step, poses)


@dataclass(frozen=True)
class SyntheticWorld:
    """World points (P, 3) m with class ids and velocities (m/s; non-zero for walkers)."""

    points: np.ndarray
    labels: np.ndarray
    velocity: np.ndarray
    ground_alt: np.ndarray  # (P,) altitude of the floor under each point (m): its level

    def at(self, t: float) -> np.ndarray:
        """Point positions at time ``t`` (s)."""
        return self.points + self.velocity * t


def make_world(path: GroundTruthPath, seed: int = 0, *, half_width: float = 7.5,
               ceiling: float = 2.7, density: float = 1.0, extend_m: float = 25.0
               ) -> SyntheticWorld:
    """Garage corridor around ``path``: ground, lines, walls, pillars, ceiling, cars, walkers.

    ``density`` scales every point count (1.0: roughly 200-400 visible points per frame);
    the corridor continues ``extend_m`` (m) beyond the end of the path.
    """
    rng = np.random.default_rng(seed)
    names = load_labels().names
    lab = {name: names.index(name) for name in names}
    pts: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    vel: list[np.ndarray] = []
    alt: list[np.ndarray] = []
    ground = [0.0]

    def add(p: np.ndarray, name: str, v: np.ndarray | None = None) -> None:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        pts.append(p)
        labels.append(np.full(len(p), lab[name], np.uint8))
        vel.append(np.zeros_like(p) if v is None else np.broadcast_to(v, p.shape).copy())
        alt.append(np.full(len(p), ground[0]))

    step = float(path.s[1] - path.s[0]) if len(path.s) > 1 else 1.0
    every = max(1, int(round(1.0 / step)))
    samples = [(path.poses[i], float(path.s[i])) for i in range(0, len(path.s), every)]
    last, s_end = path.poses[-1], float(path.s[-1])
    flat = np.array(last)
    flat[:3, :3] = np.stack([unit(last[:3, 0] * [1, 1, 0]), unit(last[:3, 1] * [1, 1, 0]),
                             [0.0, 0.0, 1.0]], axis=1)
    for k in range(1, int(extend_m) + 1):  # the structure continues beyond the drive (level)
        T = np.array(flat)
        T[:3, 3] = last[:3, 3] + k * flat[:3, 0]
        samples.append((T, s_end + k))
    for T, s in samples:
        c, fwd, left, up = T[:3, 3], T[:3, 0], T[:3, 1], T[:3, 2]
        ground[0] = float(c[2])

        def place(u: np.ndarray, lat: np.ndarray, h: np.ndarray, c: np.ndarray = c,
                  fwd: np.ndarray = fwd, left: np.ndarray = left, up: np.ndarray = up
                  ) -> np.ndarray:
            return c + u[:, None] * fwd + lat[:, None] * left + h[:, None] * up

        k = rng.poisson(6.0 * density)
        u, lat = rng.uniform(-0.5, 0.5, k), rng.uniform(-half_width, half_width, k)
        add(place(u, lat, np.zeros(k)), 'road')
        if int(s) % 3 == 0:  # painted bay lines across the parking bays on both sides
            k = rng.poisson(2.0 * density)
            lat = rng.choice([-1.0, 1.0], k) * rng.uniform(3.5, half_width - 0.3, k)
            add(place(rng.uniform(-0.06, 0.06, k), lat, np.zeros(k)), 'parking_line')
        if int(s) % 4 < 2:  # dashed centre divider
            k = rng.poisson(1.0 * density)
            add(place(rng.uniform(-0.5, 0.5, k), rng.uniform(-0.07, 0.07, k), np.zeros(k)),
                'lane_divider')
        for side in (-1.0, 1.0):
            k = rng.poisson(2.0 * density)
            add(place(rng.uniform(-0.5, 0.5, k), np.full(k, side * half_width),
                      rng.uniform(0.05, ceiling, k)), 'wall')
        k = rng.poisson(2.5 * density)
        add(place(rng.uniform(-0.5, 0.5, k), rng.uniform(-half_width, half_width, k),
                  np.full(k, ceiling)), 'ceiling')
        if int(s) % 8 == 0:
            for side in (-1.0, 1.0):
                ang = rng.uniform(0, 2 * np.pi, int(8 * density) + 2)
                h = rng.uniform(0.05, ceiling, len(ang))
                p = place(0.3 * np.cos(ang), side * 4.2 + 0.3 * np.sin(ang), h)
                add(p, 'pillar')
        if int(s) % 12 == 6:
            side = rng.choice([-1.0, 1.0])
            add(place(rng.uniform(-0.3, 0.3, 3), np.full(3, side * (half_width - 0.01)),
                      rng.uniform(1.8, 2.2, 3)), 'sign')
        if int(s) % 5 == 2 and rng.random() < 0.6:  # parked car: dynamic class, static shape
            side = rng.choice([-1.0, 1.0])
            k = int(12 * density) + 2
            add(place(rng.uniform(-2.2, 2.2, k), side * 5.5 + rng.uniform(-0.9, 0.9, k),
                      rng.uniform(0.3, 1.5, k)), 'car')
        if int(s) % 15 == 10:  # a pedestrian crossing the lane at 1.2 m/s
            k = 6
            p = place(rng.uniform(-0.2, 0.2, k), np.full(k, -4.0) + rng.uniform(-0.2, 0.2, k),
                      rng.uniform(0.2, 1.8, k))
            add(p, 'pedestrian', 1.2 * left)
    return SyntheticWorld(np.concatenate(pts), np.concatenate(labels), np.concatenate(vel),
                          np.concatenate(alt))


@dataclass(frozen=True)
class SyntheticFrame:
    """One frame of a synthetic drive with its ground truth."""

    tracks: Tracks
    T_map_base: np.ndarray  # (4, 4) ground-truth base pose (m)
    point_index: np.ndarray  # (N,) world point of each track (ground truth association)
    outlier: np.ndarray  # (N,) bool: observation replaced by a wrong pixel
    odometry: OdometryDelta | None
    gnss: GnssFix | None


#: Keypoint noise (px) a mapper is told for the synthetic tracks (they carry
#: ``DriveConfig.pixel_sigma_px``, 0.5 px, by default), not the one sized for the network.
MAPPER_SIGMA_PX = 1.0


@dataclass
class DriveConfig:
    """Sensor simulation of :class:`SyntheticDrive` (units in the names)."""

    frame_step_m: float = 0.25  # distance between frames (m)
    speed_mps: float = 2.5  # vehicle speed (m/s): frame period = step / speed
    max_range_m: float = 18.0  # matcher range (m)
    pixel_sigma_px: float = 0.5  # keypoint noise (px)
    outlier_fraction: float = 0.0  # observations replaced by random pixels in every frame
    bursts: dict[int, float] = field(default_factory=dict)  # frame -> outlier fraction
    track_break_prob: float = 0.01  # per frame: a track is lost and restarts with a new id
    drop_frames: frozenset[int] = frozenset()  # frames never emitted (their motion is kept)
    odometry: bool = False  # emit wheel odometry (SE(2) deltas)
    odom_sigma_rel: float = 0.01  # odometry noise: fraction of the distance per frame
    odom_sigma_yaw: float = 0.002  # odometry yaw noise per frame (rad)
    odom_yaw_bias: float = 0.0  # odometry yaw-rate bias (rad/s)
    odom_yaw_scale: float = 0.0  # odometry yaw scale error (measured = (1 + this) * true)
    odom_dist_scale: float = 0.0  # odometry distance scale error (same convention)
    gnss_every: int = 0  # emit a GNSS fix every this many frames (0: never) ...
    gnss_start: int = 0  # ... from this frame on (e.g. the drive leaves a covered deck) ...
    gnss_end: int | None = None  # ... and before this frame (None: to the end)
    gnss_sigma_m: float = 0.03  # fix noise (m)
    gnss_jumps: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    T_enu_map: np.ndarray = field(default_factory=lambda: np.eye(4))  # GNSS frame vs map
    seed: int = 0


class SyntheticDrive:
    """Frames of a drive along ``path`` through ``world`` seen by ``camera`` at ``T_base_cam``."""

    def __init__(self, world: SyntheticWorld, path: GroundTruthPath, camera: CameraModel,
                 T_base_cam: np.ndarray, conf: DriveConfig | None = None) -> None:
        self.world = world
        self.path = path
        self.camera = camera
        self.T_base_cam = np.asarray(T_base_cam, dtype=np.float64)
        self.conf = conf or DriveConfig()
        step = float(path.s[1] - path.s[0])
        every = max(1, int(round(self.conf.frame_step_m / step)))
        self.frame_poses = path.poses[::every]
        period_ns = int(round(self.conf.frame_step_m / self.conf.speed_mps * 1e9))
        self.stamps_ns = 1_000_000_000 + np.arange(len(self.frame_poses)) * period_ns
        self._tree = cKDTree(world.points) if not world.velocity.any() else None

    def __len__(self) -> int:
        return len(self.frame_poses)

    def _visible(self, T_map_base: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        T_map_cam = T_map_base @ self.T_base_cam
        c = T_map_cam[:3, 3]
        if self._tree is not None:
            idx = np.array(self._tree.query_ball_point(c, self.conf.max_range_m), dtype=int)
            pts = self.world.points[idx] if len(idx) else np.zeros((0, 3))
        else:
            pts_all = self.world.at(t)
            idx = np.flatnonzero(
                np.linalg.norm(pts_all - c, axis=1) <= self.conf.max_range_m)
            pts = pts_all[idx]
        p_c = (pts - c) @ T_map_cam[:3, :3]
        px, valid = self.camera.project(p_c)
        valid &= self.camera.in_image(px, border=2.0)
        valid &= np.linalg.norm(p_c, axis=1) > 0.5
        return idx[valid], px[valid]

    def frames(self) -> Iterator[SyntheticFrame]:
        """Emit the frames in order (``drop_frames`` skipped, odometry composed across them)."""
        conf = self.conf
        rng = np.random.default_rng(conf.seed)
        next_id = 1
        track_of: dict[int, int] = {}
        T_odom_from = self.frame_poses[0]
        for f, T in enumerate(self.frame_poses):
            t = (self.stamps_ns[f] - self.stamps_ns[0]) * 1e-9
            idx, px = self._visible(T, t)
            new_track_of: dict[int, int] = {}
            ids = np.empty(len(idx), np.int64)
            for j, pi in enumerate(idx.tolist()):
                tid = track_of.get(pi)
                if tid is None or rng.random() < conf.track_break_prob:
                    tid = next_id
                    next_id += 1
                new_track_of[pi] = tid
                ids[j] = tid
            track_of = new_track_of
            if f in conf.drop_frames:
                continue
            px = px + rng.normal(0.0, conf.pixel_sigma_px, px.shape)
            frac = conf.bursts.get(f, conf.outlier_fraction)
            outlier = rng.random(len(px)) < frac
            if outlier.any():
                r = rng.uniform(0.0, 1.0, (int(outlier.sum()), 2))
                px[outlier] = r * [self.camera.width - 1, self.camera.height - 1]
            bearings = self.camera.unproject(px, check=False)
            ok = np.isfinite(bearings).all(axis=1)
            tracks = Tracks(int(self.stamps_ns[f]), ids[ok].astype(np.uint32), bearings[ok],
                            px[ok], self.world.labels[idx[ok]])
            odom = None
            if conf.odometry and f > 0:
                odom = self._odometry(T_odom_from, T, rng)
            T_odom_from = T
            gnss = None
            if (conf.gnss_every and f >= conf.gnss_start and f % conf.gnss_every == 0
                    and (conf.gnss_end is None or f < conf.gnss_end)):
                p = conf.T_enu_map[:3, :3] @ T[:3, 3] + conf.T_enu_map[:3, 3]
                p = p + rng.normal(0.0, conf.gnss_sigma_m, 3)
                if f in conf.gnss_jumps:
                    p = p + np.asarray(conf.gnss_jumps[f])
                gnss = GnssFix(int(self.stamps_ns[f]), p, np.eye(3) * conf.gnss_sigma_m**2)
            yield SyntheticFrame(tracks, T.copy(), idx[ok], outlier[ok], odom, gnss)

    def _odometry(self, T_from: np.ndarray, T_to: np.ndarray, rng: np.random.Generator
                  ) -> OdometryDelta:
        c = self.conf
        rel = se3_inv(T_from) @ T_to
        dist = float(np.linalg.norm(rel[:3, 3]))
        sig = c.odom_sigma_rel * dist + 1e-3
        k = 1.0 + c.odom_dist_scale
        dx, dy = k * rel[0, 3] + rng.normal(0, sig), k * rel[1, 3] + rng.normal(0, sig)
        dt = dist / c.speed_mps  # time in motion (s)
        dyaw = ((1.0 + c.odom_yaw_scale) * yaw_of(rel[:3, :3]) + c.odom_yaw_bias * dt
                + rng.normal(0, c.odom_sigma_yaw))
        cov = np.diag([sig**2, sig**2, self.conf.odom_sigma_yaw**2])
        return OdometryDelta.from_se2(dx, dy, dyaw, cov, sigma_z=0.01 + 0.05 * dist,
                                      sigma_roll_pitch=0.005 + 0.05 * dist)


def garage_drive(camera: CameraModel, T_base_cam: np.ndarray, conf: DriveConfig | None = None,
                 segments: tuple[PathSegment, ...] = GARAGE_SEGMENTS, world_seed: int = 0,
                 density: float = 1.0) -> SyntheticDrive:
    """The standard two-level synthetic garage drive (see :data:`GARAGE_SEGMENTS`)."""
    path = make_path(segments)
    world = make_world(path, world_seed, density=density)
    return SyntheticDrive(world, path, camera, T_base_cam, conf)


__all__ = [
    'DriveConfig', 'GARAGE_SEGMENTS', 'GroundTruthPath', 'PathSegment', 'SyntheticDrive',
    'SyntheticFrame', 'SyntheticWorld', 'garage_drive', 'long_drive_segments', 'make_path',
    'make_world',
]
