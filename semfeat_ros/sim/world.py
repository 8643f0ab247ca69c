"""Procedural two-level parking garage: geometry, markings, lights, surroundings and agents.

:func:`build_world` turns a seed and a :class:`~semfeat_ros.sim.config.GarageConfig` into a
:class:`World`: static primitives (boxes, ellipsoids, cylinders, floor planes), floor decals,
the ceiling-light grid, the sun and sky, the sign designs and the dynamic agents (moving cars,
pedestrians) whose primitives :meth:`World.dynamic_primitives` places at any time ``t`` (s).
Everything is deterministic in the seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semfeat_ros.sim import materials as mt
from semfeat_ros.sim.config import GarageConfig
from semfeat_ros.sim.decals import ARROW, RECT, STAIN, TEXT, DecalBuilder, DecalSet
from semfeat_ros.sim.layout import LANE, WALK, WALL, Layout
from semfeat_ros.sim.polyline import Polyline, offset, round_corners
from semfeat_ros.sim.primitives import (
    Boxes,
    Cylinders,
    Ellipsoids,
    PlaneSet,
    SceneBuilder,
    boxes_from_rows,
    ellipsoids_from_rows,
    yaw_pitch,
)
from semfeat_ros.sim.textures import TextureBank, encode_text, make_texture_bank

# Decal groups (floor surfaces).
G_COVERED, G_DECK, G_RAMP, G_STREET = 0, 1, 2, 3

SIGN_TEXT_LEN = 6

_CAR_COLORS = np.array([
    [0.80, 0.80, 0.78], [0.03, 0.03, 0.035], [0.45, 0.46, 0.48], [0.22, 0.23, 0.24],
    [0.04, 0.07, 0.20], [0.45, 0.03, 0.03], [0.55, 0.48, 0.36], [0.06, 0.18, 0.10],
    [0.70, 0.70, 0.72], [0.12, 0.12, 0.14], [0.10, 0.25, 0.45], [0.60, 0.30, 0.05],
], dtype=np.float32)

# Car types: length, width, height (m).
_CAR_TYPES = np.array([[3.9, 1.72, 1.45], [4.4, 1.80, 1.45], [4.7, 1.85, 1.48],
                       [4.6, 1.88, 1.70], [4.95, 1.95, 1.75], [5.1, 2.0, 1.95]])


@dataclass(frozen=True)
class SignDesigns:
    """Lettering and colours of sign faces (indexed by a sign box's ``param``)."""

    codes: np.ndarray  # (S, SIGN_TEXT_LEN) int16
    n_chars: np.ndarray  # (S,) int16
    fg: np.ndarray  # (S, 3) float32
    bg: np.ndarray  # (S, 3) float32


@dataclass(frozen=True)
class LightGrid:
    """Ceiling lights of the covered level on a grid ``xs x ys`` at height ``z`` (m)."""

    xs: np.ndarray  # (nx,) uniform spacing
    ys: np.ndarray  # (ny,) increasing, not necessarily uniform
    z: float
    power: np.ndarray  # (ny, nx) float32 (0: no light or switched off)
    color: np.ndarray  # (3,) float32 light colour


@dataclass
class Agent:
    """A moving car or pedestrian following a path with smoothly varying speed."""

    kind: str  # 'car' or 'pedestrian'
    path: Polyline
    level_z: float  # floor height of the path (m); ramp paths are not used by agents
    speed: float  # mean speed (m/s)
    phase: float  # arc length at t = 0 (m)
    period: float  # speed modulation period (s)
    pingpong: bool
    dims: np.ndarray  # car: length, width, height; pedestrian: height, width, depth
    color: np.ndarray  # (3,) body / clothing colour
    color2: np.ndarray  # (3,) trousers
    inst: int

    def arc_length(self, t: float) -> float:
        """Distance travelled along the path at time ``t`` (s), speed in [0.1, 1.9] x mean."""
        w = 2.0 * np.pi / self.period
        return self.phase + self.speed * (t - 0.9 * np.sin(w * t) / w)

    def pose(self, t: float) -> tuple[np.ndarray, float]:
        """Ground position (x, y) m and heading (rad) at time ``t``."""
        s = self.arc_length(t)
        if self.pingpong:
            length = self.path.length
            k = np.floor(s / length)
            u = s - k * length
            back = int(k) % 2 == 1
            xy, h = self.path.at(length - u if back else u)
            return xy[0], float(h[0] + (np.pi if back else 0.0))
        xy, h = self.path.at(s)
        return xy[0], float(h[0])


@dataclass
class CrossingAgent:
    """A pedestrian crossing an aisle on a zebra crossing, back and forth, but only while the
    ego car is not close to the crossing (precomputed schedule of crossing start times)."""

    start: np.ndarray  # (2,) one end of the crossing (m)
    end: np.ndarray  # (2,) the other end
    level_z: float
    speed: float  # m/s
    starts: np.ndarray  # (K,) crossing start times (s), increasing
    dims: np.ndarray
    color: np.ndarray
    color2: np.ndarray
    inst: int
    kind: str = 'pedestrian'

    @property
    def crossing_time(self) -> float:
        return float(np.linalg.norm(self.end - self.start) / self.speed)

    def _state(self, t: float) -> tuple[float, int, bool]:
        """(fraction crossed, crossing index, walking) at time ``t``."""
        k = int(np.searchsorted(self.starts, t, side='right')) - 1
        if k < 0:
            return 0.0, 0, False
        u = (t - self.starts[k]) / self.crossing_time
        return (min(u, 1.0), k, u < 1.0)

    def arc_length(self, t: float) -> float:
        u, k, walking = self._state(t)
        return (k + u) * self.crossing_time * self.speed if walking else 0.0

    def pose(self, t: float) -> tuple[np.ndarray, float]:
        """Ground position (x, y) m and heading (rad) at time ``t``."""
        if len(self.starts) == 0 or t < self.starts[0]:
            d = self.end - self.start
            return self.start.copy(), float(np.arctan2(d[1], d[0]))
        u, k, _ = self._state(t)
        a, b = (self.start, self.end) if k % 2 == 0 else (self.end, self.start)
        d = b - a
        return a + d * u, float(np.arctan2(d[1], d[0]))


@dataclass
class World:
    """A generated garage; see the module docstring."""

    seed: int
    config: GarageConfig
    layout: Layout
    boxes: Boxes
    ellipsoids: Ellipsoids
    cylinders: Cylinders
    planes: list[PlaneSet]
    decals: dict[int, DecalSet]
    textures: TextureBank
    lights: LightGrid
    signs: SignDesigns
    agents: list[Agent | CrossingAgent]
    sun_dir: np.ndarray  # (3,) unit vector towards the sun
    sun_color: np.ndarray  # (3,) irradiance of the sun (linear)
    sky_color: np.ndarray  # (3,) ambient sky irradiance
    zenith: np.ndarray  # (3,) sky radiance at the zenith
    horizon: np.ndarray  # (3,) sky radiance at the horizon
    indoor_ambient: np.ndarray  # (3,)
    portals: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # light openings

    def dynamic_primitives(self, t: float) -> tuple[Boxes, Ellipsoids]:
        """Boxes and ellipsoids of all agents at time ``t`` (s)."""
        boxes: list[tuple] = []
        ells: list[tuple] = []
        for ag in self.agents:
            (x, y), yaw = ag.pose(t)
            if ag.kind == 'car':
                _car_rows(boxes, np.array([x, y, ag.level_z]), yaw, ag.dims, ag.color, ag.inst,
                          dynamic=True)
            else:
                _pedestrian_rows(boxes, ells, np.array([x, y, ag.level_z]), yaw, ag.dims,
                                 ag.color, ag.color2, ag.inst, ag.arc_length(t))
        return boxes_from_rows(boxes), ellipsoids_from_rows(ells)

    def openness(self, p: np.ndarray) -> np.ndarray:
        """Fraction (N,) in [0, 1] of outdoor light (sky, sun) reaching world points ``p``.

        1 on the deck and outside, 0 deep inside the covered level, in between on the ramp
        (deeper in the trench = darker) and near openings of the covered level.
        """
        lay = self.layout
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        inside = lay.in_footprint(x, y) & (z < lay.deck_z - 0.02)
        trench = lay.in_trench(x, y)
        depth = np.clip((lay.deck_z - z) * (1.0 / lay.deck_z), 0.0, 1.0)
        w_trench = 1.0 - 0.7 * depth ** 1.3
        w = np.zeros(len(p), np.float32)
        for px0, px1, py0, py1, pz0, pz1 in self.portals.tolist():
            dx = np.maximum(np.maximum(px0 - x, x - px1), 0.0)
            dy = np.maximum(np.maximum(py0 - y, y - py1), 0.0)
            dz = np.maximum(np.maximum(pz0 - z, z - pz1), 0.0)
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            w = np.maximum(w, 0.55 * np.exp(-d / 3.5))
        w = np.where(trench, np.maximum(w_trench, w), w)
        return np.where(inside, w, 1.0).astype(np.float32)


# ------------------------------------------------------------------------------ agent geometry


def _car_rows(rows: list[tuple], base: np.ndarray, yaw: float, dims: np.ndarray,
              color: np.ndarray, inst: int, dynamic: bool) -> None:
    """Append the 4 boxes of a car (body, cabin, two axles) standing at ``base`` (x, y, z)."""
    length, width, height = (float(v) for v in dims)
    R = yaw_pitch(yaw)
    col = tuple(float(c) for c in color)

    def add(cx: float, cz: float, hx: float, hy: float, hz: float, mats) -> None:
        center = base + R @ np.array([cx, 0.0, cz])
        rows.append((center, R, np.array([hx, hy, hz]), (mt.CAR,) * 6, mats, inst, col, 0, -1,
                     dynamic))

    body_top = 0.28 + 0.42 * (height - 0.9)
    body_top = min(max(body_top, 0.85), 1.1)
    add(0.0, (0.30 + body_top) / 2, length / 2, width / 2, (body_top - 0.30) / 2, (mt.M_CAR,) * 6)
    cab_len = 0.52 * length if height < 1.6 else 0.62 * length
    cab_x = -0.06 * length if height < 1.6 else -0.1 * length
    glass = (mt.M_GLASS, mt.M_GLASS, mt.M_GLASS, mt.M_GLASS, mt.M_CAR, mt.M_CAR)
    add(cab_x, (body_top + height) / 2, cab_len / 2, width / 2 - 0.07,
        (height - body_top) / 2, glass)
    for ax in (0.33 * length, -0.31 * length):
        add(ax, 0.33, 0.33, width / 2 - 0.04, 0.33, (mt.M_RUBBER,) * 6)


def _pedestrian_rows(boxes: list[tuple], ells: list[tuple], base: np.ndarray, yaw: float,
                     dims: np.ndarray, color: np.ndarray, color2: np.ndarray, inst: int,
                     walked: float) -> None:
    """Append the boxes (legs, torso) and ellipsoid (head) of a walking pedestrian."""
    height, width, depth = (float(v) for v in dims)
    R = yaw_pitch(yaw)
    leg_len = 0.47 * height
    swing = 0.35 * np.sin(walked / 0.75 * np.pi)
    for side, sgn in ((-1.0, 1.0), (1.0, -1.0)):
        Rl = yaw_pitch(yaw, sgn * swing)
        hip = base + R @ np.array([0.0, side * width * 0.22, leg_len])
        center = hip + Rl @ np.array([0.0, 0.0, -leg_len / 2])
        boxes.append((center, Rl, np.array([0.07, 0.075, leg_len / 2]), (mt.PEDESTRIAN,) * 6,
                      (mt.M_CLOTH,) * 6, inst, tuple(float(c) for c in color2), 0, -1, True))
    torso_h = 0.33 * height
    center = base + R @ np.array([0.0, 0.0, leg_len + torso_h / 2])
    boxes.append((center, R, np.array([depth / 2, width / 2, torso_h / 2]), (mt.PEDESTRIAN,) * 6,
                  (mt.M_CLOTH,) * 6, inst, tuple(float(c) for c in color), 0, -1, True))
    head_r = 0.105 * height / 1.75
    head = base + np.array([0.0, 0.0, leg_len + torso_h + 0.02 + head_r * 1.15])
    ells.append((tuple(head), (head_r, head_r, head_r * 1.2), mt.PEDESTRIAN, mt.M_SKIN, inst,
                 (0.45, 0.32, 0.25), 0, True))


# --------------------------------------------------------------------------------- the builder


class _Builder:
    def __init__(self, seed: int, cfg: GarageConfig) -> None:
        self.seed = seed
        self.cfg = cfg
        self.lay = Layout(cfg)
        self.rng = np.random.default_rng([seed, 0x5EED])
        self.sb = SceneBuilder()
        self.decals = {g: DecalBuilder() for g in (G_COVERED, G_DECK, G_RAMP, G_STREET)}
        self.sign_rows: list[tuple[str, tuple, tuple]] = []
        self.agents: list[Agent | CrossingAgent] = []
        self.portals: list[tuple[float, ...]] = []
        r = self.rng
        self.paint_white = np.array([0.85, 0.85, 0.82]) * r.uniform(0.85, 1.0)
        self.paint_yellow = np.array([0.85, 0.62, 0.08]) * r.uniform(0.85, 1.0)
        self.level_colors = [np.array(c) for c in ([0.05, 0.2, 0.6], [0.6, 0.08, 0.05],
                                                    [0.05, 0.4, 0.15], [0.55, 0.35, 0.0])]
        r.shuffle(self.level_colors)
        self.concrete = np.array([0.50, 0.49, 0.46]) * r.uniform(0.85, 1.1)
        lay = self.lay
        self.zebra2_x = lay.x_rows0 + cfg.bay_width * (round(0.7 * cfg.n_bays) + 0.5)

    # ---- signs
    def sign_design(self, text: str, fg, bg) -> int:
        encode_text(text, SIGN_TEXT_LEN)  # validates the characters
        self.sign_rows.append((text, tuple(fg), tuple(bg)))
        return len(self.sign_rows) - 1

    def sign(self, center, half, yaw: float, text: str, fg, bg, inst: int | None = None) -> int:
        """A thin sign box (local x: width, y: thickness, z: height) with text on both faces."""
        design = self.sign_design(text, fg, bg)
        return self.sb.obox(center, half, yaw_pitch(yaw), mt.SIGN, mt.M_SIGN, inst=inst,
                            color=bg, param=design)

    # ---- build steps
    def build(self) -> World:
        self.floors()
        self.ramp()
        self.walls()
        self.pillars_beams_lights()
        self.walkways_and_stops()
        self.markings()
        self.parked_cars()
        self.railings_poles_signs()
        self.barriers()
        self.details()
        self.surroundings()
        self.make_agents()
        return self.finish()

    def floors(self) -> None:
        lay, sb = self.lay, self.sb
        L, W = lay.length, lay.width
        x0, x1, y0, y1 = lay.ramp_x0, lay.ramp_x1, lay.ramp_y0 - WALL, lay.ramp_y1 + WALL
        deck_rects = [(0.0, L, 0.0, y0), (0.0, x0, y0, W), (x1, L, y0, W), (x0, x1, y1, W)]
        sb.plane(0.0, True, [(0.0, L, 0.0, W)], mt.ROAD, mt.M_FLOOR_IN, decal_group=G_COVERED,
                 color=tuple(self.concrete * 0.85))
        sb.plane(lay.deck_z, True, deck_rects, mt.ROAD, mt.M_FLOOR_DECK, decal_group=G_DECK,
                 color=tuple(self.concrete * self.rng.uniform(0.9, 1.15)))
        sb.plane(lay.ceiling_z, False, deck_rects, mt.CEILING, mt.M_CEILING,
                 color=tuple(self.concrete * 1.05))
        far = 400.0
        street = [(-far, L + far, -far, 0.0), (-far, L + far, W, W + far), (-far, 0.0, 0.0, W),
                  (L, L + far, 0.0, W)]
        sb.plane(0.0, True, street, mt.ROAD, mt.M_ASPHALT, decal_group=G_STREET,
                 color=(0.16, 0.16, 0.17))

    def ramp(self) -> None:
        lay, sb, c = self.lay, self.sb, self.cfg
        x0, lt, lm = lay.ramp_x0, c.ramp_transition, c.ramp_main_length
        g = c.ramp_grade
        inst = sb.new_instance()
        pieces = [(x0, x0 + lt, g / 2)]
        n_main = max(1, int(np.ceil(lm / 6.0)))
        edges = np.linspace(x0 + lt, x0 + lt + lm, n_main + 1)
        pieces += [(edges[k], edges[k + 1], g) for k in range(n_main)]
        pieces.append((x0 + lt + lm, lay.ramp_x1, g / 2))
        thick = 0.3
        half_w = c.ramp_width / 2
        for xa, xb, grade in pieces:
            za, zb = float(lay.ramp_profile(np.array(xa))), float(lay.ramp_profile(np.array(xb)))
            theta = np.arctan(grade)
            R = yaw_pitch(0.0, theta)
            n_up = R @ np.array([0.0, 0.0, 1.0])
            mid_top = np.array([(xa + xb) / 2, lay.ramp_yc, (za + zb) / 2])
            center = mid_top - n_up * thick / 2
            half_len = np.hypot(xb - xa, zb - za) / 2
            cls = (mt.WALL, mt.WALL, mt.WALL, mt.WALL, mt.CEILING, mt.ROAD)
            mat = (mt.M_CONCRETE,) * 5 + (mt.M_RAMP,)
            sb.obox(center, (half_len, half_w, thick / 2), R, cls, mat, inst=inst,
                    color=tuple(self.concrete * 0.9), decal_group=G_RAMP)

    def walls(self) -> None:
        lay, sb = self.lay, self.sb
        L, W, D, C = lay.length, lay.width, lay.deck_z, lay.ceiling_z
        top = D + 1.0
        col = tuple(self.concrete * 1.1)
        wall = mt.WALL
        # Perimeter walls (floor to the deck parapet top); a gate in the west wall of the
        # covered level at aisle 1 (exit to the street).
        a1 = lay.aisles[0]
        g0, g1 = a1 - 3.0, a1 + 3.0
        inst = sb.new_instance()
        sb.box((-WALL, -WALL, 0.0), (L + WALL, 0.0, top), wall, mt.M_CONCRETE, inst=inst,
               color=col)
        sb.box((-WALL, W, 0.0), (L + WALL, W + WALL, top), wall, mt.M_CONCRETE, inst=inst,
               color=col)
        sb.box((L, 0.0, 0.0), (L + WALL, W, top), wall, mt.M_CONCRETE, inst=inst, color=col)
        sb.box((-WALL, 0.0, 0.0), (0.0, g0, top), wall, mt.M_CONCRETE, inst=inst, color=col)
        sb.box((-WALL, g1, 0.0), (0.0, W, top), wall, mt.M_CONCRETE, inst=inst, color=col)
        sb.box((-WALL, g0, C), (0.0, g1, top), wall, mt.M_CONCRETE, inst=inst, color=col)
        self.portals.append((-3.0, 0.0, g0, g1, 0.0, C))
        # Ramp trench: inner and outer walls from the covered floor to 0.3 m above the deck,
        # and the header wall over the ramp's lower end.
        x0, x1 = lay.ramp_x0, lay.ramp_x1
        t_top = D + 0.3
        inst = sb.new_instance()
        sb.box((x0 - WALL, lay.trench_y0, 0.0), (x1, lay.ramp_y0, t_top), wall, mt.M_CONCRETE,
               inst=inst, color=col, split=4.0)
        sb.box((x0 - WALL, lay.ramp_y1, 0.0), (x1, lay.ramp_y1 + WALL, t_top), wall,
               mt.M_CONCRETE, inst=inst, color=col, split=4.0)
        sb.box((x1, lay.trench_y0, C), (x1 + WALL, lay.ramp_y1 + WALL, t_top), wall,
               mt.M_CONCRETE, inst=inst, color=col)
        # wall closing the space under the ramp's upper end on the covered level
        sb.box((x0 - WALL, lay.ramp_y0, 0.0), (x0, lay.ramp_y1, C), wall, mt.M_CONCRETE,
               inst=inst, color=col)
        self.portals.append((x0, x1, lay.ramp_y0, lay.ramp_y1, C, D + 5.0))
        # Stair core in row A (two bays), from the covered floor to 3 m above the deck.
        bw = self.cfg.bay_width
        sx0 = lay.x_rows0 + 5 * bw
        self.stair = (sx0, sx0 + 2 * bw, 0.0, lay.rows[0].y0 + 3.5)
        inst = sb.new_instance()
        sb.box((sx0, 0.0, 0.0), (sx0 + 2 * bw, self.stair[3], D + 3.0), wall, mt.M_CONCRETE,
               inst=inst, color=tuple(self.concrete * 0.95), split=None)
        for z in (0.0, D):
            self.sign((sx0 + bw, self.stair[3] + 0.03, z + 2.35), (0.5, 0.02, 0.14), 0.0,
                      'EXIT', (0.9, 0.95, 0.9), (0.02, 0.35, 0.08))

    def pillars_beams_lights(self) -> None:
        lay, sb, c = self.lay, self.sb, self.cfg
        C = lay.ceiling_z
        span = lay.span
        n_span = int(round(c.row_length / span))
        xs = lay.x_rows0 + span * np.arange(n_span + 1)
        rows = lay.rows
        pillar_lines = [rows[0].y0, rows[1].y1, rows[3].y1]
        pcol = tuple(self.concrete * 1.15)
        level_color = self.level_colors[0]
        for j, yl in enumerate(pillar_lines):
            for k, x in enumerate(xs):
                if j == 2 and lay.ramp_x0 - 1.0 <= x <= lay.ramp_x1 + 1.0:
                    continue  # the trench wall carries the slab there
                if j == 0 and self.stair[0] - 0.5 <= x <= self.stair[1] + 0.5:
                    continue
                yc = yl - 0.3 if j != 1 else yl
                if j == 2:
                    yc = yl - 0.3
                if j == 0:
                    yc = yl - 0.3
                inst = sb.box((x - 0.3, yc - 0.3, 0.0), (x + 0.3, yc + 0.3, C), mt.PILLAR,
                              mt.M_PILLAR, color=pcol, param=j, split=None)
                text = f'{"ABD"[j]}{k + 1}'
                for side in (-1.0, 1.0):
                    if j == 0 and side < 0 or j == 2 and side > 0:
                        continue
                    self.sign((x, yc + side * 0.32, 2.1), (0.26, 0.015, 0.17), 0.0, text,
                              (0.95, 0.95, 0.95), tuple(level_color), inst=inst)
        # Beams under the slab along y at the pillar lines (interrupted by the ramp opening).
        inst = sb.new_instance()
        for x in xs:
            spans = [(0.0, lay.width)]
            if lay.ramp_x0 - 0.2 <= x <= lay.ramp_x1 + 0.2:
                spans = [(0.0, lay.trench_y0), (lay.ramp_y1 + WALL, lay.width)]
            for ya, yb in spans:
                sb.box((x - 0.2, ya, C - 0.5), (x + 0.2, yb, C), mt.CEILING, mt.M_CONCRETE,
                       inst=inst, color=tuple(self.concrete * 1.05), split=6.0)
        # Ceiling lights between the beams.
        lx = np.concatenate([[lay.x_rows0 - span / 2], xs + span / 2])
        lx = lx[(lx > 1.0) & (lx < lay.length - 1.0)]
        step = float(np.median(np.diff(lx)))
        lx = lx[0] + step * np.arange(len(lx))
        ly = np.array([(rows[0].y0 + rows[0].y1) / 2, lay.aisles[0], rows[1].y1, lay.aisles[1],
                       (rows[3].y0 + rows[3].y1) / 2, lay.ramp_yc])
        power = np.zeros((len(ly), len(lx)), np.float32)
        temp = self.rng.uniform(0.0, 1.0)
        lcolor = np.array([1.0, 0.93 + 0.05 * temp, 0.8 + 0.18 * temp], np.float32)
        z = C - 0.12
        for j, y in enumerate(ly):
            for i, x in enumerate(lx):
                if (lay.ramp_x0 - 1.0 <= x <= lay.ramp_x1 + 1.0
                        and lay.trench_y0 - 1.0 <= y <= lay.ramp_y1 + WALL + 1.0):
                    continue
                if self.stair[0] - 1 <= x <= self.stair[1] + 1 and y <= self.stair[3] + 1:
                    continue
                on = self.rng.random() > 0.06
                power[j, i] = self.rng.uniform(0.85, 1.0) if on else 0.0
                sb.box((x - 0.7, y - 0.13, z - 0.05), (x + 0.7, y + 0.13, z + 0.05), mt.LIGHT,
                       mt.M_LAMP if on else mt.M_METAL, color=tuple(lcolor), split=None,
                       param=1 if on else 0)
        self.lights = LightGrid(xs=lx, ys=ly, z=z, power=power, color=lcolor)

    def walkways_and_stops(self) -> None:
        lay, sb = self.lay, self.sb
        L = lay.length
        col = tuple(self.concrete * 1.2)
        faces = (mt.CURB, mt.CURB, mt.CURB, mt.CURB, mt.CURB, mt.SIDEWALK)
        mats = (mt.M_CURB,) * 5 + (mt.M_PAVER,)
        for z in (0.0, lay.deck_z):
            # south walkway (gap at the stair core door)
            sb.box((0.0, 0.0, z), (self.stair[0], WALK, z + 0.15), faces, mats, color=col)
            sb.box((self.stair[1], 0.0, z), (L, WALK, z + 0.15), faces, mats, color=col)
        # deck: north walkway along the parapet
        sb.box((0.0, lay.width - WALK, lay.deck_z), (L, lay.width, lay.deck_z + 0.15), faces,
               mats, color=col)
        # Wheel stops in every bay of both levels.
        bw = self.cfg.bay_width
        for z in (0.0, lay.deck_z):
            inst = sb.new_instance()
            for row in lay.rows:
                y = row.back + row.entry * 0.75
                for k in range(self.cfg.n_bays):
                    xc = lay.x_rows0 + (k + 0.5) * bw
                    if row.name == 'A' and self.stair[0] <= xc <= self.stair[1]:
                        continue
                    if self.rng.random() < 0.15:
                        continue
                    sb.box((xc - 0.8, y - 0.08, z), (xc + 0.8, y + 0.08, z + 0.11), mt.CURB,
                           mt.M_CURB, inst=inst, color=(0.55, 0.53, 0.5), split=None)

    def markings(self) -> None:
        lay, cfg, r = self.lay, self.cfg, self.rng
        bw = cfg.bay_width
        for level, group in ((0, G_COVERED), (1, G_DECK)):
            db = self.decals[group]
            line_col = self.paint_white if (level == 1 or r.random() < 0.5) else self.paint_yellow
            for ri, row in enumerate(lay.rows):
                ym = (row.y0 + row.y1) / 2
                hl = (row.y1 - row.y0) / 2
                for k in range(cfg.n_bays + 1):
                    x = lay.x_rows0 + k * bw
                    if row.name == 'A' and self.stair[0] + 0.1 < x < self.stair[1] - 0.1:
                        continue
                    db.add(RECT, (x, ym), np.pi / 2, hl - 0.02, 0.06, mt.PARKING_LINE,
                           tuple(line_col), inst=self.sb.new_instance(),
                           wear=float(r.uniform(0.1, 0.5)))
                for k in range(cfg.n_bays):
                    xc = lay.x_rows0 + (k + 0.5) * bw
                    if row.name == 'A' and self.stair[0] <= xc <= self.stair[1]:
                        continue
                    # bay number near the aisle edge, readable when driving in
                    heading = np.pi / 2 if row.entry < 0 else -np.pi / 2
                    yn = row.front - row.entry * 0.75
                    db.add(TEXT, (xc, yn), heading, 0.3, 0.55, mt.ROAD_MARKING, tuple(line_col),
                           inst=self.sb.new_instance(), wear=float(r.uniform(0.1, 0.5)),
                           text=f'{level}{ri * cfg.n_bays + k + 1:02d}'[-3:])
                    if r.random() < 0.55:
                        yc = row.back + row.entry * r.uniform(1.5, 3.2)
                        db.add(STAIN, (xc + r.normal(0, 0.2), yc), r.uniform(0, np.pi),
                               r.uniform(0.3, 0.8), r.uniform(0.2, 0.5), -1,
                               wear=float(r.uniform(0.25, 0.6)))
            # dashed lane dividers along the aisles and the cross aisles
            div_col = tuple(self.paint_yellow)
            for ya in lay.aisles:
                for x in np.arange(lay.x_rows0 + 2.0, lay.x_rows1 - 2.0, 6.0):
                    db.add(RECT, (x + 1.5, ya), 0.0, 1.5, 0.06, mt.LANE_DIVIDER, div_col,
                           inst=self.sb.new_instance(), wear=float(r.uniform(0.1, 0.4)))
                # arrows in both lanes near the aisle ends (keep right)
                for x, sgn in ((lay.x_rows0 + 3.5, 1.0), (lay.x_rows1 - 3.5, -1.0)):
                    db.add(ARROW, (x, ya - sgn * LANE), 0.0 if sgn > 0 else np.pi, 1.6, 0.45,
                           mt.ROAD_MARKING, tuple(self.paint_white), inst=self.sb.new_instance(),
                           wear=float(r.uniform(0.1, 0.4)))
            for xa in (lay.x_west, lay.x_east):
                for y in np.arange(WALK + 3.0, lay.rows[3].y1 - 3.0, 6.0):
                    db.add(RECT, (xa, y + 1.5), np.pi / 2, 1.5, 0.06, mt.LANE_DIVIDER, div_col,
                           inst=self.sb.new_instance(), wear=float(r.uniform(0.1, 0.4)))
            # zebra crossing from the stair core door across aisle 1
            xz = (self.stair[0] + self.stair[1]) / 2
            inst = self.sb.new_instance()
            y_a, y_b = lay.rows[0].y1, lay.rows[1].y0
            for dx in (-1.5, -0.5, 0.5, 1.5):
                db.add(RECT, (xz + dx, (y_a + y_b) / 2), np.pi / 2, (y_b - y_a) / 2 - 0.2, 0.25,
                       mt.ROAD_MARKING, tuple(self.paint_white), inst=inst, wear=0.2)
            # zebra crossing across aisle 2 between rows C and D
            inst = self.sb.new_instance()
            y_a, y_b = lay.rows[2].y1, lay.rows[3].y0
            for dx in (-1.5, -0.5, 0.5, 1.5):
                db.add(RECT, (self.zebra2_x + dx, (y_a + y_b) / 2), np.pi / 2,
                       (y_b - y_a) / 2 - 0.2, 0.25, mt.ROAD_MARKING, tuple(self.paint_white),
                       inst=inst, wear=0.2)
            # level lettering in the cross aisles
            for xa, hd in ((lay.x_west, np.pi / 2), (lay.x_east, -np.pi / 2)):
                db.add(TEXT, (xa, lay.aisles[1] - 2.0 * np.sign(np.sin(hd))), hd, 1.0, 1.6,
                       mt.ROAD_MARKING, tuple(self.paint_white), inst=self.sb.new_instance(),
                       wear=0.25, text=f'P{level}')
            # tyre marks / stains in the aisles
            for _ in range(14):
                x = r.uniform(1.0, lay.length - 1.0)
                y = lay.aisles[int(r.integers(2))] + r.normal(0, 1.2)
                db.add(STAIN, (x, y), r.uniform(-0.3, 0.3), r.uniform(0.8, 2.5),
                       r.uniform(0.15, 0.4), -1, wear=float(r.uniform(0.15, 0.4)))
        # covered level: stop line and "EXIT" at the gate, stop line at the ramp bottom
        db = self.decals[G_COVERED]
        a1 = lay.aisles[0]
        db.add(RECT, (3.0, a1 + LANE), 0.0, 0.2, 1.4, mt.ROAD_MARKING, tuple(self.paint_white),
               inst=self.sb.new_instance(), wear=0.2)
        db.add(TEXT, (5.5, a1 + LANE), np.pi, 0.9, 1.3, mt.ROAD_MARKING, tuple(self.paint_white),
               inst=self.sb.new_instance(), wear=0.2, text='EXIT')
        # ramp: solid centre line, arrows, lettering
        dr = self.decals[G_RAMP]
        x0, x1 = lay.ramp_x0, lay.ramp_x1
        n = int(np.ceil((x1 - x0 - 1.0) / 3.0))
        xs = np.linspace(x0 + 0.5, x1 - 0.5, n + 1)
        inst = self.sb.new_instance()
        for xa, xb in zip(xs[:-1], xs[1:]):
            dr.add(RECT, ((xa + xb) / 2, lay.ramp_yc), 0.0, (xb - xa) / 2 + 0.01, 0.07,
                   mt.LANE_DIVIDER, tuple(self.paint_yellow), inst=inst, wear=0.15)
        for x, sgn in ((x0 + 4.5, 1.0), (x1 - 4.5, -1.0), (x1 - 12.0, 1.0), (x0 + 12.0, -1.0)):
            dr.add(ARROW, (x, lay.ramp_yc - sgn * LANE), 0.0 if sgn > 0 else np.pi, 1.6, 0.45,
                   mt.ROAD_MARKING, tuple(self.paint_white), inst=self.sb.new_instance(),
                   wear=0.2)
        dr.add(TEXT, ((x0 + x1) / 2, lay.ramp_yc - LANE), 0.0, 0.8, 1.2, mt.ROAD_MARKING,
               tuple(self.paint_white), inst=self.sb.new_instance(), wear=0.3, text='SLOW')
        for _ in range(6):
            dr.add(STAIN, (r.uniform(x0 + 2, x1 - 2), lay.ramp_yc + r.normal(0, 1.5)),
                   r.uniform(-0.2, 0.2), r.uniform(1.0, 3.0), r.uniform(0.15, 0.3), -1,
                   wear=float(r.uniform(0.15, 0.35)))

    def parked_cars(self) -> None:
        lay, cfg, r = self.lay, self.cfg, self.rng
        bw = cfg.bay_width
        for z in (0.0, lay.deck_z):
            occ = cfg.occupancy * (1.0 if z == 0.0 else 0.8)
            for row in lay.rows:
                for k in range(cfg.n_bays):
                    xc = lay.x_rows0 + (k + 0.5) * bw
                    if row.name == 'A' and self.stair[0] - 0.5 <= xc <= self.stair[1] + 0.5:
                        continue
                    if r.random() >= occ:
                        continue
                    dims = _CAR_TYPES[r.integers(len(_CAR_TYPES))].copy()
                    dims *= r.uniform(0.97, 1.03, 3)
                    color = _CAR_COLORS[r.integers(len(_CAR_COLORS))] * r.uniform(0.9, 1.1)
                    nose_in = r.random() < 0.75
                    yaw = -np.pi / 2 * row.entry if nose_in else np.pi / 2 * row.entry
                    # nose 0.35..0.65 m from the back line; long cars closer (they may
                    # still stick out of the bay by a few decimetres)
                    gap = min(0.35 + r.uniform(0.0, 0.3), max(0.1, cfg.bay_depth - dims[0]))
                    y = row.back + row.entry * (gap + dims[0] / 2)
                    x = xc + r.uniform(-0.12, 0.12)
                    rows: list[tuple] = []
                    _car_rows(rows, np.array([x, y, z]), yaw, dims, color,
                              self.sb.new_instance(), dynamic=False)
                    for row_ in rows:
                        self.sb.obox(row_[0], row_[2], row_[1], row_[3], row_[4], inst=row_[5],
                                     color=row_[6])

    def railings_poles_signs(self) -> None:
        lay, sb, r = self.lay, self.sb, self.rng
        D = lay.deck_z
        metal = (0.55, 0.56, 0.58)
        rail_inst = sb.new_instance()

        def railing(xa: float, ya: float, xb: float, yb: float, z0: float, height: float) -> None:
            n = max(1, int(np.ceil(np.hypot(xb - xa, yb - ya) / 2.0)))
            for t in np.linspace(0.0, 1.0, n + 1):
                x, y = xa + t * (xb - xa), ya + t * (yb - ya)
                sb.box((x - 0.03, y - 0.03, z0), (x + 0.03, y + 0.03, z0 + height), mt.RAILING,
                       mt.M_METAL, inst=rail_inst, color=metal, split=None)
            for zr in (z0 + height - 0.03, z0 + height * 0.5):
                lo = (min(xa, xb) - 0.03, min(ya, yb) - 0.03, zr - 0.03)
                hi = (max(xa, xb) + 0.03, max(ya, yb) + 0.03, zr + 0.03)
                sb.box(lo, hi, mt.RAILING, mt.M_METAL, inst=rail_inst, color=metal, split=6.0)

        L, W = lay.length, lay.width
        top = D + 1.0
        railing(0.0, 0.1, L, 0.1, top, 0.3)
        railing(0.0, W - 0.1, L, W - 0.1, top, 0.3)
        railing(0.1, 0.0, 0.1, W, top, 0.3)
        railing(L - 0.1, 0.0, L - 0.1, W, top, 0.3)
        x0, x1 = lay.ramp_x0, lay.ramp_x1
        for y in (lay.trench_y0 + WALL / 2, lay.ramp_y1 + WALL / 2):
            railing(x0 + 0.5, y, x1, y, D + 0.3, 0.8)
        railing(x1 + WALL / 2, lay.trench_y0, x1 + WALL / 2, lay.ramp_y1 + WALL, D + 0.3, 0.8)
        # Deck light poles along the row B/C line and the walkways, with lamp heads.
        yb = lay.rows[1].y1
        pole_inst = sb.new_instance()
        for x in np.arange(lay.x_rows0, lay.x_rows1 + 0.1, 2 * lay.span):
            for y, arm in ((yb, 1.0), (0.6, 1.0), (W - 0.6, -1.0)):
                sb.cylinder(x, y, D, D + 6.0, 0.09, mt.POLE, mt.M_METAL, inst=pole_inst,
                            color=(0.4, 0.42, 0.45))
                sb.box((x - 0.04, y, D + 5.9), (x + 0.04, y + arm * 1.2, D + 5.98), mt.POLE,
                       mt.M_METAL, inst=pole_inst, color=(0.4, 0.42, 0.45), split=None) \
                    if arm > 0 else \
                    sb.box((x - 0.04, y - 1.2, D + 5.9), (x + 0.04, y, D + 5.98), mt.POLE,
                           mt.M_METAL, inst=pole_inst, color=(0.4, 0.42, 0.45), split=None)
                ly = y + arm * 1.2
                sb.box((x - 0.35, ly - 0.18, D + 5.78), (x + 0.35, ly + 0.18, D + 5.92), mt.LIGHT,
                       mt.M_METAL, color=(0.8, 0.8, 0.75), split=None)
        # Parking signs on the deck poles (blue P).
        for x in np.arange(lay.x_rows0, lay.x_rows1 + 0.1, 4 * lay.span):
            self.sign((x, yb + 0.12, D + 3.2), (0.35, 0.02, 0.35), 0.0, 'P', (0.95, 0.95, 0.95),
                      (0.05, 0.2, 0.6))
        # Ramp entry signs: level and speed limit on poles, bollards.
        for (x, yaw, text) in ((x0 - 2.0, np.pi / 2, 'P0 >'), (x1 + 2.0, -np.pi / 2, 'P1 <')):
            z = D if x < x0 else 0.0
            if x < x0:
                # on the deck, next to the inner trench wall
                px, py = x, lay.trench_y0 - 0.4
            else:
                px, py = x, lay.ramp_y1 - 0.4
            if z == 0.0:
                py = lay.width - 0.4
            sb.cylinder(px, py, z, z + 2.6, 0.05, mt.POLE, mt.M_METAL, color=(0.5, 0.5, 0.52))
            self.sign((px, py, z + 2.3), (0.45, 0.02, 0.2), yaw + np.pi / 2, text,
                      (0.95, 0.95, 0.95), tuple(self.level_colors[1]))
            self.sign((px, py, z + 1.7), (0.22, 0.02, 0.22), yaw + np.pi / 2, '10', (0.05,) * 3,
                      (0.9, 0.9, 0.9))
        for k in range(4):
            sb.cylinder(x0 - 1.0 - 1.5 * k, lay.trench_y0 - 0.5, D, D + 0.9, 0.1, mt.POLE,
                        mt.M_STRIPES, color=(0.85, 0.65, 0.05), param=1)
        # Height limit sign over the ramp's lower end (facing the covered level) and hanging
        # exit signs under the beams of the covered level.
        self.sign((x1 + WALL + 0.03, lay.ramp_yc, lay.ceiling_z - 0.25), (0.6, 0.02, 0.2),
                  np.pi / 2, '2.1m', (0.05, 0.05, 0.05), (0.95, 0.8, 0.1))
        span = lay.span
        for k, x in enumerate(np.arange(lay.x_rows0 + span, lay.x_rows1, 2 * span)):
            for ya in lay.aisles:
                arrow = '<' if (k + int(ya)) % 2 else '>'
                self.sign((x + 0.05, ya, lay.ceiling_z - 0.75), (0.5, 0.03, 0.15), np.pi / 2,
                          f'EXIT{arrow}', (0.9, 0.95, 0.9), (0.02, 0.35, 0.08))
        del r

    def details(self) -> None:
        """Wall signs, fire-hose cabinets and sprinkler pipes of the covered level."""
        lay, sb = self.lay, self.sb
        C, L, W = lay.ceiling_z, lay.length, lay.width
        # big level sign on the east wall facing the north-east lane, exit sign on the north wall
        self.sign((L - 0.03, lay.ramp_yc, 1.9), (0.7, 0.02, 0.45), np.pi / 2, 'P0',
                  (0.95, 0.95, 0.95), tuple(self.level_colors[0]))
        self.sign(((lay.ramp_x1 + L) / 2, W - 0.03, 2.0), (0.6, 0.02, 0.15), 0.0, 'EXIT<',
                  (0.9, 0.95, 0.9), (0.02, 0.35, 0.08))
        # fire-hose cabinets every 3 spans on the south and north walls
        for x in np.arange(lay.x_rows0 + lay.span / 2, L - 2.0, 3 * lay.span):
            for y, yaw in ((0.03, 0.0), (W - 0.03, np.pi)):
                if y > 1.0 and lay.ramp_x0 - 1.0 < x < lay.ramp_x1 + 1.0:
                    continue
                if y < 1.0 and self.stair[0] - 1.0 < x < self.stair[1] + 1.0:
                    continue
                self.sign((x, y + (0.1 if y < 1.0 else -0.1), 1.3), (0.35, 0.1, 0.4), yaw,
                          'FIRE', (0.95, 0.95, 0.95), (0.6, 0.04, 0.03))
        # sprinkler mains under the slab along x (interrupted at the ramp opening)
        inst = sb.new_instance()
        for y in (lay.aisles[0] + 2.2, lay.aisles[1] - 2.2):
            sb.box((0.3, y - 0.06, C - 0.72), (L - 0.3, y + 0.06, C - 0.6), mt.CEILING,
                   mt.M_METAL, inst=inst, color=(0.55, 0.12, 0.1), split=6.0)
        y = lay.ramp_y1 + WALL + 0.6
        for xa, xb in ((0.3, lay.ramp_x0 - 0.5), (lay.ramp_x1 + 0.8, L - 0.3)):
            sb.box((xa, y - 0.06, C - 0.72), (xb, y + 0.06, C - 0.6), mt.CEILING, mt.M_METAL,
                   inst=inst, color=(0.55, 0.12, 0.1), split=6.0)

    def barriers(self) -> None:
        lay, sb, r = self.lay, self.sb, self.rng
        a1 = lay.aisles[0]
        # Boom barrier at the covered level's street gate (closed).
        inst = sb.new_instance()
        sb.box((0.6, a1 - 2.9, 0.0), (1.0, a1 - 2.5, 1.05), mt.BARRIER, mt.M_STRIPES, inst=inst,
               color=(0.9, 0.5, 0.05), split=None, param=0)
        sb.box((0.72, a1 - 2.5, 0.92), (0.88, a1 + 2.9, 1.04), mt.BARRIER, mt.M_STRIPES, inst=inst,
               color=(0.85, 0.05, 0.03), split=None, param=2)
        # Ticket machine next to it.
        self.sign((1.6, a1 - 2.7, 1.55), (0.25, 0.02, 0.15), np.pi / 2, 'PAY', (0.95,) * 3,
                  (0.05, 0.2, 0.6))
        sb.box((1.4, a1 - 3.0, 0.0), (1.8, a1 - 2.4, 1.4), mt.BARRIER, mt.M_METAL,
               color=(0.3, 0.32, 0.36), split=None)
        # Jersey barriers closing the covered level's dead-end lane north of row D.
        x_end = lay.ramp_x0 - 1.5
        for k in range(3):
            y0 = lay.trench_y0 + 0.5 + 2.1 * k
            sb.box((x_end - 0.6, y0, 0.0), (x_end, y0 + 2.0, 0.8), mt.BARRIER, mt.M_STRIPES,
                   color=(0.9, 0.9, 0.88), split=None, param=3)
        # Cones on the deck near the east end of row D.
        for k in range(4):
            sb.cylinder(lay.x_rows1 - 1.0 - 1.2 * k, lay.rows[3].y0 - 0.4, lay.deck_z,
                        lay.deck_z + 0.7, 0.13, mt.BARRIER, mt.M_STRIPES,
                        color=(0.95, 0.35, 0.02), param=1)
        del r

    def surroundings(self) -> None:
        lay, sb, r = self.lay, self.sb, self.rng
        L, W = lay.length, lay.width
        curb_faces = (mt.CURB, mt.CURB, mt.CURB, mt.CURB, mt.CURB, mt.SIDEWALK)
        mats = (mt.M_CURB,) * 5 + (mt.M_PAVER,)
        pav = (0.55, 0.52, 0.48)
        a1 = lay.aisles[0]
        sw, street = 3.0, 10.0
        # Inner sidewalk ring (gap at the gate).
        sb.box((-WALL - sw, -WALL - sw, 0.0), (L + WALL + sw, -WALL, 0.12), curb_faces, mats,
               color=pav)
        sb.box((-WALL - sw, W + WALL, 0.0), (L + WALL + sw, W + WALL + sw, 0.12), curb_faces,
               mats, color=pav)
        sb.box((L + WALL, -WALL, 0.0), (L + WALL + sw, W + WALL, 0.12), curb_faces, mats,
               color=pav)
        sb.box((-WALL - sw, -WALL, 0.0), (-WALL, a1 - 3.0, 0.12), curb_faces, mats, color=pav)
        sb.box((-WALL - sw, a1 + 3.0, 0.0), (-WALL, W + WALL, 0.12), curb_faces, mats, color=pav)
        # Outer sidewalks beyond the streets.
        o = WALL + sw + street
        sb.box((-o - sw, -o - sw, 0.0), (L + o + sw, -o, 0.12), curb_faces, mats, color=pav)
        sb.box((-o - sw, W + o, 0.0), (L + o + sw, W + o + sw, 0.12), curb_faces, mats, color=pav)
        sb.box((-o - sw, -o, 0.0), (-o, W + o, 0.12), curb_faces, mats, color=pav)
        sb.box((L + o, -o, 0.0), (L + o + sw, W + o, 0.12), curb_faces, mats, color=pav)
        # Street markings: dashed centre lines, zebra crossing at the gate.
        ds = self.decals[G_STREET]
        mid = WALL + sw + street / 2
        dash = tuple(self.paint_white)
        for x in np.arange(-mid, L + mid, 6.0):
            for y in (-mid, W + mid):
                ds.add(RECT, (x + 1.5, y), 0.0, 1.5, 0.07, mt.LANE_DIVIDER, dash,
                       inst=self.sb.new_instance(), wear=0.3)
        for y in np.arange(-mid + 6.0, W + mid - 3.0, 6.0):
            for x in (-mid, L + mid):
                ds.add(RECT, (x, y + 1.5), np.pi / 2, 1.5, 0.07, mt.LANE_DIVIDER, dash,
                       inst=self.sb.new_instance(), wear=0.3)
        inst = sb.new_instance()
        for k in range(6):
            ds.add(RECT, (-WALL - sw - street / 2, a1 - 5.5 + 0.9 * k + 2.5 + 0.45), 0.0,
                   street / 2 - 0.5, 0.22, mt.ROAD_MARKING, dash, inst=inst, wear=0.3)
        # Trees and street lamps on the sidewalks.
        tree_pos = []
        for x in np.arange(-8.0, L + 8.0, 9.0):
            for y in (-WALL - sw / 2, W + WALL + sw / 2, -o - sw / 2, W + o + sw / 2):
                tree_pos.append((x + r.uniform(-1, 1), y))
        for y in np.arange(4.0, W, 9.0):
            for x in (L + WALL + sw / 2, -o - sw / 2, L + o + sw / 2):
                tree_pos.append((x, y + r.uniform(-1, 1)))
        for x, y in tree_pos:
            if r.random() < 0.25:
                continue
            if abs(y - a1) < 6.0 and x < 0:
                continue
            h = r.uniform(2.2, 3.2)
            inst = sb.new_instance()
            sb.cylinder(x, y, 0.1, h + 0.5, r.uniform(0.12, 0.2), mt.VEGETATION, mt.M_BARK,
                        inst=inst, color=(0.25, 0.18, 0.12))
            rad = r.uniform(1.5, 2.6)
            sb.ellipsoid((x, y, h + rad * 0.9), (rad, rad * r.uniform(0.85, 1.15), rad * 1.2),
                         mt.VEGETATION, mt.M_FOLIAGE, inst=inst,
                         color=tuple(np.array([0.09, 0.16, 0.05]) * r.uniform(0.7, 1.3)))
        for x in np.arange(-o - sw / 2, L + o + sw, 18.0):
            for y in (-o - 0.4, W + o + 0.4):
                sb.cylinder(x, y, 0.1, 7.5, 0.1, mt.POLE, mt.M_METAL, color=(0.35, 0.36, 0.38))
                sb.box((x - 0.3, y - 0.15, 7.35), (x + 0.3, y + 0.15, 7.5), mt.LIGHT, mt.M_METAL,
                       color=(0.8, 0.8, 0.75), split=None)
        # Hedges along part of the inner sidewalk.
        for x0 in np.arange(4.0, L - 6.0, 14.0):
            if r.random() < 0.5:
                sb.box((x0, W + WALL + 0.2, 0.12), (x0 + 5.0, W + WALL + 1.0, 0.9), mt.VEGETATION,
                       mt.M_FOLIAGE, color=(0.08, 0.15, 0.05), split=None)
        # City blocks behind the outer sidewalks and a far skyline.
        b0 = o + sw + 1.0
        shop = ['SHOP', 'BANK', 'HOTEL', 'CAFE', 'PHARM', 'BAKERY', 'BOOKS', 'SUSHI', 'FOOD']
        sides = [((-b0 - 40.0, L + b0 + 40.0), -1, 'y', -b0),
                 ((-b0 - 40.0, L + b0 + 40.0), 1, 'y', W + b0),
                 ((-b0, W + b0), -1, 'x', -b0), ((-b0, W + b0), 1, 'x', L + b0)]
        for (a_lo, a_hi), sgn, axis, base in sides:
            a = a_lo
            while a < a_hi:
                wdt = r.uniform(10.0, 24.0)
                if r.random() < 0.15:
                    a += wdt * 0.6  # side street / gap
                    continue
                dep = r.uniform(10.0, 18.0)
                hgt = r.choice([r.uniform(7.0, 14.0), r.uniform(14.0, 32.0)])
                lo_b, hi_b = base, base + sgn * dep
                lo_b, hi_b = min(lo_b, hi_b), max(lo_b, hi_b)
                a_end = min(a + wdt, a_hi)
                if a_end - a < 4.0:
                    break
                tint = np.array([0.45, 0.42, 0.38]) * r.uniform(0.6, 1.3)
                tint = np.clip(tint + r.normal(0, 0.04, 3), 0.05, 0.9)
                if axis == 'y':
                    lo, hi = (a, lo_b, 0.0), (a_end - 0.5, hi_b, hgt)
                else:
                    lo, hi = (lo_b, a, 0.0), (hi_b, a_end - 0.5, hgt)
                inst = sb.box(lo, hi, mt.BUILDING, mt.M_FACADE, color=tuple(tint),
                              param=int(r.integers(1 << 20)), split=None)
                if r.random() < 0.5:
                    text = shop[int(r.integers(len(shop)))]
                    mid_a = (a + a_end - 0.5) / 2
                    if axis == 'y':
                        face = base - sgn * 0.03
                        self.sign((mid_a, face, 3.6), (0.35 * len(text), 0.03, 0.4), 0.0, text,
                                  (0.95, 0.95, 0.9), tuple(r.uniform(0.05, 0.5, 3)), inst=inst)
                    else:
                        face = base - sgn * 0.03
                        self.sign((face, mid_a, 3.6), (0.35 * len(text), 0.03, 0.4), np.pi / 2,
                                  text, (0.95, 0.95, 0.9), tuple(r.uniform(0.05, 0.5, 3)),
                                  inst=inst)
                a = a_end
        cx, cy = L / 2, W / 2
        for ang in np.linspace(0, 2 * np.pi, 28, endpoint=False):
            ang += r.uniform(-0.08, 0.08)
            dist = r.uniform(110.0, 200.0)
            x, y = cx + dist * np.cos(ang), cy + dist * np.sin(ang)
            hw = r.uniform(8.0, 20.0)
            hgt = r.uniform(15.0, 60.0)
            tint = np.array([0.45, 0.44, 0.43]) * r.uniform(0.5, 1.3)
            sb.box((x - hw, y - hw, 0.0), (x + hw, y + hw, hgt), mt.BUILDING, mt.M_FACADE,
                   color=tuple(np.clip(tint, 0.05, 0.9)), param=int(r.integers(1 << 20)),
                   split=None)

    def make_agents(self) -> None:
        lay, cfg, r = self.lay, self.cfg, self.rng
        a1, a2 = lay.aisles
        loop = np.array([[lay.x_west, a1], [lay.x_east, a1], [lay.x_east, a2],
                         [lay.x_west, a2]])
        # reversed loop with keep-right offset: opposite lanes of the ego car's loops
        rev = round_corners(loop[::-1], 6.0, 0.2, closed=True)
        lane = Polyline(offset(rev, LANE, closed=True), closed=True)
        for i in range(cfg.n_moving_cars):
            level_z = lay.deck_z if i % 2 == 0 else 0.0
            dims = _CAR_TYPES[r.integers(len(_CAR_TYPES))] * r.uniform(0.97, 1.03, 3)
            self.agents.append(Agent(
                kind='car', path=lane, level_z=level_z, speed=float(r.uniform(2.5, 4.5)),
                phase=float(r.uniform(0, lane.length)), period=float(r.uniform(15, 30)),
                pingpong=False, dims=dims, color=_CAR_COLORS[r.integers(len(_CAR_COLORS))],
                color2=np.zeros(3), inst=self.sb.new_instance()))
        walk_paths = [
            (np.array([[2.0, 0.75], [self.stair[0] - 0.6, 0.75]]), 0.15),
            (np.array([[self.stair[1] + 0.6, 0.75], [lay.length - 2.0, 0.75]]), 0.15),
            (np.array([[2.0, lay.width - 0.75], [lay.length - 2.0, lay.width - 0.75]]),
             lay.deck_z + 0.15),
            (np.array([[-30.0, -WALL - 1.5], [lay.length + 20.0, -WALL - 1.5]]), 0.12),
            (np.array([[-10.0, lay.width + WALL + 1.5], [lay.length + 10.0,
                                                         lay.width + WALL + 1.5]]), 0.12),
        ]
        for i in range(cfg.n_pedestrians):
            pts, z = walk_paths[i % len(walk_paths)]
            if i % len(walk_paths) < 2 and (i // len(walk_paths)) % 2 == 1:
                z = lay.deck_z + 0.15
            path = Polyline(pts, closed=False)
            self.agents.append(Agent(
                kind='pedestrian', path=path, level_z=z, speed=float(r.uniform(1.0, 1.5)),
                phase=float(r.uniform(0, path.length)), period=float(r.uniform(8, 20)),
                pingpong=True, dims=np.array([r.uniform(1.55, 1.9), r.uniform(0.4, 0.5),
                                              r.uniform(0.22, 0.3)]),
                color=r.uniform(0.03, 0.6, 3), color2=r.uniform(0.02, 0.3, 3),
                inst=self.sb.new_instance()))
        self.crossing_pedestrians()

    def crossing_pedestrians(self) -> None:
        """Pedestrians crossing the aisles on the two zebra crossings of each level, timed so
        that the ego car (on its long drive) is never near the crossing meanwhile."""
        from semfeat_ros.sim.trajectory import Trajectory

        lay, r = self.lay, self.rng
        traj = Trajectory(lay)
        times = np.arange(0.0, traj.duration + 120.0, 0.25)
        ego = np.array([traj.sample(t).T_map_base[:3, 3] for t in times])
        crossings = [((self.stair[0] + self.stair[1]) / 2, lay.aisles[0],
                      self.stair[3] + 0.6, lay.rows[1].y0 - 0.2),
                     (self.zebra2_x, lay.aisles[1], lay.rows[2].y1 + 0.25,
                      lay.rows[3].y0 - 0.25)]
        for (xz, ya, y0, y1), z in [(c, z) for c in crossings for z in (0.0, lay.deck_z)]:
            speed = float(r.uniform(1.1, 1.4))
            a, b = np.array([xz, y0]), np.array([xz, y1])
            dur = float(np.linalg.norm(b - a) / speed)
            # ego near the crossing on this level (with margins for the car's length)
            near = ((np.abs(ego[:, 0] - xz) < 12.0) & (np.abs(ego[:, 1] - ya) < 6.0)
                    & (np.abs(ego[:, 2] - z) < 1.0))
            starts = []
            t = float(r.uniform(0.0, 6.0))
            while t < times[-1] - dur:
                win = (times >= t - 1.0) & (times <= t + dur + 1.0)
                if near[win].any():
                    t += 0.5
                    continue
                starts.append(t)
                t += dur + float(r.uniform(2.0, 8.0))
            self.agents.append(CrossingAgent(
                start=a, end=b, level_z=z + 0.0, speed=speed, starts=np.array(starts),
                dims=np.array([r.uniform(1.55, 1.9), r.uniform(0.4, 0.5), r.uniform(0.22, 0.3)]),
                color=r.uniform(0.03, 0.6, 3), color2=r.uniform(0.02, 0.3, 3),
                inst=self.sb.new_instance()))

    def finish(self) -> World:
        r = self.rng
        elev = np.radians(r.uniform(25.0, 60.0))
        azim = r.uniform(0.0, 2 * np.pi)
        sun_dir = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim),
                            np.sin(elev)])
        sun_color = np.array([1.0, 0.93, 0.82]) * 3.2 * np.sin(elev) ** 0.3
        haze = r.uniform(0.0, 1.0)
        zenith = np.array([0.18, 0.32, 0.75]) * (1.0 - 0.4 * haze) + 0.25 * haze
        horizon = np.array([0.72, 0.80, 0.92]) * (1.0 + 0.15 * haze)
        sky_color = np.array([0.45, 0.55, 0.75]) * 1.1
        designs = self.sign_rows
        signs = SignDesigns(
            codes=np.array([encode_text(t, SIGN_TEXT_LEN) for t, _, _ in designs],
                           np.int16).reshape(-1, SIGN_TEXT_LEN),
            n_chars=np.array([len(t) for t, _, _ in designs], np.int16),
            fg=np.array([f for _, f, _ in designs], np.float32).reshape(-1, 3),
            bg=np.array([b for _, _, b in designs], np.float32).reshape(-1, 3))
        return World(
            seed=self.seed, config=self.cfg, layout=self.lay,
            boxes=self.sb.finish_boxes(), ellipsoids=self.sb.finish_ellipsoids(),
            cylinders=self.sb.finish_cylinders(), planes=self.sb.planes,
            decals={g: b.finish() for g, b in self.decals.items()},
            textures=make_texture_bank(self.seed), lights=self.lights, signs=signs,
            agents=self.agents, sun_dir=sun_dir, sun_color=sun_color.astype(np.float32),
            sky_color=sky_color.astype(np.float32), zenith=zenith.astype(np.float32),
            horizon=horizon.astype(np.float32),
            indoor_ambient=(np.array([0.05, 0.05, 0.05]) * r.uniform(0.8, 1.3)).astype(
                np.float32),
            portals=np.array(self.portals, np.float64).reshape(-1, 6))


def build_world(seed: int, config: GarageConfig | None = None) -> World:
    """Generate the garage world of ``seed`` (deterministic)."""
    return _Builder(int(seed), config or GarageConfig()).build()
