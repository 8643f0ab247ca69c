"""Keyframe policy: when a tracked frame becomes a keyframe.

A frame becomes a keyframe once the base moved ``kf_min_distance_m`` from the last keyframe (and
the wheels agree that it moved), and then when it moved ``kf_max_distance_m``, tracks few
inliers, shares too few mappable tracks with the last keyframe or sees them under enough
parallax (``kf_parallax_deg``, rotation compensated).
"""
from __future__ import annotations

import numpy as np

from semfeat_ros.mapping.geometry import angle_between
from semfeat_ros.mapping.state import MapperSetup, MapState
from semfeat_ros.mapping.types import Tracks


class KeyframePolicy:
    """The keyframe decision of one mapper."""

    def __init__(self, setup: MapperSetup, st: MapState) -> None:
        self.setup = setup
        self.st = st

    def is_keyframe(self, frame: Tracks, mappable: np.ndarray, T_wc: np.ndarray,
                    n_inl: int) -> bool:
        """Whether ``frame``, tracked at camera pose ``T_wc`` (m) with ``n_inl`` inliers,
        becomes a keyframe (``mappable``: its tracks allowed into the map)."""
        kid = self.st.last_kid
        T_kf = self.st.kf_T_wc[kid]
        T_cb, c = self.setup.T_cb, self.setup.conf
        dist = float(np.linalg.norm((T_wc @ T_cb)[:3, 3] - (T_kf @ T_cb)[:3, 3]))
        if dist < c['kf_min_distance_m']:
            return False
        if self.st.kf_odom.ok and self.st.kf_odom.dist < c['kf_min_distance_m']:
            return False  # the wheels say the base stood still: the estimate only jitters
        if dist > c['kf_max_distance_m'] or n_inl < 2 * c['min_tracking_inliers']:
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
        if kf is None or common < c['kf_min_tracked_fraction'] * kf.n_tracks:
            return True
        par = angle_between(np.array(b_kf), np.array(b_cur) @ R_rel.T)
        return float(np.degrees(np.median(par))) > c['kf_parallax_deg']

