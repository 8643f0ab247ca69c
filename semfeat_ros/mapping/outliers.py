"""Outlier handling of the mapper: the checks of a keyframe's landmarks after its update.

After each keyframe update the landmarks it observed are checked (at the next frame, see
:meth:`OutlierHandler.run_due`): bearing factors failing a chi-square test are removed at the
next update, landmarks with too few consistent bearings or receding along their rays are killed
(their factors removed, a loose prior keeps the variable determined until it is marginalised,
and their track never maps again).
"""
from __future__ import annotations

import gtsam
from gtsam.symbol_shorthand import L
import numpy as np

from semfeat_ros.mapping import factors as fac
from semfeat_ros.mapping.backend import Backend
from semfeat_ros.mapping.geometry import angle_between
from semfeat_ros.mapping.state import MapperSetup, MapState, RecordKind


class OutlierHandler:
    """Consistency checks of the window's landmarks against the backend's estimate."""

    def __init__(self, setup: MapperSetup, st: MapState, backend: Backend) -> None:
        self.setup = setup
        self.st = st
        self._backend = backend
        self._due: list[int] | None = None  # landmarks of the last update, not yet checked

    @property
    def checks_pending(self) -> bool:
        """True while the landmarks of the last keyframe update wait for their checks."""
        return self._due is not None

    def schedule(self, lids: list[int]) -> None:
        """Check landmarks ``lids`` (just observed by a keyframe update) at :meth:`run_due`."""
        self._due = list(lids)

    def run_due(self) -> None:
        """The scheduled checks: depths of the window's landmarks, then the bearing factors
        of the landmarks of the last update."""
        if self._due is not None:
            lids, self._due = self._due, None
            self.check_depths(self._backend.estimate)
            self.check_bearings(lids)

    def check_depths(self, est: gtsam.Values) -> None:
        """Kill the window's landmarks that estimate ``est`` moved beyond ``lm_lost_depth_m`` of
        their last observer. A point with nearly parallel rays (a ceiling seen three times
        ahead, a track that slid along a repeated texture) fits its bearings ever better as it
        recedes along them, with no factor to stop it; its information then vanishes and the
        next update fails as an indeterminate system. Landmarks seen again are caught earlier by
        the chi-square test; these are the ones nothing re-checks."""
        lids = sorted(lid for lid in self.st.lms if est.exists(L(lid)))
        if not lids:
            return
        P = gtsam.utilities.extractPoint3(est)  # every Point3 in key order: the landmarks
        if P.shape[0] != len(lids):
            P = np.array([est.atPoint3(L(lid)) for lid in lids])
        lms = [self.st.lms[lid] for lid in lids]
        centres = np.array([self.st.kf_T_wc[lm.kf_ids[-1]][:3, 3] for lm in lms])
        far = np.linalg.norm(P - centres, axis=1) > self.setup.conf['lm_lost_depth_m']
        far &= np.array([lm.alive for lm in lms])  # the dead ones are out of the graph already
        for j in np.flatnonzero(far).tolist():
            lm = self.st.lms[lids[j]]
            lm.xyz = P[j]
            self.st.stats['landmarks_lost_depth'] += 1
            self.kill_landmark(lm.lid)

    def check_bearings(self, lids: list[int]) -> None:
        """Chi-square test of the bearing factors of the landmarks just observed; factors
        failing it are removed at the next update, landmarks left with < 2 are killed."""
        recs = []  # the bearing factors of those landmarks (each knows its landmark, keyframe)
        records = self._backend.records
        for lid in lids:
            lm = self.st.lms.get(lid)
            if lm is None or not lm.alive:
                continue
            for rid in lm.rids:
                rec = records.get(rid)
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
        proj, valid = self.setup.camera.project(p_c)
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
                self.kill_landmark(lid)
                continue
            for r in np.flatnonzero((inv == j) & bad).tolist():
                self._backend.remove(recs[r].rid)
                lm.n_obs -= 1

    def kill_landmark(self, lid: int) -> None:
        """Remove an inconsistent landmark's factors; a loose prior keeps its variable
        determined until it is marginalised. Its track never maps again."""
        lm = self.st.lms[lid]
        lm.alive = False
        self.st.stats['landmarks_killed'] += 1
        for rid in lm.rids:
            if rid in self._backend.records:
                self._backend.remove(rid)
        rec = self.st.record(fac.point_prior(L(lid), lm.xyz, 10.0), RecordKind.DEAD, lid=lid)
        lm.rids.append(rec.rid)
        self._backend.queue(rec)
        tr = self.st.tracks.get(lm.track)
        if tr is not None:
            tr.rejected = True
