"""The mapper's backend: the only owner of the GTSAM fixed-lag smoother.

:class:`Backend` holds an ``IncrementalFixedLagSmoother`` (iSAM2 with states older than
``window_keyframes`` marginalised), fed like GTSAM's VisualISAM2Example: per keyframe the new
factors, values and smoother timestamps (:meth:`Backend.commit`). It keeps the records of the
factors in the smoother (by slot, for removal), the factors queued for the next update and those
marked for removal, and the current estimate. A failed update is recovered by rebuilding the
smoother from the window (:meth:`Backend.recover`, :meth:`Backend.rebuild`), as a last resort by
a fresh window (:meth:`Backend.reset_window`); solver failures are never raised.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any, Protocol

import gtsam
from gtsam.symbol_shorthand import L, X
import numpy as np

from semfeat_ros.mapping import factors as fac
from semfeat_ros.mapping.errors import MapperConfigError
from semfeat_ros.mapping.state import FactorRecord, Landmark, MapperSetup, MapState, RecordKind

# What gtsam raises from a failed update: IndeterminantLinearSystem and cheirality/other C++
# exceptions arrive as RuntimeError, std::out_of_range as IndexError, invalid_argument as
# ValueError.
SOLVER_ERRORS = (RuntimeError, IndexError, ValueError)


def first_line(exc: BaseException) -> str:
    """First non-empty line of an exception message (gtsam's start with a newline)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return (lines[0] if lines else type(exc).__name__)[:100]


class Smoother(Protocol):
    """The part of ``gtsam.IncrementalFixedLagSmoother`` the backend uses."""

    def update(self, *args: Any) -> Any: ...  # noqa: D102
    def calculateEstimate(self) -> gtsam.Values: ...  # noqa: D102, N802
    def marginalCovariance(self, key: int) -> np.ndarray: ...  # noqa: D102, N802
    def getISAM2Result(self) -> Any: ...  # noqa: D102, N802
    def getLinearizationPoint(self) -> gtsam.Values: ...  # noqa: D102, N802
    def getFactors(self) -> gtsam.NonlinearFactorGraph: ...  # noqa: D102, N802


#: Called with a landmark leaving the window and its final position (m).
FinalizeLandmark = Callable[[Landmark, np.ndarray], None]
#: Called when the window cannot be kept: (stamp ns, predicted camera pose or None, events).
LoseTracking = Callable[[int, 'np.ndarray | None', list[str]], None]


class Backend:
    """Smoother, its factor records and the estimate of one mapper's window.

    ``finalize`` is called for every landmark that leaves the window; ``lose`` when a window
    reset fails and mapping must start over. ``wrap_smoother`` (optional) wraps every smoother
    the backend makes (instrumentation, fault injection).
    """

    def __init__(self, setup: MapperSetup, st: MapState, finalize: FinalizeLandmark,
                 lose: LoseTracking,
                 wrap_smoother: Callable[[Smoother], Smoother] | None = None) -> None:
        self.setup = setup
        self.st = st
        self._finalize = finalize
        self._lose = lose
        self._wrap = wrap_smoother
        self._recs: dict[int, FactorRecord] = {}  # rid -> record of a factor in the smoother
        self._records = MappingProxyType(self._recs)
        self._pending_remove: set[int] = set()  # rids removed at the next update
        self._pending_recs: list[FactorRecord] = []  # records added at the next update
        self._smoother = self._new_smoother()
        self._estimate = gtsam.Values()
        self._max_ts = -1

    @property
    def estimate(self) -> gtsam.Values:
        """The smoother's current estimate of the window (camera poses ``X``, landmarks ``L``)."""
        return self._estimate

    @property
    def records(self) -> Mapping[int, FactorRecord]:
        """Read-only view: record id -> record of every factor in the smoother."""
        return self._records

    def queue(self, rec: FactorRecord) -> None:
        """Add ``rec`` to the next update (dropped then if its variables left the window)."""
        self._pending_recs.append(rec)

    def remove(self, rid: int) -> None:
        """Remove factor ``rid`` at the next update (rejected: it leaves the full graph)."""
        self._pending_remove.add(rid)
        self._recs[rid].removed = True

    def move_estimate(self, values: gtsam.Values) -> None:
        """Replace the estimate by ``values`` (the window moved to another map frame); the
        smoother follows at the next :meth:`rebuild`."""
        self._estimate = values

    def refresh(self) -> None:
        """Read the smoother's estimate into the estimate and the window's keyframe poses."""
        self._estimate = self._smoother.calculateEstimate()
        for kid in self.st.kfs:
            if self._estimate.exists(X(kid)):
                self.st.kf_T_wc[kid] = self._estimate.atPose3(X(kid)).matrix()

    def marginal_covariance(self, key: int) -> np.ndarray | None:
        """(6, 6) or (3, 3) marginal covariance of variable ``key`` (None: not computable)."""
        try:
            return np.asarray(self._smoother.marginalCovariance(key))
        except SOLVER_ERRORS:
            return None

    def _new_smoother(self) -> Smoother:
        """A new smoother with the configured lag and relinearisation."""
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.setup.conf['relinearize_threshold'])
        params.relinearizeSkip = self.setup.conf['relinearize_skip']
        params.findUnusedFactorSlots = True
        smoother = gtsam.IncrementalFixedLagSmoother(float(self.setup.conf['window_keyframes']),
                                                     params)
        return smoother if self._wrap is None else self._wrap(smoother)

    def commit(self, recs: list[FactorRecord], values: gtsam.Values, ts: dict[int, float],
               kid: int, events: list[str]) -> None:
        """Send keyframe ``kid``'s factors ``recs`` (with the queued ones), new ``values`` and
        their smoother timestamps ``ts`` to the smoother, removing the factors marked for
        removal; a failed update is recovered (:meth:`recover`), never raised."""
        live = [r for r in self._pending_recs
                if all(self._estimate.exists(k) or values.exists(k) for k in r.factor.keys())]
        for r in self._pending_recs:
            if r not in live:
                r.removed = True
        recs = live + recs
        self._pending_recs = []
        remove = sorted(self._pending_remove & set(self._recs))
        graph = gtsam.NonlinearFactorGraph()
        for rec in recs:
            graph.add(rec.factor)
        try:
            self._smoother.update(graph, values, ts, [self._recs[r].index for r in remove])
            new_idx = list(self._smoother.getISAM2Result().getNewFactorsIndices())
            for _ in range(self.setup.conf['extra_iterations']):
                self._smoother.update()
        except SOLVER_ERRORS as exc:
            self.st.stats['update_failures'] += 1
            events.append(f'update_failed: {first_line(exc)}')
            self.recover(recs, values, ts, kid, events)
        else:
            for r in remove:
                self.drop(r, removed=True)
            self._pending_remove.clear()
            for rec, i in zip(recs, new_idx):
                rec.index = int(i)
                self._register(rec)

    def _register(self, rec: FactorRecord) -> None:
        """Record ``rec`` as a factor of the smoother (and of its keyframe)."""
        self._recs[rec.rid] = rec
        if rec.kid in self.st.kfs:
            self.st.kfs[rec.kid].rids.append(rec.rid)

    def drop(self, rid: int, removed: bool = False) -> None:
        """Forget a record of the smoother's factors; ``removed``: the factor is rejected (an
        outlier, a superseded prior), not merely marginalised, and leaves the full graph."""
        rec = self._recs.pop(rid, None)
        if rec is not None and removed:
            rec.removed = True

    def recover(self, recs: list[FactorRecord], values: gtsam.Values, ts: dict[int, float],
                 kid: int, events: list[str]) -> None:
        """Rebuild the smoother after a failed update: first everything with weak priors, then
        without this keyframe's new landmarks, then the new pose alone; never raises."""
        new_lids = {int(gtsam.Symbol(k).index()) for k in values.keys()
                    if chr(gtsam.Symbol(k).chr()) == 'l'}
        if self.rebuild(recs, values, ts, weak=True, events=events, marginals=True):
            self.st.stats['recoveries'] += 1
            events.append('update_recovered')
            return
        for lid in new_lids:
            self.forget_landmark(lid)
        poses = self._only_poses(values)
        pose_ts = {k: v for k, v in ts.items() if poses.exists(k)}
        without = [r for r in recs if r.lid not in new_lids]
        odom = [r for r in without if r.kid == kid and r.kind == RecordKind.ODOM]
        for attempt in (without, odom):
            if self.rebuild(attempt, poses, pose_ts, weak=True, events=events,
                             marginals=True):
                kept = {r.rid for r in attempt}
                for r in recs:
                    if r.rid not in kept:
                        r.removed = True
                self.st.stats['recoveries'] += 1
                events.append('update_recovered')
                return
        for r in recs:
            r.removed = True
        self.reset_window(kid, events)

    def reset_window(self, kid: int, events: list[str]) -> None:
        """Last resort: a fresh window holding only keyframe ``kid`` (the map so far is kept)."""
        events.append('window_reset')
        for lid in list(self.st.lms):
            self._finalize_landmark(lid, self.st.lms[lid].xyz)
        for k in list(self.st.kfs):
            if k != kid:
                del self.st.kfs[k]
        self._recs.clear()
        self._pending_remove.clear()
        self._pending_recs = []
        self.st.lm_by_ts.clear()
        self._smoother = self._new_smoother()
        T = self.st.kf_T_wc[kid]
        prior = fac.pose_prior(X(kid), T, self.setup.prior_cov())
        rec = self.st.record(prior, RecordKind.ANCHOR, kid)
        g = gtsam.NonlinearFactorGraph()
        g.add(rec.factor)
        v = gtsam.Values()
        v.insert(X(kid), gtsam.Pose3(T))
        try:
            self._smoother.update(g, v, {X(kid): self.setup.smoother_ts(kid)})
        except SOLVER_ERRORS as exc:  # nothing left to keep: start over from the next frames
            events.append(f'smoother_reset: {first_line(exc)}')
            rec.removed = True
            self.st.kfs.clear()
            self._smoother = self._new_smoother()
            self._estimate = gtsam.Values()
            self._lose(self.st.kf_stamps[kid], None, events)
            return
        rec.index = 0
        self.st.kfs[kid].rids = []
        self._register(rec)
        self._estimate = self._smoother.calculateEstimate()

    def _only_poses(self, values: gtsam.Values) -> gtsam.Values:
        """The pose variables of ``values``."""
        out = gtsam.Values()
        for k in values.keys():
            if chr(gtsam.Symbol(k).chr()) == 'x':
                out.insert(k, values.atPose3(k))
        return out

    def _finalize_landmark(self, lid: int, xyz: np.ndarray) -> None:
        """Landmark ``lid`` leaves the window at ``xyz`` (m): its factors are forgotten, its
        track keeps the position (tracking against it goes on), then ``finalize``."""
        lm = self.st.lms.pop(lid)
        self.st.lm_by_ts.get(lm.last_kf, set()).discard(lid)
        for rid in lm.rids:
            self.drop(rid)
        tr = self.st.tracks.get(lm.track)
        if tr is not None and lm.alive:
            tr.frozen = np.array(xyz)
        if self.setup.conf['keep_full_graph']:
            self.st.final_xyz[lid] = np.array(xyz)
        self._finalize(lm, xyz)

    def forget_landmark(self, lid: int) -> None:
        """Remove landmark ``lid`` from the window with its factors, as if never made (its
        track may triangulate again)."""
        lm = self.st.lms.pop(lid, None)
        if lm is None:
            return
        self.st.lm_by_ts.get(lm.last_kf, set()).discard(lid)
        for rid in lm.rids:
            self.drop(rid, removed=True)
        tr = self.st.tracks.get(lm.track)
        if tr is not None:
            tr.lid = -1

    def _marginal_records(self, values: gtsam.Values) -> list[FactorRecord]:
        """The smoother's marginal factors as records for a rebuilt smoother.

        A fixed-lag smoother keeps what it knew of the states it marginalised as linear factors
        on the remaining ones (GNSS-anchored heading, say). Each becomes a linear factor pinned
        to the linearisation point it was computed at, so that it stays correct when the new
        smoother moves or relinearises those variables. Empty when a factor involves a variable
        missing from ``values`` (the caller then falls back to priors).
        """
        lin = self._smoother.getLinearizationPoint()
        graph = self._smoother.getFactors()
        out: list[FactorRecord] = []
        for i in range(graph.size()):
            f = graph.at(i)
            if not isinstance(f, gtsam.LinearContainerFactor):
                continue
            point = gtsam.Values()
            for k in f.keys():
                if not (values.exists(k) and lin.exists(k)):
                    return []
                if chr(gtsam.Symbol(k).chr()) == 'x':
                    point.insert(k, lin.atPose3(k))
                else:
                    point.insert(k, lin.atPoint3(k))
            out.append(FactorRecord(self.st.next_rid,
                                    gtsam.LinearContainerFactor(f.factor(), point),
                                    RecordKind.MARGINAL))
            self.st.next_rid += 1
        return out

    def rebuild(self, new_recs: list[FactorRecord], new_values: gtsam.Values,
                 new_ts: dict[int, float], weak: bool, events: list[str],
                 marginals: bool = False) -> bool:
        """A fresh smoother from the window's records and current estimates plus new items.

        With ``marginals`` the old smoother's marginal factors (what it kept of the states it
        marginalised: :meth:`_marginal_records`) move into the new one; otherwise, or when it has
        none, priors on the two oldest window poses stand in for them. Landmarks left with fewer
        than two bearings get a prior; ``weak`` adds loose priors on every variable so that the
        system is determined whatever failed.
        """
        c = self.setup.conf
        values = gtsam.Values()
        ts: dict[int, float] = {}
        for kid in self.st.kfs:
            values.insert(X(kid), gtsam.Pose3(self.st.kf_T_wc[kid]))
            ts[X(kid)] = self.setup.smoother_ts(kid)
        for lid, lm in self.st.lms.items():
            key = L(lid)
            xyz = self._estimate.atPoint3(key) if self._estimate.exists(key) else lm.xyz
            values.insert(key, xyz)
            ts[key] = self.setup.smoother_ts(lm.last_kf)
        for k in new_values.keys():
            if not values.exists(k):
                if chr(gtsam.Symbol(k).chr()) == 'x':
                    values.insert(k, new_values.atPose3(k))
                else:
                    values.insert(k, new_values.atPoint3(k))
        ts.update(new_ts)
        marg = self._marginal_records(values) if marginals else []
        # the old priors stay when the marginal factors carry over (they are the same graph)
        replaced = (RecordKind.ANCHOR, RecordKind.PRIOR) if not marg else ()
        keep = [r for rid, r in self._recs.items()
                if rid not in self._pending_remove and r.kind not in replaced]
        keep = [r for r in keep if all(values.exists(k) for k in r.factor.keys())] + marg
        new_ok = [r for r in new_recs if all(values.exists(k) for k in r.factor.keys())]
        extra: list[FactorRecord] = []
        # without them the two oldest window poses stand in for the lost marginal information
        # (two poses also keep the scale of a camera-only map)
        for n, k in enumerate([] if marg else sorted(self.st.kfs)[:2]):
            if n > 0 and new_values.exists(X(k)):
                break
            kind = RecordKind.PRIOR if k == 0 and not self.st.gnss_aligned else RecordKind.ANCHOR
            prior = fac.pose_prior(X(k), self.st.kf_T_wc[k], self.setup.prior_cov())
            extra.append(self.st.record(prior, kind, k))
        n_bear: dict[int, int] = {}
        for r in keep + new_ok:
            if r.kind == RecordKind.BEARING:
                n_bear[r.lid] = n_bear.get(r.lid, 0) + 1
        for lid in self.st.lms:
            if n_bear.get(lid, 0) < 2:
                prior = fac.point_prior(L(lid), values.atPoint3(L(lid)), 0.2)
                extra.append(self.st.record(prior, RecordKind.ANCHOR, lid=lid))
        if weak:
            sr, sm = c['recovery_sigma_rad'], c['recovery_sigma_m']
            cov = np.diag([sr**2] * 3 + [sm**2] * 3)
            for k in values.keys():
                sym = gtsam.Symbol(k)
                if chr(sym.chr()) == 'x':
                    prior = fac.pose_prior(k, values.atPose3(k).matrix(), cov)
                    extra.append(self.st.record(prior, RecordKind.RECOVERY, int(sym.index())))
                else:
                    prior = fac.point_prior(k, values.atPoint3(k), sm)
                    extra.append(self.st.record(prior, RecordKind.RECOVERY,
                                                lid=int(sym.index())))
        recs = keep + new_ok + extra
        graph = gtsam.NonlinearFactorGraph()
        for r in recs:
            graph.add(r.factor)
        smoother = self._new_smoother()
        try:
            smoother.update(graph, values, ts)
            idx = list(smoother.getISAM2Result().getNewFactorsIndices())
        except SOLVER_ERRORS as exc:
            events.append(f'rebuild_failed: {first_line(exc)}')
            for r in extra:
                r.removed = True
            return False
        self._smoother = smoother
        kept = {r.rid for r in keep}
        for rid, r in list(self._recs.items()):
            if rid not in kept:  # outliers and superseded priors are rejected for good
                self.drop(rid, removed=rid in self._pending_remove
                               or r.kind in (RecordKind.ANCHOR, RecordKind.PRIOR))
        self._recs.clear()
        for kf in self.st.kfs.values():
            kf.rids = []
        for r, i in zip(recs, idx):
            r.index = int(i)
            self._register(r)
            if r.lid in self.st.lms and r.kind in (RecordKind.ANCHOR, RecordKind.RECOVERY):
                self.st.lms[r.lid].rids.append(r.rid)
        self._pending_remove.clear()
        for kid in {gtsam.Symbol(k).index() for k in new_values.keys()
                    if chr(gtsam.Symbol(k).chr()) == 'x'}:
            if kid in self.st.kfs:
                self.st.kfs[kid].rids = [r.rid for r in recs if r.kid == kid]
        return True

    def sync(self, kid: int, lids: list[int]) -> list[int]:
        """After keyframe ``kid``'s update: read the estimate into the keyframe poses and the
        landmarks ``lids`` just observed, finalise the marginalised landmarks; returns the
        keyframes that left the window (marginalised), oldest first."""
        gone: list[int] = []
        old = self._estimate
        self._estimate = self._smoother.calculateEstimate()
        est = self._estimate
        self._max_ts = max(self._max_ts, kid)
        for k in list(self.st.kfs):
            if est.exists(X(k)):
                self.st.kf_T_wc[k] = est.atPose3(X(k)).matrix()
                self.st.kf_alt[k] = float((self.st.kf_T_wc[k] @ self.setup.T_cb)[2, 3])
            else:  # marginalised: its last estimate stays in the trajectory
                for rid in self.st.kfs[k].rids:
                    self.drop(rid)
                del self.st.kfs[k]
                gone.append(k)
        c = self.setup.conf
        cutoff = self._max_ts - c['window_keyframes'] + c['marginalize_every']
        for t in [t for t in self.st.lm_by_ts if t <= cutoff]:
            for lid in list(self.st.lm_by_ts[t]):
                if not est.exists(L(lid)):
                    lm = self.st.lms[lid]
                    xyz = old.atPoint3(L(lid)) if old.exists(L(lid)) else lm.xyz
                    self._finalize_landmark(lid, xyz)
            if not self.st.lm_by_ts.get(t):
                self.st.lm_by_ts.pop(t, None)
        for lid in lids:
            lm = self.st.lms.get(lid)
            if lm is not None and est.exists(L(lid)):
                lm.xyz = est.atPoint3(L(lid))
        return gone

    def batch_optimize(self, max_iterations: int = 100
                       ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """Levenberg-Marquardt on every factor ever kept (needs ``keep_full_graph``).

        Returns ``(T_map_base (K, 4, 4), {landmark id: position (m)})``; the incremental
        estimates are the initial values. Used to check the incremental solution.
        """
        if not self.setup.conf['keep_full_graph']:
            raise MapperConfigError('batch_optimize needs keep_full_graph=True in the conf')
        skip = {RecordKind.ANCHOR, RecordKind.RECOVERY, RecordKind.DEAD, RecordKind.MARGINAL}
        if self.st.gnss_aligned:
            skip.add(RecordKind.PRIOR)
        graph = gtsam.NonlinearFactorGraph()
        keys: set[int] = set()
        for rec in self.st.all_recs:
            if rec.removed or rec.kind in skip:
                continue
            graph.add(rec.factor)
            keys.update(rec.factor.keys())
        values = gtsam.Values()
        for key in keys:
            sym = gtsam.Symbol(key)
            idx = sym.index()
            if chr(sym.chr()) == 'x':
                values.insert(key, gtsam.Pose3(self.st.kf_T_wc[idx]))
            else:
                if self._estimate.exists(key):
                    xyz = self._estimate.atPoint3(key)
                elif idx in self.st.final_xyz:
                    xyz = self.st.final_xyz[idx]
                else:
                    xyz = self.st.lms[idx].xyz
                values.insert(key, xyz)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        poses = np.array([
            (result.atPose3(X(k)).matrix() if result.exists(X(k)) else self.st.kf_T_wc[k])
            @ self.setup.T_cb for k in range(len(self.st.kf_T_wc))])
        lms = {}
        for key in keys:
            sym = gtsam.Symbol(key)
            if chr(sym.chr()) == 'l':
                lms[int(sym.index())] = result.atPoint3(key)
        return poses.reshape(-1, 4, 4), lms

