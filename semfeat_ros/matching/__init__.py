"""Sequential matching: descriptor NN matching, geometric verification on bearings, tracks.

numpy + OpenCV (no rclpy; torch only for the learned matcher, imported when it is configured);
the same core runs in ``matcher_node`` and offline.
"""
from __future__ import annotations

from semfeat_ros.matching.draw import draw_matches, draw_track_result
from semfeat_ros.matching.errors import (
    FeatureInputError,
    FrameOrderError,
    MatchingConfigError,
    MatchingError,
    TrackIdOverflowError,
)
from semfeat_ros.matching.geometry import Verification, verify_bearings
from semfeat_ros.matching.nn import (
    Matches,
    compatibility_from_labels,
    match_binary,
    match_float,
    semantic_compatibility,
)
from semfeat_ros.matching.sequential import (
    FrameFeatures,
    SequentialMatcher,
    TrackResult,
    default_conf,
)
from semfeat_ros.matching.tracks import TrackManager

__all__ = [
    'FeatureInputError', 'FrameFeatures', 'FrameOrderError', 'MatchingConfigError',
    'MatchingError', 'Matches', 'SequentialMatcher', 'TrackIdOverflowError', 'TrackManager',
    'TrackResult', 'Verification', 'compatibility_from_labels', 'default_conf', 'match_binary',
    'draw_matches', 'draw_track_result', 'match_float', 'semantic_compatibility',
    'verify_bearings',
]
