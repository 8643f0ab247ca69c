"""GNSS in the mapper: fix gating, GNSS factors, alignment of the map frame to ENU, and the
wheel-odometry calibration learnt on GNSS-anchored keyframes.

Until the map is aligned, accepted fixes wait as (keyframe, position, covariance) pairs; once
they span enough distance the alignment finds ``map_in_enu``, the rigid transform (a rotation
about z and a translation) from the map frame to ENU, and every fix from then on enters the map
frame through it: the waiting pairs and every later keyframe with a fix get a GNSS factor. The
map frame itself never moves, so the trajectory a subscriber receives has no step where GNSS
arrives (REP-105's ``earth``/``map`` split: ENU is a parent of ``map``). Only a map whose scale
came from nothing metric (no wheel odometry) is rescaled once, by the alignment's scale. Fixes
are gated on their covariance and, once aligned, on their distance to the predicted antenna.
"""
from __future__ import annotations

import gtsam
from gtsam.symbol_shorthand import L, X
import numpy as np

from semfeat_ros.mapping import factors as fac
from semfeat_ros.mapping.backend import Backend
from semfeat_ros.mapping.geometry import align_yaw, yaw_of
from semfeat_ros.mapping.landmark_map import LandmarkMap
from semfeat_ros.mapping.odometry import OdometryCalibration
from semfeat_ros.mapping.state import FactorRecord, MapperSetup, MapState, PendingFix, RecordKind
from semfeat_ros.mapping.types import GnssFix

GNSS_ANCHOR_KF = 3  # a keyframe pair counts as GNSS-anchored with fixes this close (keyframes)


