"""Nearest-neighbour descriptor matching with a semantic consistency constraint.

Two flavours share one core:

* :func:`match_float`: L2-normalised float descriptors compared by cosine similarity
  (the learned descriptors of the network; for unit vectors ``|a - b|^2 = 2 - 2 a.b``).
* :func:`match_binary`: packed binary descriptors (uint8, ORB/BRISK/AKAZE baselines) compared
  by Hamming distance (bits).

A pair ``(i, j)`` is accepted when

1. labels ``labels0[i]`` and ``labels1[j]`` are compatible (``compatibility[l0, l1]``; skipped
   without labels); candidates are searched among compatible features only,
2. ``j`` is the nearest neighbour of ``i`` and, with ``mutual``, ``i`` is the nearest neighbour of
   ``j`` (ties resolve to the lowest index),
3. Lowe's ratio test: ``d(i, j) <= ratio * d(i, j2)`` with ``j2`` the second-nearest compatible
   neighbour of ``i`` (L2 distance for float, Hamming for binary); passes when ``i`` has a single
   compatible candidate; disabled with ``ratio=None`` or ``ratio >= 1``,
4. the absolute threshold: cosine similarity ``>= min_similarity`` (float, equivalent to
   ``L2 <= sqrt(2 - 2 min_similarity)``) or Hamming distance ``<= max_distance`` (binary).

Semantic compatibility is applied inside the similarity matrix product (the descriptors are
augmented with a one-hot label block), so it costs one slightly wider matrix product.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from semfeat_ros.matching.errors import FeatureInputError, MatchingConfigError

DEFAULT_COMPATIBLE_GROUPS: tuple[tuple[str, ...], ...] = (
    ('parking_line', 'lane_divider', 'road_marking'),
)
"""Classes that are easily confused by the segmentation head and may match each other."""

_BONUS_FLOAT = 4.0  # added to compatible cosine similarities (range [-1, 1]) by the label block


@dataclass
class Matches:
    """M accepted matches between two feature sets."""

    indices: np.ndarray
    """(M, 2) int64: ``(index in set 0, index in set 1)``."""
    scores: np.ndarray
    """(M,) float32 match confidence in [0, 1]: cosine similarity clipped at 0 (float) or
    ``1 - hamming / n_bits`` (binary)."""
    distances: np.ndarray
    """(M,) float32: L2 distance between unit descriptors (float) or Hamming distance (bits)."""

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    @staticmethod
    def empty() -> Matches:
        return Matches(np.zeros((0, 2), np.int64), np.zeros(0, np.float32),
                       np.zeros(0, np.float32))


def semantic_compatibility(num_classes: int, *, dynamic: Sequence[bool] | np.ndarray = (),
                           groups: Sequence[Sequence[int]] = (), match_dynamic: bool = False,
                           ) -> np.ndarray:
    """(C + 1, C + 1) bool matrix of compatible label pairs.

    Index ``C`` stands for every label outside ``0..C-1`` (unknown/ignore, e.g. 255): unknown
    labels match only unknown labels. Same label is compatible; each group of class ids is
    mutually compatible; classes flagged ``dynamic`` (per class, length C) match nothing unless
    ``match_dynamic``.
    """
    if num_classes < 1:
        raise MatchingConfigError(f'num_classes: expected >= 1, got {num_classes}')
    C = int(num_classes)
    compat = np.eye(C + 1, dtype=bool)
    for group in groups:
        ids = [int(g) for g in group]
        bad = [g for g in ids if not 0 <= g < C]
        if bad:
            raise MatchingConfigError(
                f'compatible group {list(group)}: class ids must be in 0..{C - 1}, got {bad}')
        compat[np.ix_(ids, ids)] = True
    dyn = np.zeros(C, dtype=bool)
    if len(dynamic):
        dyn_in = np.asarray(dynamic, dtype=bool)
        if dyn_in.shape != (C,):
            raise MatchingConfigError(
                f'dynamic: expected {C} flags (one per class), got shape {dyn_in.shape}')
        dyn = dyn_in
    if not match_dynamic and dyn.any():
        compat[:C][dyn] = False
        compat[:, :C][:, dyn] = False
    return compat


def compatibility_from_labels(label_set: Any = None,
                              groups: Sequence[Sequence[str]] = DEFAULT_COMPATIBLE_GROUPS,
                              match_dynamic: bool = False) -> np.ndarray:
    """:func:`semantic_compatibility` from a ``LabelSet`` (default: the shipped labels.yaml).

    ``groups`` are lists of class names; unknown names raise :class:`MatchingConfigError`.
    """
    if label_set is None:
        from semfeat_ros.labels import load_labels
        label_set = load_labels()
    id_groups = []
    for group in groups:
        try:
            id_groups.append([label_set.id_of(str(name)) for name in group])
        except KeyError as exc:
            raise MatchingConfigError(f'compatible group {list(group)}: {exc.args[0]}') from None
    return semantic_compatibility(len(label_set.names), dynamic=label_set.dynamic,
                                  groups=id_groups, match_dynamic=match_dynamic)


def _check_labels(labels: np.ndarray | None, n: int, name: str,
                  compatibility: np.ndarray) -> np.ndarray:
    if labels is None:
        raise FeatureInputError(f'{name}: labels are required with a compatibility matrix')
    arr = np.asarray(labels)
    if arr.shape != (n,):
        raise FeatureInputError(f'{name}: expected shape ({n},), got {arr.shape}')
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise FeatureInputError(f'{name}: expected integer class ids, got dtype {arr.dtype}')
    unknown = compatibility.shape[0] - 1
    arr = arr.astype(np.int64)
    return np.where((arr >= 0) & (arr < unknown), arr, unknown)


def _check_compat(compatibility: np.ndarray) -> np.ndarray:
    c = np.asarray(compatibility)
    if c.ndim != 2 or c.shape[0] != c.shape[1] or c.shape[0] < 2 or c.dtype != bool:
        raise MatchingConfigError(
            f'compatibility: expected a square bool matrix of size C+1 >= 2, got {c.dtype} '
            f'{c.shape}')
    return c


def _check_ratio(ratio: float | None) -> float | None:
    if ratio is None:
        return None
    if not 0.0 < float(ratio):
        raise MatchingConfigError(f'ratio: expected > 0 (or None to disable), got {ratio}')
    return None if ratio >= 1.0 else float(ratio)


_BLOCK_ROWS = 1024  # rows of the similarity matrix computed at once (bounded memory)


def _nn_core(a: np.ndarray, b: np.ndarray, valid_min: float, mutual: bool,
             gate: tuple[np.ndarray, np.ndarray, float] | None = None,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Best and second-best columns per row of the similarity ``a @ b.T`` (higher is better).

    ``gate = (pos0 (N0, 2), pos1 (N1, 2), radius)``: pairs farther apart than ``radius`` (px)
    are excluded (as if their similarity were -inf), before the mutual and ratio checks.

    The matrix is computed in blocks of rows. Returns ``(rows, cols, best, second)`` for rows
    whose best entry is ``>= valid_min`` and that pass the mutual check (``sim[i, j]`` is the
    maximum of column ``j``; among rows tied for the same column the lowest index wins).
    ``second`` is ``-inf`` where no second entry ``>= valid_min`` exists.
    """
    n0, n1 = a.shape[0], b.shape[0]
    bt = np.ascontiguousarray(b.T)
    nn01 = np.empty(n0, dtype=np.int64)
    best = np.empty(n0, dtype=a.dtype)
    second = np.full(n0, -np.inf, dtype=a.dtype)
    col_max = np.full(n1, -np.inf, dtype=a.dtype)
    for s in range(0, n0, _BLOCK_ROWS):
        sim = a[s:s + _BLOCK_ROWS] @ bt
        if gate is not None:
            p0, p1, radius = gate
            q = p0[s:s + _BLOCK_ROWS]
            dx = q[:, 0, None] - p1[None, :, 0]  # per axis: no (rows, N1, 2) temporary
            dy = q[:, 1, None] - p1[None, :, 1]
            d2 = dx * dx + dy * dy
            sim[d2 > radius * radius] = -np.inf
        r = np.arange(sim.shape[0])
        j = np.argmax(sim, axis=1)
        nn01[s:s + sim.shape[0]] = j
        best[s:s + sim.shape[0]] = sim[r, j]
        if mutual:  # a max-reduction over axis 0 is fast, an argmax over it is not
            np.maximum(col_max, sim.max(axis=0), out=col_max)
        if n1 > 1:
            sim[r, j] = -np.inf  # mask the best: the row max is now the second best
            second[s:s + sim.shape[0]] = sim.max(axis=1)
    keep = best >= valid_min
    if mutual:
        keep &= best >= col_max[nn01]
    if mutual:
        keep &= np.isfinite(best)
    rows = np.flatnonzero(keep)
    cols, best, second = nn01[keep], best[keep], second[keep]
    if mutual and rows.size:
        _, first = np.unique(cols, return_index=True)  # rows ascending: first = lowest row
        if first.size != rows.size:
            first.sort()
            rows, cols, best, second = rows[first], cols[first], best[first], second[first]
    second = np.where(second >= valid_min, second, -np.inf)
    return rows, cols, best, second


