"""Local mapping: the factors of a new keyframe (it produces factors, the backend commits them).

Per keyframe: wheel-odometry between-factor, bearing factors of the tracked landmarks, new
landmarks triangulated from tracks seen in enough keyframes with enough parallax (static classes
only), ground-plane factors of ground landmarks near the vehicle, a level-floor prior on an
earlier keyframe of a plateau, and (one keyframe later, see :meth:`LocalMapping.queue_rotation`)
the two-view relative rotation to the keyframe before.
"""
from __future__ import annotations

from collections.abc import Callable

import gtsam
from gtsam.symbol_shorthand import L, X
import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.mapping import factors as fac
from semfeat_ros.mapping.geometry import (
    angle_between,
    fit_plane_ransac,
    se3_inv,
    transform_covariance,
    triangulate_bearings,
    vehicle_camera_translation,
)
from semfeat_ros.mapping.state import (
    FactorRecord,
    Landmark,
    MapperSetup,
    MapState,
    OdomChain,
    RecordKind,
    Track,
)
from semfeat_ros.mapping.types import Tracks
from semfeat_ros.matching.geometry import epipolar_sines, refine_rotation, verify_bearings
from semfeat_ros.rotations import skew, so3_exp, so3_log


def spread(pixels: np.ndarray, priority: np.ndarray, n: int, camera: CameraModel) -> np.ndarray:
    """Indices of ``n`` of the items at ``pixels`` (N, 2) px spread over ``camera``'s image:
    round-robin over an 8x8 grid of cells, each cell in decreasing ``priority`` (N,)."""
    cx = np.clip((pixels[:, 0] / camera.width * 8).astype(int), 0, 7)
    cy = np.clip((pixels[:, 1] / camera.height * 8).astype(int), 0, 7)
    cell = cy * 8 + cx
    order = np.lexsort((-priority, cell))
    sorted_cell = cell[order]
    first = np.searchsorted(sorted_cell, sorted_cell, side='left')
    rank = np.arange(len(order)) - first
    pick = order[np.lexsort((-priority[order], rank))][:n]
    return np.sort(pick)


