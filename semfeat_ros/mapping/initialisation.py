"""Initialisation of the mapper: the start of a map segment.

With wheel odometry the map starts at the first frame (:meth:`Initializer.start_from_odometry`,
metric at once). Otherwise, and after tracking was lost, a two-view start
(:meth:`Initializer.two_view`) between a reference frame and a later one with enough parallax;
its metric scale comes from the odometry or from the ground-class points lying
``camera_height_m`` below the camera (:meth:`Initializer.ground_scale`). A segment started after
a loss is linked to the last keyframe of the old one.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gtsam
from gtsam.symbol_shorthand import X
import numpy as np

from semfeat_ros.mapping import factors as fac
from semfeat_ros.mapping.geometry import (
    angle_between,
    fit_plane_ransac,
    relative_pose_known_motion,
    se3_exp,
    se3_inv,
)
from semfeat_ros.mapping.gnss import GnssAlignment
from semfeat_ros.mapping.local_mapping import LocalMapping
from semfeat_ros.mapping.state import (
    FactorRecord,
    MapperSetup,
    MapState,
    OdomChain,
    RecordKind,
)
from semfeat_ros.mapping.types import GnssFix, Tracks
from semfeat_ros.matching.geometry import refine_pose, verify_bearings

#: Sends a segment start's factors to the smoother: (records, values, smoother timestamps,
#: landmark ids, keyframe id, events).
Commit = Callable[[list[FactorRecord], gtsam.Values, dict[int, float], list[int], int,
                   list[str]], None]


class Initializer:
    """Starts and restarts the map; ``commit`` sends a start's factors to the smoother."""

    def __init__(self, setup: MapperSetup, st: MapState, local_mapping: LocalMapping,
                 gnss: GnssAlignment, commit: Commit) -> None:
        self.setup = setup
        self.st = st
        self._local = local_mapping
        self._gnss = gnss
        self._commit = commit
        self._ref: dict[str, Any] | None = None  # first view: stamp, frames since, observations
        self._init_attempts = 0  # two-view starts without a metric scale

    def restart(self) -> None:
        """Forget the reference frame (tracking was lost)."""
        self._ref = None
        self._init_attempts = 0

    def can_start_from_odometry(self, odometry: object | None) -> bool:
        """True when the map has not started, ``odometry`` came with the frame and
        ``init_from_odometry`` is on."""
        return (self.st.state == 'initializing' and odometry is not None
                and self.setup.conf['init_from_odometry'])

    def _set_reference(self, frame: Tracks, mappable: np.ndarray) -> None:
        """``frame`` becomes the first view of the two-view start."""
        idx = np.flatnonzero(mappable)
        self._ref = dict(
            stamp=frame.stamp_ns, frames=0,
            obs={int(frame.track_id[i]): (frame.bearing[i], frame.pixel[i]) for i in idx})
        self.st.ref_odom = OdomChain(self.setup.conf['use_odometry'])

    def start_from_odometry(self, frame: Tracks, mappable: np.ndarray, fix: GnssFix | None,
                             events: list[str]) -> tuple[np.ndarray, bool]:
        """With wheel odometry the map starts at once: a first keyframe at the origin (metric
        from the start), the next ones placed by odometry until triangulated landmarks take
        over (state 'odometry_only' -> 'tracking'). No two-view initialisation is needed, so
        a front end whose tracks are mostly far (little parallax) still builds a map."""
        T_wc = self.setup.T_bc.copy()
        kid = self.st.new_keyframe(frame.stamp_ns, T_wc, int(mappable.sum()))
        prior = fac.pose_prior(X(kid), T_wc, self.setup.prior_cov())
        recs = [self.st.record(prior, RecordKind.PRIOR, kid)]
        values = gtsam.Values()
        values.insert(X(kid), gtsam.Pose3(T_wc))
        ts = {X(kid): self.setup.smoother_ts(kid)}
        self._local.observe_keyframe(frame, mappable, kid)
        self._gnss.attach(kid, fix, recs)
        self.st.metric = self.st.scale_from_odometry = True
        self._start_segment('odometry_only', [(frame.stamp_ns, T_wc)], recs, values, ts, [],
                            kid, events, 'initialised_from_odometry')
        return T_wc, True

    def _start_segment(self, state: str, history: list[tuple[int, np.ndarray]],
                       recs: list[FactorRecord], values: gtsam.Values, ts: dict[int, float],
                       lids: list[int], kid: int, events: list[str], event: str) -> None:
        """Common end of both starts (from odometry, two-view): state, bookkeeping, commit."""
        self.st.state = state
        self._ref = self.st.link = None
        self.st.stats['initialisations'] += 1
        self.st.kf_odom = OdomChain(self.setup.conf['use_odometry'])
        self.st.history = history
        self._commit(recs, values, ts, lids, kid, events)
        events.append(event)

    def two_view(self, frame: Tracks, mappable: np.ndarray, fix: GnssFix | None,
                 events: list[str]) -> tuple[np.ndarray | None, bool]:
        """Two-view start (or restart after a loss) between a reference frame and ``frame``:
        relative motion from the bearings (5-point RANSAC, or the odometry refined on the
        tracks), scale from odometry or the ground plane, two keyframes and the landmarks of
        the inliers. Returns the camera pose of ``frame`` (m) and True once started, else
        ``(None, False)``."""
        c = self.setup.conf
        if self._ref is None or len(self._ref['obs']) < c['init_min_tracks']:
            self._set_reference(frame, mappable)
            return None, False
        ref = self._ref
        ref['frames'] += 1
        idx = [i for i in np.flatnonzero(mappable).tolist()
               if int(frame.track_id[i]) in ref['obs']]
        if len(idx) < c['init_min_tracks'] or ref['frames'] > c['init_max_frames']:
            self._set_reference(frame, mappable)
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
        thr = c['init_ransac_px'] / self.setup.camera.fx
        from_odom = self.st.ref_odom.ok and c['use_odometry']
        ver = verify_bearings(b1, b2, {'threshold_rad': thr, 'seed': c['seed'],
                                       'min_inliers': 8})
        R, t = (ver.R, ver.t) if ver.ok and ver.model == 'essential' else (None, None)
        if R is not None and ver.inlier_ratio < c['init_min_inlier_ratio']:
            R, t = None, None
        if from_odom:
            T_c2c1 = se3_inv(self.setup.T_cb @ self.st.ref_odom.T @ self.setup.T_bc)
            s = float(np.linalg.norm(T_c2c1[:3, 3]))
            if s < 0.05:
                return None, False
            t_odom = T_c2c1[:3, 3] / s
            if R is None or np.degrees(angle_between(t, t_odom)) > c['init_odom_max_angle_deg']:
                gate = relative_pose_known_motion(T_c2c1[:3, :3], t_odom, b1, b2,
                                                  c['init_odom_gate_px'] / self.setup.camera.fx)
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
            s = self.ground_scale(rp.points, good, ids)
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
            T_wc1 = self.setup.T_bc.copy()
        T_wc2 = T_wc1 @ T_c1c2
        self._create_initial_map(frame, mappable, ids, idx, rp.points[good] * s, good, T_wc1,
                                 T_wc2, link, fix, events)
        self.st.metric = self.st.metric or metric
        self.st.scale_from_odometry = self.st.scale_from_odometry or from_odom
        return self.st.kf_T_wc[-1], True

    def ground_scale(self, pts: np.ndarray, good: np.ndarray, ids: list[int]) -> float | None:
        """Scale making the ground-labelled two-view points ``pts`` (N, 3) (camera frame,
        unit scale; ``good`` the usable ones, ``ids`` their tracks) lie ``camera_height`` below
        the camera; None when they fit no level plane."""
        labs = np.array([self.st.tracks[t].major for t in ids])
        g = good & self.setup.ground[labs]
        if g.sum() < 10:
            return None
        P = pts[g]
        below = -(P @ self.setup.up_c)  # unit-scale depth below the camera along base z
        d0 = float(np.median(below))
        if d0 <= 0:
            return None
        thr = self.setup.conf['init_plane_threshold_m'] / self.setup.camera_height * d0
        fit = fit_plane_ransac(P, thr, self.st.rng)
        if fit is None or fit[2].sum() < 10:
            return None
        n, d, _ = fit
        if n @ self.setup.up_c < 0:
            n, d = -n, -d
        # plane n . x = d with n ~ up: the camera (origin) is -d above it
        if n @ self.setup.up_c < np.cos(np.radians(15.0)) or -d <= 0:
            return None
        return self.setup.camera_height / -d

    def _create_initial_map(self, frame: Tracks, mappable: np.ndarray, ids: list[int],
                            idx: list[int], pts_c1: np.ndarray, good: np.ndarray,
                            T_wc1: np.ndarray, T_wc2: np.ndarray, link: dict | None,
                            fix: GnssFix | None, events: list[str]) -> None:
        """Keyframes ``ka`` (the reference frame, camera pose ``T_wc1``) and ``kb`` (``frame``,
        ``T_wc2``), landmarks of the tracks ``ids`` marked ``good`` at ``pts_c1`` (m, camera 1),
        the segment's prior or link to the old segment, odometry, ground and GNSS factors."""
        ref = self._ref
        ka = self.st.new_keyframe(ref['stamp'], T_wc1, len(ref['obs']))
        kb = self.st.new_keyframe(frame.stamp_ns, T_wc2, int(mappable.sum()))
        recs: list[FactorRecord] = []
        values = gtsam.Values()
        values.insert(X(ka), gtsam.Pose3(T_wc1))
        values.insert(X(kb), gtsam.Pose3(T_wc2))
        ts = {X(ka): self.setup.smoother_ts(ka), X(kb): self.setup.smoother_ts(kb)}
        if link is not None and link['kid'] in self.st.kfs:
            c = self.setup.conf
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
        if self.st.ref_odom.ok:
            self._local.add_odometry_record(ka, kb, self.st.ref_odom, recs)
        for t in ids:  # keyframe observations of every common mappable track
            tr = self.st.tracks[t]
            tr.kf_obs[ka] = ref['obs'][t]
        self._local.observe_keyframe(frame, mappable, kb)
        new_lids = []
        R1, t1 = T_wc1[:3, :3], T_wc1[:3, 3]
        for t, p in zip(np.array(ids)[good], pts_c1):
            tr = self.st.tracks[int(t)]
            lid = self._local.new_landmark(int(t), tr, R1 @ p + t1, [ka, kb], recs,
                                                  values, kb, ts)
            new_lids.append(lid)
        for kid in (ka, kb):
            self._local.add_ground_records(kid, new_lids, recs)
        self._gnss.attach(kb, fix, recs)
        self._start_segment('tracking', [(ref['stamp'], T_wc1), (frame.stamp_ns, T_wc2)], recs,
                            values, ts, new_lids, kb, events, 'initialised')

