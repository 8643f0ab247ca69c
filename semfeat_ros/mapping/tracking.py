"""Tracking: label votes of the tracks, pose prediction, pose tracking against the landmarks.

Each frame's pose is predicted from wheel odometry or a constant-velocity model, then refined
on the bearings of the tracks whose landmarks are known (in the window, or marginalised into
the map). Without enough inliers the odometry prediction stands in ('odometry_only'); without
odometry tracking is lost and the mapper re-initialises.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.mapping.geometry import (
    angle_between,
    refine_pose_bearings,
    se3_exp,
    se3_inv,
    se3_log,
)
from semfeat_ros.mapping.local_mapping import spread
from semfeat_ros.mapping.state import MapperSetup, MapState, Track
from semfeat_ros.mapping.types import OdometryDelta, Tracks


@dataclass(frozen=True)
class TrackedPose:
    """A frame's tracked camera pose."""

    T_wc: np.ndarray | None  # (4, 4) camera pose in map (m); the prediction when lost
    covariance: np.ndarray | None  # (6, 6) camera frame (rad^2, m^2); None without tracking
    n_inliers: int  # bearings consistent with the pose
    observations: list[tuple[int, int]] | None  # (track id, row) of landmarks seen; None: lost


class Tracker:
    """Per-frame pose of the camera against the map (the frame-to-map front of the mapper)."""

    def __init__(self, setup: MapperSetup, st: MapState) -> None:
        self.setup = setup
        self.st = st

    def predict(self, stamp_ns: int, odometry: OdometryDelta | None) -> np.ndarray | None:
        """Camera pose at ``stamp_ns`` from odometry or a constant-velocity model."""
        if not self.st.history:
            return None
        t1, T1 = self.st.history[-1]
        if odometry is not None:
            return T1 @ self.setup.T_cb @ odometry.T @ self.setup.T_bc
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
        """Camera pose ``T_wc`` of the frame at ``stamp_ns`` for the next predictions."""
        self.st.history.append((stamp_ns, T_wc))
        del self.st.history[:-2]

    def _landmark_of(self, tr: Track) -> np.ndarray | None:
        """Position (m) of track ``tr``'s landmark: in the window, else marginalised."""
        if tr.lid >= 0:
            lm = self.st.lms.get(tr.lid)
            if lm is not None:
                return lm.xyz if lm.alive else None
        return tr.frozen

    def vote(self, frame: Tracks) -> np.ndarray:
        """Update label votes; returns the (N,) mask of tracks allowed into the map."""
        n = len(frame)
        ok = np.zeros(n, bool)
        max_dyn = self.setup.conf['dynamic_max_fraction']
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

    def prune(self, frame: Tracks) -> None:
        """Tracks absent from this frame ended (ids are never reused): forget them."""
        alive = set(frame.track_id.tolist())
        for tid in [t for t in self.st.tracks if t not in alive]:
            del self.st.tracks[tid]

    def track(self, frame: Tracks, mappable: np.ndarray, odometry: OdometryDelta | None,
              events: list[str]) -> TrackedPose:
        """Camera pose of ``frame`` from its bearings to the landmarks (robust refinement
        from the prediction, state 'tracking'), else from odometry alone ('odometry_only'),
        else tracking is lost (no observations: the caller calls :meth:`lose`)."""
        pred = self.predict(frame.stamp_ns, odometry)
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
            est = refine_pose_bearings(pred, P, frame.bearing[sel_a], self.setup.sigma,
                                       huber_k=self.setup.conf['robust_k'],
                                       chi2=self.setup.conf['outlier_chi2'])
        n_inl = int(est.inliers.sum()) if est is not None else 0
        cov_c = None
        if n_inl >= self.setup.conf['min_tracking_inliers']:
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
            return TrackedPose(pred, None, n_inl, None)
        self._push_pose(frame.stamp_ns, T_wc)
        obs_idx = sel_a[np.flatnonzero(inliers)].tolist() if len(sel_a) else []
        if len(obs_idx) > self.setup.conf['max_obs_per_keyframe']:
            prio = np.array([self.st.lms[self.st.tracks[int(frame.track_id[i])].lid].n_obs
                             if self.st.tracks[int(frame.track_id[i])].lid in self.st.lms else 0
                             for i in obs_idx], dtype=float)
            keep = spread(frame.pixel[obs_idx], prio, self.setup.conf['max_obs_per_keyframe'],
                          self.setup.camera)
            obs_idx = [obs_idx[k] for k in keep]
        lm_obs = [(int(frame.track_id[i]), i) for i in obs_idx]
        return TrackedPose(T_wc, cov_c, n_inl, lm_obs)

    def follow_keyframe(self, stamp_ns: int) -> np.ndarray:
        """The frame at ``stamp_ns`` became the last keyframe: the next predictions start
        from its smoothed pose (chained on the tracked or odometry-predicted one they drift
        away from the map). Returns that pose."""
        if self.st.history and self.st.history[-1][0] == stamp_ns:
            self.st.history[-1] = (stamp_ns, self.st.kf_T_wc[-1])
        return self.st.kf_T_wc[-1]

    def lose(self, stamp_ns: int, pred: np.ndarray | None, events: list[str]) -> None:
        """Tracking is lost at ``stamp_ns``: state 'lost'; the last motion is kept so that a
        re-initialised segment can be linked to the last keyframe."""
        events.append('tracking_lost')
        self.st.stats['tracking_lost'] += 1
        self.st.state = 'lost'
        if self.st.last_kid >= 0 and self.st.history:
            t1, T1 = self.st.history[-1]
            xi = np.zeros(6)
            if len(self.st.history) >= 2:
                t0, T0 = self.st.history[-2]
                if t1 > t0:
                    xi = se3_log(se3_inv(T0) @ T1) / ((t1 - t0) * 1e-9)
            self.st.link = dict(kid=self.st.last_kid, stamp=t1, T_wc=T1, xi=xi)