class LocalMapping:
    """Factors and landmarks of new keyframes; every new record goes to the caller's list."""

    def __init__(self, setup: MapperSetup, st: MapState) -> None:
        self.setup = setup
        self.st = st
        # the keyframe pair whose rotation is verified at the next frame (ka, kb, bearings a, b)
        self._rot_job: tuple[int, int, np.ndarray, np.ndarray] | None = None

    @property
    def rotation_pending(self) -> bool:
        """True while a keyframe pair's rotation waits for :meth:`run_rotation_job`."""
        return self._rot_job is not None

    def keyframe_factors(self, frame: Tracks, mappable: np.ndarray, prev: int, kid: int,
                         lm_obs: list[tuple[int, int]], recs: list[FactorRecord],
                         values: gtsam.Values, ts: dict[int, float]) -> list[int]:
        """The factors of new keyframe ``kid`` (previous keyframe ``prev``) into ``recs``, its
        new landmarks into ``values`` and ``ts``; ``lm_obs`` are (track id, row of ``frame``)
        of the tracked landmarks it observes. Returns the landmarks it observed or created."""
        if self.st.kf_odom.ok and prev in self.st.kfs:
            self.add_odometry_record(prev, kid, self.st.kf_odom, recs)
        self.observe_keyframe(frame, mappable, kid)
        if prev in self.st.kfs:
            self.queue_rotation(frame, mappable, prev, kid, recs)
        self.add_level_record(kid, recs)
        seen = self._observe_landmarks(frame, kid, lm_obs, recs, ts)
        new_lids = self.triangulate(frame, mappable, kid, recs, values, ts)
        self.add_ground_records(kid, seen + new_lids, recs)
        return seen + new_lids

    def _observe_landmarks(self, frame: Tracks, kid: int, lm_obs: list[tuple[int, int]],
                           recs: list[FactorRecord], ts: dict[int, float]) -> list[int]:
        """Bearing factors of keyframe ``kid`` to the live landmarks of ``lm_obs``."""
        T_wc = self.st.kf_T_wc[kid]
        seen: list[int] = []
        seen_rows: list[int] = []
        for tid, i in lm_obs:
            tr = self.st.tracks[tid]
            lm = self.st.lms.get(tr.lid)
            if lm is None or not lm.alive:
                continue
            f = fac.bearing_factor(X(kid), L(lm.lid), frame.bearing[i],
                                   self.setup.bearing_noise)
            rec = self.st.record(f, RecordKind.BEARING, kid, lm.lid, frame.bearing[i],
                                 frame.pixel[i])
            recs.append(rec)
            lm.rids.append(rec.rid)
            self._observed(lm, kid, frame.bearing[i])
            self._touch(lm, kid, ts)
            seen.append(lm.lid)
            seen_rows.append(i)
        self._update_parallax([self.st.lms[lid] for lid in seen],
                              frame.bearing[seen_rows] @ T_wc[:3, :3].T)
        return seen

    def observe_keyframe(self, frame: Tracks, mappable: np.ndarray, kid: int) -> None:
        """Keyframe ``kid`` observes every mappable track of ``frame`` (bearing, pixel)."""
        for i in np.flatnonzero(mappable).tolist():
            self.st.tracks[int(frame.track_id[i])].kf_obs[kid] = (frame.bearing[i], frame.pixel[i])

    def add_odometry_record(self, ka: int, kb: int, chain: OdomChain,
                            recs: list[FactorRecord]) -> None:
        """Between-factor of keyframes ``ka`` and ``kb`` from the composed odometry ``chain``
        (its covariance floored at ``odom_min_sigma``)."""
        floor = self.setup.conf['odom_min_sigma'] ** 2
        T_rel_c = self.setup.T_cb @ chain.T @ self.setup.T_bc
        cov_c = transform_covariance(chain.cov, self.setup.T_bc) + np.eye(6) * floor
        recs.append(self.st.record(fac.between(X(ka), X(kb), T_rel_c, cov_c), RecordKind.ODOM, kb))
        self.st.kfs[kb].odom_linked = True

    def queue_rotation(self, frame: Tracks, mappable: np.ndarray, ka: int, kb: int,
                       recs: list[FactorRecord]) -> None:
        """Collect the common tracks of keyframes ka and kb (unit bearings in each) for their
        relative rotation (:meth:`rotation_record`). The RANSAC runs when the next frame arrives
        (:meth:`run_rotation_job`) and its factor joins the next keyframe's update, not this
        keyframe's ``recs``: the keyframe's own update stays short, and the robust factor is
        first linearised at kb's smoothed pose instead of its tracked one."""
        c = self.setup.conf
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

    def run_rotation_job(self, add: Callable[[FactorRecord], None]) -> None:
        """Verify the queued keyframe pair, if both are still in the window; its factor goes
        to ``add``."""
        job, self._rot_job = self._rot_job, None
        if job is None or job[0] not in self.st.kfs or job[1] not in self.st.kfs:
            return
        rec = self.rotation_record(*job)
        if rec is not None:
            add(rec)

    def rotation_record(self, ka: int, kb: int, ba: np.ndarray, bb: np.ndarray
                      ) -> FactorRecord | None:
        """Relative rotation between keyframes ka and kb from the two-view geometry of their
        common tracks, unit bearings ``ba`` and ``bb`` (N, 3) (5-point RANSAC). Far points,
        which never become landmarks, fix the rotation well: this bounds the heading drift
        between landmark observations."""
        c = self.setup.conf
        thr = c['init_ransac_px'] / self.setup.camera.fx
        ver = verify_bearings(ba, bb, {'threshold_rad': thr, 'seed': c['seed'],
                                       'min_inliers': c['vision_rotation_min_tracks']})
        if not ver.ok:
            return None
        T_ab = se3_inv(self.st.kf_T_wc[ka]) @ self.st.kf_T_wc[kb]
        R = ver.R
        if c['vision_rotation_kinematic'] and self.st.metric:
            dist = float(np.linalg.norm((self.setup.T_bc @ T_ab @ self.setup.T_cb)[:3, 3]))
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
        driven. A free translation absorbs part of a pitch change as a vertical tilt. The yaw
        stays the free estimate's (the refined yaw maps the long drives worse). Kept only when
        the fixed motion explains at least 90 % of the inliers (no slip, the distance right);
        otherwise ``R`` is returned."""
        if dist < self.setup.conf['kf_min_distance_m'] or inliers.sum() < 3:
            return R
        Rk = R
        for _ in range(3):  # the translation follows the rotation (arc chord, lever arm)
            Rk = refine_rotation(Rk, vehicle_camera_translation(Rk, self.setup.T_bc, dist),
                                 b_a[inliers], b_b[inliers])
        t = vehicle_camera_translation(Rk, self.setup.T_bc, dist)
        agree = epipolar_sines(skew(t / np.linalg.norm(t)) @ Rk, b_a, b_b) < np.sin(thr)
        if agree.sum() < 0.9 * inliers.sum():
            return R
        R_bc = self.setup.T_bc[:3, :3]
        d = R_bc @ so3_log(Rk @ R.T)  # the correction in base axes
        d[2] = 0.0  # keep the free estimate's yaw
        return so3_exp(R_bc.T @ d) @ R

    def add_level_record(self, kid: int, recs: list[FactorRecord]) -> None:
        """Level-floor prior on keyframe ``k = kid - level_delay_keyframes``, once the smoother
        has seen the keyframes after it. Every keyframe from ``level_delay`` before ``k`` to the
        last one the smoother has estimated must be below ``level_max_tilt_deg`` and tilted by
        less than ``level_max_change_deg`` against ``k``: a plateau, not a ramp or its
        transition. The tilt change between neighbours is observed well (odometry, tracks)
        even where the absolute tilt lags; deciding on the predicted pose of a new keyframe
        alone would hold a ramp level. That prediction (``kid``) is left out: it chains
        odometry on the last prediction and keeps a ramp's pitch after the ramp when tracking
        falls back to odometry."""
        c = self.setup.conf
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

    def _touch(self, lm: Landmark, kid: int, ts: dict[int, float]) -> None:
        """Landmark seen at keyframe ``kid``: refresh its smoother timestamp."""
        if lm.last_kf in self.st.lm_by_ts:
            self.st.lm_by_ts[lm.last_kf].discard(lm.lid)
        lm.last_kf = kid
        self.st.lm_by_ts.setdefault(kid, set()).add(lm.lid)
        ts[L(lm.lid)] = self.setup.smoother_ts(kid)

    def new_landmark(self, tid: int, tr: Track, xyz: np.ndarray, kids: list[int],
                      recs: list[FactorRecord], values: gtsam.Values, kid_now: int,
                      ts: dict[int, float] | None = None, rays: np.ndarray | None = None,
                      max_par: float | None = None) -> int:
        """Create landmark ``L(lid)`` of track ``tid`` at ``xyz`` (m) with bearing factors from
        keyframes ``kids``; ``rays`` are those observations in the map frame if known, and
        ``max_par`` their largest angle to the first (rad)."""
        lid = self.st.next_lid
        self.st.next_lid += 1
        label = tr.major
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

    def triangulate(self, frame: Tracks, mappable: np.ndarray, kid: int,
                    recs: list[FactorRecord], values: gtsam.Values,
                    ts: dict[int, float]) -> list[int]:
        """New landmarks at keyframe ``kid``: the mappable tracks without a landmark seen in
        ``lm_min_keyframes`` window keyframes, triangulated from their rays (twice: without the
        grossly wrong rays the second time) and accepted with enough parallax, depth within
        ``lm_min_depth_m``..``lm_max_depth_m`` and at most one bad ray; at most
        ``max_new_landmarks``, spread over the image. Returns their ids."""
        c = self.setup.conf
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
            acc = acc[spread(px, tri2.max_parallax[acc], c['max_new_landmarks'],
                             self.setup.camera)]
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
            new.append(self.new_landmark(tid, self.st.tracks[tid], tri2.points[j],
                                          [obs_kid[o] for o in r.tolist()], recs, values, kid,
                                          ts, rays_a[r], float(max_par[g])))
        return new

    def add_ground_records(self, kid: int, lids: list[int], recs: list[FactorRecord]) -> None:
        """Ground factors (camera height above the local ground plane) of keyframe ``kid`` to
        the ground landmarks of ``lids`` near the vehicle that lie on one plane parallel to it
        (``ground_factor``: 'auto' only for keyframes without odometry)."""
        mode = self.setup.conf['ground_factor']
        if mode == 'never' or (mode == 'auto' and self.st.kfs[kid].odom_linked):
            return
        lids = [lid for lid in lids if self.st.lms[lid].ground and self.st.lms[lid].alive]
        if not lids:
            return
        c = self.setup.conf
        T_cw = se3_inv(self.st.kf_T_wc[kid])
        P = np.array([self.st.lms[lid].xyz for lid in lids]) @ T_cw[:3, :3].T + T_cw[:3, 3]
        height = P @ self.setup.up_c  # along base z, relative to the camera (m, ~ -camera_height)
        horiz = np.linalg.norm(P - height[:, None] * self.setup.up_c, axis=1)  # from the nadir
        near = (horiz <= c['ground_plane_radius_m']) \
            & (np.abs(height + self.setup.camera_height) < c['ground_gate_m'])
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
        for lid in order[: self.setup.conf['ground_max_per_keyframe']]:
            f = fac.ground_factor(X(kid), L(lid), self.setup.up_c, self.setup.camera_height,
                                  self.setup.ground_noise)
            rec = self.st.record(f, RecordKind.GROUND, kid, lid)
            recs.append(rec)
            self.st.lms[lid].rids.append(rec.rid)

