"""Contact sheet of sample frames: image, class-label overlay and depth, plus the class legend."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from semfeat_ros.labels import load_labels
from semfeat_ros.sim import materials as mt
from semfeat_ros.sim.render import Frame
from semfeat_ros.sim.scenario import Scenario


def label_overlay(rgb: np.ndarray, label: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    """RGB image blended with the class colours of ``label`` (255 stays black)."""
    colors = load_labels().colorize(label).astype(np.float32)
    out = rgb.astype(np.float32) * (1.0 - alpha) + colors * alpha
    out[label == mt.IGNORE] = 0
    return np.clip(out, 0, 255).astype(np.uint8)


def depth_image(depth: np.ndarray, max_range: float = 60.0) -> np.ndarray:
    """Depth (m) as a colour image (log scale, turbo colormap); sky white, outside black."""
    d = np.nan_to_num(depth, nan=0.0, posinf=max_range)
    v = np.log1p(np.clip(d, 0.0, max_range)) / np.log1p(max_range)
    img = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1].copy()
    img[np.isinf(depth)] = 255
    img[np.isnan(depth)] = 0
    return img


def _legend(width: int) -> np.ndarray:
    labels = load_labels()
    cols = 4
    rows = -(-len(labels) // cols)
    cell_w = width // cols
    img = np.full((rows * 22 + 8, width, 3), 255, np.uint8)
    for i, name in enumerate(labels.names):
        r, c = divmod(i, cols)
        x, y = c * cell_w + 8, r * 22 + 6
        color = tuple(int(v) for v in labels.colors[i])
        cv2.rectangle(img, (x, y), (x + 16, y + 14), color, -1)
        cv2.rectangle(img, (x, y), (x + 16, y + 14), (0, 0, 0), 1)
        cv2.putText(img, f'{i} {name}', (x + 22, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                    (0, 0, 0), 1, cv2.LINE_AA)
    return img


def contact_sheet(scenario: Scenario, times: list[float]) -> np.ndarray:
    """Rows of (image | label overlay | depth) for the given drive times (s), with captions."""
    rows = []
    sensor = scenario.sensor
    for k, t in enumerate(times):
        sensor.reset()
        frame: Frame = scenario.renderer.render(scenario.camera_pose(t), t)
        rgb, _ = sensor.expose(frame, scenario.camera, k)
        row = np.concatenate([rgb, label_overlay(rgb, frame.label), depth_image(frame.depth)],
                             axis=1)
        st = scenario.trajectory.sample(t)
        z = st.T_map_base[2, 3]
        place = 'deck' if z > scenario.world.layout.deck_z - 0.05 else (
            'ramp' if z > 0.05 else 'covered level')
        text = f't = {t:5.1f} s   z = {z:4.2f} m   {place}'
        cv2.putText(row, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 2,
                    cv2.LINE_AA)
        cv2.putText(row, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1,
                    cv2.LINE_AA)
        rows.append(row)
    sheet = np.concatenate(rows, axis=0)
    return np.concatenate([sheet, _legend(sheet.shape[1])], axis=0)


def default_times(scenario: Scenario) -> list[float]:
    """Sample times covering deck, ramp and covered level."""
    tr = scenario.trajectory
    s0, s1 = tr.s_ramp
    return [tr.time_at(20.0), tr.time_at(s0 - 25.0), tr.time_at((s0 + s1) / 2),
            tr.time_at(s1 + 30.0), tr.time_at(min(s1 + 140.0, tr.length - 5.0))]


def write_preview(out: str | Path, seed: int = 0, size: tuple[int, int] = (320, 256),
                  times: list[float] | None = None) -> Path:
    """Render a contact sheet PNG of ``seed``'s drive; returns the path."""
    sc = Scenario.create(seed=seed, size=size)
    sheet = contact_sheet(sc, times if times is not None else default_times(sc))
    p = Path(out)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(p), sheet[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f'could not write {p}')
    return p
