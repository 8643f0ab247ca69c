"""Incremental semantic mapper: tracks (+ wheel odometry, GNSS) -> poses and a labelled map.

:class:`Mapper` runs the per-frame loop over its parts, each a module of this package:

* :mod:`~semfeat_ros.mapping.state`: the records (tracks, landmarks, keyframes, factor records
  of one :class:`~semfeat_ros.mapping.state.RecordKind`) and the state the parts share;
* :mod:`~semfeat_ros.mapping.tracking`: label votes, pose prediction, tracking, loss;
* :mod:`~semfeat_ros.mapping.keyframes`: the keyframe policy;
* :mod:`~semfeat_ros.mapping.initialisation`: the start of a map segment (from odometry, two
  views; scale from the ground plane);
* :mod:`~semfeat_ros.mapping.local_mapping`: a keyframe's factors (bearings, triangulation,
  odometry, ground, level and rotation factors);
* :mod:`~semfeat_ros.mapping.gnss`: fix gating, GNSS factors, alignment to ENU, odometry
  calibration;
* :mod:`~semfeat_ros.mapping.outliers`: checks of the landmarks after each update;
* :mod:`~semfeat_ros.mapping.backend`: the GTSAM fixed-lag smoother (iSAM2 with states older
  than ``window_keyframes`` marginalised), fed like GTSAM's VisualISAM2Example: per keyframe the
  new factors and values, keys from ``gtsam.symbol_shorthand`` (``X`` camera poses, ``L``
  landmarks);
* :mod:`~semfeat_ros.mapping.landmark_map`: marginalised landmarks in a voxel-bounded map, so
  per-keyframe cost and smoother memory stay flat on a long drive; the published cloud.

Frames: poses returned are base_link in ``map`` (z up, m); internally the pose variables are the
camera optical frame in ``map`` so that bearings need no extrinsic inside the factors. The map
frame is set when the map starts and never moves: GNSS, once aligned, enters through
:attr:`Mapper.map_in_enu` (ENU is the map frame's parent), so consecutive estimates have no step
where GNSS arrives.
"""
from __future__ import annotations

from collections.abc import Callable
import time
from typing import Any

import gtsam
from gtsam.symbol_shorthand import X
import numpy as np

from semfeat_ros.camera import CameraModel
from semfeat_ros.labels import LabelSet
from semfeat_ros.mapping.backend import Backend, Smoother
from semfeat_ros.mapping.cloud import SemanticCloud
from semfeat_ros.mapping.errors import MapperConfigError, StampOrderError
from semfeat_ros.mapping.floors import FloorLevels
from semfeat_ros.mapping.geometry import transform_covariance, yaw_of
from semfeat_ros.mapping.gnss import GnssAlignment
from semfeat_ros.mapping.initialisation import Initializer
from semfeat_ros.mapping.keyframes import KeyframePolicy
from semfeat_ros.mapping.landmark_map import LandmarkMap
from semfeat_ros.mapping.local_mapping import LocalMapping
from semfeat_ros.mapping.outliers import OutlierHandler
from semfeat_ros.mapping.state import FactorRecord, MapperSetup, MapState, OdomChain
from semfeat_ros.mapping.tracking import Tracker
from semfeat_ros.mapping.types import GnssFix, MapperResult, OdometryDelta, Tracks

STILL_M = 1e-3  # an odometry delta shorter than this (m) is a stop


