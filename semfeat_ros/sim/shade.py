"""Surface attributes, procedural materials, decals and lighting of ray hits.

Every texture is a function of the hit point on the surface (world coordinates for static
primitives, object coordinates for moving ones), so the same surface looks the same from every
view. Lighting mixes the outdoor model (sky ambient + sun) and the indoor one (dim ambient + the
ceiling-light grid) with the :meth:`World.openness` of the point.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.sim import materials as mt
from semfeat_ros.sim.decals import evaluate as evaluate_decals
from semfeat_ros.sim.raycast import Hits, SceneArrays
from semfeat_ros.sim.textures import glyph_mask, hash_unit
from semfeat_ros.sim.world import World

F32 = np.float32


@dataclass
class Shaded:
    """Per valid pixel: linear radiance (P, 3), class (P,), instance (P,)."""

    radiance: np.ndarray
    label: np.ndarray
    instance: np.ndarray


class PlaneTable:
    """Flattened attributes of all plane rectangles (indexed by ``prim - offset0``)."""

    def __init__(self, scene: SceneArrays) -> None:
        planes = scene.planes
        self.offset0 = scene.nb + scene.ne + scene.nc
        if planes:
            self.up = np.concatenate([np.full(len(p.rects), p.up) for p in planes])
            self.cls = np.concatenate([p.cls for p in planes])
            self.mat = np.concatenate([p.mat for p in planes])
            self.inst = np.concatenate([p.inst for p in planes])
            self.color = np.concatenate([p.color for p in planes])
            self.group = np.concatenate([p.decal_group for p in planes])
        else:
            self.up = np.zeros(0, bool)
            self.cls = self.mat = np.zeros(0, np.uint8)
            self.inst = np.zeros(0, np.int32)
            self.color = np.zeros((0, 3), np.float32)
            self.group = np.zeros(0, np.int8)


@dataclass
class Surface:
    """Attributes of N hit points."""

    p: np.ndarray  # (N, 3) world point (m)
    n: np.ndarray  # (N, 3) world normal
    q: np.ndarray  # (N, 3) texture-space point (world, or object frame for moving objects)
    qn: np.ndarray  # (N, 3) texture-space normal
    local: np.ndarray  # (N, 3) box-local point (boxes), else 0
    half: np.ndarray  # (N, 3) box half extents (boxes), else 1
    face: np.ndarray  # (N,) int8 box face (0..5), -1 otherwise
    cls: np.ndarray  # (N,) uint8
    mat: np.ndarray  # (N,) uint8
    inst: np.ndarray  # (N,) int32
    color: np.ndarray  # (N, 3) float32
    param: np.ndarray  # (N,) int32
    group: np.ndarray  # (N,) int8 decal group (-1 none)
    fp: np.ndarray  # (N,) pixel footprint on the surface (m)


def hit_order(scene: SceneArrays, prim: np.ndarray) -> np.ndarray:
    """Indices of the hit slots (``prim >= 0``) sorted by primitive kind (boxes, ellipsoids,
    cylinders, planes), as :func:`surface_attributes` expects."""
    nb, ne, nc = scene.nb, scene.ne, scene.nc
    kind = ((prim >= nb).astype(np.int8) + (prim >= nb + ne) + (prim >= nb + ne + nc)
            - 4 * (prim < 0))
    order = np.argsort(kind, kind='stable')
    return order[kind[order] >= 0]


def surface_attributes(scene: SceneArrays, planes: PlaneTable, prim: np.ndarray, t: np.ndarray,
                       d: np.ndarray, origin: np.ndarray, pixel_angle: float) -> Surface:
    """Attributes of hits ``prim`` (N,) at range ``t`` (N,) along directions ``d`` (N, 3).

    The hits must be sorted by primitive kind (:func:`hit_order`).
    """
    nb, ne, nc = scene.nb, scene.ne, scene.nc
    bounds = np.searchsorted(prim, [nb, nb + ne, nb + ne + nc])
    if np.any(np.diff(prim >= nb).astype(np.int8) < 0):
        raise ValueError('surface_attributes: hits must be sorted by primitive kind')
    n_hit = len(prim)
    p_rel = d * t[:, None]
    p = p_rel + origin.astype(F32)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in (
        'n', 'q', 'qn', 'local', 'half', 'face', 'cls', 'mat', 'inst', 'color', 'param',
        'group')}

    def add(**kw: np.ndarray) -> None:
        for k, v in kw.items():
            parts[k].append(v)

    # Boxes.
    sl = slice(0, bounds[0])
    if bounds[0]:
        b = prim[sl]
        m = len(b)
        bx = scene.boxes
        rel = p_rel[sl] - (bx.center[b] - origin).astype(F32)
        rt = scene.rot_t32[b]
        loc = (rt[:, :, 0] * rel[:, 0:1] + rt[:, :, 1] * rel[:, 1:2]
               + rt[:, :, 2] * rel[:, 2:3])
        h = scene.half32[b]
        axis = np.argmax(np.abs(loc) / h, axis=1)
        ar = np.arange(m)
        sgn = np.where(loc[ar, axis] < 0, F32(-1.0), F32(1.0))
        f = (2 * axis + (sgn > 0)).astype(np.int8)
        nl = np.zeros((m, 3), F32)
        nl[ar, axis] = sgn
        nw = scene.rot32[b, :, axis] * sgn[:, None]  # column ``axis`` of rot
        dyn = bx.dynamic[b]
        q = p[sl].copy()
        qn = nw.copy()
        if dyn.any():
            qn[dyn] = nl[dyn]
            q[dyn] = loc[dyn] + (bx.inst[b][dyn] % 97).astype(F32)[:, None] * F32(3.1)
        add(n=nw, q=q, qn=qn, local=loc, half=h, face=f, cls=bx.face_cls[b, f],
            mat=bx.face_mat[b, f], inst=bx.inst[b], color=bx.color[b], param=bx.param[b],
            group=np.where(f == 5, bx.decal_group[b], np.int8(-1)).astype(np.int8))
    others = []
    # Ellipsoids.
    sl = slice(bounds[0], bounds[1])
    if bounds[1] > bounds[0]:
        e = prim[sl] - nb
        el = scene.ellipsoids
        rel = p_rel[sl] - (el.center[e] - origin).astype(F32)
        r = el.radii[e].astype(F32)
        nw = rel / (r * r)
        nw /= np.linalg.norm(nw, axis=1, keepdims=True)
        q = p[sl].copy()
        dyn = el.dynamic[e]
        if dyn.any():
            q[dyn] = rel[dyn] + (el.inst[e][dyn] % 97).astype(F32)[:, None] * F32(3.1)
        others.append((nw, q, el.cls[e], el.mat[e], el.inst[e], el.color[e], el.param[e],
                       np.full(len(e), -1, np.int8)))
    # Cylinders.
    sl = slice(bounds[1], bounds[2])
    if bounds[2] > bounds[1]:
        c = prim[sl] - nb - ne
        cy = scene.cylinders
        top = np.abs(p[sl, 2] - cy.z1[c]) < 1e-3 * np.maximum(1.0, t[sl])
        radial = p[sl, :2] - cy.center[c].astype(F32)
        radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-6)
        nw = np.zeros((len(c), 3), F32)
        nw[:, :2] = np.where(top[:, None], 0.0, radial)
        nw[:, 2] = np.where(top, 1.0, 0.0)
        others.append((nw, p[sl], cy.cls[c], cy.mat[c], cy.inst[c], cy.color[c], cy.param[c],
                       np.full(len(c), -1, np.int8)))
    # Planes.
    sl = slice(bounds[2], n_hit)
    if n_hit > bounds[2]:
        k = prim[sl] - planes.offset0
        nw = np.zeros((len(k), 3), F32)
        nw[:, 2] = np.where(planes.up[k], 1.0, -1.0)
        others.append((nw, p[sl], planes.cls[k], planes.mat[k], planes.inst[k],
                       planes.color[k], np.zeros(len(k), np.int32), planes.group[k]))
    for nw, q, cls, mat, inst, color, param, group in others:
        m = len(nw)
        add(n=nw, q=q, qn=nw, local=np.zeros((m, 3), F32), half=np.ones((m, 3), F32),
            face=np.full(m, -1, np.int8), cls=cls, mat=mat, inst=inst, color=color,
            param=param, group=group)
    cat = {k: (np.concatenate(v) if len(v) > 1 else v[0]) for k, v in parts.items()}
    normal = cat['n'].astype(F32, copy=False)
    cosi = np.abs(normal[:, 0] * d[:, 0] + normal[:, 1] * d[:, 1] + normal[:, 2] * d[:, 2])
    fp = t * F32(pixel_angle) / np.maximum(cosi, F32(0.2))
    return Surface(p=p.astype(F32, copy=False), n=normal,
                   q=cat['q'].astype(F32, copy=False), qn=cat['qn'].astype(F32, copy=False),
                   local=cat['local'].astype(F32, copy=False),
                   half=cat['half'].astype(F32, copy=False), face=cat['face'], cls=cat['cls'],
                   mat=cat['mat'], inst=cat['inst'].astype(np.int32, copy=False),
                   color=cat['color'].astype(F32, copy=False),
                   param=cat['param'].astype(np.int32, copy=False),
                   group=cat['group'].astype(np.int8, copy=False),
                   fp=fp.astype(F32, copy=False))


# ----------------------------------------------------------------------------------- materials


def _aa_line(dist: np.ndarray, width: float, fp: np.ndarray) -> np.ndarray:
    """Coverage in [0, 1] of a line of ``width`` m at distance ``dist`` m, anti-aliased over the
    pixel footprint ``fp`` m."""
    edge = np.clip((width * 0.5 - dist) / np.maximum(fp, 1e-4) + 0.5, 0.0, 1.0)
    return edge * np.minimum(1.0, width / np.maximum(fp, 1e-4))


def _grid_dist(v: np.ndarray, period: float, offset: float = 0.0) -> np.ndarray:
    """Distance (m) of ``v`` to the nearest multiple of ``period`` (shifted by ``offset``)."""
    w = (v - offset) / period
    return np.abs(w - np.round(w)) * period


def _tangent(q: np.ndarray, qn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface coordinates (s, t) from the dominant axis of the normal; returns the axis too."""
    ax = np.argmax(np.abs(qn), axis=1)
    s = np.where(ax == 0, q[:, 1], q[:, 0])
    t = np.where(ax == 2, q[:, 1], q[:, 2])
    return s, t, ax


