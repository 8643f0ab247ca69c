"""State records of the mapper: tracks, landmarks, keyframes, factor records and the shared state.

:class:`MapperSetup` is what a mapper derives once from its configuration, camera and extrinsic
(frames, class masks, noise models); :class:`MapState` is the state that tracking,
initialisation, local mapping, GNSS alignment, outlier handling and the backend share (the
trajectory, the window's keyframes and landmarks, the live tracks, counters). Every factor sent
to the smoother is a :class:`FactorRecord` of one :class:`RecordKind`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import gtsam
import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.labels import LabelSet, load_labels
from semfeat_ros.mapping import factors as fac
from semfeat_ros.mapping.config import merge_conf
from semfeat_ros.mapping.errors import MapperConfigError
from semfeat_ros.mapping.geometry import adjoint, se3_inv, transform_covariance
from semfeat_ros.mapping.types import OdometryDelta


class RecordKind(Enum):
    """What a factor record constrains, and why it is in the graph."""

    BEARING = 'bearing'  # unit bearing of a landmark from a keyframe
    GROUND = 'ground'  # ground landmark at the camera height below a keyframe
    ODOM = 'odom'  # wheel odometry between two keyframes
    VROT = 'vrot'  # two-view relative rotation between two keyframes
    LEVEL = 'level'  # a keyframe on a level plateau: base z axis up
    GNSS = 'gnss'  # GNSS antenna position of a keyframe
    PRIOR = 'prior'  # pose prior fixing the map frame (first keyframe)
    LINK = 'link'  # re-initialised segment tied to the one before tracking was lost
    ANCHOR = 'anchor'  # stand-in prior of a rebuilt window (oldest poses, thin landmarks)
    RECOVERY = 'recovery'  # loose prior on every variable after a failed update
    DEAD = 'dead'  # loose prior keeping a killed landmark's variable determined
    MARGINAL = 'marginal'  # marginal factor of states the smoother marginalised


@dataclass(eq=False)
class FactorRecord:
    """One factor of the smoother's graph with what it belongs to (keyframe, landmark)."""

    rid: int
    factor: Any  # gtsam.NonlinearFactor
    kind: RecordKind
    kid: int = -1
    lid: int = -1
    index: int = -1  # slot in the smoother's factor graph
    removed: bool = False  # rejected (outlier, superseded prior): not in the full graph
    bearing: np.ndarray | None = None  # (3,) unit bearing of a BEARING record
    pixel: np.ndarray | None = None  # (2,) px of a BEARING record


@dataclass(eq=False)
class Track:
    """A front-end track while it is seen: label votes and its keyframe observations."""

    counts: dict[int, int] = field(default_factory=dict)  # label -> frames
    n: int = 0  # frames seen
    n_dyn: int = 0  # frames labelled with a dynamic class
    major: int = 0  # majority label
    kf_obs: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # kid ->
    #                                                 (unit bearing (3,), pixel (2,) px)
    lid: int = -1  # landmark id (-1: none)
    frozen: np.ndarray | None = None  # position of its marginalised landmark (m)
    rejected: bool = False


@dataclass(eq=False)
class Landmark:
    """A landmark of the window (variable ``L(lid)``)."""

    lid: int
    track: int
    label: int
    ground: bool
    xyz: np.ndarray  # (3,) position in map (m)
    rids: list[int] = field(default_factory=list)
    n_obs: int = 0
    n_bad: int = 0
    kf_ids: list[int] = field(default_factory=list)  # keyframes that observed it
    ray0: np.ndarray | None = None  # first observation ray in the map frame
    max_par: float = 0.0  # largest angle between its observation rays (rad)
    last_kf: int = 0
    reproj_px: float = 0.0
    alive: bool = True
    anchor: tuple[int, float, float] = (-1, np.nan, np.nan)  # (stamp ns, u px, v px): where it
    #                                   was triangulated (kept for evaluation against truth)


@dataclass(eq=False)
class Keyframe:
    """A keyframe of the window (variable ``X(kid)``)."""

    kid: int
    stamp_ns: int
    n_tracks: int
    odom_linked: bool = False
    rids: list[int] = field(default_factory=list)


