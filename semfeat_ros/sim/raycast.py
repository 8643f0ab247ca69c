"""Exact vectorised ray casting of the scene primitives with hierarchical cone culling.

All rays of a frame share the camera centre ``o``; primitives are moved into camera-centred
coordinates (float32) so the slab / quadric tests are cheap.

Rays are stored in *slot* order: the image is cut into 4x4-pixel subtiles, each subtile's valid
pixels occupy 16 consecutive slots (padded by repeating a pixel). Subtiles are grouped into
16x16-pixel tiles and those into 64x64-pixel blocks; every (sub)tile has a cone (axis, half
angle) containing all of its rays. Culling walks the hierarchy with a conservative
cone-vs-box test: the cone's axis ray must hit the primitive's axis-aligned bounding box
inflated by ``t_far * tan(half angle)`` (any ray of the cone stays that close to the axis up to
the box's far distance). Only the rays of surviving subtiles are tested exactly against the
primitive. Horizontal planes (floors, ceilings, ground) are tested against all rays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.sim.primitives import Boxes, Cylinders, Ellipsoids, PlaneSet

SUB = 4  # subtile edge (px)
FAN = 4  # subtiles per tile edge, tiles per block edge
_EPS_DIR = np.float32(1e-9)
F32 = np.float32


@dataclass(frozen=True)
class Level:
    """One level of the culling hierarchy."""

    axis: np.ndarray  # (T, 3) float32 unit cone axes (camera frame)
    tan_half: np.ndarray  # (T,) float32 tangent of the cone half angle
    children: np.ndarray  # (T, FAN*FAN) int32 indices into the next level (-1: none)


@dataclass(frozen=True)
class RayLayout:
    """Slot order of the valid pixels and the culling hierarchy (block -> tile -> subtile)."""

    slot_pixel: np.ndarray  # (S,) int64 flat image index of each slot (S = n_sub * 16)
    slot_real: np.ndarray  # (S,) bool: first occurrence of the pixel (not padding)
    bearings: np.ndarray  # (S, 3) float32 unit rays in the camera frame
    blocks: Level
    tiles: Level
    subs: Level  # children unused

    @property
    def n_sub(self) -> int:
        return len(self.subs.axis)


def _cone(rays: np.ndarray) -> tuple[np.ndarray, float]:
    axis = rays.mean(axis=0)
    axis /= np.linalg.norm(axis)
    half = float(np.arccos(np.clip(rays @ axis, -1.0, 1.0)).max()) + 1e-4
    return axis, half


def make_layout(bearings: np.ndarray, valid: np.ndarray) -> RayLayout:
    """Slot layout and culling hierarchy of an (H, W) grid of unit ``bearings`` (H, W, 3)."""
    h, w = valid.shape
    ns_y, ns_x = -(-h // SUB), -(-w // SUB)
    sub_id = np.full((ns_y, ns_x), -1, np.int64)
    slot_pixel, slot_real, sub_axis, sub_half = [], [], [], []
    for sy in range(ns_y):
        for sx in range(ns_x):
            ys, xs = slice(sy * SUB, sy * SUB + SUB), slice(sx * SUB, sx * SUB + SUB)
            vv = valid[ys, xs]
            if not vv.any():
                continue
            yy, xx = np.nonzero(vv)
            pix = (yy + sy * SUB) * w + (xx + sx * SUB)
            pad = np.full(SUB * SUB, pix[0], np.int64)
            pad[:len(pix)] = pix
            real = np.zeros(SUB * SUB, bool)
            real[:len(pix)] = True
            sub_id[sy, sx] = len(sub_axis)
            slot_pixel.append(pad)
            slot_real.append(real)
            a, hh = _cone(bearings[ys, xs][vv])
            sub_axis.append(a)
            sub_half.append(hh)
    slot_pixel_a = np.concatenate(slot_pixel)
    flat_b = bearings.reshape(-1, 3)

    def group(child_id: np.ndarray, child_rays) -> tuple[Level, np.ndarray]:
        cy, cx = child_id.shape
        gy, gx = -(-cy // FAN), -(-cx // FAN)
        ids = np.full((gy, gx), -1, np.int64)
        axes, halves, children = [], [], []
        for y in range(gy):
            for x in range(gx):
                block = child_id[y * FAN:y * FAN + FAN, x * FAN:x * FAN + FAN]
                ch = np.full((FAN, FAN), -1, np.int64)
                ch[:block.shape[0], :block.shape[1]] = block
                if (ch < 0).all():
                    continue
                rays = np.concatenate([child_rays(c) for c in ch.ravel() if c >= 0])
                a, hh = _cone(rays)
                ids[y, x] = len(axes)
                axes.append(a)
                halves.append(hh)
                children.append(ch.ravel())
        lvl = Level(axis=np.array(axes, F32), tan_half=np.tan(np.array(halves)).astype(F32),
                    children=np.array(children, np.int32))
        return lvl, ids

    sub_rays = [flat_b[p] for p in slot_pixel]
    tiles, tile_id = group(sub_id, lambda c: sub_rays[c])
    tile_rays = [np.concatenate([sub_rays[c] for c in ch if c >= 0]) for ch in tiles.children]
    blocks, _ = group(tile_id, lambda c: tile_rays[c])
    subs = Level(axis=np.array(sub_axis, F32), tan_half=np.tan(np.array(sub_half)).astype(F32),
                 children=np.zeros((len(sub_axis), 0), np.int32))
    return RayLayout(slot_pixel=slot_pixel_a, slot_real=np.concatenate(slot_real),
                     bearings=flat_b[slot_pixel_a].astype(F32), blocks=blocks, tiles=tiles,
                     subs=subs)


@dataclass
class Hits:
    """Nearest hits of the rays in slot order."""

    t: np.ndarray  # (S,) float32 range (m), inf for misses
    prim: np.ndarray  # (S,) int32 global primitive id, -1 for misses


class SceneArrays:
    """Static + dynamic primitives of one frame in the global id space.

    Ids: boxes ``[0, nb)``, ellipsoids ``[nb, nb + ne)``, cylinders ``[.., + nc)``, plane
    rectangles after that (in the order of ``planes`` and their rects).
    """

    def __init__(self, boxes: Boxes, ellipsoids: Ellipsoids, cylinders: Cylinders,
                 planes: list[PlaneSet]) -> None:
        self.boxes = boxes
        self.ellipsoids = ellipsoids
        self.cylinders = cylinders
        self.planes = planes
        self.nb = len(boxes)
        self.ne = len(ellipsoids)
        self.nc = len(cylinders)
        self.plane_offsets = []
        off = self.nb + self.ne + self.nc
        for p in planes:
            self.plane_offsets.append(off)
            off += len(p.rects)
        self.n_total = off
        aa = boxes.axis_aligned
        self.box_is_aabb = aa
        self.rot_t = np.transpose(boxes.rot, (0, 2, 1))
        self.rot_t32 = np.ascontiguousarray(self.rot_t, dtype=F32)
        self.rot32 = np.ascontiguousarray(boxes.rot, dtype=F32)
        self.half32 = boxes.half.astype(F32)
        # world AABBs of all culled primitives (boxes, ellipsoids, cylinders)
        cyl = cylinders
        lo = [boxes.center - boxes.world_half, ellipsoids.center - ellipsoids.radii,
              np.column_stack([cyl.center - cyl.radius[:, None], cyl.z0])]
        hi = [boxes.center + boxes.world_half, ellipsoids.center + ellipsoids.radii,
              np.column_stack([cyl.center + cyl.radius[:, None], cyl.z1])]
        self.aabb_lo = np.concatenate(lo).reshape(-1, 3)
        self.aabb_hi = np.concatenate(hi).reshape(-1, 3)


def _safe_inv(v: np.ndarray) -> np.ndarray:
    return (F32(1.0) / np.where(np.abs(v) < _EPS_DIR, np.copysign(_EPS_DIR, v), v)).astype(F32)


def _cone_box(axis: np.ndarray, tan_half: np.ndarray, lo: np.ndarray, hi: np.ndarray,
              tfar: np.ndarray) -> np.ndarray:
    """Conservative cone (apex at the origin) vs box test; broadcasting over leading dims.

    ``axis`` (..., 3) unit, ``lo``/``hi`` (..., 3) camera-relative box, ``tfar`` (...) an upper
    bound of the distance to the box.
    """
    m = tfar * tan_half * F32(1.02) + F32(1e-3)
    inv = _safe_inv(axis)
    t1 = (lo[..., 0] - m) * inv[..., 0]
    t2 = (hi[..., 0] + m) * inv[..., 0]
    tn = np.minimum(t1, t2)
    tf = np.maximum(t1, t2)
    for k in (1, 2):
        t1 = (lo[..., k] - m) * inv[..., k]
        t2 = (hi[..., k] + m) * inv[..., k]
        np.maximum(tn, np.minimum(t1, t2), out=tn)
        np.minimum(tf, np.maximum(t1, t2), out=tf)
    return (tn <= tf) & (tf >= 0)


def cull(layout: RayLayout, axes_world: tuple[np.ndarray, np.ndarray, np.ndarray],
         lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(subtile, primitive) pairs whose cones meet the primitives' boxes (camera-relative
    ``lo``/``hi`` (N, 3)); sorted by subtile."""
    n = len(lo)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo = lo.astype(F32)
    hi = hi.astype(F32)
    far = np.maximum(np.abs(lo), np.abs(hi))
    tfar = np.sqrt((far * far).sum(axis=1)).astype(F32)
    ax_b, ax_t, ax_s = axes_world
    # blocks x primitives (full matrix)
    hit = _cone_box(ax_b[:, None, :], layout.blocks.tan_half[:, None], lo[None], hi[None],
                    tfar[None])
    parent, prim = np.nonzero(hit)
    for level, ax_child, tan_child in ((layout.blocks, ax_t, layout.tiles.tan_half),
                                       (layout.tiles, ax_s, layout.subs.tan_half)):
        ch = level.children[parent]
        rows, cols = np.nonzero(ch >= 0)
        child = ch[rows, cols]
        pr = prim[rows]
        ok = _cone_box(ax_child[child], tan_child[child], lo[pr], hi[pr], tfar[pr])
        parent, prim = child[ok], pr[ok]
    order = np.argsort(parent, kind='stable')
    return parent[order], prim[order]


