"""The multi-task network (keypoints, descriptors, segmentation): model, losses, training data,
training loop and the inference API :class:`FeatureExtractor`. torch is imported only here.

OpenMP threads wait passively unless ``OMP_WAIT_POLICY`` is set: the nodes share the CPU with
each other, and spinning OpenMP workers made the network 3-15x slower beside another busy
process on 2 cores (70 ms instead of 188 ms per 640x512 forward, measured).
"""
from __future__ import annotations

import os

os.environ.setdefault('OMP_WAIT_POLICY', 'PASSIVE')  # before torch loads its OpenMP runtime

from semfeat_ros.model.errors import (  # noqa: E402
    DatasetError,
    ModelConfigError,
    ModelInputError,
    WeightsFormatError,
    WeightsNotFoundError,
)
from semfeat_ros.model.extractor import FeatureExtractor, Features, load_model_yaml  # noqa: E402
from semfeat_ros.model.semfeatnet import CrossTaskMixer, SemFeatNet  # noqa: E402
from semfeat_ros.model.weights_io import load_weights, save_weights  # noqa: E402

__all__ = [
    'CrossTaskMixer', 'DatasetError', 'FeatureExtractor', 'Features', 'ModelConfigError',
    'ModelInputError', 'SemFeatNet', 'WeightsFormatError', 'WeightsNotFoundError',
    'load_model_yaml', 'load_weights', 'save_weights',
]
