"""Configuration of the mapping core: ``default_conf`` with one comment per key (LightGlue style).

``merge_conf(conf)`` returns a full, validated copy; unknown keys raise
:class:`~semfeat_ros.mapping.errors.MapperConfigError`.
"""
from __future__ import annotations

from typing import Any

from semfeat_ros import conf as common_conf
from semfeat_ros.mapping.errors import MapperConfigError

default_conf: dict[str, Any] = {
    # ---- inputs -------------------------------------------------------------------------------
    'use_odometry': True,  # use wheel-odometry deltas passed to update() (False: ignore them)
    'use_gnss': True,  # use GNSS fixes passed to update() (False: ignore them)
    'labels_path': None,  # labels.yaml path (None: the shipped config/labels.yaml)
    'camera_height_m': None,  # camera height above the ground (m); None: z of T_base_cam
    'bearing_sigma_px': 2.5,  # keypoint noise (px), turned into rad by the focal length; sized
    #                           for the network's keypoints (OpenCV detectors: about 1 px)
    'robust_kernel': 'huber',  # kernel of the bearing factors: 'huber' or 'cauchy'
    'robust_k': 1.345,  # kernel width in whitened units (sigmas)
    'outlier_chi2': 9.21,  # chi-square gate (2 dof, 99 %) on whitened bearing residuals
    'max_reprojection_px': 4.0,  # landmarks with a mean reprojection error above leave the cloud
    'min_tracking_inliers': 15,  # fewer landmark inliers in a frame: visual tracking is lost
    'seed': 0,  # seed of every RANSAC in the mapper (deterministic runs)
    # ---- keyframes ----------------------------------------------------------------------------
    'kf_parallax_deg': 4.0,  # new keyframe when the rotation-compensated median parallax to the
    #                          last keyframe exceeds this (deg) ...
    'kf_min_tracked_fraction': 0.6,  # ... or fewer of the last keyframe's tracks survive ...
    'kf_max_distance_m': 1.0,  # ... or the base moved farther than this (m, when metric) ...
    'kf_min_distance_m': 0.05,  # ... but never while the base moved less than this (m)
    # ---- two-view initialisation ------------------------------------------------------------
    'init_from_odometry': True,  # with wheel odometry: start at the first frame, keyframes
    #                              placed by odometry until landmarks exist (no two-view step)
    'init_min_tracks': 40,  # common static tracks needed between the two views
    'init_min_parallax_deg': 3.0,  # try once init_min_tracks / 2 common tracks have a bearing
    #                                angle between the views above this (deg)
    'init_ransac_px': 1.5,  # epipolar RANSAC threshold (px, through the focal length)
    'init_min_inlier_ratio': 0.6,  # minimum fraction of essential-matrix inliers
    'init_odom_max_angle_deg': 15.0,  # with odometry: a RANSAC translation farther than this
    #                                   from the odometry direction is replaced by the odometry
    #                                   motion refined on the tracks within ...
    'init_odom_gate_px': 4.0,  # ... this epipolar gate (px through the focal length)
    'init_odom_min_inlier_ratio': 0.3,  # with odometry: fraction of tracks that must be inliers
    'init_max_frames': 40,  # frames without success before the reference view is replaced
    'init_require_metric': True,  # camera-only: retry until the ground plane gives the scale
    # ---- visual rotation between keyframes --------------------------------------------------
    'vision_rotation_sigma_deg': 0.3,  # sigma of the keyframe-to-keyframe rotation from the
    #                                    5-point geometry of common tracks (deg; 0 disables);
    #                                    long drive, ORB: 0.1 -> ATE 0.53 m, 0.3 -> 0.23, 1 -> 0.34
    'vision_rotation_min_tracks': 20,  # common tracks (and inliers) needed for it
    'vision_rotation_kinematic': True,  # with metric scale: that rotation's roll and pitch
    #                                     from a refinement with the camera's translation known
    #                                     from the vehicle's motion (base along its arc, camera
    #                                     at its lever arm). A free translation trades pitch for
    #                                     a vertical tilt of it
    # ---- level floors (parking decks are level; ramps are not) ------------------------------
    'level_prior_sigma_deg': 1.0,  # keyframes whose vehicle tilt (estimate) is below
    #                                level_max_tilt_deg get a robust prior: base z-axis along
    #                                map z with this sigma (deg, per axis; 0 disables). Without
    #                                it the pitch is unobserved on a level without GNSS and the
    #                                altitude drifts (long drive: ~1 m over 70 m)
    'level_max_tilt_deg': 3.0,  # tilt above which a keyframe is taken to be on a ramp (deg):
    #                             between a deck's drainage fall (~1 deg) and a ramp (~6 deg+)
    'level_max_change_deg': 1.0,  # ... and whose neighbours are tilted by less than this against
    #                               it (deg): a ramp's start or end is not level yet
    'level_delay_keyframes': 5,  # the prior goes to the keyframe this many keyframes back, when
    #                              it and its neighbours on both sides are all estimated level
    # ---- landmarks ----------------------------------------------------------------------------
    'lm_min_keyframes': 3,  # keyframes that must see a track before it becomes a landmark
    'lm_min_parallax_deg': 2.0,  # largest angle between its rays (deg)
    'lm_min_depth_m': 0.3,  # nearest allowed distance to an observing camera (m)
    'lm_max_depth_m': 40.0,  # farthest allowed distance to an observing camera (m)
    'lm_lost_depth_m': 100.0,  # a landmark the smoother moves farther than this from its last
    #                            observer (m) has lost its depth (rays nearly parallel): it is
    #                            killed before its information vanishes and iSAM2 fails
    'dynamic_max_fraction': 0.2,  # tracks labelled dynamic more often than this never map
    'max_obs_per_keyframe': 80,  # landmark observations added per keyframe (spread over the
    #                              image, long-lived landmarks first): bounds the update cost.
    #                              The long drives' tracks never reach it (at most 38 with
    #                              the network's, 66 with ORB's); a dense scene does
    'max_new_landmarks': 50,  # landmarks created per keyframe (spread, widest parallax first)
    # ---- ground plane (camera-only metric scale and gravity) ----------------------------------
    # classes (labels.yaml names) lying on the ground plane:
    'ground_labels': ['road', 'sidewalk', 'parking_line', 'lane_divider', 'road_marking'],
    'ground_factor': 'auto',  # 'auto': keyframes without odometry link; 'always'; 'never'
    'ground_sigma_m': 0.05,  # height noise of a ground landmark about the ground plane (m)
    'ground_max_distance_m': 3.0,  # only ground landmarks this close to the camera's nadir (m,
    #                                horizontal): the local plane holds near the front wheels
    'ground_gate_m': 0.3,  # skip ground landmarks currently this far off the plane (m)
    'ground_plane_radius_m': 8.0,  # a plane is fitted to ground landmarks this close (m) ...
    'ground_plane_threshold_m': 0.05,  # ... with this RANSAC inlier distance (m) ...
    'ground_min_points': 5,  # ... and at least this many inliers ...
    'ground_max_tilt_deg': 2.0,  # ... and must be this parallel to the vehicle (deg), else
    #                              (ramp transition) the keyframe gets no ground factors
    'ground_max_per_keyframe': 10,  # at most this many ground factors per keyframe
    'init_plane_threshold_m': 0.05,  # RANSAC inlier distance of the initial ground plane (m at
    #                                  the camera height)
    # ---- odometry -----------------------------------------------------------------------------
    'odom_min_sigma': 1e-4,  # floor of every odometry standard deviation (m or rad)
    'odom_calibration': True,  # learn the odometry's yaw-rate bias, yaw scale and distance
    #                            scale errors on keyframes anchored by GNSS and correct later
    #                            odometry with them (mapping/odometry.py): under a slab,
    #                            without GNSS, the motion otherwise drifts with those errors
    'odom_calib_sigma_rad': 0.002,  # noise of one keyframe pair's heading residual (rad) ...
    'odom_calib_sigma_m': 0.01,  # ... and of its distance residual (m)
    'odom_calib_prior_bias': 0.005,  # prior sigma of the yaw-rate bias (rad/s) ...
    'odom_calib_prior_scale': 0.02,  # ... and of the yaw and distance scale errors (tyres and
    #                                  track width: a few %)
    'odom_calib_min_pairs': 30,  # anchored keyframe pairs needed before it corrects anything
    # ---- GNSS ---------------------------------------------------------------------------------
    'gnss_max_sigma_m': 0.5,  # reject fixes with any position sigma above this (m)
    'gnss_min_sigma_m': 0.02,  # floor of the fix sigma (m): never a zero covariance
    'gnss_max_age_s': 1.0,  # a fix is attached to a keyframe at most this long after it (s)
    'gnss_lever_arm_m': [0.0, 0.0, 0.0],  # antenna position in base_link (m)
    'gnss_align_min_fixes': 10,  # fixes needed before the map is aligned to ENU
    'gnss_align_min_span_m': 20.0,  # horizontal extent those fixes must cover (m): over 5 m
    #                                the yaw from fixes with ~0.1 m noise is off by degrees,
    #                                which moves the marginalised map by decimetres (tested)
    'gnss_align_max_rms_m': 1.5,  # alignment residual above which it is retried later (m)
    'gnss_gate_chi2': 16.27,  # chi-square gate (3 dof, 99.9 %) of a fix against the estimate
    'gnss_gate_sigma_m': 0.5,  # position uncertainty of the estimate used in the gate (m)
    'gnss_max_rejects': 50,  # after this many consecutive gated fixes the gate is reopened
    # ---- smoother -----------------------------------------------------------------------------
    'window_keyframes': 15,  # fixed lag (keyframes): older states are marginalised
    'marginalize_every': 10,  # old states leave the window in batches of this many keyframes
    #                           (each batch re-eliminates the whole window: rare spikes instead
    #                           of a full re-elimination at every keyframe)
    'relinearize_threshold': 0.05,  # iSAM2 relinearisation threshold (tangent units)
    'relinearize_skip': 5,  # iSAM2 relinearises every this many updates (1: every update,
    #                         about 3x slower per keyframe in the benchmark)
    'extra_iterations': 0,  # additional iSAM2 iterations after each keyframe update
    'prior_sigma_rad': 0.01,  # first pose: roll/pitch/yaw prior (rad); the start is level
    'prior_sigma_m': 0.01,  # first pose: position prior (m)
    'recovery_sigma_m': 1.0,  # weak priors added after a failed update (m) ...
    'recovery_sigma_rad': 0.1,  # ... and (rad)
    'reinit_link_sigma_m': 1.0,  # camera-only re-initialisation: link to the old segment (m)
    'reinit_link_sigma_rad': 0.1,  # ... (rad)
    # ---- map ----------------------------------------------------------------------------------
    'voxel_size_m': 0.1,  # one marginalised landmark per voxel, floor and class (m)
    'cloud_min_obs': 3,  # keyframe observations a landmark needs to be published
    'max_map_points': 2_000_000,  # cap of the marginalised map (oldest voxels dropped first)
    'cloud_min_parallax_deg': 5.0,  # published landmarks need this angle between their rays
    #                                 (deg): depth of far, barely moving points is unreliable
    # ---- floors -------------------------------------------------------------------------------
    'floor_max_slope': 0.05,  # |dz/ds| below this is a plateau (level), above a ramp
    'floor_slope_window_m': 4.0,  # travelled distance over which the slope is measured (m)
    'floor_min_plateau_m': 4.0,  # shortest plateau that makes a level (m travelled); the
    #                              flat run measured along the estimate is about 1.5 m
    #                              shorter than the deck (the slope window reaches into
    #                              the ramp's rounded start): the bundled bag's 7.3 m
    #                              upper deck measures 5.8-6.0 m
    'floor_merge_m': 1.2,  # plateaus closer in altitude than this are one level (m)
    # classes hung under the slab above the vehicle (labels.yaml names): such a landmark takes
    # the storey of the plateau keyframes that saw it, not of its altitude (a covered level's
    # ceiling seen far ahead is often estimated metres too high)
    'ceiling_labels': ['ceiling', 'light'],
    'floor_point_margin_m': 0.5,  # a landmark within this of a level's altitude (m) takes the
    #                               level of the plateau keyframes that saw it (a ceiling seen from
    #                               below is the lower storey, the deck seen from above the upper);
    #                               any other landmark belongs to the storey its altitude is in
    # ---- evaluation ---------------------------------------------------------------------------
    'keep_full_graph': False,  # keep every factor for batch_optimize() (memory grows)
}

