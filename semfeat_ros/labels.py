"""The 19 semantic classes of ``config/labels.yaml`` (ids, names, colours, flags)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import yaml

from semfeat_ros.paths import config_path

NUM_CLASSES = 19
IGNORE_LABEL = 255
"""Label of pixels without a class (outside the lens's image circle); ignored by losses/metrics."""


class LabelsError(ValueError):
    """``labels.yaml`` is malformed."""


@dataclass(frozen=True)
class LabelSet:
    """Class table indexed by class id (0..18)."""

    names: tuple[str, ...]
    colors: np.ndarray  # (C, 3) uint8 RGB
    static: np.ndarray  # (C,) bool: may become a map landmark
    planar: np.ndarray  # (C,) bool: homography-derived correspondences are valid
    dynamic: np.ndarray  # (C,) bool: movable object, never tracked or mapped

    def __len__(self) -> int:
        return len(self.names)

    def id_of(self, name: str) -> int:
        """Class id of ``name``; ``KeyError`` if unknown."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f'unknown class {name!r}; known: {", ".join(self.names)}') from None

    def ids_of(self, names: list[str] | tuple[str, ...]) -> list[int]:
        return [self.id_of(n) for n in names]

    def colorize(self, mask: np.ndarray) -> np.ndarray:
        """(H, W) class ids -> (H, W, 3) uint8 RGB; ignore/unknown ids are black."""
        lut = np.zeros((256, 3), np.uint8)
        lut[: len(self.names)] = self.colors
        return lut[np.asarray(mask, dtype=np.uint8)]


def parse_labels(data: object, source: str = '<labels>') -> LabelSet:
    """Validate the parsed YAML of a labels file."""
    if not isinstance(data, dict) or not isinstance(data.get('classes'), list):
        raise LabelsError(f'{source}: expected a mapping with a "classes" list')
    rows = data['classes']
    by_id: dict[int, dict] = {}
    for row in rows:
        if not isinstance(row, dict):
            raise LabelsError(f'{source}: every class must be a mapping, got {row!r}')
        missing = {'id', 'name', 'color', 'static', 'planar', 'dynamic'} - set(row)
        if missing:
            raise LabelsError(f'{source}: class {row.get("name")!r} lacks {sorted(missing)}')
        cid = row['id']
        if not isinstance(cid, int) or cid in by_id:
            raise LabelsError(f'{source}: class ids must be unique integers, got {cid!r}')
        color = row['color']
        if (not isinstance(color, list) or len(color) != 3
                or not all(isinstance(c, int) and 0 <= c <= 255 for c in color)):
            raise LabelsError(f'{source}: class {row["name"]!r} color must be 3 ints 0..255')
        by_id[cid] = row
    if sorted(by_id) != list(range(len(by_id))):
        raise LabelsError(f'{source}: class ids must be 0..{len(by_id) - 1} without gaps')
    ordered = [by_id[i] for i in range(len(by_id))]
    if ordered and any(r['static'] and r['dynamic'] for r in ordered):
        raise LabelsError(f'{source}: a class cannot be both static and dynamic')
    return LabelSet(
        names=tuple(str(r['name']) for r in ordered),
        colors=np.array([r['color'] for r in ordered], dtype=np.uint8).reshape(-1, 3),
        static=np.array([bool(r['static']) for r in ordered]),
        planar=np.array([bool(r['planar']) for r in ordered]),
        dynamic=np.array([bool(r['dynamic']) for r in ordered]),
    )


@lru_cache(maxsize=8)
def _load_cached(path: str) -> LabelSet:
    with open(path, encoding='utf-8') as f:
        return parse_labels(yaml.safe_load(f), path)


def load_labels(path: str | Path | None = None) -> LabelSet:
    """Load a labels file (default: the shipped ``config/labels.yaml``)."""
    p = Path(path) if path is not None else config_path('labels.yaml')
    if not p.is_file():
        raise FileNotFoundError(f'labels file not found: {p}')
    return _load_cached(str(p.resolve()))