class OdomChain:
    """Composition of odometry deltas with first-order covariance propagation."""

    def __init__(self, ok: bool) -> None:
        self.T = np.eye(4)
        self.cov = np.zeros((6, 6))
        self.ok = ok
        self.dist = 0.0
        self.raw_yaw = 0.0  # heading change as measured, before the calibration (rad)
        self.raw_dist = 0.0  # distance as measured, before the calibration (m)
        self.dt = 0.0  # time in motion (s)

    def add(self, d: OdometryDelta, raw: tuple[float, float, float] = (0.0, 0.0, 0.0)
            ) -> None:
        """Compose delta ``d``; ``raw``: its measured (heading change rad, distance m, time in
        motion s)."""
        A = adjoint(se3_inv(d.T))
        self.cov = A @ self.cov @ A.T + d.covariance
        self.T = self.T @ d.T
        self.dist += float(np.linalg.norm(d.T[:3, 3]))
        self.raw_yaw += raw[0]
        self.raw_dist += raw[1]
        self.dt += raw[2]


@dataclass
class PendingFix:
    """A GNSS fix of a frame that was not a keyframe, waiting for the next keyframe."""

    stamp_ns: int
    position: np.ndarray  # (3,) antenna (m): ENU before the alignment, map frame after
    covariance: np.ndarray  # (3, 3) m^2
    T_wb: np.ndarray | None  # estimated base pose at the fix's frame


