"""Floor decals: painted lines, arrows, lettering (with their own class labels) and stains.

Decals live in the plane coordinates ``(x, y)`` (m) of a *decal group* (a floor surface: the
covered floor, the deck, the ramp, the streets). A uniform grid of 1 m cells lists the decals that
may cover each cell, so evaluating the decals of a pixel costs a few lookups.

Decal kinds (local frame: ``a`` along the decal's direction, ``c`` across it, to its right):

* ``RECT``: ``|a| <= hl`` and ``|c| <= hw`` (lines, dashes, stop bars, zebra stripes).
* ``ARROW``: a shaft of half width ``0.3 hw`` for ``a`` in ``[-hl, 0.25 hl]`` and a triangular
  head up to ``a = hl`` (pointing along ``+a``).
* ``TEXT``: lettering read by a driver moving along ``+a`` (bitmap font).
* ``STAIN``: soft darkening (oil, tyre marks); it keeps the floor's class.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semfeat_ros.sim.errors import SimConfigError
from semfeat_ros.sim.textures import encode_text, glyph_mask

RECT, ARROW, TEXT, STAIN = 0, 1, 2, 3
TEXT_LEN = 6
CELL = 1.0  # m
SLOTS = 8


@dataclass
class DecalSet:
    """Decals of one group plus their cell index."""

    kind: np.ndarray  # (D,) int8
    center: np.ndarray  # (D, 2) m
    cs: np.ndarray  # (D, 2) cos, sin of the direction
    half: np.ndarray  # (D, 2) hl, hw (m)
    cls: np.ndarray  # (D,) int16, -1 for stains
    color: np.ndarray  # (D, 3) float32 paint albedo (stains: darkening factor in [0])
    wear: np.ndarray  # (D,) float32 in [0, 1]
    inst: np.ndarray  # (D,) int32
    text: np.ndarray  # (D, TEXT_LEN) int16 font codes
    n_chars: np.ndarray  # (D,) int16
    origin: np.ndarray  # (2,) grid origin (m)
    table: np.ndarray  # (ny, nx, SLOTS) int32 decal ids, -1 empty

    def __len__(self) -> int:
        return len(self.kind)


@dataclass
class DecalBuilder:
    """Collects decals of one group."""

    rows: list[tuple] = field(default_factory=list)

    def add(self, kind: int, center: tuple[float, float], direction: float, hl: float, hw: float,
            cls: int, color=(0.9, 0.9, 0.9), *, inst: int = 0, wear: float = 0.2,
            text: str = '') -> None:
        """Add a decal; ``direction`` (rad) is the heading of its ``+a`` axis in the plane."""
        codes = encode_text(text, TEXT_LEN) if text else np.zeros(TEXT_LEN, np.int16)
        self.rows.append((kind, center, (np.cos(direction), np.sin(direction)), (hl, hw), cls,
                          color, wear, inst, codes, len(text)))

    def finish(self) -> DecalSet:
        rows = self.rows
        d = len(rows)
        center = np.array([r[1] for r in rows], np.float64).reshape(d, 2)
        cs = np.array([r[2] for r in rows], np.float64).reshape(d, 2)
        half = np.array([r[3] for r in rows], np.float64).reshape(d, 2)
        # Conservative axis-aligned extents of each decal.
        ext = np.abs(cs[:, :1]) * half[:, :1] + np.abs(cs[:, 1:]) * half[:, 1:]
        ext_y = np.abs(cs[:, 1:]) * half[:, :1] + np.abs(cs[:, :1]) * half[:, 1:]
        lo = center - np.concatenate([ext, ext_y], axis=1)
        hi = center + np.concatenate([ext, ext_y], axis=1)
        if d:
            origin = np.floor(lo.min(axis=0)) - CELL
            top = np.ceil(hi.max(axis=0)) + CELL
        else:
            origin, top = np.zeros(2), np.full(2, CELL)
        nx, ny = (int(v) for v in np.ceil((top - origin) / CELL))
        table = np.full((ny, nx, SLOTS), -1, np.int32)
        fill = np.zeros((ny, nx), np.int32)
        for i in range(d):
            i0, j0 = (int(v) for v in np.floor((lo[i] - origin) / CELL))
            i1, j1 = (int(v) for v in np.floor((hi[i] - origin) / CELL))
            for j in range(j0, j1 + 1):
                for k in range(i0, i1 + 1):
                    if fill[j, k] >= SLOTS:
                        raise SimConfigError(
                            f'more than {SLOTS} decals overlap the cell at '
                            f'({origin[0] + k * CELL:.0f}, {origin[1] + j * CELL:.0f}) m')
                    table[j, k, fill[j, k]] = i
                    fill[j, k] += 1
        return DecalSet(
            kind=np.array([r[0] for r in rows], np.int8), center=center, cs=cs, half=half,
            cls=np.array([r[4] for r in rows], np.int16),
            color=np.array([r[5] for r in rows], np.float32).reshape(d, 3),
            wear=np.array([r[6] for r in rows], np.float32),
            inst=np.array([r[7] for r in rows], np.int32),
            text=np.array([r[8] for r in rows], np.int16).reshape(d, TEXT_LEN),
            n_chars=np.array([r[9] for r in rows], np.int16), origin=origin, table=table)


@dataclass
class DecalHits:
    """Result of :func:`evaluate` for N points."""

    cls: np.ndarray  # (N,) int16, -1: no paint
    color: np.ndarray  # (N, 3) float32 paint albedo where cls >= 0
    wear: np.ndarray  # (N,) float32
    inst: np.ndarray  # (N,) int32
    stain: np.ndarray  # (N,) float32 darkening in [0, 1]
    local: np.ndarray  # (N, 2) float32 decal-local (a, c) of the paint hit (m)


def evaluate(decals: DecalSet, x: np.ndarray, y: np.ndarray) -> DecalHits:
    """Paint and stains of a decal group at plane points ``x, y`` (m)."""
    n = len(x)
    out = DecalHits(cls=np.full(n, -1, np.int16), color=np.zeros((n, 3), np.float32),
                    wear=np.zeros(n, np.float32), inst=np.zeros(n, np.int32),
                    stain=np.zeros(n, np.float32), local=np.zeros((n, 2), np.float32))
    if len(decals) == 0 or n == 0:
        return out
    ny, nx, _ = decals.table.shape
    ci = np.floor((x - decals.origin[0]) * (1.0 / CELL)).astype(np.int64)
    cj = np.floor((y - decals.origin[1]) * (1.0 / CELL)).astype(np.int64)
    inside = (ci >= 0) & (ci < nx) & (cj >= 0) & (cj < ny)
    idx_pts = np.flatnonzero(inside)
    if len(idx_pts) == 0:
        return out
    ids_all = decals.table[cj[idx_pts], ci[idx_pts]]  # (M, SLOTS)
    for slot in range(SLOTS):
        ids = ids_all[:, slot]
        sel = ids >= 0
        if not sel.any():
            break
        pts = idx_pts[sel]
        d = ids[sel]
        dx = x[pts] - decals.center[d, 0]
        dy = y[pts] - decals.center[d, 1]
        c, s = decals.cs[d, 0], decals.cs[d, 1]
        a = dx * c + dy * s
        r = dx * s - dy * c  # to the right of the direction
        hl, hw = decals.half[d, 0], decals.half[d, 1]
        kind = decals.kind[d]
        inside_box = (np.abs(a) <= hl) & (np.abs(r) <= hw)
        hit = inside_box & (kind == RECT)
        arrow = inside_box & (kind == ARROW)
        if arrow.any():
            split = 0.25 * hl
            shaft = (a <= split) & (np.abs(r) <= 0.3 * hw)
            head = (a > split) & (np.abs(r) <= hw * (hl - a) / np.maximum(hl - split, 1e-9))
            hit |= arrow & (shaft | head)
        text = inside_box & (kind == TEXT)
        if text.any():
            ti = np.flatnonzero(text)
            su = (r[ti] + hw[ti]) / (2 * hw[ti])
            tu = (hl[ti] - a[ti]) / (2 * hl[ti])
            ink = glyph_mask(decals.text[d[ti]], decals.n_chars[d[ti]], su, tu, margin=0.02)
            hit[ti[ink]] = True
        stain = inside_box & (kind == STAIN)
        if stain.any():
            si = np.flatnonzero(stain)
            q = (a[si] / hl[si]) ** 2 + (r[si] / hw[si]) ** 2
            dark = np.clip(1.0 - q, 0.0, 1.0) ** 0.7 * decals.wear[d[si]]
            out.stain[pts[si]] = np.maximum(out.stain[pts[si]], dark)
        if hit.any():
            hi_ = np.flatnonzero(hit)
            p = pts[hi_]
            dd = d[hi_]
            out.cls[p] = decals.cls[dd]
            out.color[p] = decals.color[dd]
            out.wear[p] = decals.wear[dd]
            out.inst[p] = decals.inst[dd]
            out.local[p, 0] = a[hi_]
            out.local[p, 1] = r[hi_]
    return out