def _one_hot_blocks(l0: np.ndarray, l1: np.ndarray, compat: np.ndarray, bonus: float,
                    dtype: type) -> tuple[np.ndarray, np.ndarray]:
    """Label blocks whose product is ``bonus * compat[l0, l1]``."""
    k = compat.shape[0]
    a = (bonus * compat[l0]).astype(dtype)  # (N0, K)
    b = np.zeros((l1.size, k), dtype=dtype)
    b[np.arange(l1.size), l1] = 1.0
    return a, b


def _check_gate(positions0: np.ndarray | None, positions1: np.ndarray | None,
                max_distance_px: float | None, n0: int, n1: int
                ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Validated spatial gate for :func:`_nn_core` (None: no gate)."""
    if max_distance_px is None:
        return None
    r = float(max_distance_px)
    if not r > 0:
        raise MatchingConfigError(f'max_distance_px: expected > 0 px or None, got {r}')
    out = []
    for name, pos, n in (('positions0', positions0, n0), ('positions1', positions1, n1)):
        a = None if pos is None else np.asarray(pos, dtype=np.float32)
        if a is None or a.shape != (n, 2) or not np.isfinite(a).all():
            raise FeatureInputError(f'{name}: a spatial gate needs finite (N, 2) px positions '
                                    f'of the {n} features, got '
                                    f'{None if a is None else a.shape}')
        out.append(a)
    return out[0], out[1], r


def normalize_descriptors(desc: np.ndarray, name: str = 'descriptors') -> np.ndarray:
    """(N, D) float32 rows scaled to unit L2 norm; all-zero rows stay zero (never matched)."""
    d = np.asarray(desc)
    if d.ndim != 2:
        raise FeatureInputError(f'{name}: expected shape (N, D), got {d.shape}')
    if not np.issubdtype(d.dtype, np.floating):
        raise FeatureInputError(f'{name}: expected float descriptors, got dtype {d.dtype}')
    d = d.astype(np.float32, copy=True)
    if not np.isfinite(d).all():
        raise FeatureInputError(f'{name}: contains NaN or inf')
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    np.divide(d, norm, out=d, where=norm > 1e-12)
    d[norm[:, 0] <= 1e-12] = 0.0
    return d


def match_float(desc0: np.ndarray, desc1: np.ndarray, *, labels0: np.ndarray | None = None,
                labels1: np.ndarray | None = None, compatibility: np.ndarray | None = None,
                mutual: bool = True, ratio: float | None = 0.9, min_similarity: float = 0.5,
                positions0: np.ndarray | None = None, positions1: np.ndarray | None = None,
                max_distance_px: float | None = None) -> Matches:
    """Match float descriptors (N0, D) and (N1, D) by cosine similarity (see the module doc).

    Descriptors are L2-normalised here. ``labels*`` are (N,) class ids, used only with a
    ``compatibility`` matrix from :func:`semantic_compatibility`. With ``max_distance_px``,
    only pairs whose ``positions0`` / ``positions1`` (N, 2) px lie within that distance compete
    (a motion bound between consecutive frames: fewer ambiguous candidates).
    """
    d0 = normalize_descriptors(desc0, 'desc0')
    d1 = normalize_descriptors(desc1, 'desc1')
    if d0.shape[1] != d1.shape[1]:
        raise FeatureInputError(
            f'descriptor sizes differ: desc0 has D={d0.shape[1]}, desc1 has D={d1.shape[1]}')
    if not -1.0 <= float(min_similarity) <= 1.0:
        raise MatchingConfigError(f'min_similarity: expected in [-1, 1], got {min_similarity}')
    ratio = _check_ratio(ratio)
    if d0.shape[0] == 0 or d1.shape[0] == 0:
        return Matches.empty()
    offset = 0.0
    dim = d0.shape[1]
    if compatibility is not None:
        compat = _check_compat(compatibility)
        l0 = _check_labels(labels0, d0.shape[0], 'labels0', compat)
        l1 = _check_labels(labels1, d1.shape[0], 'labels1', compat)
        a, b = _one_hot_blocks(l0, l1, compat, _BONUS_FLOAT, np.float32)
        d0 = np.concatenate([d0, a], axis=1)
        d1 = np.concatenate([d1, b], axis=1)
        offset = _BONUS_FLOAT
    # All-zero descriptors never match: a penalty block pushes their similarities below any
    # valid value (so they neither match nor take part in the mutual check).
    zero0 = ~d0[:, :dim].any(axis=1)
    zero1 = ~d1[:, :dim].any(axis=1)
    if zero0.any() or zero1.any():
        pen0 = np.stack([np.ones(d0.shape[0]), -8.0 * zero0], axis=1).astype(np.float32)
        pen1 = np.stack([-8.0 * zero1, np.ones(d1.shape[0])], axis=1).astype(np.float32)
        d0 = np.concatenate([d0, pen0], axis=1)
        d1 = np.concatenate([d1, pen1], axis=1)
    # Incompatible pairs score <= 1 < offset - 1 <= compatible pairs (float32 slack 1e-3).
    gate = _check_gate(positions0, positions1, max_distance_px, d0.shape[0], d1.shape[0])
    rows, cols, best, second = _nn_core(d0, d1, offset - 1.0 - 1e-3, mutual, gate)
    best = best - offset
    second = np.where(np.isfinite(second), second - offset, -np.inf)
    keep = best >= float(min_similarity) - 1e-6
    if ratio is not None:
        d_best = np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0))
        d_second = np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0))  # inf where no second
        keep &= d_best <= ratio * d_second
    rows, cols, best = rows[keep], cols[keep], best[keep]
    return Matches(indices=np.stack([rows, cols], axis=1).astype(np.int64),
                   scores=np.clip(best, 0.0, 1.0).astype(np.float32),
                   distances=np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0)).astype(np.float32))


def fill_unmatched(res: Matches, n0: int, n1: int,
                   match: Callable[[np.ndarray, np.ndarray], Matches]) -> Matches:
    """``res`` (indices into sets of ``n0`` and ``n1`` features) and the matches that
    ``match(free0, free1)`` finds among the features ``res`` leaves unmatched on both sides
    (``free0`` / ``free1``: their indices; it returns indices into those arrays)."""
    free0 = np.setdiff1d(np.arange(n0), res.indices[:, 0])
    free1 = np.setdiff1d(np.arange(n1), res.indices[:, 1])
    if free0.size == 0 or free1.size == 0:
        return res
    fill = match(free0, free1)
    added = np.stack([free0[fill.indices[:, 0]], free1[fill.indices[:, 1]]], axis=1)
    return Matches(np.concatenate([res.indices, added]).astype(np.int64),
                   np.concatenate([res.scores, fill.scores]).astype(np.float32),
                   np.concatenate([res.distances, fill.distances]).astype(np.float32))


def bytes_from_floats(desc: np.ndarray) -> np.ndarray:
    """(N, B) uint8 packed binary descriptors from their float copy (each value a byte 0..255,
    as they travel in ``/semfeat/features``); raises FeatureInputError for other values."""
    a = np.asarray(desc)
    if a.ndim != 2:
        raise FeatureInputError(f'binary descriptors: expected shape (N, B), got {a.shape}')
    if a.size and not (np.isfinite(a).all() and (a == np.rint(a)).all()
                       and a.min() >= 0 and a.max() <= 255):
        raise FeatureInputError('binary descriptors: expected byte values 0..255 (ORB '
                                'descriptors as float32); are the features binary?')
    return a.astype(np.uint8)


def hamming_distances(desc0: np.ndarray, desc1: np.ndarray) -> np.ndarray:
    """(N0, N1) float32 Hamming distances (bits) between packed uint8 descriptors."""
    b0 = np.unpackbits(desc0, axis=1).astype(np.float32)
    b1 = np.unpackbits(desc1, axis=1).astype(np.float32)
    return b0.sum(1)[:, None] + b1.sum(1)[None, :] - 2.0 * (b0 @ b1.T)


def match_binary(desc0: np.ndarray, desc1: np.ndarray, *, labels0: np.ndarray | None = None,
                 labels1: np.ndarray | None = None, compatibility: np.ndarray | None = None,
                 mutual: bool = True, ratio: float | None = 0.8, max_distance: float = 64,
                 positions0: np.ndarray | None = None, positions1: np.ndarray | None = None,
                 max_distance_px: float | None = None) -> Matches:
    """Match packed binary descriptors (N0, B) and (N1, B) uint8 by Hamming distance (bits).

    Same rules as :func:`match_float` (see the module doc) with ``max_distance`` in bits.
    """
    arrs = []
    for name, d in (('desc0', desc0), ('desc1', desc1)):
        a = np.asarray(d)
        if a.ndim != 2 or a.dtype != np.uint8:
            raise FeatureInputError(f'{name}: expected (N, B) uint8, got {a.dtype} {a.shape}')
        arrs.append(a)
    d0, d1 = arrs
    if d0.shape[1] != d1.shape[1]:
        raise FeatureInputError(
            f'descriptor sizes differ: desc0 has {d0.shape[1]} bytes, desc1 {d1.shape[1]}')
    ratio = _check_ratio(ratio)
    n_bits = 8 * d0.shape[1]
    if not 0 <= float(max_distance):
        raise MatchingConfigError(f'max_distance: expected >= 0 bits, got {max_distance}')
    if d0.shape[0] == 0 or d1.shape[0] == 0:
        return Matches.empty()
    # Similarity n_bits - hamming in [0, n_bits] (+ offset when compatible) as one product:
    # [2 b0, n_bits - |b0|, 1, offset compat[l0]] . [b1, 1, -|b1|, onehot(l1)] (exact in float32).
    b0 = np.unpackbits(d0, axis=1).astype(np.float32)
    b1 = np.unpackbits(d1, axis=1).astype(np.float32)
    cols0 = [2.0 * b0, (n_bits - b0.sum(1))[:, None], np.ones((b0.shape[0], 1), np.float32)]
    cols1 = [b1, np.ones((b1.shape[0], 1), np.float32), -b1.sum(1)[:, None]]
    offset = 0.0
    if compatibility is not None:
        compat = _check_compat(compatibility)
        l0 = _check_labels(labels0, d0.shape[0], 'labels0', compat)
        l1 = _check_labels(labels1, d1.shape[0], 'labels1', compat)
        offset = float(n_bits + 1)
        a, b = _one_hot_blocks(l0, l1, compat, offset, np.float32)
        cols0.append(a)
        cols1.append(b)
    gate = _check_gate(positions0, positions1, max_distance_px, d0.shape[0], d1.shape[0])
    rows, cols, best, second = _nn_core(np.concatenate(cols0, axis=1),
                                        np.concatenate(cols1, axis=1), offset - 0.5, mutual,
                                        gate)
    dist = n_bits - (best - offset)
    dist2 = np.where(np.isfinite(second), n_bits - (second - offset), np.inf)
    keep = dist <= float(max_distance) + 1e-3
    if ratio is not None:
        keep &= dist <= ratio * dist2
    rows, cols, dist = rows[keep], cols[keep], dist[keep]
    return Matches(indices=np.stack([rows, cols], axis=1).astype(np.int64),
                   scores=(1.0 - dist / n_bits).astype(np.float32),
                   distances=dist.astype(np.float32))
