"""Incremental semantic mapper: tracks (+ wheel odometry, GNSS) -> poses and a labelled map.

One :class:`Mapper` owns a GTSAM fixed-lag smoother (``IncrementalFixedLagSmoother``: iSAM2 with
states older than ``window_keyframes`` marginalised), fed like GTSAM's VisualISAM2Example: per
keyframe the new factors and values, keys from ``gtsam.symbol_shorthand`` (``X`` camera poses,
``L`` landmarks). Marginalised landmarks move into a voxel-bounded map, so per-keyframe cost and
smoother memory stay flat on a long drive.

Pipeline per frame: validate -> the last keyframe's deferred work (outlier rejection of its
landmarks, its two-view rotation to the keyframe before, whose factor joins the next update) ->
label votes -> (two-view initialisation | pose tracking against the landmarks) -> keyframe
decision -> keyframe: bearing factors of the tracked landmarks, odometry between-factor, GNSS
factor, new landmarks triangulated from tracks seen in enough keyframes with enough parallax
(static classes only), ground-plane factors -> smoother update (failures recovered, never
raised) -> marginalisation bookkeeping.

Frames: poses returned are base_link in ``map`` (z up, m); internally the pose variables are the
camera optical frame in ``map`` so that bearings need no extrinsic inside the factors.
"""
from __future__ import annotations

from collections.abc import Callable
import time
from typing import Any

import gtsam
from gtsam.symbol_shorthand import L, X
import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.labels import LabelSet
from semfeat_ros.mapping import factors as fac
from semfeat_ros.mapping.backend import Backend, Smoother
from semfeat_ros.mapping.cloud import SemanticCloud, VoxelMap
from semfeat_ros.mapping.errors import MapperConfigError, StampOrderError
from semfeat_ros.mapping.floors import FloorLevels, detect_floors, storey_altitude
from semfeat_ros.mapping.geometry import (
    align_yaw,
    angle_between,
    fit_plane_ransac,
    refine_pose_bearings,
    relative_pose_known_motion,
    se3_exp,
    se3_inv,
    se3_log,
    skew,
    so3_exp,
    so3_log,
    transform_covariance,
    triangulate_bearings,
    vehicle_camera_translation,
    yaw_of,
)
from semfeat_ros.mapping.odometry import OdometryCalibration
from semfeat_ros.mapping.state import (
    FactorRecord,
    Landmark,
    MapperSetup,
    MapState,
    OdomChain,
    PendingFix,
    RecordKind,
    Track,
)
from semfeat_ros.mapping.types import GnssFix, MapperResult, OdometryDelta, Tracks
from semfeat_ros.matching.geometry import (
    epipolar_sines,
    refine_pose,
    refine_rotation,
    verify_bearings,
)

