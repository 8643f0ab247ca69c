"""The mapper's landmark map: the window's landmarks and the marginalised, voxel-bounded map.

Landmarks leaving the smoother's window move into a :class:`~semfeat_ros.mapping.cloud.VoxelMap`
(one point per voxel, class and level; bounded by ``max_map_points``). The published cloud is
that map plus the window's publishable landmarks; every point carries the level (floor) of the
storey it belongs to, from the levels detected on the keyframe altitude profile.
"""
from __future__ import annotations

import gtsam
from gtsam.symbol_shorthand import L
import numpy as np

from semfeat_ros.mapping.cloud import SemanticCloud, VoxelMap
from semfeat_ros.mapping.floors import FloorLevels, detect_floors, storey_altitude
from semfeat_ros.mapping.state import Landmark, MapperSetup, MapState


class LandmarkMap:
    """Marginalised landmarks (voxel map), the published cloud and the floor levels."""

    def __init__(self, setup: MapperSetup, st: MapState) -> None:
        self.setup = setup
        self.st = st
        c = setup.conf
        self._voxels = VoxelMap(c['voxel_size_m'], c['max_map_points'])
        self._floors: FloorLevels | None = None
        self._floors_at = -1  # keyframe count the levels were detected at

    def floor_levels(self) -> FloorLevels:
        """Levels detected from the keyframe altitude profile (recomputed when stale)."""
        k = len(self.st.kf_T_wc)
        if self._floors is None or self._floors_at != k:
            _, poses = self.st.trajectory()
            c = self.setup.conf
            self._floors = detect_floors(
                poses[:, :3, 3] if k else np.zeros((0, 3)), max_slope=c['floor_max_slope'],
                slope_window_m=c['floor_slope_window_m'], min_plateau_m=c['floor_min_plateau_m'],
                merge_m=c['floor_merge_m'])
            self._floors_at = k
        return self._floors

    def insert(self, lm: Landmark, xyz: np.ndarray) -> None:
        """Keep landmark ``lm``, leaving the window at ``xyz`` (m), in the voxel map when it is
        publishable (:meth:`publishable`)."""
        if self.publishable(lm):
            levels = self.floor_levels()
            seen = self.seen_altitude(lm, levels)
            self._voxels.insert(np.asarray(xyz), lm.label, lm.lid, lm.n_obs, seen, int(
                levels.assign(np.array(self.storey(float(xyz[2]), seen, levels, lm.label)))),
                lm.anchor)

    def transform(self, s: float, R: np.ndarray, t: np.ndarray) -> None:
        """Move the marginalised map by ``x -> s R x + t`` (the trajectory already moved);
        every point's level is assigned again from the moved trajectory's levels."""
        self._floors = None
        levels = self.floor_levels()
        self._voxels.transform(s, R, t, lambda p, a, lab: int(levels.assign(
            np.array(self.storey(float(p[2]), a, levels, lab)))))

    def __len__(self) -> int:
        """Points of the marginalised (voxel) map."""
        return len(self._voxels)

    def cloud(self, estimate: gtsam.Values) -> SemanticCloud:
        """The map: marginalised (voxel-bounded) landmarks plus the current window's landmarks.

        Only static classes, landmarks with ``cloud_min_obs`` observations and a mean
        reprojection error within ``max_reprojection_px``; floors from :meth:`floor_levels`.
        The window's landmarks are where ``estimate`` puts them.
        """
        levels = self.floor_levels()
        xyz_f, lab_f, lid_f, nobs_f, alt_f = self._voxels.arrays()
        rows = []
        for lm in self.st.lms.values():
            if self.publishable(lm):
                key = L(lm.lid)
                xyz = estimate.atPoint3(key) if estimate.exists(key) else lm.xyz
                rows.append((xyz, lm.label, lm.lid, lm.n_obs, self.seen_altitude(lm, levels)))
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
                              self.setup.conf['floor_point_margin_m'], self.setup.hangs[lab])[keep]
        return SemanticCloud.build(
            xyz[keep], lab[keep], levels.assign(alt),
            np.concatenate([lid_f, lid_w])[keep], np.concatenate([nobs_f, nobs_w])[keep],
            self.setup.labels.colors)

    def anchors(self, landmark_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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

    def publishable(self, lm: Landmark) -> bool:
        """Alive, static, observed often enough, consistent and well triangulated."""
        c = self.setup.conf
        return (lm.alive and lm.n_obs >= c['cloud_min_obs'] and self.setup.static[lm.label]
                and lm.reproj_px <= c['max_reprojection_px']
                and lm.max_par >= np.radians(c['cloud_min_parallax_deg']))

    def seen_altitude(self, lm: Landmark, levels: FloorLevels) -> float:
        """Highest altitude (m) of a plateau keyframe that observed ``lm`` (NaN: none)."""
        seen = [self.st.kf_alt[k] for k in lm.kf_ids if k < len(levels.flat) and levels.flat[k]]
        return float(max(seen)) if seen else float('nan')

    def storey(self, z: float, seen: float, levels: FloorLevels, label: int) -> float:
        """Altitude (m) of the level of a point of class ``label`` at altitude ``z`` (m) whose
        highest plateau observer stood at ``seen`` (m; NaN: none): :func:`storey_altitude` (the
        street seen over a roof deck's railing is the ground storey's; the observers decide
        within ``floor_point_margin_m`` of a level's slab, and always for ``ceiling_labels``)."""
        return float(storey_altitude(np.array([z]), np.array([seen]), levels.altitudes,
                                     self.setup.conf['floor_point_margin_m'],
                                     self.setup.hangs[[label]])[0])

    def level_altitude(self, lm: Landmark, xyz: np.ndarray, levels: FloorLevels) -> float:
        """Altitude (m) of the level of landmark ``lm`` at ``xyz`` (:meth:`storey`)."""
        return self.storey(float(xyz[2]), self.seen_altitude(lm, levels), levels, lm.label)

