"""Incremental mapping core: tracks (+ wheel odometry, GNSS) -> base poses and a semantic map.

Public API
----------
* ``Mapper(camera, T_base_cam, conf=None, labels=None)``: one GTSAM
  ``IncrementalFixedLagSmoother`` (iSAM2 with a fixed lag of keyframes; marginalised landmarks
  move to a voxel-bounded map). ``update(Tracks, OdometryDelta | None, GnssFix | None) ->
  MapperResult`` per frame; ``cloud() -> SemanticCloud``; ``trajectory() -> (stamps_ns,
  T_map_base)``; ``floor_levels() -> FloorLevels``; ``window()``; ``stats``;
  ``batch_optimize()`` (Levenberg-Marquardt on the full graph, with ``keep_full_graph``);
  ``odometry_calibration`` (the wheel odometry's yaw-rate bias, yaw scale and distance scale
  errors, learnt on GNSS-anchored keyframes and removed from later odometry: ``odometry``).
* Inputs: ``Tracks`` (track ids, unit bearings in the optical frame, pixels, labels),
  ``OdometryDelta`` (base motion since the previous frame, SE(3) or ``from_se2``, covariance in
  GTSAM's (rot, trans) order), ``GnssFix`` (antenna position in the map/ENU frame + 3x3
  covariance; fixes without a usable covariance are rejected).
* Files: ``write_ply`` / ``read_ply`` (x y z red green blue label floor landmark_id n_obs),
  ``write_tum`` / ``read_tum``. Evaluation: ``align_umeyama`` (Sim(3) / SE(3)), ``ate_rmse``.
* ``default_conf`` (one comment per key), ``merge_conf``; errors in ``errors``.
* ``benchmark.benchmark_update_time`` (update time vs keyframe count; not a test) and the
  synthetic two-level garage in ``synthetic`` used by the tests.

Conventions
-----------
Poses are base_link in ``map`` (z up, m); altitude is the pose z. Internally the smoother's pose
variables are the camera optical frame in ``map`` (``X(k)``), landmarks ``L(j)``; bearing factors
are ``gtsam.BearingFactor3D`` (valid on the whole sphere: fisheye points beyond 90 degrees
off-axis constrain the graph). Metric scale comes from wheel odometry, GNSS or, camera-only, from
ground-class landmarks lying ``camera_height_m`` below the camera on the local ground plane.
The map frame is the first base pose (level start), or ENU once GNSS fixes aligned it.
Only classes that are ``static`` and not ``dynamic`` in labels.yaml become landmarks; every
landmark carries a floor (level) index and landmarks of different floors never share a voxel.
The mapper's parts: ``state`` (records), ``tracking``, ``keyframes`` (policy), ``initialisation``,
``local_mapping``, ``gnss``, ``outliers``, ``backend`` (the only owner of the smoother) and
``landmark_map``. gtsam is imported only inside this package.
"""
from __future__ import annotations

from semfeat_ros.mapping.cloud import SemanticCloud
from semfeat_ros.mapping.config import default_conf, merge_conf
from semfeat_ros.mapping.errors import (
    AlignmentError,
    MapperConfigError,
    MapperInputError,
    MappingError,
    PlyFormatError,
    StampOrderError,
    TumFormatError,
)
from semfeat_ros.mapping.evaluation import Similarity, align_umeyama, ate_rmse
from semfeat_ros.mapping.floors import FloorLevels, detect_floors
from semfeat_ros.mapping.io import read_ply, read_tum, write_ply, write_tum
from semfeat_ros.mapping.mapper import Mapper
from semfeat_ros.mapping.types import GnssFix, MapperResult, OdometryDelta, Tracks

__all__ = [
    'AlignmentError', 'FloorLevels', 'GnssFix', 'Mapper', 'MapperConfigError',
    'MapperInputError', 'MapperResult', 'MappingError', 'OdometryDelta', 'PlyFormatError',
    'SemanticCloud', 'Similarity', 'StampOrderError', 'Tracks', 'TumFormatError',
    'align_umeyama', 'ate_rmse', 'default_conf', 'detect_floors', 'merge_conf', 'read_ply',
    'read_tum', 'write_ply', 'write_tum',
]