class GnssAlignment:
    """GNSS fixes of one mapper: gate, attach to keyframes, align the map frame with ENU."""

    def __init__(self, setup: MapperSetup, st: MapState, backend: Backend,
                 landmark_map: LandmarkMap) -> None:
        self.setup = setup
        self.st = st
        self._backend = backend
        self._map = landmark_map
        self._pending: PendingFix | None = None  # a fix of a frame that was no keyframe
        self._pairs: list[tuple[int, np.ndarray, np.ndarray]] = []  # before the alignment
        self._rejects = 0  # consecutive fixes rejected by the distance gate
        self._kids: set[int] = set()  # keyframes with a GNSS factor, not yet marginalised
        self._T_enu_map: np.ndarray | None = None  # (4, 4) map -> ENU once aligned (m)
        c = setup.conf
        # odometry calibration; per keyframe the raw (heading change, distance, time in
        # motion) of the odometry from the previous keyframe
        self.calibration = OdometryCalibration(
            c['odom_calib_sigma_rad'], c['odom_calib_sigma_m'], c['odom_calib_prior_bias'],
            c['odom_calib_prior_scale'], c['odom_calib_min_pairs']
        ) if c['odom_calibration'] else None
        self._kf_odom_raw: dict[int, tuple[float, float, float]] = {}

    @property
    def anchored_keyframes(self) -> frozenset[int]:
        """Window keyframes with a GNSS factor."""
        return frozenset(self._kids)

    @property
    def map_in_enu(self) -> np.ndarray | None:
        """(4, 4) pose of the map frame in ENU (m; a rotation about z), None until aligned."""
        return None if self._T_enu_map is None else self._T_enu_map.copy()

    def to_map(self, position: np.ndarray, covariance: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """An ENU fix ``position`` (3,) m with ``covariance`` (3, 3) m^2 in the map frame."""
        if self._T_enu_map is None:
            raise RuntimeError('the map is not aligned with ENU yet')
        R, t = self._T_enu_map[:3, :3], self._T_enu_map[:3, 3]
        return R.T @ (np.asarray(position) - t), R.T @ np.asarray(covariance) @ R

    @property
    def waiting(self) -> bool:
        """True while fixes wait for the alignment."""
        return bool(self._pairs)

    def hold(self, fix: GnssFix, T_wb: np.ndarray | None) -> None:
        """Keep the fix of a frame that made no keyframe, with the frame's base pose
        ``T_wb`` (4, 4), for the next keyframe (:meth:`attach`)."""
        self._pending = PendingFix(fix.stamp_ns, fix.position, fix.covariance, T_wb)

    def note_odometry(self, kid: int, raw: tuple[float, float, float]) -> None:
        """The odometry from keyframe ``kid - 1`` to ``kid`` as measured: (heading change
        rad, distance m, time in motion s)."""
        self._kf_odom_raw[kid] = raw

    def check_fix(self, fix: GnssFix | None, T_wc_pred: np.ndarray | None,
                   events: list[str]) -> GnssFix | None:
        """Covariance gate of an ENU fix; returns it (with a floored covariance) or None:
        in ENU until the alignment, in the map frame after it."""
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
            elif np.sqrt(w.max()) > self.setup.conf['gnss_max_sigma_m']:
                reason = (f'sigma {np.sqrt(w.max()):.2f} m above gnss_max_sigma_m '
                          f'{self.setup.conf["gnss_max_sigma_m"]}')
            else:
                w = np.maximum(w, self.setup.conf['gnss_min_sigma_m'] ** 2)
                cov = (V * w) @ V.T
                if self.st.gnss_aligned:
                    pos, cov = self.to_map(pos, cov)
        if reason is None and self.st.gnss_aligned and T_wc_pred is not None:
            T_wb = T_wc_pred @ self.setup.T_cb
            pred = T_wb[:3, :3] @ self.setup.arm_b + T_wb[:3, 3]
            d = pos - pred
            S = cov + np.eye(3) * self.setup.conf['gnss_gate_sigma_m'] ** 2
            m2 = float(d @ np.linalg.solve(S, d))
            if m2 > self.setup.conf['gnss_gate_chi2']:
                self._rejects += 1
                if self._rejects >= self.setup.conf['gnss_max_rejects']:
                    events.append('gnss_gate_reopened')
                    self._rejects = 0
                else:
                    reason = f'inconsistent with the estimate ({np.linalg.norm(d):.2f} m off)'
        if reason is not None:
            self.st.stats['gnss_rejected'] += 1
            events.append(f'gnss_rejected: {reason}')
            return None
        self._rejects = 0
        self.st.stats['gnss_accepted'] += 1
        return GnssFix(int(fix.stamp_ns), pos, cov)

    def attach(self, kid: int, fix: GnssFix | None, recs: list[FactorRecord]) -> None:
        """Attach this frame's fix (or the pending one, moved by the tracked motion)."""
        T_wb = self.st.kf_T_wc[kid] @ self.setup.T_cb
        if fix is not None:
            pos, cov = fix.position, fix.covariance
        else:
            p = self._pending
            self._pending = None
            if p is None or p.T_wb is None:
                return
            if (self.st.kf_stamps[kid] - p.stamp_ns) * 1e-9 > self.setup.conf['gnss_max_age_s']:
                return
            ant_then = p.T_wb[:3, :3] @ self.setup.arm_b + p.T_wb[:3, 3]
            ant_now = T_wb[:3, :3] @ self.setup.arm_b + T_wb[:3, 3]
            pos = p.position + (ant_now - ant_then)
            moved = float(np.linalg.norm(ant_now - ant_then))
            cov = p.covariance + np.eye(3) * (0.02 + 0.02 * moved) ** 2
        self._pending = None
        if self.st.gnss_aligned:
            f = fac.gnss_factor(X(kid), pos, cov, self.setup.arm_c, 2.0)
            recs.append(self.st.record(f, RecordKind.GNSS, kid))
            self._kids.add(kid)
        else:
            self._pairs.append((kid, pos, cov))
            del self._pairs[:-500]  # bounded while waiting for enough spread to align

    def try_align(self, events: list[str]) -> None:
        """Align the map frame with ENU once enough fixes with enough spread wait: a yaw (and,
        without odometry scale, scale) similarity of the keyframes' antenna positions to the
        fixes, outliers dropped while the rms exceeds ``gnss_align_max_rms_m``. Its rotation
        and translation become :attr:`map_in_enu`; a scale other than 1 rescales the whole
        estimate (:meth:`_rescale`). The window is rebuilt with the fixes' factors."""
        c = self.setup.conf
        pairs = self._pairs
        if len(pairs) < c['gnss_align_min_fixes']:
            return
        dst = np.array([p[1] for p in pairs])
        T_wb = np.array([self.st.kf_T_wc[p[0]] for p in pairs]) @ self.setup.T_cb
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
        if s != 1.0:
            self._rescale(s)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        self._T_enu_map = T
        self.st.gnss_aligned = True
        events.append(f'gnss_aligned: rms {rms:.2f} m, scale {s:.3f}')
        recs = [self.st.record(fac.gnss_factor(X(k), *self.to_map(pos, cov),
                                               self.setup.arm_c, 2.0), RecordKind.GNSS, k)
                for (k, pos, cov), ok in zip(pairs, keep) if ok and k in self.st.kfs]
        p = self._pending
        if p is not None:  # held in ENU before the alignment
            p.position, p.covariance = self.to_map(p.position, p.covariance)
        self._kids.update(r.kid for r in recs)
        self._pairs = []
        self.st.metric = True
        be = self._backend
        if not (be.rebuild(recs, gtsam.Values(), {}, weak=False, events=events)
                or be.rebuild(recs, gtsam.Values(), {}, weak=True, events=events)):
            be.reset_window(self.st.last_kid, events)
        be.refresh()

    def _rescale(self, s: float) -> None:
        """Scale the whole estimate by ``x -> s x`` about the map origin: a map whose scale was
        not metric takes the GNSS scale (positions only; rotations and the extrinsic stay)."""
        T_cb, T_bc = self.setup.T_cb, self.setup.T_bc

        def move(T: np.ndarray) -> np.ndarray:
            out = np.array(T)
            out[:3, 3] = s * T[:3, 3]
            return out

        # the camera pose moves with the base: T_wc' = S T_wb T_bc; keep T_bc, scale positions
        self.st.kf_T_wc = [move(T @ T_cb) @ T_bc for T in self.st.kf_T_wc]
        self.st.kf_alt = [float((T @ T_cb)[2, 3]) for T in self.st.kf_T_wc]
        values = gtsam.Values()
        for kid in self.st.kfs:
            values.insert(X(kid), gtsam.Pose3(self.st.kf_T_wc[kid]))
        for lid, lm in self.st.lms.items():
            est = self._backend.estimate
            xyz = est.atPoint3(L(lid)) if est.exists(L(lid)) else lm.xyz
            lm.xyz = s * np.asarray(xyz)
            values.insert(L(lid), lm.xyz)
        self._backend.move_estimate(values)
        for tr in self.st.tracks.values():
            if tr.frozen is not None:
                tr.frozen = s * tr.frozen
        self.st.final_xyz = {k: s * v for k, v in self.st.final_xyz.items()}
        self.st.history = [(st, move(T @ T_cb) @ T_bc) for st, T in self.st.history]
        self._map.transform(s, np.eye(3), np.zeros(3))
        if self.st.link is not None:
            self.st.link['T_wc'] = move(self.st.link['T_wc'] @ T_cb) @ T_bc
        p = self._pending
        if p is not None and p.T_wb is not None:
            p.T_wb = move(p.T_wb)

    def learn_odometry(self, k: int) -> None:
        """Feed the odometry calibration with marginalised keyframe ``k`` and its predecessor:
        their final heading change and distance against the odometry's, when GNSS factors sit
        within ``GNSS_ANCHOR_KF`` keyframes on both sides (an anchored estimate; without GNSS
        the motion follows the odometry itself)."""
        odo = self._kf_odom_raw.pop(k, None)
        gap = GNSS_ANCHOR_KF
        anchored = (any(k - gap <= g < k for g in self._kids)
                    and any(k <= g <= k + gap for g in self._kids))
        self._kids = {g for g in self._kids if g >= k - gap}
        for old in [j for j in self._kf_odom_raw if j < k]:
            del self._kf_odom_raw[old]
        if self.calibration is None or odo is None or not anchored:
            return
        T0 = self.st.kf_T_wc[k - 1] @ self.setup.T_cb
        T1 = self.st.kf_T_wc[k] @ self.setup.T_cb
        self.calibration.add(odo[0], yaw_of(T0[:3, :3].T @ T1[:3, :3]), odo[2], odo[1],
                           float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])))

    def calibration_summary(self) -> dict[str, float | int]:
        """The learnt odometry errors: ``yaw_bias_rad_s``, ``yaw_scale``, ``distance_scale``
        (all 0 until enough GNSS-anchored keyframe pairs) and ``pairs`` used so far."""
        c = self.calibration
        if c is None:
            return {'yaw_bias_rad_s': 0.0, 'yaw_scale': 0.0, 'distance_scale': 0.0, 'pairs': 0}
        return {'yaw_bias_rad_s': c.yaw_bias, 'yaw_scale': c.yaw_scale,
                'distance_scale': c.distance_scale, 'pairs': c.n_pairs}

