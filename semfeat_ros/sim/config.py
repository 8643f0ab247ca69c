"""The small configuration of the procedural parking garage (everything else comes from the seed).

Units: metres, fractions (grade), degrees for geodetic coordinates. A YAML file with any subset of
the fields of :class:`GarageConfig` overrides the defaults (``semfeat-sim --config FILE``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import yaml

from semfeat_ros.sim.errors import SimConfigError


@dataclass(frozen=True)
class GarageConfig:
    """Geometry and population of the two-level garage (covered level below an open roof deck).

    Attributes:
        n_bays: parking bays per row along x (each row spans ``n_bays * bay_width`` m).
        bay_width: bay width (m).
        bay_depth: bay depth (m).
        aisle_width: two-way driving aisle width (m).
        cross_aisle: width of the cross aisles at both ends of the rows (m).
        level_height: floor-to-floor height = ramp rise (m).
        slab_thickness: deck slab thickness (m); the covered level's clear height is
            ``level_height - slab_thickness``.
        ramp_grade: grade of the ramp's main section (rise/run, 0.10..0.15); the two transition
            sections of ``ramp_transition`` m each have half of it.
        ramp_transition: length of each half-grade transition section (m).
        ramp_width: ramp width (two lanes, m).
        pillar_every: pillars every this many bays on the covered level.
        occupancy: fraction of bays holding a parked car.
        n_moving_cars: cars driving their own loops (half on each level).
        n_pedestrians: pedestrians walking their own paths.
        geo_origin: latitude (deg), longitude (deg), ellipsoidal altitude (m) of the map origin
            (map x east, y north) for ``/gnss/fix``.
    """

    n_bays: int = 22
    bay_width: float = 2.5
    bay_depth: float = 5.0
    aisle_width: float = 6.5
    cross_aisle: float = 8.5
    level_height: float = 3.6
    slab_thickness: float = 0.35
    ramp_grade: float = 0.12
    ramp_transition: float = 3.0
    ramp_width: float = 6.5
    pillar_every: int = 3
    occupancy: float = 0.65
    n_moving_cars: int = 4
    n_pedestrians: int = 6
    geo_origin: tuple[float, float, float] = (48.1372, 11.5756, 520.0)

    def __post_init__(self) -> None:
        checks = [
            ('n_bays', 12 <= self.n_bays <= 40, '12..40'),
            ('bay_width', 2.2 <= self.bay_width <= 3.2, '2.2..3.2 m'),
            ('bay_depth', 4.5 <= self.bay_depth <= 6.0, '4.5..6.0 m'),
            ('aisle_width', 5.5 <= self.aisle_width <= 8.0, '5.5..8.0 m'),
            ('cross_aisle', 7.0 <= self.cross_aisle <= 12.0, '7..12 m'),
            ('level_height', 3.0 <= self.level_height <= 4.5, '3.0..4.5 m'),
            ('slab_thickness', 0.2 <= self.slab_thickness <= 0.6, '0.2..0.6 m'),
            ('ramp_grade', 0.10 <= self.ramp_grade <= 0.15, '0.10..0.15'),
            ('ramp_transition', 1.0 <= self.ramp_transition <= 5.0, '1..5 m'),
            ('ramp_width', 5.5 <= self.ramp_width <= 8.0, '5.5..8.0 m'),
            ('pillar_every', 2 <= self.pillar_every <= 4, '2..4'),
            ('occupancy', 0.0 <= self.occupancy <= 1.0, '0..1'),
            ('n_moving_cars', 0 <= self.n_moving_cars <= 12, '0..12'),
            ('n_pedestrians', 0 <= self.n_pedestrians <= 20, '0..20'),
        ]
        for name, ok, expected in checks:
            if not ok:
                raise SimConfigError(
                    f'GarageConfig.{name} must be in {expected}, got {getattr(self, name)!r}')
        if len(self.geo_origin) != 3:
            raise SimConfigError(
                f'GarageConfig.geo_origin must be (lat, lon, alt), got {self.geo_origin!r}')
        lat, lon, _ = self.geo_origin
        if not (-80.0 <= lat <= 80.0 and -180.0 <= lon <= 180.0):
            raise SimConfigError(f'GarageConfig.geo_origin lat/lon out of range: {lat}, {lon}')
        if self.ramp_length > self.row_length - 6.0:
            raise SimConfigError(
                f'ramp of {self.ramp_length:.1f} m (level_height / ramp_grade) does not fit '
                f'beside rows of {self.row_length:.1f} m; raise n_bays or ramp_grade')

    @property
    def row_length(self) -> float:
        """Length of a bay row along x (m)."""
        return self.n_bays * self.bay_width

    @property
    def ramp_main_length(self) -> float:
        """Horizontal length of the full-grade ramp section (m)."""
        return self.level_height / self.ramp_grade - self.ramp_transition

    @property
    def ramp_length(self) -> float:
        """Horizontal length of the whole ramp including both transitions (m)."""
        return self.ramp_main_length + 2.0 * self.ramp_transition

    def to_dict(self) -> dict:
        """Plain dict (YAML-serialisable)."""
        d = asdict(self)
        d['geo_origin'] = list(self.geo_origin)
        return d


def random_config(rng: np.random.Generator) -> GarageConfig:
    """A random but valid garage configuration (for diverse training data)."""
    for _ in range(100):
        try:
            return GarageConfig(
                n_bays=int(rng.integers(18, 27)), bay_width=float(rng.uniform(2.4, 2.7)),
                bay_depth=float(rng.uniform(4.8, 5.5)), aisle_width=float(rng.uniform(6.0, 7.5)),
                cross_aisle=float(rng.uniform(8.0, 10.0)),
                level_height=float(rng.uniform(3.2, 4.0)),
                slab_thickness=float(rng.uniform(0.3, 0.45)),
                ramp_grade=float(rng.uniform(0.10, 0.15)),
                ramp_transition=float(rng.uniform(2.0, 4.0)),
                ramp_width=float(rng.uniform(6.0, 7.0)), pillar_every=int(rng.integers(2, 5)),
                occupancy=float(rng.uniform(0.3, 0.9)), n_moving_cars=int(rng.integers(2, 7)),
                n_pedestrians=int(rng.integers(3, 11)))
        except SimConfigError:
            continue
    raise SimConfigError('could not draw a valid random GarageConfig')


def load_config(path: str | Path | None) -> GarageConfig:
    """Load a YAML override of :class:`GarageConfig` (``None``: defaults)."""
    if path is None:
        return GarageConfig()
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f'sim config not found: {p}')
    with open(p, encoding='utf-8') as f:
        data = yaml.safe_load(f) or {}
    if not isinstance(data, dict):
        raise SimConfigError(f'{p}: expected a mapping of GarageConfig fields')
    known = {f.name for f in fields(GarageConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SimConfigError(f'{p}: unknown fields {unknown}; known: {sorted(known)}')
    if 'geo_origin' in data:
        data['geo_origin'] = tuple(float(x) for x in data['geo_origin'])
    try:
        return GarageConfig(**data)
    except TypeError as exc:
        raise SimConfigError(f'{p}: {exc}') from exc
