"""Exceptions of the camera models."""
from __future__ import annotations


class CameraModelError(ValueError):
    """Inconsistent or unusable camera parameters (size, intrinsics, distortion)."""


class OutsideImageCircleError(ValueError):
    """A pixel has no valid bearing: it lies outside the lens's image circle or valid region."""