class Mapper:
    """Incremental fixed-lag factor-graph mapper.

    ``camera`` is the model the bearings came through (used for its focal length and for
    reprojection errors in px); ``T_base_cam`` (4, 4) the base_link -> camera optical frame
    extrinsic (m); ``conf`` overrides :data:`semfeat_ros.mapping.config.default_conf`.
    ``wrap_smoother`` (optional) wraps every smoother the backend makes (instrumentation, fault
    injection).
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
        setup = self.setup
        self.st = st = MapState(setup)
        self._last_stamp: int | None = None
        self.landmark_map = LandmarkMap(setup, st)
        self.backend = Backend(setup, st, self.landmark_map.insert, self._lose_tracking,
                               self._wrap_smoother)
        self.outliers = OutlierHandler(setup, st, self.backend)
        self.gnss = GnssAlignment(setup, st, self.backend, self.landmark_map)
        self.local_mapping = LocalMapping(setup, st)
        self.tracker = Tracker(setup, st)
        self.keyframes = KeyframePolicy(setup, st)
        self.initializer = Initializer(setup, st, self.local_mapping, self.gnss, self._commit)

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
    def gnss_aligned(self) -> bool:
        """True once the map frame's pose in the GNSS (ENU) frame is known."""
        return self.st.gnss_aligned

    @property
    def map_in_enu(self) -> np.ndarray | None:
        """(4, 4) pose of the map frame in ENU (m; rotation about z), None until aligned."""
        return self.gnss.map_in_enu

    def update(self, tracks: Tracks, odometry: OdometryDelta | None = None,
               gnss: GnssFix | None = None) -> MapperResult:
        """Process one frame; returns the base pose estimate and what happened.

        ``odometry`` is the base motion since the previous frame given to ``update`` (ignored
        unless ``use_odometry``); ``gnss`` a fix near this frame (ignored unless ``use_gnss``).
        Invalid inputs raise :class:`MapperInputError`; solver failures are recovered.
        """
        t0 = time.perf_counter()
        events: list[str] = []
        frame, odometry = self._next_frame(tracks, odometry)
        mappable = self.tracker.vote(frame)  # the tracks allowed into the map
        fix = None
        if self.conf['use_gnss'] and gnss is not None:
            fix = self.gnss.check_fix(gnss, self.tracker.predict(frame.stamp_ns, odometry),
                                      events)
        keyframe, cov_c, n_inl = False, None, 0
        if self.initializer.can_start_from_odometry(odometry):
            T_wc, keyframe = self.initializer.start_from_odometry(frame, mappable, fix, events)
        elif self.st.state in ('initializing', 'lost'):
            T_wc, keyframe = self.initializer.two_view(frame, mappable, fix, events)
            if T_wc is None and self.st.state == 'lost':
                T_wc = self.tracker.predict(frame.stamp_ns, odometry)
            elif keyframe:  # just initialised: the smoother's marginal of the new pose
                cov_c = self.backend.marginal_covariance(X(self.st.last_kid))
        else:
            pose = self.tracker.track(frame, mappable, odometry, events)
            T_wc, cov_c, n_inl = pose.T_wc, pose.covariance, pose.n_inliers
            if pose.observations is None:
                self._lose_tracking(frame.stamp_ns, T_wc, events)
            elif self.keyframes.is_keyframe(frame, mappable, T_wc, n_inl):
                self._add_keyframe(frame, mappable, T_wc, pose.observations, fix, events)
                T_wc, keyframe = self.tracker.follow_keyframe(frame.stamp_ns), True
        self.tracker.prune(frame)
        T_wb = None if T_wc is None else T_wc @ self.T_cb
        if fix is not None and not keyframe:
            self.gnss.hold(fix, T_wb)
        if keyframe:
            events.append('keyframe')
        cov_b = None if cov_c is None else transform_covariance(cov_c, self.T_cb)
        return MapperResult(
            frame.stamp_ns, T_wb, cov_b, self.st.state, keyframe, self.st.metric, len(frame),
            int(n_inl), len(self.st.lms) + len(self.landmark_map),
            (time.perf_counter() - t0) * 1e3, tuple(events))

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe trajectory: ``(stamps_ns (K,) int64, T_map_base (K, 4, 4))`` (m)."""
        return self.st.trajectory()

    def floor_levels(self) -> FloorLevels:
        """Levels detected from the keyframe altitude profile (recomputed when stale)."""
        return self.landmark_map.floor_levels()

    def cloud(self) -> SemanticCloud:
        """The map: marginalised (voxel-bounded) landmarks plus the current window's landmarks
        (:meth:`LandmarkMap.cloud <semfeat_ros.mapping.landmark_map.LandmarkMap.cloud>`)."""
        self._settle()
        return self.landmark_map.cloud(self.backend.estimate)

    def landmark_anchors(self, landmark_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the map's landmarks ``landmark_ids`` (N,) were triangulated: the keyframe
        stamp (N,) ns and the pixel (N, 2) px of that observation (stamp -1: not in the map)."""
        return self.landmark_map.anchors(landmark_ids)

    @property
    def odometry_calibration(self) -> dict[str, float | int]:
        """The learnt odometry errors: ``yaw_bias_rad_s``, ``yaw_scale``, ``distance_scale``
        (all 0 until enough GNSS-anchored keyframe pairs) and ``pairs`` used so far."""
        return self.gnss.calibration_summary()

    def window(self) -> dict[str, int]:
        """Size of the smoother's window: keyframes, landmarks, factors; and the voxel map."""
        return dict(keyframes=len(self.st.kfs), landmarks=len(self.st.lms),
                    factors=len(self.backend.records),
                    map_points=len(self.landmark_map))

    def _next_frame(self, tracks: Tracks, odometry: OdometryDelta | None
                    ) -> tuple[Tracks, OdometryDelta | None]:
        """Validate the frame (stamps strictly increasing) and its odometry, run the last
        keyframe's deferred work (:meth:`_settle`), correct the odometry by the learnt
        calibration and compose it into the keyframe and reference chains."""
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
            raw = (yaw_of(odometry.T[:3, :3]), dist, dt if dist >= STILL_M else 0.0)
            if self.gnss.calibration is not None:
                odometry = self.gnss.calibration.correct(odometry, raw[2])
        if self.conf['use_odometry']:
            for chain in (self.st.kf_odom, self.st.ref_odom):
                if odometry is None:
                    chain.ok = False
                else:
                    chain.add(odometry, raw)
        return frame, odometry

    def _lose_tracking(self, stamp_ns: int, pred: np.ndarray | None, events: list[str]) -> None:
        """Tracking is lost at ``stamp_ns`` (camera pose ``pred`` predicted): the next frames
        re-initialise."""
        self.tracker.lose(stamp_ns, pred, events)
        self.initializer.restart()

    def _add_keyframe(self, frame: Tracks, mappable: np.ndarray, T_wc: np.ndarray,
                      lm_obs: list[tuple[int, int]], fix: GnssFix | None,
                      events: list[str]) -> None:
        """A keyframe at camera pose ``T_wc`` (m) observing the landmarks of ``lm_obs`` (track
        id, row of ``frame``): its factors (local mapping, GNSS), then the smoother update."""
        prev = self.st.last_kid
        kid = self.st.new_keyframe(frame.stamp_ns, T_wc, int(mappable.sum()))
        recs: list[FactorRecord] = []
        values = gtsam.Values()
        values.insert(X(kid), gtsam.Pose3(T_wc))
        ts = {X(kid): self.setup.smoother_ts(kid)}
        ch = self.st.kf_odom
        if ch.ok and prev in self.st.kfs:
            self.gnss.note_odometry(kid, (ch.raw_yaw, ch.raw_dist, ch.dt))
        lids = self.local_mapping.keyframe_factors(frame, mappable, prev, kid, lm_obs, recs,
                                                   values, ts)
        self.st.kf_odom = OdomChain(self.conf['use_odometry'])
        self.gnss.attach(kid, fix, recs)
        self._commit(recs, values, ts, lids, kid, events)

    def _commit(self, recs: list[FactorRecord], values: gtsam.Values, ts: dict[int, float],
                lids: list[int], kid: int, events: list[str]) -> None:
        """Send keyframe ``kid``'s factors to the backend; then learn from the keyframes it
        marginalised, schedule the checks of the landmarks ``lids`` it observed and try the
        GNSS alignment."""
        self.backend.commit(recs, values, ts, kid, events)
        for k in self.backend.sync(kid, lids):
            self.gnss.learn_odometry(k)
        self.outliers.schedule(lids)  # one commit per frame; the frame's _settle ran before
        if self.conf['use_gnss'] and not self.st.gnss_aligned and self.gnss.waiting:
            self.gnss.try_align(events)

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

    def _settle(self) -> None:
        """The work the last keyframe left for the next frame: the chi-square and depth checks
        of its landmarks and the verification of its rotation to the keyframe before (its
        factor joins the next keyframe's update). Their results are first needed by the next
        frame's tracking, so a keyframe's own update returns without them. Also run before the
        map is read."""
        self.outliers.run_due()
        if self.local_mapping.rotation_pending:
            self.local_mapping.run_rotation_job(self.backend.queue)