class MapperSetup:
    """What a mapper derives once from ``conf``, the camera and the extrinsic.

    ``camera`` is the model the bearings came through (its focal length and reprojection
    errors in px); ``T_base_cam`` (4, 4) the base_link -> camera optical frame extrinsic (m).
    """

    def __init__(self, camera: CameraModel, T_base_cam: np.ndarray,
                 conf: dict[str, Any] | None = None, labels: LabelSet | None = None) -> None:
        self.conf = merge_conf(conf)
        self.camera = camera
        T = np.asarray(T_base_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(
                T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6):
            raise MapperConfigError(
                f'T_base_cam must be a finite 4x4 rigid transform, got shape {T.shape}')
        self.T_bc = T
        self.T_cb = se3_inv(T)
        self.up_c = self.T_bc[2, :3].copy()  # base_link z axis in the optical frame
        height = self.conf['camera_height_m']
        self.camera_height = float(height if height is not None else self.T_bc[2, 3])  # m
        if self.camera_height <= 0:
            raise MapperConfigError(
                f'camera height above the ground must be > 0 m, got {self.camera_height} '
                '(set camera_height_m or the z of T_base_cam)')
        self.labels = labels if labels is not None else load_labels(self.conf['labels_path'])
        n_cls = len(self.labels.names)
        self.static = np.zeros(256, bool)  # class id -> may become a landmark
        self.static[:n_cls] = self.labels.static & ~self.labels.dynamic
        self.dynamic = np.zeros(256, bool)
        self.dynamic[:n_cls] = self.labels.dynamic
        self.hangs = self._class_mask('ceiling_labels')
        self.ground = self._class_mask('ground_labels')
        self.sigma = self.conf['bearing_sigma_px'] / float(camera.fx)  # rad
        self.gate = float(np.sqrt(self.conf['outlier_chi2'])) * self.sigma  # rad
        self.bearing_noise = fac.bearing_noise(self.sigma, self.conf['robust_kernel'],
                                               self.conf['robust_k'])
        self.ground_noise = fac.robust(
            gtsam.noiseModel.Isotropic.Sigma(1, self.conf['ground_sigma_m']), 'huber', 1.345)
        self.arm_b = np.asarray(self.conf['gnss_lever_arm_m'], dtype=np.float64)  # m
        self.arm_c = self.T_cb[:3, :3] @ self.arm_b + self.T_cb[:3, 3]  # m

    def _class_mask(self, key: str) -> np.ndarray:
        """(256,) bool lookup by class id of the class names in ``conf[key]``."""
        mask = np.zeros(256, bool)
        for name in self.conf[key]:
            try:
                mask[self.labels.id_of(name)] = True
            except KeyError as exc:
                raise MapperConfigError(f'{key}: {exc.args[0]}') from None
        return mask

    def prior_cov(self) -> np.ndarray:
        """(6, 6) covariance (rad^2, m^2) of a pose prior, in the camera frame."""
        sr, sm = self.conf['prior_sigma_rad'], self.conf['prior_sigma_m']
        cov_b = np.diag([sr**2] * 3 + [sm**2] * 3)
        return transform_covariance(cov_b, self.T_bc)

    def smoother_ts(self, kid: int) -> float:
        """Smoother timestamp of keyframe ``kid``: quantised to ``marginalize_every`` so that
        old states leave the window in batches (one full re-elimination per batch instead of
        one per keyframe)."""
        m = self.conf['marginalize_every']
        return float(kid // m * m)


STATS_KEYS = (
    'frames', 'keyframes', 'landmarks', 'update_failures', 'recoveries', 'outlier_factors',
    'landmarks_killed', 'landmarks_lost_depth', 'gnss_accepted', 'gnss_rejected',
    'tracking_lost', 'initialisations', 'rejected_rows', 'obs_beyond_90deg',
    'rotation_factors', 'level_factors')


class MapState:
    """The mapper's state shared by its parts; :meth:`MapState.__init__` is a new map."""

    def __init__(self, setup: MapperSetup) -> None:
        self.setup = setup
        self.rng = np.random.default_rng(setup.conf['seed'])
        self.state = 'initializing'  # 'initializing', 'tracking', 'odometry_only' or 'lost'
        self.metric = False
        self.scale_from_odometry = False
        self.gnss_aligned = False  # the map frame's pose in ENU is known (mapping/gnss.py)
        self.tracks: dict[int, Track] = {}
        # the trajectory: every keyframe ever made, in order (kid = index)
        self.kf_stamps: list[int] = []
        self.kf_T_wc: list[np.ndarray] = []  # camera poses in map (m)
        self.kf_alt: list[float] = []  # base altitudes (m)
        self.kfs: dict[int, Keyframe] = {}  # the window's keyframes
        self.last_kid = -1
        self.lms: dict[int, Landmark] = {}  # the window's landmarks
        self.lm_by_ts: dict[int, set[int]] = {}  # last observing keyframe -> landmarks
        self.next_lid = 0
        self.next_rid = 0
        self.all_recs: list[FactorRecord] = []  # every record made (keep_full_graph)
        self.final_xyz: dict[int, np.ndarray] = {}  # marginalised landmarks (keep_full_graph)
        self.history: list[tuple[int, np.ndarray]] = []  # (stamp, T_wc) of the last frames
        self.kf_odom = OdomChain(False)  # odometry since the last keyframe
        self.ref_odom = OdomChain(False)  # odometry since the two-view reference frame
        self.link: dict[str, Any] | None = None  # where tracking was lost (kid, stamp, T_wc, xi)
        self.stats: dict[str, int] = dict.fromkeys(STATS_KEYS, 0)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe trajectory: ``(stamps_ns (K,) int64, T_map_base (K, 4, 4))`` (m)."""
        stamps = np.array(self.kf_stamps, dtype=np.int64)
        if not self.kf_T_wc:
            return stamps, np.zeros((0, 4, 4))
        return stamps, np.array(self.kf_T_wc) @ self.setup.T_cb

    def record(self, factor: Any, kind: RecordKind, kid: int = -1, lid: int = -1,
               bearing: np.ndarray | None = None, pixel: np.ndarray | None = None
               ) -> FactorRecord:
        """A new factor record (kept for the full graph with ``keep_full_graph``)."""
        rec = FactorRecord(self.next_rid, factor, kind, kid, lid, bearing=bearing, pixel=pixel)
        self.next_rid += 1
        if self.setup.conf['keep_full_graph']:
            self.all_recs.append(rec)
        return rec

    def new_keyframe(self, stamp_ns: int, T_wc: np.ndarray, n_tracks: int) -> int:
        """Append keyframe ``kid`` at camera pose ``T_wc`` to the trajectory and window."""
        kid = len(self.kf_stamps)
        self.kf_stamps.append(int(stamp_ns))
        self.kf_T_wc.append(np.array(T_wc))
        self.kf_alt.append(float((T_wc @ self.setup.T_cb)[2, 3]))
        self.kfs[kid] = Keyframe(kid, int(stamp_ns), n_tracks)
        self.last_kid = kid
        self.stats['keyframes'] += 1
        return kid