_CHOICES = {
    'robust_kernel': ('huber', 'cauchy'),
    'ground_factor': ('auto', 'always', 'never'),
}
_POSITIVE = (
    'bearing_sigma_px', 'robust_k', 'outlier_chi2', 'max_reprojection_px', 'kf_parallax_deg',
    'kf_max_distance_m', 'init_min_parallax_deg', 'init_ransac_px', 'init_odom_gate_px',
    'init_odom_max_angle_deg', 'lm_min_depth_m', 'lm_max_depth_m', 'lm_lost_depth_m',
    'ground_sigma_m', 'ground_max_distance_m', 'init_plane_threshold_m',
    'odom_min_sigma', 'odom_calib_sigma_rad', 'odom_calib_sigma_m', 'odom_calib_prior_bias',
    'odom_calib_prior_scale', 'gnss_max_sigma_m', 'gnss_min_sigma_m', 'gnss_max_age_s',
    'gnss_align_min_span_m', 'gnss_align_max_rms_m', 'gnss_gate_chi2', 'gnss_gate_sigma_m',
    'window_keyframes', 'relinearize_threshold', 'prior_sigma_rad', 'prior_sigma_m',
    'recovery_sigma_m', 'recovery_sigma_rad', 'reinit_link_sigma_m', 'reinit_link_sigma_rad',
    'voxel_size_m', 'floor_max_slope', 'floor_slope_window_m', 'floor_min_plateau_m',
    'floor_merge_m', 'floor_point_margin_m', 'cloud_min_parallax_deg', 'level_max_tilt_deg',
    'level_max_change_deg',
)
_INT_MIN = {
    'min_tracking_inliers': 4, 'init_min_tracks': 8, 'vision_rotation_min_tracks': 8,
    'init_max_frames': 1,
    'lm_min_keyframes': 2, 'ground_max_per_keyframe': 0, 'max_obs_per_keyframe': 10,
    'max_new_landmarks': 1, 'ground_min_points': 3, 'gnss_align_min_fixes': 2,
    'gnss_max_rejects': 1, 'relinearize_skip': 1, 'marginalize_every': 1, 'extra_iterations': 0,
    'cloud_min_obs': 1, 'level_delay_keyframes': 1, 'odom_calib_min_pairs': 1,
    'max_map_points': 1, 'seed': 0,
}
_FRACTIONS = ('kf_min_tracked_fraction', 'init_min_inlier_ratio', 'init_odom_min_inlier_ratio',
              'dynamic_max_fraction')