def _concrete(world: World, base: np.ndarray, s: np.ndarray, t: np.ndarray, fp: np.ndarray,
              bands=(0.35, 0.3, 0.35), stains: float = 0.25, cracks: float = 0.45,
              contrast: float = 0.22) -> np.ndarray:
    tex = world.textures
    v = tex.noise(s, t, fp, bands)
    shade = 1.0 + contrast * v
    if stains:
        shade *= 1.0 - stains * tex.blob.sample(s * 0.6 + 11.0, t * 0.6 - 7.0)
    if cracks:
        shade *= 1.0 - cracks * tex.cracks(s, t, fp)
    return base * np.clip(shade, 0.15, 2.0)[:, None]


def material_albedo(world: World, sf: Surface, idx: np.ndarray, mat: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Albedo (n, 3) and emission (n, 3) of material ``mat`` at surface points ``idx``."""
    base = sf.color[idx]
    q, qn, fp = sf.q[idx], sf.qn[idx], sf.fp[idx]
    s, t, ax = _tangent(q, qn)
    emis = np.zeros_like(base)
    tex = world.textures
    if mat == mt.M_FLOOR_IN:
        alb = _concrete(world, base, s, t, fp, (0.4, 0.35, 0.45), stains=0.3, cracks=0.3)
    elif mat == mt.M_FLOOR_DECK:
        alb = _concrete(world, base, s, t, fp, (0.55, 0.3, 0.3), stains=0.2, cracks=0.3,
                        contrast=0.2)
        joint = _aa_line(np.minimum(_grid_dist(s, 7.5, 0.3), _grid_dist(t, 6.0, 0.2)), 0.02, fp)
        alb *= (1.0 - 0.45 * joint)[:, None]
    elif mat == mt.M_RAMP:
        alb = _concrete(world, base, s, t, fp, (0.4, 0.3, 0.3), stains=0.2, cracks=0.4)
        groove = _aa_line(_grid_dist(q[:, 0], 0.25), 0.04, fp)
        alb *= (1.0 - 0.3 * groove)[:, None]
    elif mat == mt.M_CONCRETE:
        alb = _concrete(world, base, s, t, fp, (0.3, 0.3, 0.35), stains=0.3, cracks=0.35)
        vertical = ax != 2
        z = q[:, 2]
        lines = _aa_line(_grid_dist(z, 1.2, 0.05), 0.015, fp)
        lines = np.maximum(lines, _aa_line(_grid_dist(s, 2.4, 0.1), 0.012, fp))
        holes = np.hypot(_grid_dist(s, 0.6, 0.3), _grid_dist(z, 0.6, 0.35))
        dots = _aa_line(holes, 0.035, fp)
        dark = np.where(vertical, 0.4 * lines + 0.5 * dots, 0.0)
        alb *= (1.0 - dark)[:, None]
        # painted dado band on the lower 1 m of vertical faces on the covered level
        band = vertical & (z < 1.0) & (z > 0.02) & (q[:, 2] < world.layout.ceiling_z)
        alb[band] = alb[band] * 0.35 + F32(0.5) * np.array([0.75, 0.75, 0.72], F32)
    elif mat == mt.M_PILLAR:
        alb = _concrete(world, base, s, t, fp, (0.3, 0.3, 0.3), stains=0.15, cracks=0.3)
        z = q[:, 2]
        hazard = (z < 1.0) & (ax != 2)
        diag = np.floor((s + z) / 0.2).astype(np.int64) % 2 == 0
        yellow = np.array([0.85, 0.65, 0.05], F32)
        black = np.array([0.03, 0.03, 0.03], F32)
        alb[hazard] = np.where(diag[hazard, None], yellow, black)
        edge = _aa_line(np.abs(z - 1.0), 0.05, fp)
        alb *= (1.0 - 0.6 * edge * (ax != 2))[:, None]
    elif mat == mt.M_CEILING:
        alb = _concrete(world, base, s, t, fp, (0.3, 0.3, 0.3), stains=0.35, cracks=0.3)
        panel = _aa_line(np.minimum(_grid_dist(s, 2.4), _grid_dist(t, 1.2)), 0.02, fp)
        alb *= (1.0 - 0.45 * panel)[:, None]
    elif mat == mt.M_ASPHALT:
        alb = _concrete(world, base, s, t, fp, (0.8, 0.35, 0.35), stains=0.25, cracks=0.35,
                        contrast=0.28)
    elif mat == mt.M_PAVER:
        ti, tj = np.floor(s / 0.3), np.floor(t / 0.3)
        tone = 0.85 + 0.3 * hash_unit(ti.astype(np.int64), tj.astype(np.int64), 7)
        joint = _aa_line(np.minimum(_grid_dist(s, 0.3), _grid_dist(t, 0.3)), 0.012, fp)
        alb = _concrete(world, base, s, t, fp, (0.35, 0.2, 0.3), stains=0.2, cracks=0.0)
        top = ax == 2
        alb *= np.where(top, tone * (1.0 - 0.6 * joint), 1.0)[:, None]
    elif mat == mt.M_CURB:
        alb = _concrete(world, base, s, t, fp, (0.3, 0.3, 0.3), stains=0.2, cracks=0.2)
    elif mat == mt.M_METAL:
        alb = base * (1.0 + 0.08 * tex.noise(s, t, fp, (0.3, 0.4, 0.3)))[:, None]
    elif mat == mt.M_SIGN:
        alb = _sign(world, sf, idx)
        emis = alb * F32(0.12)
    elif mat == mt.M_CAR:
        alb, emis = _car(sf, idx, base)
    elif mat == mt.M_GLASS:
        alb = _glass(sf, idx, base)
    elif mat == mt.M_RUBBER:
        alb = np.full_like(base, 0.035)
        side = (sf.face[idx] == 2) | (sf.face[idx] == 3)
        loc, h = sf.local[idx], sf.half[idx]
        hub = side & (np.hypot(loc[:, 0] / h[:, 0], loc[:, 2] / h[:, 2]) < 0.6)
        alb[hub] = np.array([0.32, 0.32, 0.34], F32)
    elif mat == mt.M_FACADE:
        alb, emis = _facade(world, sf, idx, base, s, t, ax, fp)
    elif mat == mt.M_FOLIAGE:
        leafy = tex.noise(s * 1.7, t * 1.7 + q[:, 0] * 0.3, fp, (0.7, 0.8, 0.4))
        alb = base * np.clip(1.0 + 0.55 * leafy, 0.25, 2.2)[:, None]
    elif mat == mt.M_BARK:
        streak = tex.noise(s * 6.0, q[:, 2] * 0.4, fp, (0.5, 0.5, 0.2))
        alb = base * np.clip(1.0 + 0.35 * streak, 0.3, 2.0)[:, None]
    elif mat == mt.M_LAMP:
        alb = np.full_like(base, 0.85)
        on = sf.param[idx] > 0
        emis = np.where(on[:, None], base * F32(9.0), 0.0).astype(F32)
    elif mat == mt.M_STRIPES:
        alb = _stripes(sf, idx, base, s, q)
    elif mat == mt.M_CLOTH:
        alb = base * (1.0 + 0.15 * tex.noise(s * 3, t * 3, fp, (0.3, 0.5, 0.2)))[:, None]
    elif mat == mt.M_SKIN:
        alb = base.copy()
    else:
        alb = base.copy()
    return np.clip(alb, 0.0, 1.0).astype(F32), emis.astype(F32)


def _sign(world: World, sf: Surface, idx: np.ndarray) -> np.ndarray:
    face = sf.face[idx]
    loc, h = sf.local[idx], sf.half[idx]
    design = np.clip(sf.param[idx], 0, len(world.signs.n_chars) - 1)
    alb = np.tile(np.array([0.45, 0.46, 0.48], F32), (len(idx), 1))
    front = (face == 2) | (face == 3)
    if front.any():
        fi = np.flatnonzero(front)
        u = loc[fi, 0] / h[fi, 0]
        s = np.where(face[fi] == 3, (1.0 - u) / 2.0, (1.0 + u) / 2.0)
        t = (1.0 - loc[fi, 2] / h[fi, 2]) / 2.0
        dsg = design[fi]
        aspect = h[fi, 0] / h[fi, 2]
        margin = np.clip(0.12 / np.maximum(aspect, 1.0), 0.04, 0.12)
        ink = glyph_mask(world.signs.codes[dsg], world.signs.n_chars[dsg], s, t,
                         margin=margin)
        border = (s < 0.035) | (s > 0.965) | (t < 0.06) | (t > 0.94)
        fg = world.signs.fg[dsg]
        bg = world.signs.bg[dsg]
        alb[fi] = np.where((ink | border)[:, None], fg, bg)
    return alb


def _car(sf: Surface, idx: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    face = sf.face[idx]
    loc, h = sf.local[idx], sf.half[idx]
    alb = base.copy()
    emis = np.zeros_like(base)
    uy = loc[:, 1] / h[:, 1]
    uz = loc[:, 2] / h[:, 2]
    ends = (face == 0) | (face == 1)
    lamp = ends & (np.abs(uy) > 0.55) & (np.abs(uy) < 0.92) & (uz > 0.05) & (uz < 0.65)
    front = face == 1
    alb[lamp & front] = np.array([0.9, 0.9, 0.85], F32)
    emis[lamp & front] = np.array([0.25, 0.25, 0.22], F32)
    alb[lamp & ~front] = np.array([0.6, 0.03, 0.02], F32)
    emis[lamp & ~front] = np.array([0.15, 0.0, 0.0], F32)
    plate = ends & (np.abs(loc[:, 1]) < 0.26) & (uz > -0.75) & (uz < -0.3)
    alb[plate] = np.array([0.85, 0.85, 0.82], F32)
    chars = plate & (np.abs(loc[:, 1]) < 0.22) & (uz > -0.66) & (uz < -0.4) & (
        np.floor(loc[:, 1] / 0.035).astype(np.int64) % 2 == 0)
    alb[chars] = np.array([0.04, 0.04, 0.04], F32)
    grille = front & (np.abs(uy) < 0.4) & (uz > 0.0) & (uz < 0.5)
    alb[grille] = alb[grille] * 0.25
    bottom = ends | (face == 2) | (face == 3)
    sill = bottom & (uz < -0.85)
    alb[sill] = alb[sill] * 0.4
    return alb, emis


def _glass(sf: Surface, idx: np.ndarray, base: np.ndarray) -> np.ndarray:
    face = sf.face[idx]
    loc, h = sf.local[idx], sf.half[idx]
    alb = np.tile(np.array([0.05, 0.06, 0.07], F32), (len(idx), 1))
    ux = loc[:, 0] / h[:, 0]
    uy = loc[:, 1] / h[:, 1]
    uz = loc[:, 2] / h[:, 2]
    side = (face == 2) | (face == 3)
    pillar = side & ((np.abs(ux) > 0.88) | (np.abs(ux) < 0.05) | (uz > 0.8) | (uz < -0.85))
    ends = (face == 0) | (face == 1)
    frame = ends & ((np.abs(uy) > 0.9) | (uz > 0.82) | (uz < -0.85))
    paint = pillar | frame
    alb[paint] = base[paint]
    # faint reflection gradient (brighter towards the top)
    glass = ~paint
    alb[glass] += (0.03 * (uz[glass] + 1.0))[:, None].astype(F32)
    return alb


def _facade(world: World, sf: Surface, idx: np.ndarray, base: np.ndarray, s: np.ndarray,
            t: np.ndarray, ax: np.ndarray, fp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tex = world.textures
    prm = sf.param[idx].astype(np.int64)
    h1 = hash_unit(prm, 1)
    h2 = hash_unit(prm, 2)
    spacing = 2.2 + 1.6 * h1
    floor_h = 3.0 + 0.7 * h2
    win_w = spacing * (0.45 + 0.25 * hash_unit(prm, 3))
    win_h = floor_h * (0.45 + 0.2 * hash_unit(prm, 4))
    z = sf.q[idx, 2]
    col = np.floor(s / spacing)
    row = np.floor(z / floor_h)
    ds = np.abs(s - (col + 0.5) * spacing)
    dz = np.abs(z - (row * floor_h + floor_h * 0.55))
    vertical = ax != 2
    inside_w = vertical & (ds < win_w / 2) & (dz < win_h / 2) & (z > 1.0)
    alb = base * np.clip(1.0 + 0.15 * tex.noise(s, t, fp, (0.2, 0.3, 0.4)), 0.5, 1.5)[:, None]
    lit = hash_unit(col.astype(np.int64), row.astype(np.int64), prm)
    glass = np.stack([0.06 + 0.12 * lit, 0.08 + 0.12 * lit, 0.11 + 0.14 * lit], axis=1)
    alb = np.where(inside_w[:, None], glass.astype(F32), alb)
    frame = vertical & ~inside_w & (ds < win_w / 2 + 0.08) & (dz < win_h / 2 + 0.08) & (z > 1.0)
    alb[frame] = alb[frame] * 0.55 + 0.35
    roof = ~vertical
    alb[roof] = base[roof] * 0.6
    return alb.astype(F32), np.zeros_like(alb, dtype=F32)


def _stripes(sf: Surface, idx: np.ndarray, base: np.ndarray, s: np.ndarray,
             q: np.ndarray) -> np.ndarray:
    prm = sf.param[idx]
    white = np.array([0.85, 0.85, 0.83], F32)
    z = q[:, 2]
    band = np.floor(z / 0.15).astype(np.int64) % 2 == 0
    along = np.floor(sf.local[idx, 0] / 0.45).astype(np.int64) % 2 == 0
    diag = np.floor((s + z) / 0.5).astype(np.int64) % 2 == 0
    red = np.array([0.7, 0.04, 0.03], F32)
    alb = base.copy()
    alb = np.where(((prm == 1) & band)[:, None], white, alb)
    alb = np.where(((prm == 2) & along)[:, None], white, alb)
    alb = np.where(((prm == 3) & diag)[:, None], red, alb)
    return alb


# ------------------------------------------------------------------------------------ lighting


def _dot3(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise dot product of (N, 3) with a 3-vector (faster than numpy's matmul here)."""
    v = np.asarray(v, F32)
    return a[:, 0] * v[0] + a[:, 1] * v[1] + a[:, 2] * v[2]


def _window(u: np.ndarray) -> np.ndarray:
    v = np.clip(1.0 - u * u, 0.0, 1.0)
    return v * v


def indoor_irradiance(world: World, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Irradiance (N, 3) from the ceiling-light grid (4 nearest lights, smooth window) and the
    indoor ambient."""
    lg = world.lights
    xs = lg.xs.astype(F32)
    ys = lg.ys.astype(F32)
    nx = len(xs)
    power = lg.power.ravel().astype(F32)
    dxg = float(xs[1] - xs[0]) if nx > 1 else 1.0
    fx = (p[:, 0] - float(xs[0])) * F32(1.0 / dxg)
    i0 = np.clip(fx.astype(np.int32), 0, nx - 2)
    fx = np.clip(fx - i0, F32(0.0), F32(1.0))
    j0 = np.clip(np.searchsorted(ys, p[:, 1]) - 1, 0, len(ys) - 2).astype(np.int32)
    gap = ys[j0 + 1] - ys[j0]
    fy = np.clip((p[:, 1] - ys[j0]) / gap, F32(0.0), F32(1.0))
    lz = F32(lg.z) - p[:, 2]
    lz2 = lz * lz
    ndz = n[:, 2] * lz
    e = np.zeros(len(p), F32)
    for a in (0, 1):
        wx = _window(fx if a == 0 else 1.0 - fx)
        ii = i0 + a
        lx = xs[ii] - p[:, 0]
        for b in (0, 1):
            wy = _window(fy if b == 0 else 1.0 - fy)
            jj = j0 + b
            ly = ys[jj] - p[:, 1]
            d2 = lx * lx + ly * ly + lz2
            ndl = (n[:, 0] * lx + n[:, 1] * ly + ndz) / np.sqrt(d2 + F32(1e-6))
            e += (power[jj * nx + ii] * F32(6.0) * np.maximum(ndl, F32(0.1))
                  / (d2 + F32(0.6)) * (wx * wy))
    amb = world.indoor_ambient[None] * (0.8 + 0.2 * np.abs(n[:, 2:3]))
    return amb + e[:, None] * lg.color[None]


def outdoor_irradiance(world: World, n: np.ndarray, openness: np.ndarray) -> np.ndarray:
    """Sky ambient (hemisphere, scaled by the openness) plus direct sun (no shadows; only where
    the point is nearly fully open) for normals ``n``."""
    sky = world.sky_color[None] * (0.55 + 0.45 * n[:, 2:3]) * openness[:, None]
    sun_w = np.clip((openness - 0.8) * 5.0, 0.0, 1.0)
    sun = (np.maximum(_dot3(n, world.sun_dir), 0.0) * sun_w)[:, None] * world.sun_color[None]
    return (sky + sun).astype(F32)


def sky_radiance(world: World, d: np.ndarray) -> np.ndarray:
    """Radiance (N, 3) of the sky dome (gradient, clouds, sun) in directions ``d``."""
    el = np.clip(d[:, 2], -1.0, 1.0)
    g = np.clip(el, 0.0, 1.0) ** 0.6
    rad = world.horizon[None] * (1.0 - g[:, None]) + world.zenith[None] * g[:, None]
    up = el > 0.02
    if up.any():
        k = np.flatnonzero(up)
        scale = F32(40.0) / el[k]
        cu = world.textures.cloud.sample(d[k, 0] * scale, d[k, 1] * scale)
        cover = (cu * np.clip(el[k] * 8.0, 0.0, 1.0))[:, None]
        rad[k] = rad[k] * (1.0 - cover) + cover * F32(1.25)
    cosang = _dot3(d, world.sun_dir)
    glow = np.exp((cosang - 1.0) * 3000.0) * 40.0 + np.exp((cosang - 1.0) * 25.0) * 0.6
    rad = rad + glow[:, None] * world.sun_color[None] * 0.3
    below = el < 0
    rad[below] = world.horizon * 0.6
    return rad.astype(F32)


# --------------------------------------------------------------------------------------- shade


def shade(world: World, scene: SceneArrays, planes: PlaneTable, hits: Hits, dirs: np.ndarray,
          origin: np.ndarray, pixel_angle: float) -> Shaded:
    """Radiance, class and instance of every valid pixel."""
    n_pix = len(dirs)
    radiance = np.zeros((n_pix, 3), F32)
    label = np.full(n_pix, mt.SKY, np.uint8)
    instance = np.zeros(n_pix, np.int32)
    hit = hit_order(scene, hits.prim)
    miss = np.flatnonzero(hits.prim < 0)
    if len(miss):
        radiance[miss] = sky_radiance(world, dirs[miss])
    if len(hit) == 0:
        return Shaded(radiance, label, instance)
    sf = surface_attributes(scene, planes, hits.prim[hit], hits.t[hit], dirs[hit], origin,
                            pixel_angle)
    n = len(hit)
    albedo = np.zeros((n, 3), F32)
    emission = np.zeros((n, 3), F32)
    order = np.argsort(sf.mat, kind='stable')
    bounds = np.concatenate([[0], np.cumsum(np.bincount(sf.mat, minlength=mt.N_MATERIALS))])
    for m in range(len(bounds) - 1):
        if bounds[m + 1] == bounds[m]:
            continue
        idx = order[bounds[m]:bounds[m + 1]]
        a, e = material_albedo(world, sf, idx, m)
        albedo[idx] = a
        emission[idx] = e
    cls = sf.cls.copy()
    inst = sf.inst.copy()
    # Floor decals (paint with its own classes, stains).
    for g, decals in world.decals.items():
        idx = np.flatnonzero((sf.group == g) & (sf.n[:, 2] > 0.5))
        if len(idx) == 0:
            continue
        dh = evaluate_decals(decals, sf.p[idx, 0].astype(np.float64),
                             sf.p[idx, 1].astype(np.float64))
        if dh.stain.any():
            albedo[idx] *= (1.0 - 0.65 * dh.stain)[:, None]
        painted = np.flatnonzero(dh.cls >= 0)
        if len(painted):
            k = idx[painted]
            s = sf.p[k, 0] * 1.3 + dh.local[painted, 0]
            t = sf.p[k, 1] * 1.3 + dh.local[painted, 1]
            wear_n = world.textures.noise(s, t, sf.fp[k], (0.6, 0.5, 0.4))
            strength = np.clip(1.0 - dh.wear[painted] * (0.7 + 0.8 * wear_n), 0.3, 1.0)
            albedo[k] = (albedo[k] * (1.0 - strength[:, None])
                         + dh.color[painted] * strength[:, None])
            cls[k] = dh.cls[painted].astype(np.uint8)
            inst[k] = dh.inst[painted]
    # Lighting.
    w_out = world.openness(sf.p)
    irr = np.zeros((n, 3), F32)
    outdoor = np.flatnonzero(w_out > 0)
    if len(outdoor):
        irr[outdoor] = outdoor_irradiance(world, sf.n[outdoor], w_out[outdoor])
    indoor = np.flatnonzero(w_out < 1)
    if len(indoor):
        irr[indoor] += (indoor_irradiance(world, sf.p[indoor], sf.n[indoor])
                        * (1.0 - w_out[indoor, None]))
    radiance[hit] = albedo * irr + emission
    label[hit] = cls
    instance[hit] = inst
    return Shaded(radiance, label, instance)
