"""Evaluation harness of feature matching (``semfeat-eval``); metrics in docs/METRICS.md.

Stages (hloc-like, each a module with a typed ``main(conf, paths)``):
:mod:`.run_transforms` (the paper's synthetic transforms), :mod:`.run_homography` (Oxford /
HPatches), :mod:`.run_sequence` (rendered drives). The shared loop is :func:`.pipeline.evaluate`;
methods are pluggable through :func:`.methods.register_method`.
"""
from __future__ import annotations

from semfeat_ros.evaluation.errors import (
    ConfigError,
    DatasetError,
    EvalError,
    HomographyFileError,
    ImageReadError,
    MethodUnavailableError,
    TopicError,
)
from semfeat_ros.evaluation.groundtruth import (
    DepthGroundTruth,
    GroundTruth,
    HomographyGroundTruth,
    Pair,
)
from semfeat_ros.evaluation.methods import (
    Features,
    MatchResult,
    Method,
    MethodConf,
    build_method,
    method_names,
    register_method,
)
from semfeat_ros.evaluation.metrics import pair_metrics, summarize
from semfeat_ros.evaluation.pipeline import DEFAULT_METHODS, EvalConf, evaluate
from semfeat_ros.evaluation.transforms import TransformConf, sample_transform

__all__ = [
    'DEFAULT_METHODS', 'ConfigError', 'DatasetError', 'DepthGroundTruth', 'EvalConf', 'EvalError',
    'Features', 'GroundTruth', 'HomographyFileError', 'HomographyGroundTruth', 'ImageReadError',
    'MatchResult', 'Method', 'MethodConf', 'MethodUnavailableError', 'Pair', 'TopicError',
    'TransformConf', 'build_method', 'evaluate', 'method_names', 'pair_metrics',
    'register_method', 'sample_transform', 'summarize',
]
