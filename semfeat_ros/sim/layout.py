"""Derived dimensions of the garage (all in metres, map frame: x east, y north, z up).

The footprint is ``[0, length] x [0, width]``. From south to north: a walkway, bay row A, aisle 1,
bay rows B and C back to back, aisle 2, bay row D, then the ramp trench (two walls around the
two-lane ramp) and a walkway. Cross aisles run north-south at both ends of the rows. The covered
level's floor is at z = 0; the open deck's floor at z = ``level_height``; the ramp descends from
the deck at ``ramp_x0`` to the covered floor at ``ramp_x1`` (heading east).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.sim.config import GarageConfig

WALL = 0.3  # wall thickness (m)
WALK = 1.5  # walkway width (m)
LANE = 1.6  # lane centre offset from an aisle's centreline (m)


@dataclass(frozen=True)
class Row:
    """A row of parking bays: y range, the side the cars enter from (+1: north, -1: south)."""

    name: str
    y0: float
    y1: float
    entry: int  # +1: from the aisle north of the row, -1: from the south

    @property
    def back(self) -> float:
        """y of the row's back line (where car noses point when parked nose-in)."""
        return self.y0 if self.entry > 0 else self.y1

    @property
    def front(self) -> float:
        """y of the row's aisle edge."""
        return self.y1 if self.entry > 0 else self.y0


@dataclass(frozen=True)
class Layout:
    """Dimensions derived from a :class:`GarageConfig`."""

    cfg: GarageConfig

    # ---- x
    @property
    def x_rows0(self) -> float:
        return self.cfg.cross_aisle

    @property
    def x_rows1(self) -> float:
        return self.cfg.cross_aisle + self.cfg.row_length

    @property
    def length(self) -> float:
        return self.x_rows1 + self.cfg.cross_aisle

    @property
    def x_west(self) -> float:
        """Centreline of the west cross aisle."""
        return self.cfg.cross_aisle / 2.0

    @property
    def x_east(self) -> float:
        """Centreline of the east cross aisle."""
        return self.length - self.cfg.cross_aisle / 2.0

    @property
    def ramp_x0(self) -> float:
        """x where the ramp leaves the deck (top)."""
        return self.x_rows0 + 0.5 * (self.cfg.row_length - self.cfg.ramp_length)

    @property
    def ramp_x1(self) -> float:
        """x where the ramp reaches the covered floor (bottom)."""
        return self.ramp_x0 + self.cfg.ramp_length

    # ---- y
    @property
    def rows(self) -> tuple[Row, Row, Row, Row]:
        c = self.cfg
        ya = WALK
        a1 = ya + c.bay_depth
        b0 = a1 + c.aisle_width
        bc = b0 + c.bay_depth
        c1 = bc + c.bay_depth
        d0 = c1 + c.aisle_width
        return (Row('A', ya, a1, +1), Row('B', b0, bc, -1), Row('C', bc, c1, +1),
                Row('D', d0, d0 + c.bay_depth, -1))

    @property
    def aisles(self) -> tuple[float, float]:
        """Centrelines (y) of aisle 1 (south) and aisle 2 (north)."""
        r = self.rows
        return ((r[0].y1 + r[1].y0) / 2.0, (r[2].y1 + r[3].y0) / 2.0)

    @property
    def trench_y0(self) -> float:
        """South face of the ramp trench's inner wall."""
        return self.rows[3].y1

    @property
    def ramp_y0(self) -> float:
        return self.trench_y0 + WALL

    @property
    def ramp_y1(self) -> float:
        return self.ramp_y0 + self.cfg.ramp_width

    @property
    def ramp_yc(self) -> float:
        return (self.ramp_y0 + self.ramp_y1) / 2.0

    @property
    def width(self) -> float:
        return self.ramp_y1 + WALL + WALK

    # ---- z
    @property
    def deck_z(self) -> float:
        return self.cfg.level_height

    @property
    def ceiling_z(self) -> float:
        return self.cfg.level_height - self.cfg.slab_thickness

    @property
    def span(self) -> float:
        """Pillar / beam spacing along x (m)."""
        return self.cfg.pillar_every * self.cfg.bay_width

    def ramp_profile(self, x: np.ndarray) -> np.ndarray:
        """Height (m) of the ramp surface at ``x``: deck height before the ramp, 0 after it.

        Half-grade transition, full-grade main section, half-grade transition.
        """
        c = self.cfg
        s = np.clip(np.asarray(x, dtype=np.float64) - self.ramp_x0, 0.0, c.ramp_length)
        g, lt, lm = c.ramp_grade, c.ramp_transition, c.ramp_main_length
        drop = (0.5 * g * np.minimum(s, lt) + g * np.clip(s - lt, 0.0, lm)
                + 0.5 * g * np.clip(s - lt - lm, 0.0, lt))
        return self.deck_z - drop

    def in_trench(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N,) bool: (x, y) lies on the ramp (between the trench walls, along the ramp)."""
        return ((x >= self.ramp_x0) & (x <= self.ramp_x1) & (y >= self.ramp_y0)
                & (y <= self.ramp_y1))

    def in_footprint(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (x >= 0.0) & (x <= self.length) & (y >= 0.0) & (y <= self.width)

    def ground_height(self, x: np.ndarray, y: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Driving-surface height (m) at (x, y) on ``level`` (0 covered, 1 deck); the ramp
        profile inside the trench regardless of the level."""
        x = np.asarray(x, dtype=np.float64)
        z = np.where(np.asarray(level) > 0, self.deck_z, 0.0)
        return np.where(self.in_trench(x, np.asarray(y)), self.ramp_profile(x), z)