def merge_conf(conf: dict[str, Any] | None = None) -> dict[str, Any]:
    """``default_conf`` updated with ``conf``; validated (raises ``MapperConfigError``)."""
    out = common_conf.merge_conf(default_conf, conf, MapperConfigError,
                                 what='mapping config key')
    for key, choices in _CHOICES.items():
        common_conf.check_choice(out[key], key, MapperConfigError, choices)
    for key in _POSITIVE:
        common_conf.check_number(out[key], key, MapperConfigError, 0.0, lo_open=True)
    for key, lo in _INT_MIN.items():
        common_conf.check_int_min(out[key], key, MapperConfigError, lo)
    for key in _FRACTIONS:
        common_conf.check_fraction(out[key], key, MapperConfigError)
    for key in ('vision_rotation_sigma_deg', 'level_prior_sigma_deg', 'kf_min_distance_m'):
        common_conf.check_number(out[key], key, MapperConfigError, 0.0)
    if out['camera_height_m'] is not None and not (
            isinstance(out['camera_height_m'], int | float) and out['camera_height_m'] > 0):
        raise MapperConfigError(
            f'camera_height_m must be None or > 0 (m), got {out["camera_height_m"]!r}')
    arm = out['gnss_lever_arm_m']
    if not (isinstance(arm, list | tuple) and len(arm) == 3
            and all(isinstance(a, int | float) for a in arm)):
        raise MapperConfigError(f'gnss_lever_arm_m must be 3 numbers (m), got {arm!r}')
    for key in ('ground_labels', 'ceiling_labels'):
        if not (isinstance(out[key], list | tuple) and all(isinstance(n, str) for n in out[key])):
            raise MapperConfigError(f'{key} must be a list of class names, got {out[key]!r}')
    for key in ('use_odometry', 'use_gnss', 'init_require_metric', 'keep_full_graph',
                'init_from_odometry', 'odom_calibration', 'vision_rotation_kinematic'):
        if not isinstance(out[key], bool):
            raise MapperConfigError(f'{key} must be true or false, got {out[key]!r}')
    if out['lm_max_depth_m'] <= out['lm_min_depth_m']:
        raise MapperConfigError(
            f'lm_max_depth_m ({out["lm_max_depth_m"]}) must exceed lm_min_depth_m '
            f'({out["lm_min_depth_m"]})')
    if out['lm_lost_depth_m'] < out['lm_max_depth_m']:
        raise MapperConfigError(
            f'lm_lost_depth_m ({out["lm_lost_depth_m"]}) must be at least lm_max_depth_m '
            f'({out["lm_max_depth_m"]})')
    return out
