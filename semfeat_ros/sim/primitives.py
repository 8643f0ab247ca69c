"""Scene primitives: oriented boxes, ellipsoids, vertical cylinders and horizontal plane sets.

Every primitive carries a class id per face (boxes) or per primitive, a material id, an instance
id, a colour (linear RGB albedo tint) and an integer material parameter (e.g. a sign design).
Box faces are numbered ``0: -x, 1: +x, 2: -y, 3: +y, 4: -z, 5: +z`` in the box's local frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semfeat_ros.rotations import rot_y, rot_z
from semfeat_ros.sim.errors import SimConfigError


@dataclass
class Boxes:
    """N oriented boxes (arrays of length N)."""

    center: np.ndarray  # (N, 3) m
    rot: np.ndarray  # (N, 3, 3) world-from-local rotation
    half: np.ndarray  # (N, 3) half extents (m)
    face_cls: np.ndarray  # (N, 6) uint8
    face_mat: np.ndarray  # (N, 6) uint8
    inst: np.ndarray  # (N,) int32
    color: np.ndarray  # (N, 3) float32
    param: np.ndarray  # (N,) int32
    decal_group: np.ndarray  # (N,) int8, decal group of the +z face (-1: none)
    dynamic: np.ndarray  # (N,) bool: textures follow the object (local coordinates)

    def __len__(self) -> int:
        return len(self.center)

    @property
    def axis_aligned(self) -> np.ndarray:
        """(N,) bool: the rotation is a signed permutation (the box is a world AABB)."""
        a = np.abs(self.rot)
        return np.all((a < 1e-9) | (np.abs(a - 1.0) < 1e-9), axis=(1, 2))

    @property
    def world_half(self) -> np.ndarray:
        """(N, 3) half extents of the world-axis-aligned bounding boxes (m)."""
        return np.einsum('nij,nj->ni', np.abs(self.rot), self.half)


@dataclass
class Ellipsoids:
    """N axis-aligned ellipsoids."""

    center: np.ndarray  # (N, 3)
    radii: np.ndarray  # (N, 3)
    cls: np.ndarray  # (N,) uint8
    mat: np.ndarray  # (N,) uint8
    inst: np.ndarray  # (N,) int32
    color: np.ndarray  # (N, 3) float32
    param: np.ndarray  # (N,) int32
    dynamic: np.ndarray  # (N,) bool

    def __len__(self) -> int:
        return len(self.center)


@dataclass
class Cylinders:
    """N vertical cylinders (closed at the top)."""

    center: np.ndarray  # (N, 2) x, y
    z0: np.ndarray  # (N,)
    z1: np.ndarray  # (N,)
    radius: np.ndarray  # (N,)
    cls: np.ndarray  # (N,) uint8
    mat: np.ndarray  # (N,) uint8
    inst: np.ndarray  # (N,) int32
    color: np.ndarray  # (N, 3) float32
    param: np.ndarray  # (N,) int32

    def __len__(self) -> int:
        return len(self.center)


@dataclass
class PlaneSet:
    """Axis-aligned rectangles on the horizontal plane ``z`` facing up (or down)."""

    z: float
    up: bool
    rects: np.ndarray  # (K, 4) x0, x1, y0, y1
    cls: np.ndarray  # (K,) uint8
    mat: np.ndarray  # (K,) uint8
    inst: np.ndarray  # (K,) int32
    color: np.ndarray  # (K, 3) float32
    decal_group: np.ndarray  # (K,) int8


def _faces(value: int | tuple[int, ...], name: str) -> tuple[int, ...]:
    if isinstance(value, (int, np.integer)):
        return (int(value),) * 6
    vals = tuple(int(v) for v in value)
    if len(vals) != 6:
        raise SimConfigError(f'{name}: need 1 or 6 per-face values, got {len(vals)}')
    return vals


@dataclass
class SceneBuilder:
    """Collects primitives; :meth:`finish` turns them into arrays."""

    _boxes: list[tuple] = field(default_factory=list)
    _ells: list[tuple] = field(default_factory=list)
    _cyls: list[tuple] = field(default_factory=list)
    planes: list[PlaneSet] = field(default_factory=list)
    _next_inst: int = 1

    def new_instance(self) -> int:
        """A fresh instance id (>= 1; 0 is sky / nothing)."""
        inst = self._next_inst
        self._next_inst += 1
        return inst

    def box(self, lo: tuple[float, float, float], hi: tuple[float, float, float], cls, mat, *,
            inst: int | None = None, color=(0.5, 0.5, 0.5), param: int = 0,
            decal_group: int = -1, split: float | None = 8.0) -> int:
        """Add an axis-aligned box spanning ``lo..hi`` (m); long boxes are split into pieces of
        at most ``split`` m along their longest axis (tighter culling, same instance)."""
        lo_a = np.asarray(lo, dtype=np.float64)
        hi_a = np.asarray(hi, dtype=np.float64)
        if np.any(hi_a <= lo_a):
            raise SimConfigError(f'box with non-positive size: lo={lo}, hi={hi}')
        inst = self.new_instance() if inst is None else inst
        size = hi_a - lo_a
        axis = int(np.argmax(size))
        n = 1 if split is None else max(1, int(np.ceil(size[axis] / split)))
        edges = np.linspace(lo_a[axis], hi_a[axis], n + 1)
        for k in range(n):
            a, b = lo_a.copy(), hi_a.copy()
            a[axis], b[axis] = edges[k], edges[k + 1]
            self._boxes.append(((a + b) / 2, np.eye(3), (b - a) / 2, _faces(cls, 'cls'),
                                _faces(mat, 'mat'), inst, tuple(color), param, decal_group,
                                False))
        return inst

    def obox(self, center, half, rot: np.ndarray, cls, mat, *, inst: int | None = None,
             color=(0.5, 0.5, 0.5), param: int = 0, decal_group: int = -1,
             dynamic: bool = False) -> int:
        """Add an oriented box (``rot``: world-from-local)."""
        inst = self.new_instance() if inst is None else inst
        self._boxes.append((np.asarray(center, float), np.asarray(rot, float),
                            np.asarray(half, float), _faces(cls, 'cls'), _faces(mat, 'mat'),
                            inst, tuple(color), param, decal_group, dynamic))
        return inst

    def ellipsoid(self, center, radii, cls: int, mat: int, *, inst: int | None = None,
                  color=(0.5, 0.5, 0.5), param: int = 0, dynamic: bool = False) -> int:
        inst = self.new_instance() if inst is None else inst
        self._ells.append((tuple(center), tuple(radii), cls, mat, inst, tuple(color), param,
                           dynamic))
        return inst

    def cylinder(self, x: float, y: float, z0: float, z1: float, radius: float, cls: int,
                 mat: int, *, inst: int | None = None, color=(0.5, 0.5, 0.5),
                 param: int = 0) -> int:
        inst = self.new_instance() if inst is None else inst
        self._cyls.append(((x, y), z0, z1, radius, cls, mat, inst, tuple(color), param))
        return inst

    def plane(self, z: float, up: bool, rects: list[tuple[float, float, float, float]], cls: int,
              mat: int, *, inst: int | None = None, color=(0.5, 0.5, 0.5),
              decal_group: int = -1) -> int:
        inst = self.new_instance() if inst is None else inst
        k = len(rects)
        self.planes.append(PlaneSet(
            z=float(z), up=up, rects=np.asarray(rects, dtype=np.float64).reshape(k, 4),
            cls=np.full(k, cls, np.uint8), mat=np.full(k, mat, np.uint8),
            inst=np.full(k, inst, np.int32),
            color=np.tile(np.asarray(color, np.float32), (k, 1)),
            decal_group=np.full(k, decal_group, np.int8)))
        return inst

    def finish_boxes(self) -> Boxes:
        return boxes_from_rows(self._boxes)

    def finish_ellipsoids(self) -> Ellipsoids:
        return ellipsoids_from_rows(self._ells)

    def finish_cylinders(self) -> Cylinders:
        rows = self._cyls
        return Cylinders(
            center=np.array([r[0] for r in rows], np.float64).reshape(-1, 2),
            z0=np.array([r[1] for r in rows], np.float64),
            z1=np.array([r[2] for r in rows], np.float64),
            radius=np.array([r[3] for r in rows], np.float64),
            cls=np.array([r[4] for r in rows], np.uint8),
            mat=np.array([r[5] for r in rows], np.uint8),
            inst=np.array([r[6] for r in rows], np.int32),
            color=np.array([r[7] for r in rows], np.float32).reshape(-1, 3),
            param=np.array([r[8] for r in rows], np.int32))


def boxes_from_rows(rows: list[tuple]) -> Boxes:
    """Boxes from ``(center, rot, half, face_cls, face_mat, inst, color, param, decal_group,
    dynamic)`` tuples."""
    return Boxes(
        center=np.array([r[0] for r in rows], np.float64).reshape(-1, 3),
        rot=np.array([r[1] for r in rows], np.float64).reshape(-1, 3, 3),
        half=np.array([r[2] for r in rows], np.float64).reshape(-1, 3),
        face_cls=np.array([r[3] for r in rows], np.uint8).reshape(-1, 6),
        face_mat=np.array([r[4] for r in rows], np.uint8).reshape(-1, 6),
        inst=np.array([r[5] for r in rows], np.int32),
        color=np.array([r[6] for r in rows], np.float32).reshape(-1, 3),
        param=np.array([r[7] for r in rows], np.int32),
        decal_group=np.array([r[8] for r in rows], np.int8),
        dynamic=np.array([r[9] for r in rows], bool))


def ellipsoids_from_rows(rows: list[tuple]) -> Ellipsoids:
    """Ellipsoids from ``(center, radii, cls, mat, inst, color, param, dynamic)`` tuples."""
    return Ellipsoids(
        center=np.array([r[0] for r in rows], np.float64).reshape(-1, 3),
        radii=np.array([r[1] for r in rows], np.float64).reshape(-1, 3),
        cls=np.array([r[2] for r in rows], np.uint8),
        mat=np.array([r[3] for r in rows], np.uint8),
        inst=np.array([r[4] for r in rows], np.int32),
        color=np.array([r[5] for r in rows], np.float32).reshape(-1, 3),
        param=np.array([r[6] for r in rows], np.int32),
        dynamic=np.array([r[7] for r in rows], bool))


def concat_boxes(a: Boxes, b: Boxes) -> Boxes:
    """Concatenation of two box sets."""
    return Boxes(**{f: np.concatenate([getattr(a, f), getattr(b, f)])
                    for f in Boxes.__dataclass_fields__})


def concat_ellipsoids(a: Ellipsoids, b: Ellipsoids) -> Ellipsoids:
    """Concatenation of two ellipsoid sets."""
    return Ellipsoids(**{f: np.concatenate([getattr(a, f), getattr(b, f)])
                         for f in Ellipsoids.__dataclass_fields__})


def yaw_pitch(yaw: float, pitch: float = 0.0) -> np.ndarray:
    """World-from-local rotation ``Rz(yaw) Ry(pitch)`` (rad)."""
    return rot_z(yaw) @ rot_y(pitch)