def trace(scene: SceneArrays, layout: RayLayout, dirs: np.ndarray, origin: np.ndarray,
          axes_world: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Hits:
    """Nearest hits of rays ``origin + t * dirs`` (dirs (S, 3) float32 unit, world frame, slot
    order); ``axes_world`` are the cone axes of blocks, tiles and subtiles in the world frame."""
    n_slots = len(dirs)
    n_sub = layout.n_sub
    o = np.asarray(origin, np.float64)
    dx, dy, dz = (np.ascontiguousarray(dirs[:, k]) for k in range(3))
    inv = _safe_inv(dirs)
    best_t = np.full(n_slots, np.inf, F32)
    best_p = np.full(n_slots, -1, np.int32)

    # Planes: analytic over all rays (only rays that reach the plane's side are tested).
    iz = np.ascontiguousarray(inv[:, 2])
    for p, off in zip(scene.planes, scene.plane_offsets):
        dzp = float(p.z - o[2])
        if (p.up and dzp >= 0) or (not p.up and dzp <= 0):
            continue
        t = F32(dzp) * iz
        cand = np.flatnonzero((t > 0) & (t < best_t))
        if len(cand) == 0:
            continue
        tc = t[cand]
        px = F32(o[0]) + tc * dx[cand]
        py = F32(o[1]) + tc * dy[cand]
        which = np.full(len(cand), -1, np.int32)
        for k, (x0, x1, y0, y1) in enumerate(p.rects.tolist()):
            which[(px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)] = off + k
        hit = which >= 0
        best_t[cand[hit]] = tc[hit]
        best_p[cand[hit]] = which[hit]

    lo_all = (scene.aabb_lo - o).astype(F32)
    hi_all = (scene.aabb_hi - o).astype(F32)
    sub_idx, prim = cull(layout, axes_world, lo_all, hi_all)
    if len(sub_idx) == 0:
        return Hits(best_t, best_p)
    # Per-pair exact tests on the 16 rays of the subtile.
    rows_t = np.full((len(sub_idx), SUB * SUB), np.inf, F32)
    inv3 = inv.reshape(n_sub, SUB * SUB, 3)
    d3 = dirs.reshape(n_sub, SUB * SUB, 3)
    nb, ne = scene.nb, scene.ne
    is_box = prim < nb
    # axis-aligned boxes (world AABB == box)
    sel = np.flatnonzero(is_box)
    if len(sel):
        aabb = scene.box_is_aabb[prim[sel]]
        s1 = sel[aabb]
        if len(s1):
            p = prim[s1]
            lo, hi = lo_all[p], hi_all[p]
            iv = inv3[sub_idx[s1]]  # (K, 16, 3)
            t1 = lo[:, None, 0] * iv[..., 0]
            t2 = hi[:, None, 0] * iv[..., 0]
            tn = np.minimum(t1, t2)
            tf = np.maximum(t1, t2)
            for k in (1, 2):
                t1 = lo[:, None, k] * iv[..., k]
                t2 = hi[:, None, k] * iv[..., k]
                np.maximum(tn, np.minimum(t1, t2), out=tn)
                np.minimum(tf, np.maximum(t1, t2), out=tf)
            tn[(tn > tf) | (tn <= 0)] = np.inf
            rows_t[s1] = tn
        s2 = sel[~aabb]
        if len(s2):
            p = prim[s2]
            b = scene.boxes
            rt = scene.rot_t[p].astype(F32)
            c_rel = (b.center[p] - o).astype(F32)
            o_loc = -np.einsum('nij,nj->ni', rt, c_rel)
            h = b.half[p].astype(F32)
            lo_l, hi_l = -o_loc - h, -o_loc + h
            dd = d3[sub_idx[s2]]
            tn = tf = None
            for k in range(3):
                dl = (rt[:, None, k, 0] * dd[..., 0] + rt[:, None, k, 1] * dd[..., 1]
                      + rt[:, None, k, 2] * dd[..., 2])
                il = _safe_inv(dl)
                t1 = lo_l[:, None, k] * il
                t2 = hi_l[:, None, k] * il
                if tn is None:
                    tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
                else:
                    np.maximum(tn, np.minimum(t1, t2), out=tn)
                    np.minimum(tf, np.maximum(t1, t2), out=tf)
            tn[(tn > tf) | (tn <= 0)] = np.inf
            rows_t[s2] = tn
    # ellipsoids
    sel = np.flatnonzero((prim >= nb) & (prim < nb + ne))
    if len(sel):
        e = prim[sel] - nb
        el = scene.ellipsoids
        c_rel = (el.center[e] - o).astype(F32)
        inv_r = (1.0 / el.radii[e]).astype(F32)
        oc = -c_rel * inv_r
        cc = (oc * oc).sum(axis=1) - 1.0
        dd = d3[sub_idx[sel]]
        ux = dd[..., 0] * inv_r[:, None, 0]
        uy = dd[..., 1] * inv_r[:, None, 1]
        uz = dd[..., 2] * inv_r[:, None, 2]
        a = ux * ux + uy * uy + uz * uz
        bb = oc[:, None, 0] * ux + oc[:, None, 1] * uy + oc[:, None, 2] * uz
        disc = bb * bb - a * cc[:, None]
        with np.errstate(invalid='ignore'):
            t = (-bb - np.sqrt(disc)) / a
        t[~(disc >= 0) | ~(t > 0)] = np.inf
        rows_t[sel] = t
    # vertical cylinders (side and top cap)
    sel = np.flatnonzero(prim >= nb + ne)
    if len(sel):
        c = prim[sel] - nb - ne
        cy = scene.cylinders
        ox = (o[0] - cy.center[c, 0]).astype(F32)[:, None]
        oy = (o[1] - cy.center[c, 1]).astype(F32)[:, None]
        z0 = (cy.z0[c] - o[2]).astype(F32)[:, None]
        z1 = (cy.z1[c] - o[2]).astype(F32)[:, None]
        r2 = (cy.radius[c] ** 2).astype(F32)[:, None]
        dd = d3[sub_idx[sel]]
        ddx, ddy, ddz = dd[..., 0], dd[..., 1], dd[..., 2]
        a = ddx * ddx + ddy * ddy
        bb = ox * ddx + oy * ddy
        disc = bb * bb - a * (ox * ox + oy * oy - r2)
        with np.errstate(invalid='ignore', divide='ignore'):
            ts = (-bb - np.sqrt(disc)) / a
        zs = ts * ddz
        ok = (disc >= 0) & (ts > 0) & (zs >= z0) & (zs <= z1)
        ts = np.where(ok, ts, np.inf)
        izz = inv3[sub_idx[sel]][..., 2]
        tc = z1 * izz
        hx = tc * ddx + ox
        hy = tc * ddy + oy
        okc = (tc > 0) & (z1 < 0) & (hx * hx + hy * hy <= r2)
        rows_t[sel] = np.minimum(ts, np.where(okc, tc, np.inf))
    # Reduce per subtile (pairs are sorted by subtile) and merge with the planes.
    starts = np.flatnonzero(np.concatenate([[True], sub_idx[1:] != sub_idx[:-1]]))
    subs = sub_idx[starts]
    tmin = np.minimum.reduceat(rows_t, starts, axis=0)
    counts = np.diff(np.concatenate([starts, [len(sub_idx)]]))
    seg = np.repeat(np.arange(len(starts)), counts)
    winner = np.where(rows_t == tmin[seg], prim[:, None].astype(np.int32), -1)
    wprim = np.maximum.reduceat(winner, starts, axis=0)
    bt = best_t.reshape(n_sub, SUB * SUB)
    bp = best_p.reshape(n_sub, SUB * SUB)
    cur_t = bt[subs]
    better = tmin < cur_t
    bt[subs] = np.where(better, tmin, cur_t)
    bp[subs] = np.where(better, wprim, bp[subs])
    return Hits(best_t, best_p)