STATES = ('initializing', 'tracking', 'odometry_only', 'lost')
_STILL_M = 1e-3  # an odometry delta shorter than this (m) is a stop
_GNSS_ANCHOR_KF = 3  # a keyframe pair counts as GNSS-anchored with fixes this close (keyframes)
class Mapper:
    """Incremental fixed-lag factor-graph mapper.

    ``camera`` is the model the bearings came through (used for its focal length and for
    reprojection errors in px); ``T_base_cam`` (4, 4) the base_link -> camera optical frame
    extrinsic (m); ``conf`` overrides :data:`semfeat_ros.mapping.config.default_conf`.
    """

    def __init__(self, camera: CameraModel, T_base_cam: np.ndarray,
                 conf: dict[str, Any] | None = None, labels: LabelSet | None = None, *,
                 wrap_smoother: Callable[[Smoother], Smoother] | None = None) -> None:
        self._wrap_smoother = wrap_smoother
        self.setup = MapperSetup(camera, T_base_cam, conf, labels)
        self.conf = self.setup.conf
        self.camera = camera
        self.T_bc, self.T_cb = self.setup.T_bc, self.setup.T_cb
        self.camera_height = self.setup.camera_height
        self.labels = self.setup.labels
        self.sigma = self.setup.sigma
        self.reset()

    def reset(self) -> None:
        """Forget everything (map, trajectory, smoother); the next frame starts a new map."""
        self.st = MapState(self.setup)
        self._last_stamp: int | None = None
        # the last keyframe's deferred work (see _settle): the keyframe pair whose rotation is
        # verified (ka, kb, bearings a, b) and the landmarks whose factors are checked
        self._rot_job: tuple[int, int, np.ndarray, np.ndarray] | None = None
        self._checks_due: list[int] | None = None
        self._voxels = VoxelMap(self.conf['voxel_size_m'], self.conf['max_map_points'])
        self.backend = Backend(self.setup, self.st, self._finalize_landmark,
                               self._lose_tracking, self._wrap_smoother)
        # tracking
        self._kf_odom = OdomChain(False)
        self._ref: dict[str, Any] | None = None
        self._ref_odom = OdomChain(False)
        self._init_attempts = 0
        # gnss
        self._gnss_pending: PendingFix | None = None
        self._gnss_pairs: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._gnss_rejects = 0
        self._gnss_kids: set[int] = set()  # keyframes with a GNSS factor, not yet marginalised
        # odometry calibration; per keyframe the raw (heading change, distance, time in
        # motion) of the odometry from the previous keyframe
        c = self.conf
        self._odom_cal = OdometryCalibration(
            c['odom_calib_sigma_rad'], c['odom_calib_sigma_m'], c['odom_calib_prior_bias'],
            c['odom_calib_prior_scale'], c['odom_calib_min_pairs']
        ) if c['odom_calibration'] else None
        self._kf_odom_raw: dict[int, tuple[float, float, float]] = {}
        self._floors: FloorLevels | None = None
        self._floors_at = -1

    @property
    def stats(self) -> dict[str, int]:
        """Counters since the last :meth:`reset` (frames, keyframes, landmarks, failures...)."""
        return self.st.stats

    @property
    def state(self) -> str:
        """'initializing', 'tracking', 'odometry_only' or 'lost'."""
        return self.st.state

    @property
    def metric(self) -> bool:
        """True once the scale comes from odometry, GNSS or the ground plane."""
        return self.st.metric

    @property
    def odometry_calibration(self) -> dict[str, float | int]:
        """The learnt odometry errors: ``yaw_bias_rad_s``, ``yaw_scale``, ``distance_scale``
        (all 0 until enough GNSS-anchored keyframe pairs) and ``pairs`` used so far."""
        c = self._odom_cal
        if c is None:
            return {'yaw_bias_rad_s': 0.0, 'yaw_scale': 0.0, 'distance_scale': 0.0, 'pairs': 0}
        return {'yaw_bias_rad_s': c.yaw_bias, 'yaw_scale': c.yaw_scale,
                'distance_scale': c.distance_scale, 'pairs': c.n_pairs}

    @property
    def gnss_aligned(self) -> bool:
        """True once the map frame has been aligned to the GNSS (ENU) frame."""
        return self.st.gnss_aligned

    def update(self, tracks: Tracks, odometry: OdometryDelta | None = None,
               gnss: GnssFix | None = None) -> MapperResult:
        """Process one frame; returns the base pose estimate and what happened.

        ``odometry`` is the base motion since the previous frame given to ``update`` (ignored
        unless ``use_odometry``); ``gnss`` a fix near this frame (ignored unless ``use_gnss``).
        Invalid inputs raise :class:`MapperInputError`; solver failures are recovered.
        """
        t0 = time.perf_counter()
        events: list[str] = []
        frame, n_bad = tracks.validated()
        if self._last_stamp is not None and frame.stamp_ns <= self._last_stamp:
            raise StampOrderError(
                f'stamp_ns {frame.stamp_ns} is not after the previous frame {self._last_stamp}')
        if odometry is not None and self.conf['use_odometry']:
            odometry = odometry.validated()
        else:
            odometry = None
        dt = 0.0 if self._last_stamp is None else (frame.stamp_ns - self._last_stamp) * 1e-9
        self._last_stamp = frame.stamp_ns
        self._settle()
        self.st.stats['frames'] += 1
        self.st.stats['rejected_rows'] += n_bad
        raw = (0.0, 0.0, 0.0)
        if odometry is not None:
            dist = float(np.linalg.norm(odometry.T[:3, 3]))
            # the odometry's yaw error accumulates while it reports motion (none at a stop)
            raw = (yaw_of(odometry.T[:3, :3]), dist, dt if dist >= _STILL_M else 0.0)
            if self._odom_cal is not None:
                odometry = self._odom_cal.correct(odometry, raw[2])
        if self.conf['use_odometry']:
            for chain in (self._kf_odom, self._ref_odom):
                if odometry is None:
                    chain.ok = False
                else:
                    chain.add(odometry, raw)
        mappable = self._vote(frame)
        fix = None
        if self.conf['use_gnss'] and gnss is not None:
            fix = self._check_fix(gnss, self._predict(frame.stamp_ns, odometry), events)
        keyframe = False
        T_wc, cov_c, n_inl = None, None, 0
        if (self.st.state == 'initializing' and odometry is not None
                and self.conf['init_from_odometry']):
            T_wc, keyframe = self._start_from_odometry(frame, mappable, fix, events)
        elif self.st.state in ('initializing', 'lost'):
            T_wc, keyframe = self._initialize(frame, mappable, fix, events)
            if T_wc is None and self.st.state == 'lost':
                T_wc = self._predict(frame.stamp_ns, odometry)
            elif keyframe:  # just initialised: the smoother's marginal of the new pose
                cov_c = self.backend.marginal_covariance(X(self.st.last_kid))
        else:
            T_wc, cov_c, n_inl, keyframe = self._track(frame, mappable, odometry, fix, events)
        self._prune_tracks(frame)
        T_wb = None if T_wc is None else T_wc @ self.T_cb
        if fix is not None and not keyframe:
            self._gnss_pending = PendingFix(fix.stamp_ns, fix.position, fix.covariance, T_wb)
        cov_b = None if cov_c is None else transform_covariance(cov_c, self.T_cb)
        if keyframe:
            events.append('keyframe')
        return MapperResult(
            frame.stamp_ns, T_wb, cov_b, self.st.state, keyframe, self.st.metric, len(frame),
            int(n_inl), len(self.st.lms) + len(self._voxels),
            (time.perf_counter() - t0) * 1e3, tuple(events))

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe trajectory: ``(stamps_ns (K,) int64, T_map_base (K, 4, 4))`` (m)."""
        stamps = np.array(self.st.kf_stamps, dtype=np.int64)
        if not self.st.kf_T_wc:
            return stamps, np.zeros((0, 4, 4))
        return stamps, np.array(self.st.kf_T_wc) @ self.T_cb

    def floor_levels(self) -> FloorLevels:
        """Levels detected from the keyframe altitude profile (recomputed when stale)."""
        k = len(self.st.kf_T_wc)
        if self._floors is None or self._floors_at != k:
            _, poses = self.trajectory()
            c = self.conf
            self._floors = detect_floors(
                poses[:, :3, 3] if k else np.zeros((0, 3)), max_slope=c['floor_max_slope'],
                slope_window_m=c['floor_slope_window_m'], min_plateau_m=c['floor_min_plateau_m'],
                merge_m=c['floor_merge_m'])
            self._floors_at = k
        return self._floors

    def cloud(self) -> SemanticCloud:
        """The map: marginalised (voxel-bounded) landmarks plus the current window's landmarks.

        Only static classes, landmarks with ``cloud_min_obs`` observations and a mean
        reprojection error within ``max_reprojection_px``; floors from :meth:`floor_levels`.
        """
        self._settle()
        levels = self.floor_levels()
        xyz_f, lab_f, lid_f, nobs_f, alt_f = self._voxels.arrays()
        rows = []
        for lm in self.st.lms.values():
            if self._publishable(lm):
                key = L(lm.lid)
                est = self.backend.estimate
                xyz = est.atPoint3(key) if est.exists(key) else lm.xyz
                rows.append((xyz, lm.label, lm.lid, lm.n_obs, self._seen_alt(lm, levels)))
        if rows:
            xyz_w = np.array([r[0] for r in rows])
            lab_w = np.array([r[1] for r in rows], np.uint8)
            lid_w = np.array([r[2] for r in rows], np.uint32)
            nobs_w = np.array([r[3] for r in rows])
            alt_w = np.array([r[4] for r in rows])
        else:
            xyz_w, lab_w, lid_w = np.zeros((0, 3)), np.zeros(0, np.uint8), np.zeros(0, np.uint32)
            nobs_w, alt_w = np.zeros(0), np.zeros(0)
        xyz = np.concatenate([xyz_f, xyz_w])
        lab = np.concatenate([lab_f, lab_w])
        keep = self.setup.static[lab]
        # floors from the current levels (they grow as the drive finds new ones)
        alt = storey_altitude(xyz[:, 2], np.concatenate([alt_f, alt_w]), levels.altitudes,
                              self.conf['floor_point_margin_m'], self.setup.hangs[lab])[keep]
        return SemanticCloud.build(
            xyz[keep], lab[keep], levels.assign(alt),
            np.concatenate([lid_f, lid_w])[keep], np.concatenate([nobs_f, nobs_w])[keep],
            self.labels.colors)

    def landmark_anchors(self, landmark_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the map's landmarks ``landmark_ids`` (N,) were triangulated: the keyframe
        stamp (N,) ns and the pixel (N, 2) px of that observation (stamp -1: not in the map).
        Lets an evaluation find each point's true position in a ground-truth range image."""
        ids = np.asarray(landmark_ids, dtype=np.int64).reshape(-1)
        stamps = np.full(len(ids), -1, np.int64)
        px = np.full((len(ids), 2), np.nan)
        _, _, lid_f, _, _ = self._voxels.arrays()
        ns_f, px_f = self._voxels.anchors()
        row_of = {int(lid): r for r, lid in enumerate(lid_f.tolist())}
        for i, lid in enumerate(ids.tolist()):
            lm = self.st.lms.get(lid)
            if lm is not None:
                stamps[i], px[i] = lm.anchor[0], lm.anchor[1:]
            elif lid in row_of:
                stamps[i], px[i] = ns_f[row_of[lid]], px_f[row_of[lid]]
        return stamps, px

    def window(self) -> dict[str, int]:
        """Size of the smoother's window: keyframes, landmarks, factors; and the voxel map."""
        return dict(keyframes=len(self.st.kfs), landmarks=len(self.st.lms),
                    factors=len(self.backend.records),
                    map_points=len(self._voxels))

    def landmark_positions(self) -> dict[int, np.ndarray]:
        """Current position (m) of every live landmark in the window (for diagnostics)."""
        self._settle()
        out = {}
        for lid, lm in self.st.lms.items():
            if lm.alive and self.backend.estimate.exists(L(lid)):
                out[lid] = self.backend.estimate.atPoint3(L(lid))
        return out

    # ------------------------------------------------------------------------------------------
    # tracks and labels
    # ------------------------------------------------------------------------------------------

    def _vote(self, frame: Tracks) -> np.ndarray:
        """Update label votes; returns the (N,) mask of tracks allowed into the map."""
        n = len(frame)
        ok = np.zeros(n, bool)
        max_dyn = self.conf['dynamic_max_fraction']
        dynamic, static = self.setup.dynamic.tolist(), self.setup.static.tolist()
        for i, (tid, lab) in enumerate(zip(frame.track_id.tolist(), frame.label.tolist())):
            tr = self.st.tracks.get(tid)
            if tr is None:
                tr = Track(major=lab)
                self.st.tracks[tid] = tr
            cnt = tr.counts.get(lab, 0) + 1
            tr.counts[lab] = cnt
            tr.n += 1
            tr.n_dyn += dynamic[lab]
            if cnt > tr.counts.get(tr.major, 0):
                tr.major = lab
            ok[i] = static[tr.major] and tr.n_dyn <= max_dyn * tr.n and not tr.rejected
        return ok

    def _prune_tracks(self, frame: Tracks) -> None:
        """Tracks absent from this frame ended (ids are never reused): forget them."""
        alive = set(frame.track_id.tolist())
        for tid in [t for t in self.st.tracks if t not in alive]:
            del self.st.tracks[tid]

    def _label_of(self, tr: Track) -> int:
        return tr.major

    # ------------------------------------------------------------------------------------------
    # prediction and tracking
    # ------------------------------------------------------------------------------------------

    def _predict(self, stamp_ns: int, odometry: OdometryDelta | None) -> np.ndarray | None:
        """Camera pose at ``stamp_ns`` from odometry or a constant-velocity model."""
        if not self.st.history:
            return None
        t1, T1 = self.st.history[-1]
        if odometry is not None:
            return T1 @ self.T_cb @ odometry.T @ self.T_bc
        if len(self.st.history) < 2:
            return T1.copy()
        t0, T0 = self.st.history[-2]
        dt_prev = (t1 - t0) * 1e-9
        dt = (stamp_ns - t1) * 1e-9
        if dt_prev <= 0:
            return T1.copy()
        xi = se3_log(se3_inv(T0) @ T1) * (dt / dt_prev)
        return T1 @ se3_exp(xi)

    def _push_pose(self, stamp_ns: int, T_wc: np.ndarray) -> None:
        self.st.history.append((stamp_ns, T_wc))
        del self.st.history[:-2]

    def _landmark_of(self, tr: Track) -> np.ndarray | None:
        if tr.lid >= 0:
            lm = self.st.lms.get(tr.lid)
            if lm is not None:
                return lm.xyz if lm.alive else None
        return tr.frozen

    def _track(self, frame: Tracks, mappable: np.ndarray, odometry: OdometryDelta | None,
               fix: GnssFix | None, events: list[str]
               ) -> tuple[np.ndarray | None, np.ndarray | None, int, bool]:
        pred = self._predict(frame.stamp_ns, odometry)
        idx = np.flatnonzero(mappable)
        sel, pts = [], []
        for i in idx.tolist():
            p = self._landmark_of(self.st.tracks[int(frame.track_id[i])])
            if p is not None:
                sel.append(i)
                pts.append(p)
        sel_a = np.array(sel, dtype=np.int64)
        P = np.array(pts).reshape(-1, 3)
        est = None
        if len(sel_a) >= 6:
            est = refine_pose_bearings(pred, P, frame.bearing[sel_a], self.sigma,
                                       huber_k=self.conf['robust_k'],
                                       chi2=self.conf['outlier_chi2'])
        n_inl = int(est.inliers.sum()) if est is not None else 0
        cov_c = None
        if n_inl >= self.conf['min_tracking_inliers']:
            T_wc, inliers, cov_c = est.T_w_c, est.inliers, est.covariance
            if self.st.state != 'tracking':
                events.append('tracking_resumed')
            self.st.state = 'tracking'
        elif odometry is not None:
            T_wc = pred
            if len(sel_a):
                d = (P - T_wc[:3, 3]) @ T_wc[:3, :3]
                inliers = angle_between(d, frame.bearing[sel_a]) < 3 * self.setup.gate
            else:
                inliers = np.zeros(0, bool)
            if self.st.state != 'odometry_only':
                events.append('odometry_only')
            self.st.state = 'odometry_only'
        else:
            self._lose_tracking(frame.stamp_ns, pred, events)
            return pred, None, n_inl, False
        self._push_pose(frame.stamp_ns, T_wc)
        obs_idx = sel_a[np.flatnonzero(inliers)].tolist() if len(sel_a) else []
        if len(obs_idx) > self.conf['max_obs_per_keyframe']:
            prio = np.array([self.st.lms[self.st.tracks[int(frame.track_id[i])].lid].n_obs
                             if self.st.tracks[int(frame.track_id[i])].lid in self.st.lms else 0
                             for i in obs_idx], dtype=float)
            keep = self._spread(frame.pixel[obs_idx], prio, self.conf['max_obs_per_keyframe'])
            obs_idx = [obs_idx[k] for k in keep]
        lm_obs = [(int(frame.track_id[i]), i) for i in obs_idx]
        if self._is_keyframe(frame, mappable, T_wc, n_inl):
            self._add_keyframe(frame, mappable, T_wc, lm_obs, fix, events)
            # the next predictions start from the smoothed pose: chained on the tracked (or
            # odometry-predicted) one they drift away from the map (metres along a drive)
            if self.st.history and self.st.history[-1][0] == frame.stamp_ns:
                self.st.history[-1] = (frame.stamp_ns, self.st.kf_T_wc[-1])
            return self.st.kf_T_wc[-1], cov_c, n_inl, True
        return T_wc, cov_c, n_inl, False

    def _spread(self, pixels: np.ndarray, priority: np.ndarray, n: int) -> np.ndarray:
        """Indices of ``n`` items spread over the image: round-robin over an 8x8 grid of
        cells, each cell in decreasing ``priority``."""
        cx = np.clip((pixels[:, 0] / self.camera.width * 8).astype(int), 0, 7)
        cy = np.clip((pixels[:, 1] / self.camera.height * 8).astype(int), 0, 7)
        cell = cy * 8 + cx
        order = np.lexsort((-priority, cell))
        sorted_cell = cell[order]
        first = np.searchsorted(sorted_cell, sorted_cell, side='left')
        rank = np.arange(len(order)) - first
        pick = order[np.lexsort((-priority[order], rank))][:n]
        return np.sort(pick)

    def _is_keyframe(self, frame: Tracks, mappable: np.ndarray, T_wc: np.ndarray,
                     n_inl: int) -> bool:
        kid = self.st.last_kid
        T_kf = self.st.kf_T_wc[kid]
        dist = float(np.linalg.norm((T_wc @ self.T_cb)[:3, 3] - (T_kf @ self.T_cb)[:3, 3]))
        if dist < self.conf['kf_min_distance_m']:
            return False
        if self._kf_odom.ok and self._kf_odom.dist < self.conf['kf_min_distance_m']:
            return False  # the wheels say the base stood still: the estimate only jitters
        if dist > self.conf['kf_max_distance_m'] or n_inl < 2 * self.conf['min_tracking_inliers']:
            return True
        R_rel = T_kf[:3, :3].T @ T_wc[:3, :3]
        common, b_kf, b_cur = 0, [], []
        for i in np.flatnonzero(mappable).tolist():
            obs = self.st.tracks[int(frame.track_id[i])].kf_obs.get(kid)
            if obs is not None:
                common += 1
                b_kf.append(obs[0])
                b_cur.append(frame.bearing[i])
        kf = self.st.kfs.get(kid)
        if kf is None or common < self.conf['kf_min_tracked_fraction'] * kf.n_tracks:
            return True
        par = angle_between(np.array(b_kf), np.array(b_cur) @ R_rel.T)
        return float(np.degrees(np.median(par))) > self.conf['kf_parallax_deg']

    def _lose_tracking(self, stamp_ns: int, pred: np.ndarray | None, events: list[str]) -> None:
        events.append('tracking_lost')
        self.st.stats['tracking_lost'] += 1
        self.st.state = 'lost'
        self._ref = None
        self._init_attempts = 0
        if self.st.last_kid >= 0 and self.st.history:
            t1, T1 = self.st.history[-1]
            xi = np.zeros(6)
            if len(self.st.history) >= 2:
                t0, T0 = self.st.history[-2]
                if t1 > t0:
                    xi = se3_log(se3_inv(T0) @ T1) / ((t1 - t0) * 1e-9)
            self.st.link = dict(kid=self.st.last_kid, stamp=t1, T_wc=T1, xi=xi)

    # ------------------------------------------------------------------------------------------
    # initialisation
    # ------------------------------------------------------------------------------------------

    def _set_ref(self, frame: Tracks, mappable: np.ndarray) -> None:
        idx = np.flatnonzero(mappable)
        self._ref = dict(
            stamp=frame.stamp_ns, frames=0,
            obs={int(frame.track_id[i]): (frame.bearing[i], frame.pixel[i]) for i in idx})
        self._ref_odom = OdomChain(self.conf['use_odometry'])

    def _start_from_odometry(self, frame: Tracks, mappable: np.ndarray, fix: GnssFix | None,
                             events: list[str]) -> tuple[np.ndarray, bool]:
        """With wheel odometry the map starts at once: a first keyframe at the origin (metric
        from the start), the next ones placed by odometry until triangulated landmarks take
        over (state 'odometry_only' -> 'tracking'). No two-view initialisation is needed, so
        a front end whose tracks are mostly far (little parallax) still builds a map."""
        T_wc = self.T_bc.copy()
        kid = self.st.new_keyframe(frame.stamp_ns, T_wc, int(mappable.sum()))
        prior = fac.pose_prior(X(kid), T_wc, self.setup.prior_cov())
        recs = [self.st.record(prior, RecordKind.PRIOR, kid)]
        values = gtsam.Values()
        values.insert(X(kid), gtsam.Pose3(T_wc))
        ts = {X(kid): self.setup.smoother_ts(kid)}
        self._observe_keyframe(frame, mappable, kid)
        self._attach_gnss(kid, fix, recs)
        self.st.metric = self.st.scale_from_odometry = True
        self._start_segment('odometry_only', [(frame.stamp_ns, T_wc)], recs, values, ts, [],
                            kid, events, 'initialised_from_odometry')
        return T_wc, True

    def _observe_keyframe(self, frame: Tracks, mappable: np.ndarray, kid: int) -> None:
        """Keyframe ``kid`` observes every mappable track of ``frame`` (bearing, pixel)."""
        for i in np.flatnonzero(mappable).tolist():
            self.st.tracks[int(frame.track_id[i])].kf_obs[kid] = (frame.bearing[i], frame.pixel[i])

    def _start_segment(self, state: str, history: list[tuple[int, np.ndarray]],
                       recs: list[FactorRecord], values: gtsam.Values, ts: dict[int, float],
                       lids: list[int], kid: int, events: list[str], event: str) -> None:
        """Common end of both starts (from odometry, two-view): state, bookkeeping, commit."""
        self.st.state = state
        self._ref = self.st.link = None
        self.st.stats['initialisations'] += 1
        self._kf_odom = OdomChain(self.conf['use_odometry'])
        self.st.history = history
        self._commit(recs, values, ts, lids, kid, events)
        events.append(event)

    def _initialize(self, frame: Tracks, mappable: np.ndarray, fix: GnssFix | None,
                    events: list[str]) -> tuple[np.ndarray | None, bool]:
        c = self.conf
        if self._ref is None or len(self._ref['obs']) < c['init_min_tracks']:
            self._set_ref(frame, mappable)
            return None, False
        ref = self._ref
        ref['frames'] += 1
        idx = [i for i in np.flatnonzero(mappable).tolist()
               if int(frame.track_id[i]) in ref['obs']]
        if len(idx) < c['init_min_tracks'] or ref['frames'] > c['init_max_frames']:
            self._set_ref(frame, mappable)
            return None, False
        ids = [int(frame.track_id[i]) for i in idx]
        b1 = np.array([ref['obs'][t][0] for t in ids])
        b2 = frame.bearing[idx]
        # enough tracks with parallax (not the median: on an open deck most tracks are far)
        par0 = angle_between(b1, b2)
        if (par0 >= np.radians(c['init_min_parallax_deg'])).sum() < c['init_min_tracks'] // 2:
            return None, False
        # relative motion: the matcher's 5-point RANSAC on bearings (+ LM refinement); with
        # wheel odometry its length gives the scale, and when RANSAC fails (forward motion with
        # a few degrees of parallax) the odometry motion, refined on the tracks, replaces it
        # (odometry alone is not enough: it is planar and misses the body's pitch and roll)
        metric = True
        thr = c['init_ransac_px'] / self.camera.fx
        from_odom = self._ref_odom.ok and c['use_odometry']
        ver = verify_bearings(b1, b2, {'threshold_rad': thr, 'seed': c['seed'],
                                       'min_inliers': 8})
        R, t = (ver.R, ver.t) if ver.ok and ver.model == 'essential' else (None, None)
        if R is not None and ver.inlier_ratio < c['init_min_inlier_ratio']:
            R, t = None, None
        if from_odom:
            T_c2c1 = se3_inv(self.T_cb @ self._ref_odom.T @ self.T_bc)
            s = float(np.linalg.norm(T_c2c1[:3, 3]))
            if s < 0.05:
                return None, False
            t_odom = T_c2c1[:3, 3] / s
            if R is None or np.degrees(angle_between(t, t_odom)) > c['init_odom_max_angle_deg']:
                gate = relative_pose_known_motion(T_c2c1[:3, :3], t_odom, b1, b2,
                                                  c['init_odom_gate_px'] / self.camera.fx)
                R, t = refine_pose(T_c2c1[:3, :3], t_odom, b1[gate.inliers], b2[gate.inliers])
        if R is None:
            return None, False
        rp = relative_pose_known_motion(R, t, b1, b2, thr)
        if rp.inliers.mean() < (c['init_odom_min_inlier_ratio'] if from_odom
                                else c['init_min_inlier_ratio']):
            return None, False
        par = angle_between(b1, b2 @ rp.R)
        good = rp.inliers & (par >= np.radians(c['lm_min_parallax_deg']))
        if good.sum() < c['init_min_tracks'] // 2:
            return None, False
        # metric scale: odometry (above), else the ground plane at the camera height
        if not from_odom:
            s = self._ground_scale(rp.points, good, ids)
            if s is None:
                self._init_attempts += 1
                if c['init_require_metric'] and self._init_attempts < c['init_max_frames']:
                    return None, False
                s, metric = 1.0, False
        T_c2c1 = np.eye(4)
        T_c2c1[:3, :3], T_c2c1[:3, 3] = rp.R, rp.t * s
        T_c1c2 = se3_inv(T_c2c1)
        link = self.st.link if self.st.state == 'lost' else None
        if link is not None:
            dt = (ref['stamp'] - link['stamp']) * 1e-9
            T_wc1 = link['T_wc'] @ se3_exp(link['xi'] * dt)
        else:
            T_wc1 = self.T_bc.copy()
        T_wc2 = T_wc1 @ T_c1c2
        self._create_initial_map(frame, mappable, ids, idx, rp.points[good] * s, good, T_wc1,
                                 T_wc2, link, fix, events)
        self.st.metric = self.st.metric or metric
        self.st.scale_from_odometry = self.st.scale_from_odometry or from_odom
        return self.st.kf_T_wc[-1], True

    def _ground_scale(self, pts: np.ndarray, good: np.ndarray, ids: list[int]) -> float | None:
        """Scale making the ground-labelled two-view points lie ``camera_height`` below."""
        labs = np.array([self._label_of(self.st.tracks[t]) for t in ids])
        g = good & self.setup.ground[labs]
        if g.sum() < 10:
            return None
        P = pts[g]
        below = -(P @ self.setup.up_c)  # unit-scale depth below the camera along base z
        d0 = float(np.median(below))
        if d0 <= 0:
            return None
        thr = self.conf['init_plane_threshold_m'] / self.camera_height * d0
        fit = fit_plane_ransac(P, thr, self.st.rng)
        if fit is None or fit[2].sum() < 10:
            return None
        n, d, _ = fit
        if n @ self.setup.up_c < 0:
            n, d = -n, -d
        # plane n . x = d with n ~ up: the camera (origin) is -d above it
        if n @ self.setup.up_c < np.cos(np.radians(15.0)) or -d <= 0:
            return None
        return self.camera_height / -d

    def _create_initial_map(self, frame: Tracks, mappable: np.ndarray, ids: list[int],
                            idx: list[int], pts_c1: np.ndarray, good: np.ndarray,
                            T_wc1: np.ndarray, T_wc2: np.ndarray, link: dict | None,
                            fix: GnssFix | None, events: list[str]) -> None:
        ref = self._ref
        ka = self.st.new_keyframe(ref['stamp'], T_wc1, len(ref['obs']))
        kb = self.st.new_keyframe(frame.stamp_ns, T_wc2, int(mappable.sum()))
        recs: list[FactorRecord] = []
        values = gtsam.Values()
        values.insert(X(ka), gtsam.Pose3(T_wc1))
        values.insert(X(kb), gtsam.Pose3(T_wc2))
        ts = {X(ka): self.setup.smoother_ts(ka), X(kb): self.setup.smoother_ts(kb)}
        if link is not None and link['kid'] in self.st.kfs:
            c = self.conf
            dt = max((ref['stamp'] - link['stamp']) * 1e-9, 0.1)
            sig = np.array([c['reinit_link_sigma_rad']] * 3 + [c['reinit_link_sigma_m']] * 3)
            cov = np.diag((sig * dt) ** 2)
            T_rel = se3_inv(self.st.kf_T_wc[link['kid']]) @ T_wc1
            f = fac.between(X(link['kid']), X(ka), T_rel, cov)
            recs.append(self.st.record(f, RecordKind.LINK, ka))
            events.append('reinitialised')
        elif link is not None:  # the old window is gone: anchor the new segment where predicted
            f = fac.pose_prior(X(ka), T_wc1, self.setup.prior_cov())
            recs.append(self.st.record(f, RecordKind.LINK, ka))
            events.append('reinitialised')
        else:
            f = fac.pose_prior(X(ka), T_wc1, self.setup.prior_cov())
            recs.append(self.st.record(f, RecordKind.PRIOR, ka))
        if self._ref_odom.ok:
            self._add_odom_rec(ka, kb, self._ref_odom, recs)
        for t in ids:  # keyframe observations of every common mappable track
            tr = self.st.tracks[t]
            tr.kf_obs[ka] = ref['obs'][t]
        self._observe_keyframe(frame, mappable, kb)
        new_lids = []
        R1, t1 = T_wc1[:3, :3], T_wc1[:3, 3]
        for t, p in zip(np.array(ids)[good], pts_c1):
            tr = self.st.tracks[int(t)]
            lid = self._new_landmark(int(t), tr, R1 @ p + t1, [ka, kb], recs, values, kb, ts)
            new_lids.append(lid)
        for kid in (ka, kb):
            self._add_ground_recs(kid, new_lids, recs)
        self._attach_gnss(kb, fix, recs)
        self._start_segment('tracking', [(ref['stamp'], T_wc1), (frame.stamp_ns, T_wc2)], recs,
                            values, ts, new_lids, kb, events, 'initialised')

    # ------------------------------------------------------------------------------------------
    # keyframes
    # ------------------------------------------------------------------------------------------

    def _add_odom_rec(self, ka: int, kb: int, chain: OdomChain, recs: list[FactorRecord]) -> None:
        floor = self.conf['odom_min_sigma'] ** 2
        T_rel_c = self.T_cb @ chain.T @ self.T_bc
        cov_c = transform_covariance(chain.cov, self.T_bc) + np.eye(6) * floor
        recs.append(self.st.record(fac.between(X(ka), X(kb), T_rel_c, cov_c), RecordKind.ODOM, kb))
        self.st.kfs[kb].odom_linked = True

    def _add_keyframe(self, frame: Tracks, mappable: np.ndarray, T_wc: np.ndarray,
                      lm_obs: list[tuple[int, int]], fix: GnssFix | None,
                      events: list[str]) -> None:
        prev = self.st.last_kid
        kid = self.st.new_keyframe(frame.stamp_ns, T_wc, int(mappable.sum()))
        recs: list[FactorRecord] = []
        values = gtsam.Values()
        values.insert(X(kid), gtsam.Pose3(T_wc))
        ts = {X(kid): self.setup.smoother_ts(kid)}
        if self._kf_odom.ok and prev in self.st.kfs:
            self._add_odom_rec(prev, kid, self._kf_odom, recs)
            ch = self._kf_odom
            self._kf_odom_raw[kid] = (ch.raw_yaw, ch.raw_dist, ch.dt)
        self._kf_odom = OdomChain(self.conf['use_odometry'])
        self._observe_keyframe(frame, mappable, kid)
        if prev in self.st.kfs:
            self._queue_rotation(frame, mappable, prev, kid, recs)
        self._add_level_rec(kid, recs)
        seen: list[int] = []
        seen_rows: list[int] = []
        for tid, i in lm_obs:
            tr = self.st.tracks[tid]
            lm = self.st.lms.get(tr.lid)
            if lm is None or not lm.alive:
                continue
            f = fac.bearing_factor(X(kid), L(lm.lid), frame.bearing[i],
                                   self.setup.bearing_noise)
            rec = self.st.record(f,
                            RecordKind.BEARING, kid, lm.lid, frame.bearing[i], frame.pixel[i])
            recs.append(rec)
            lm.rids.append(rec.rid)
            self._observed(lm, kid, frame.bearing[i])
            self._touch(lm, kid, ts)
            seen.append(lm.lid)
            seen_rows.append(i)
        self._update_parallax([self.st.lms[lid] for lid in seen],
                              frame.bearing[seen_rows] @ T_wc[:3, :3].T)
        new_lids = self._triangulate(frame, mappable, kid, recs, values, ts)
        self._add_ground_recs(kid, seen + new_lids, recs)
        self._attach_gnss(kid, fix, recs)
        self._commit(recs, values, ts, seen + new_lids, kid, events)

    def _queue_rotation(self, frame: Tracks, mappable: np.ndarray, ka: int, kb: int,
                        recs: list[FactorRecord]) -> None:
        """Collect the common tracks of keyframes ka and kb (unit bearings in each) for their
        relative rotation (:meth:`_rotation_rec`). The RANSAC runs when the next frame arrives
        (:meth:`_settle`), and its factor joins the next keyframe's update: a keyframe's update
        does not carry it (about 5 ms of 30 on the synthetic benchmark), and the robust factor
        is first linearised at kb's smoothed pose instead of its tracked one (the far-tracks
        test drive: ATE 0.132 -> 0.068 m). The factor joins the next keyframe's records, not
        this keyframe's ``recs``."""
        c = self.conf
        if c['vision_rotation_sigma_deg'] <= 0:
            return
        b_a, b_b = [], []
        for i in np.flatnonzero(mappable).tolist():
            obs = self.st.tracks[int(frame.track_id[i])].kf_obs
            if ka in obs:
                b_a.append(obs[ka][0])
                b_b.append(frame.bearing[i])
        if len(b_a) >= c['vision_rotation_min_tracks']:
            self._rot_job = (ka, kb, np.array(b_a), np.array(b_b))

    def _run_rotation_job(self, add: Callable[[FactorRecord], None]) -> None:
        """Verify the queued keyframe pair, if both are still in the window; its factor goes
        to ``add``."""
        job, self._rot_job = self._rot_job, None
        if job is None or job[0] not in self.st.kfs or job[1] not in self.st.kfs:
            return
        rec = self._rotation_rec(*job)
        if rec is not None:
            add(rec)

    def _rotation_rec(self, ka: int, kb: int, ba: np.ndarray, bb: np.ndarray
                      ) -> FactorRecord | None:
        """Relative rotation between keyframes ka and kb from the two-view geometry of their
        common tracks, unit bearings ``ba`` and ``bb`` (N, 3) (5-point RANSAC). Far points,
        which never become landmarks, fix the rotation well: this bounds the heading drift
        between landmark observations."""
        c = self.conf
        thr = c['init_ransac_px'] / self.camera.fx
        ver = verify_bearings(ba, bb, {'threshold_rad': thr, 'seed': c['seed'],
                                       'min_inliers': c['vision_rotation_min_tracks']})
        if not ver.ok:
            return None
        T_ab = se3_inv(self.st.kf_T_wc[ka]) @ self.st.kf_T_wc[kb]
        R = ver.R
        if c['vision_rotation_kinematic'] and self.st.metric:
            dist = float(np.linalg.norm((self.T_bc @ T_ab @ self.T_cb)[:3, 3]))
            R = self._kinematic_rotation(R, ba, bb, ver.inliers, dist, thr)
        T_ab[:3, :3] = R.T  # X_b = R X_a + t: the rotation of b in a is R^T
        f = fac.rotation_between(X(ka), X(kb), T_ab, np.radians(c['vision_rotation_sigma_deg']),
                                 100.0, c['robust_kernel'], c['robust_k'])
        self.st.stats['rotation_factors'] += 1
        return self.st.record(f, RecordKind.VROT, kb)

    def _kinematic_rotation(self, R: np.ndarray, b_a: np.ndarray, b_b: np.ndarray,
                            inliers: np.ndarray, dist: float, thr: float) -> np.ndarray:
        """The two-view rotation ``R`` with its roll and pitch refined with the camera's
        translation fixed to the vehicle's: :func:`vehicle_camera_translation` for ``dist`` (m)
        driven. A free translation absorbs part of a pitch change as a vertical tilt (network
        tracks, long drive 3: 2.9 and 4.7 deg of the ramp's 7 deg missed at its top and
        bottom). The yaw stays the free estimate's: taking it too mapped the six long drives
        worse (mean ATE 0.240 against 0.205 m). Kept only when the fixed motion explains at
        least 90 % of the inliers (no slip, the distance right); otherwise ``R`` is returned."""
        if dist < self.conf['kf_min_distance_m'] or inliers.sum() < 3:
            return R
        Rk = R
        for _ in range(3):  # the translation follows the rotation (arc chord, lever arm)
            Rk = refine_rotation(Rk, vehicle_camera_translation(Rk, self.T_bc, dist),
                                 b_a[inliers], b_b[inliers])
        t = vehicle_camera_translation(Rk, self.T_bc, dist)
        agree = epipolar_sines(skew(t / np.linalg.norm(t)) @ Rk, b_a, b_b) < np.sin(thr)
        if agree.sum() < 0.9 * inliers.sum():
            return R
        R_bc = self.T_bc[:3, :3]
        d = R_bc @ so3_log(Rk @ R.T)  # the correction in base axes
        d[2] = 0.0  # keep the free estimate's yaw
        return so3_exp(R_bc.T @ d) @ R

    def _add_level_rec(self, kid: int, recs: list[FactorRecord]) -> None:
        """Level-floor prior on keyframe ``k = kid - level_delay_keyframes``, once the smoother
        has seen the keyframes after it. Every keyframe from ``level_delay`` before ``k`` to the
        last one the smoother has estimated must be below ``level_max_tilt_deg`` and tilted by
        less than ``level_max_change_deg`` against ``k``: a plateau, not a ramp or its
        transition. The tilt change between neighbours is observed well (odometry, tracks)
        even where the absolute tilt lags; deciding on the predicted pose of a new keyframe
        alone would hold a ramp level. That prediction (``kid``) is left out: it chains
        odometry on the last prediction, keeps a ramp's pitch after the ramp when tracking
        falls back to odometry, and blocked the prior there (long drive: 45 keyframes)."""
        c = self.conf
        delay = c['level_delay_keyframes']
        k = kid - delay
        if c['level_prior_sigma_deg'] <= 0 or k < 0 or k not in self.st.kfs:
            return
        first = max(0, k - delay)
        R = np.array(self.st.kf_T_wc[first:kid])[:, :3, :3]
        up = R @ self.setup.up_c  # (n, 3) base up axes in the map
        tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1.0, 1.0)))
        change = np.degrees(np.arccos(np.clip(up @ up[k - first], -1.0, 1.0)))
        if tilt.max() > c['level_max_tilt_deg'] or change.max() > c['level_max_change_deg']:
            return
        f = fac.level_factor(X(k), self.setup.up_c, np.radians(c['level_prior_sigma_deg']),
                             c['robust_kernel'], c['robust_k'])
        recs.append(self.st.record(f, RecordKind.LEVEL, k))
        self.st.stats['level_factors'] += 1

    def _observed(self, lm: Landmark, kid: int, bearing: np.ndarray) -> None:
        """Bookkeeping of a new observation: count and observing keyframe."""
        lm.n_obs += 1
        lm.kf_ids.append(kid)
        self.st.stats['obs_beyond_90deg'] += int(bearing[2] < 0)

    def _update_parallax(self, lms: list[Landmark], rays: np.ndarray) -> None:
        """Largest angle between each landmark's first ray and its new ray (map frame)."""
        if not lms:
            return
        ray0 = np.array([lm.ray0 for lm in lms])
        ang = angle_between(ray0, rays).tolist()
        for lm, a in zip(lms, ang):
            if a > lm.max_par:
                lm.max_par = a

    def _publishable(self, lm: Landmark) -> bool:
        """Alive, static, observed often enough, consistent and well triangulated."""
        c = self.conf
        return (lm.alive and lm.n_obs >= c['cloud_min_obs'] and self.setup.static[lm.label]
                and lm.reproj_px <= c['max_reprojection_px']
                and lm.max_par >= np.radians(c['cloud_min_parallax_deg']))

    def _seen_alt(self, lm: Landmark, levels: FloorLevels) -> float:
        """Highest altitude (m) of a plateau keyframe that observed ``lm`` (NaN: none)."""
        seen = [self.st.kf_alt[k] for k in lm.kf_ids if k < len(levels.flat) and levels.flat[k]]
        return float(max(seen)) if seen else float('nan')

    def _storey(self, z: float, seen: float, levels: FloorLevels, label: int) -> float:
        """Altitude (m) of the level of a point of class ``label`` at altitude ``z`` (m) whose
        highest plateau observer stood at ``seen`` (m; NaN: none): :func:`storey_altitude` (the
        street seen over a roof deck's railing is the ground storey's; the observers decide
        within ``floor_point_margin_m`` of a level's slab, and always for ``ceiling_labels``)."""
        return float(storey_altitude(np.array([z]), np.array([seen]), levels.altitudes,
                                     self.conf['floor_point_margin_m'],
                                     self.setup.hangs[[label]])[0])

    def _floor_alt(self, lm: Landmark, xyz: np.ndarray, levels: FloorLevels) -> float:
        """Altitude (m) of the level of landmark ``lm`` at ``xyz`` (:meth:`_storey`)."""
        return self._storey(float(xyz[2]), self._seen_alt(lm, levels), levels, lm.label)

    def _touch(self, lm: Landmark, kid: int, ts: dict[int, float]) -> None:
        """Landmark seen at keyframe ``kid``: refresh its smoother timestamp."""
        if lm.last_kf in self.st.lm_by_ts:
            self.st.lm_by_ts[lm.last_kf].discard(lm.lid)
        lm.last_kf = kid
        self.st.lm_by_ts.setdefault(kid, set()).add(lm.lid)
        ts[L(lm.lid)] = self.setup.smoother_ts(kid)

    def _new_landmark(self, tid: int, tr: Track, xyz: np.ndarray, kids: list[int],
                      recs: list[FactorRecord], values: gtsam.Values, kid_now: int,
                      ts: dict[int, float] | None = None, rays: np.ndarray | None = None,
                      max_par: float | None = None) -> int:
        """Create landmark ``L(lid)`` of track ``tid`` at ``xyz`` (m) with bearing factors from
        keyframes ``kids``; ``rays`` are those observations in the map frame if known, and
        ``max_par`` their largest angle to the first (rad)."""
        lid = self.st.next_lid
        self.st.next_lid += 1
        label = self._label_of(tr)
        lm = Landmark(lid, tid, label, bool(self.setup.ground[label]), np.array(xyz, dtype=float))
        values.insert(L(lid), np.array(xyz, dtype=float))
        for k in kids:
            b, px = tr.kf_obs[k]
            f = fac.bearing_factor(X(k), L(lid), b, self.setup.bearing_noise)
            rec = self.st.record(f, RecordKind.BEARING, k, lid,
                            b, px)
            recs.append(rec)
            lm.rids.append(rec.rid)
            self._observed(lm, k, b)
        if rays is None:
            rays = np.array([self.st.kf_T_wc[k][:3, :3] @ tr.kf_obs[k][0] for k in kids])
        k_anchor = kid_now if kid_now in kids else kids[-1]
        u, v = tr.kf_obs[k_anchor][1]
        lm.anchor = (self.st.kf_stamps[k_anchor], float(u), float(v))
        lm.ray0 = rays[0]
        lm.max_par = (float(angle_between(rays[:1], rays).max()) if max_par is None
                      else max_par)
        self.st.lms[lid] = lm
        tr.lid = lid
        lm.last_kf = kid_now
        self.st.lm_by_ts.setdefault(kid_now, set()).add(lid)
        if ts is not None:
            ts[L(lid)] = self.setup.smoother_ts(kid_now)
        self.st.stats['landmarks'] += 1
        return lid

    def _triangulate(self, frame: Tracks, mappable: np.ndarray, kid: int, recs: list[FactorRecord],
                     values: gtsam.Values, ts: dict[int, float]) -> list[int]:
        c = self.conf
        cands: list[tuple[int, list[int]]] = []
        for i in np.flatnonzero(mappable).tolist():
            tid = int(frame.track_id[i])
            tr = self.st.tracks[tid]
            if tr.lid >= 0 or tr.rejected:
                continue
            for k in [k for k in tr.kf_obs if k not in self.st.kfs]:
                del tr.kf_obs[k]
            if len(tr.kf_obs) >= c['lm_min_keyframes']:
                cands.append((tid, sorted(tr.kf_obs)))
        if not cands:
            return []
        index, centers, rays, obs_kid = [], [], [], []
        for j, (tid, kids) in enumerate(cands):
            tr = self.st.tracks[tid]
            for k in kids:
                T = self.st.kf_T_wc[k]
                index.append(j)
                centers.append(T[:3, 3])
                rays.append(T[:3, :3] @ tr.kf_obs[k][0])
                obs_kid.append(k)
        index_a = np.array(index)
        centers_a, rays_a = np.array(centers), np.array(rays)
        min_par = np.radians(c['lm_min_parallax_deg'])
        tri = triangulate_bearings(index_a, centers_a, rays_a, len(cands), min_par)
        # second pass without grossly wrong rays (matcher outliers stored at a keyframe)
        keep_obs = tri.error < 3 * self.setup.gate
        if not keep_obs.all():
            tri2 = triangulate_bearings(index_a[keep_obs], centers_a[keep_obs],
                                        rays_a[keep_obs], len(cands), min_par)
        else:
            tri2 = tri
        depth = np.full(len(index_a), np.nan)
        err = np.full(len(index_a), np.inf)
        depth[keep_obs], err[keep_obs] = tri2.depth, tri2.error
        good_obs = keep_obs & (err < self.setup.gate) & (depth > c['lm_min_depth_m']) \
            & (depth < c['lm_max_depth_m'])
        n_good = np.bincount(index_a, weights=good_obs, minlength=len(cands))
        n_all = np.bincount(index_a, minlength=len(cands))
        accept = tri2.ok & (n_good >= c['lm_min_keyframes']) & (n_good >= n_all - 1)
        acc = np.flatnonzero(accept)
        if len(acc) > c['max_new_landmarks']:
            px = np.array([self.st.tracks[cands[j][0]].kf_obs[kid][1] for j in acc])
            acc = acc[self._spread(px, tri2.max_parallax[acc], c['max_new_landmarks'])]
        if not len(acc):
            return []
        # the accepted tracks' good observations, grouped by track (index_a is sorted), and
        # the largest angle of each group's rays to its first
        rows = np.flatnonzero(good_obs & np.isin(index_a, acc))
        first = np.flatnonzero(np.r_[True, index_a[rows[1:]] != index_a[rows[:-1]]])
        ray0 = rays_a[rows[first]]
        size = np.diff(np.r_[first, len(rows)])
        max_par = np.maximum.reduceat(angle_between(np.repeat(ray0, size, axis=0),
                                                    rays_a[rows]), first)
        group = {int(index_a[rows[f]]): g for g, f in enumerate(first.tolist())}
        new = []
        for j in acc.tolist():
            tid = cands[j][0]
            g = group[j]
            r = rows[first[g]:first[g] + size[g]]
            new.append(self._new_landmark(tid, self.st.tracks[tid], tri2.points[j],
                                          [obs_kid[o] for o in r.tolist()], recs, values, kid,
                                          ts, rays_a[r], float(max_par[g])))
        return new

    def _add_ground_recs(self, kid: int, lids: list[int], recs: list[FactorRecord]) -> None:
        mode = self.conf['ground_factor']
        if mode == 'never' or (mode == 'auto' and self.st.kfs[kid].odom_linked):
            return
        lids = [lid for lid in lids if self.st.lms[lid].ground and self.st.lms[lid].alive]
        if not lids:
            return
        c = self.conf
        T_cw = se3_inv(self.st.kf_T_wc[kid])
        P = np.array([self.st.lms[lid].xyz for lid in lids]) @ T_cw[:3, :3].T + T_cw[:3, 3]
        height = P @ self.setup.up_c  # along base z, relative to the camera (m, ~ -camera_height)
        horiz = np.linalg.norm(P - height[:, None] * self.setup.up_c, axis=1)  # from the nadir
        near = (horiz <= c['ground_plane_radius_m']) \
            & (np.abs(height + self.camera_height) < c['ground_gate_m'])
        if near.sum() < c['ground_min_points']:
            return
        # The local plane must hold: a robust plane through the nearby ground landmarks that is
        # parallel to the vehicle (not at a ramp transition); only its inliers get factors.
        fit = fit_plane_ransac(P[near], c['ground_plane_threshold_m'], self.st.rng, iterations=40)
        if fit is None or fit[2].sum() < c['ground_min_points']:
            return
        normal = fit[0] if fit[0] @ self.setup.up_c > 0 else -fit[0]
        tilt = np.degrees(np.arccos(min(1.0, float(normal @ self.setup.up_c))))
        if tilt > c['ground_max_tilt_deg']:
            return
        inl = np.flatnonzero(near)[fit[2]]
        inl = inl[horiz[inl] <= c['ground_max_distance_m']]
        order = [lids[i] for i in inl[np.argsort(horiz[inl])]]
        for lid in order[: self.conf['ground_max_per_keyframe']]:
            f = fac.ground_factor(X(kid), L(lid), self.setup.up_c, self.camera_height,
                                  self.setup.ground_noise)
            rec = self.st.record(f, RecordKind.GROUND, kid, lid)
            recs.append(rec)
            self.st.lms[lid].rids.append(rec.rid)

    # ------------------------------------------------------------------------------------------
    # GNSS
    # ------------------------------------------------------------------------------------------

    def _check_fix(self, fix: GnssFix | None, T_wc_pred: np.ndarray | None,
                   events: list[str]) -> GnssFix | None:
        """Covariance gate of a fix; returns it (with a floored covariance) or None."""
        if fix is None:
            return None
        reason = None
        pos = np.asarray(fix.position, dtype=np.float64).reshape(-1)
        cov = None if fix.covariance is None else np.asarray(fix.covariance, dtype=np.float64)
        if pos.shape != (3,) or not np.isfinite(pos).all():
            reason = f'position must be 3 finite values (m), got {pos.shape}'
        elif cov is None:
            reason = 'missing covariance'
        elif cov.shape != (3, 3) or not np.isfinite(cov).all():
            reason = f'covariance must be a finite 3x3 (m^2), got shape {cov.shape}'
        else:
            cov = 0.5 * (cov + cov.T)
            w, V = np.linalg.eigh(cov)
            if w.min() <= 0:
                reason = f'covariance not positive definite (eigenvalues {w.min():.3g}...)'
            elif np.sqrt(w.max()) > self.conf['gnss_max_sigma_m']:
                reason = (f'sigma {np.sqrt(w.max()):.2f} m above gnss_max_sigma_m '
                          f'{self.conf["gnss_max_sigma_m"]}')
            else:
                w = np.maximum(w, self.conf['gnss_min_sigma_m'] ** 2)
                cov = (V * w) @ V.T
        if reason is None and self.st.gnss_aligned and T_wc_pred is not None:
            T_wb = T_wc_pred @ self.T_cb
            pred = T_wb[:3, :3] @ self.setup.arm_b + T_wb[:3, 3]
            d = pos - pred
            S = cov + np.eye(3) * self.conf['gnss_gate_sigma_m'] ** 2
            m2 = float(d @ np.linalg.solve(S, d))
            if m2 > self.conf['gnss_gate_chi2']:
                self._gnss_rejects += 1
                if self._gnss_rejects >= self.conf['gnss_max_rejects']:
                    events.append('gnss_gate_reopened')
                    self._gnss_rejects = 0
                else:
                    reason = f'inconsistent with the estimate ({np.linalg.norm(d):.2f} m off)'
        if reason is not None:
            self.st.stats['gnss_rejected'] += 1
            events.append(f'gnss_rejected: {reason}')
            return None
        self._gnss_rejects = 0
        self.st.stats['gnss_accepted'] += 1
        return GnssFix(int(fix.stamp_ns), pos, cov)

    def _attach_gnss(self, kid: int, fix: GnssFix | None, recs: list[FactorRecord]) -> None:
        """Attach this frame's fix (or the pending one, moved by the tracked motion)."""
        T_wb = self.st.kf_T_wc[kid] @ self.T_cb
        if fix is not None:
            pos, cov = fix.position, fix.covariance
        else:
            p = self._gnss_pending
            self._gnss_pending = None
            if p is None or p.T_wb is None:
                return
            if (self.st.kf_stamps[kid] - p.stamp_ns) * 1e-9 > self.conf['gnss_max_age_s']:
                return
            ant_then = p.T_wb[:3, :3] @ self.setup.arm_b + p.T_wb[:3, 3]
            ant_now = T_wb[:3, :3] @ self.setup.arm_b + T_wb[:3, 3]
            pos = p.position + (ant_now - ant_then)
            moved = float(np.linalg.norm(ant_now - ant_then))
            cov = p.covariance + np.eye(3) * (0.02 + 0.02 * moved) ** 2
        self._gnss_pending = None
        if self.st.gnss_aligned:
            f = fac.gnss_factor(X(kid), pos, cov, self.setup.arm_c, 2.0)
            recs.append(self.st.record(f, RecordKind.GNSS, kid))
            self._gnss_kids.add(kid)
        else:
            self._gnss_pairs.append((kid, pos, cov))
            del self._gnss_pairs[:-500]  # bounded while waiting for enough spread to align

    def _try_gnss_align(self, events: list[str]) -> None:
        c = self.conf
        pairs = self._gnss_pairs
        if len(pairs) < c['gnss_align_min_fixes']:
            return
        dst = np.array([p[1] for p in pairs])
        T_wb = np.array([self.st.kf_T_wc[p[0]] for p in pairs]) @ self.T_cb
        src = np.einsum('kij,j->ki', T_wb[:, :3, :3], self.setup.arm_b) + T_wb[:, :3, 3]
        span = np.ptp(src[:, :2], axis=0)
        if float(np.hypot(*span)) < c['gnss_align_min_span_m']:
            return
        keep = np.ones(len(pairs), bool)
        for _ in range(3):
            s, R, t = align_yaw(src[keep], dst[keep], not self.st.scale_from_odometry)
            res = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
            rms = float(np.sqrt(np.mean(res[keep] ** 2)))
            if rms <= c['gnss_align_max_rms_m']:
                break
            worst = int(np.argmax(np.where(keep, res, -1)))
            keep[worst] = False
            if keep.sum() < c['gnss_align_min_fixes']:
                return
        else:
            return
        if not 0.5 < s < 2.0:
            return
        self._apply_similarity(s, R, t)
        self.st.gnss_aligned = True
        events.append(f'gnss_aligned: rms {rms:.2f} m, scale {s:.3f}')
        recs = [self.st.record(fac.gnss_factor(X(k), pos, cov, self.setup.arm_c, 2.0),
                               RecordKind.GNSS, k)
                for (k, pos, cov), ok in zip(pairs, keep) if ok and k in self.st.kfs]
        self._gnss_kids.update(r.kid for r in recs)
        self._gnss_pairs = []
        self.st.metric = True
        be = self.backend
        if not (be.rebuild(recs, gtsam.Values(), {}, weak=False, events=events)
                or be.rebuild(recs, gtsam.Values(), {}, weak=True, events=events)):
            be.reset_window(self.st.last_kid, events)
        be.refresh()

    def _apply_similarity(self, s: float, R: np.ndarray, t: np.ndarray) -> None:
        """Move the whole estimate by ``x -> s R x + t`` (map frame change, e.g. to ENU)."""
        def move(T: np.ndarray) -> np.ndarray:
            out = np.array(T)
            out[:3, :3] = R @ T[:3, :3]
            out[:3, 3] = s * R @ T[:3, 3] + t
            return out

        # the camera pose moves with the base: T_wc' = S T_wb T_bc; keep T_bc, scale positions
        self.st.kf_T_wc = [move(T @ self.T_cb) @ self.T_bc for T in self.st.kf_T_wc]
        self.st.kf_alt = [float((T @ self.T_cb)[2, 3]) for T in self.st.kf_T_wc]
        values = gtsam.Values()
        for kid in self.st.kfs:
            values.insert(X(kid), gtsam.Pose3(self.st.kf_T_wc[kid]))
        for lid, lm in self.st.lms.items():
            est = self.backend.estimate
            xyz = est.atPoint3(L(lid)) if est.exists(L(lid)) else lm.xyz
            lm.xyz = s * R @ xyz + t
            values.insert(L(lid), lm.xyz)
        self.backend.move_estimate(values)
        for tr in self.st.tracks.values():
            if tr.frozen is not None:
                tr.frozen = s * R @ tr.frozen + t
        self.st.final_xyz = {k: s * R @ v + t for k, v in self.st.final_xyz.items()}
        self.st.history = [(st, move(T @ self.T_cb) @ self.T_bc) for st, T in self.st.history]
        self._floors = None
        levels = self.floor_levels()
        self._voxels.transform(s, R, t, lambda p, a, lab: int(levels.assign(
            np.array(self._storey(float(p[2]), a, levels, lab)))))
        if self.st.link is not None:
            self.st.link['T_wc'] = move(self.st.link['T_wc'] @ self.T_cb) @ self.T_bc
        p = self._gnss_pending
        if p is not None and p.T_wb is not None:
            p.T_wb = move(p.T_wb)

    # ------------------------------------------------------------------------------------------
    # smoother
    # ------------------------------------------------------------------------------------------

    def _commit(self, recs: list[FactorRecord], values: gtsam.Values, ts: dict[int, float],
                lids: list[int], kid: int, events: list[str]) -> None:
        """Send keyframe ``kid``'s factors to the backend; then learn from the keyframes it
        marginalised, schedule the checks of the landmarks ``lids`` it observed and try the
        GNSS alignment."""
        self.backend.commit(recs, values, ts, kid, events)
        for k in self.backend.sync(kid, lids):
            self._learn_odometry(k)
        self._checks_due = list(lids)  # one commit per frame; the frame's _settle ran before
        if self.conf['use_gnss'] and not self.st.gnss_aligned and self._gnss_pairs:
            self._try_gnss_align(events)

    def batch_optimize(self, max_iterations: int = 100
                       ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """Levenberg-Marquardt on every factor ever kept (needs ``keep_full_graph``).

        Returns ``(T_map_base (K, 4, 4), {landmark id: position (m)})``; the incremental
        estimates are the initial values. Used to check the incremental solution.
        """
        if not self.conf['keep_full_graph']:
            raise MapperConfigError('batch_optimize needs keep_full_graph=True in the conf')
        self._settle()
        return self.backend.batch_optimize(max_iterations)

    def _learn_odometry(self, k: int) -> None:
        """Feed the odometry calibration with marginalised keyframe ``k`` and its predecessor:
        their final heading change and distance against the odometry's, when GNSS factors sit
        within ``_GNSS_ANCHOR_KF`` keyframes on both sides (an anchored estimate; without GNSS
        the motion follows the odometry itself)."""
        odo = self._kf_odom_raw.pop(k, None)
        gap = _GNSS_ANCHOR_KF
        anchored = (any(k - gap <= g < k for g in self._gnss_kids)
                    and any(k <= g <= k + gap for g in self._gnss_kids))
        self._gnss_kids = {g for g in self._gnss_kids if g >= k - gap}
        for old in [j for j in self._kf_odom_raw if j < k]:
            del self._kf_odom_raw[old]
        if self._odom_cal is None or odo is None or not anchored:
            return
        T0 = self.st.kf_T_wc[k - 1] @ self.T_cb
        T1 = self.st.kf_T_wc[k] @ self.T_cb
        self._odom_cal.add(odo[0], yaw_of(T0[:3, :3].T @ T1[:3, :3]), odo[2], odo[1],
                           float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])))

    def _finalize_landmark(self, lid: int, xyz: np.ndarray) -> None:
        lm = self.st.lms.pop(lid)
        self.st.lm_by_ts.get(lm.last_kf, set()).discard(lid)
        for rid in lm.rids:
            self.backend.drop(rid)
        tr = self.st.tracks.get(lm.track)
        if tr is not None and lm.alive:
            tr.frozen = np.array(xyz)
        if self.conf['keep_full_graph']:
            self.st.final_xyz[lid] = np.array(xyz)
        if self._publishable(lm):
            levels = self.floor_levels()
            seen = self._seen_alt(lm, levels)
            self._voxels.insert(np.asarray(xyz), lm.label, lid, lm.n_obs, seen, int(
                levels.assign(np.array(self._storey(float(xyz[2]), seen, levels, lm.label)))),
                lm.anchor)

    def _settle(self) -> None:
        """The work the last keyframe left for the next frame: the chi-square and depth checks
        of its landmarks and the verification of its rotation to the keyframe before (its
        factor joins the next keyframe's update). Their results are first needed by the next
        frame's tracking, so a keyframe's own update returns without them: on the synthetic
        benchmark that is about a third of its time, now spent at the frame after it (the
        mean time per frame is unchanged). Also run before the map is read."""
        if self._checks_due is not None:
            lids, self._checks_due = self._checks_due, None
            self._check_depths(self.backend.estimate)
            self._check_outliers(lids)
        if self._rot_job is not None:
            self._run_rotation_job(self.backend.queue)

    def _check_depths(self, est: gtsam.Values) -> None:
        """Kill the window's landmarks that the smoother moved beyond ``lm_lost_depth_m`` of
        their last observer. A point with nearly parallel rays (a ceiling seen three times
        ahead, a track that slid along a repeated texture) fits its bearings ever better as it
        recedes along them, with no factor to stop it; its information then vanishes and the
        next update fails as an indeterminate system (long drives: 1-10 window rebuilds each,
        the variable 10-100 km out). Landmarks seen again are caught earlier by the
        chi-square test; these are the ones nothing re-checks."""
        lids = sorted(lid for lid in self.st.lms if est.exists(L(lid)))
        if not lids:
            return
        P = gtsam.utilities.extractPoint3(est)  # every Point3 in key order: the landmarks
        if P.shape[0] != len(lids):
            P = np.array([est.atPoint3(L(lid)) for lid in lids])
        lms = [self.st.lms[lid] for lid in lids]
        centres = np.array([self.st.kf_T_wc[lm.kf_ids[-1]][:3, 3] for lm in lms])
        far = np.linalg.norm(P - centres, axis=1) > self.conf['lm_lost_depth_m']
        far &= np.array([lm.alive for lm in lms])  # the dead ones are out of the graph already
        for j in np.flatnonzero(far).tolist():
            lm = self.st.lms[lids[j]]
            lm.xyz = P[j]
            self.st.stats['landmarks_lost_depth'] += 1
            self._kill_landmark(lm.lid)

    def _check_outliers(self, lids: list[int]) -> None:
        """Chi-square test of the bearing factors of the landmarks just observed; factors
        failing it are removed at the next update, landmarks left with < 2 are killed."""
        recs = []  # the bearing factors of those landmarks (each knows its landmark, keyframe)
        for lid in lids:
            lm = self.st.lms.get(lid)
            if lm is None or not lm.alive:
                continue
            for rid in lm.rids:
                rec = self.backend.records.get(rid)
                if rec is not None and rec.kind == RecordKind.BEARING:
                    recs.append(rec)
        if not recs:
            return
        # poses and points once per keyframe / landmark, then gathered per observation
        kids, kid_inv = np.unique(np.array([r.kid for r in recs]), return_inverse=True)
        T = np.array([self.st.kf_T_wc[k] for k in kids.tolist()])[kid_inv]
        uniq, inv = np.unique(np.array([r.lid for r in recs]), return_inverse=True)
        P = np.array([self.st.lms[lid].xyz for lid in uniq.tolist()])[inv]
        b = np.array([r.bearing for r in recs])
        px = np.array([r.pixel for r in recs])
        p_c = np.einsum('nji,nj->ni', T[:, :3, :3], P - T[:, :3, 3])
        bad = angle_between(p_c, b) > self.setup.gate
        proj, valid = self.camera.project(p_c)
        err_px = np.where(valid, np.linalg.norm(proj - px, axis=1), 1e6)
        n_good = np.bincount(inv, weights=~bad, minlength=len(uniq))
        sum_px = np.bincount(inv, weights=np.where(bad, 0.0, err_px), minlength=len(uniq))
        n_badv = np.bincount(inv, weights=bad, minlength=len(uniq)).astype(int)
        mean_px = np.where(n_good > 0, sum_px / np.maximum(n_good, 1), np.inf)
        for j, lid in enumerate(uniq.tolist()):
            self.st.lms[lid].reproj_px = float(mean_px[j])
        for j in np.flatnonzero(n_badv).tolist():
            lid = int(uniq[j])
            lm = self.st.lms[lid]
            lm.n_bad += int(n_badv[j])
            self.st.stats['outlier_factors'] += int(n_badv[j])
            if n_good[j] < 2 or lm.n_bad > max(2, lm.n_obs // 2):
                self._kill_landmark(lid)
                continue
            for r in np.flatnonzero((inv == j) & bad).tolist():
                self.backend.remove(recs[r].rid)
                lm.n_obs -= 1

    def _kill_landmark(self, lid: int) -> None:
        """Remove an inconsistent landmark's factors; a loose prior keeps its variable
        determined until it is marginalised. Its track never maps again."""
        lm = self.st.lms[lid]
        lm.alive = False
        self.st.stats['landmarks_killed'] += 1
        for rid in lm.rids:
            if rid in self.backend.records:
                self.backend.remove(rid)
        rec = self.st.record(fac.point_prior(L(lid), lm.xyz, 10.0), RecordKind.DEAD, lid=lid)
        lm.rids.append(rec.rid)
        self.backend.queue(rec)
        tr = self.st.tracks.get(lm.track)
        if tr is not None:
            tr.rejected = True
