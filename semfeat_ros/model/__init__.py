"""The multi-task network (keypoints, descriptors, segmentation): model, losses, training data,
training loop and the inference API :class:`FeatureExtractor`. torch is imported only here."""
from __future__ import annotations

from semfeat_ros.model.errors import (
    DatasetError,
    ModelConfigError,
    ModelInputError,
    WeightsFormatError,
    WeightsNotFoundError,
)
from semfeat_ros.model.extractor import FeatureExtractor, Features, load_model_yaml
from semfeat_ros.model.semfeatnet import CrossTaskMixer, SemFeatNet
from semfeat_ros.model.weights_io import load_weights, save_weights

__all__ = [
    'CrossTaskMixer', 'DatasetError', 'FeatureExtractor', 'Features', 'ModelConfigError',
    'ModelInputError', 'SemFeatNet', 'WeightsFormatError', 'WeightsNotFoundError',
    'load_model_yaml', 'load_weights', 'save_weights',
]
