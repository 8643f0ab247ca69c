"""Outputs of a run: results.json, the Markdown table (paper's Table 1 layout + extra columns),
bar charts and match figures (correct matches green, wrong red, as the paper's Figure 2)."""
from __future__ import annotations

from collections.abc import Sequence
import json
import math
from pathlib import Path

import cv2
import numpy as np

from semfeat_ros.evaluation.metrics import HOMOGRAPHY_THRESHOLDS, MMA_THRESHOLDS


def json_safe(obj: object) -> object:
    """Recursively convert numpy types to Python, NaN/inf to None (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(data: dict, path: str | Path) -> Path:
    path = Path(path)
    path.write_text(json.dumps(json_safe(data), indent=2, allow_nan=False) + '\n',
                    encoding='utf-8')
    return path


def _pct(x: object) -> str:
    if x is None or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
        return 'n/a'
    return f'{100.0 * float(x):.1f}'


def _num(x: object, digits: int = 1) -> str:
    if x is None or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
        return 'n/a'
    return f'{float(x):.{digits}f}'


def _gt_row(s: dict) -> list[str]:
    mma = s.get('mma') or []
    mma3 = mma[MMA_THRESHOLDS.index(3)] if len(mma) >= 3 else None
    hacc = s.get('homography_accuracy')
    hstr = '/'.join(_pct(hacc.get(str(t))) for t in HOMOGRAPHY_THRESHOLDS) if hacc else 'n/a'
    return [_pct(s.get('keypoint_recall')), _pct(s.get('inlier_ratio')),
            _pct(s.get('inlier_ratio_verified')), _pct(s.get('keypoint_recall_verified')),
            _pct(s.get('gt_keypoint_recall')), _pct(mma3), _pct(s.get('repeatability')), hstr,
            _num(s.get('n_matches')), _num(s.get('n_verified'))]


def _no_gt_row(s: dict) -> list[str]:
    kpts = [s.get('n_kpts_a'), s.get('n_kpts_b')]
    mean_kpts = (sum(kpts) / 2 if all(isinstance(k, (int, float)) for k in kpts) else None)
    return [_num(s.get('n_matches')), _num(s.get('n_verified')),
            _pct(s.get('verified_ratio')), _num(mean_kpts)]


_GT_COLUMNS = ['Keypoint Recall (%)', 'Inlier Ratio (%)', 'Inlier Ratio verified (%)',
               'Recall verified (%)', 'GT-kp Recall (%)', 'MMA@3px (%)', 'Repeatability (%)',
               'H acc @1/3/5 px (%)', '#Matches', '#Verified']
_NO_GT_COLUMNS = ['#Proposed (per pair)', '#Verified (per pair)',
                  'Inlier Ratio = verified / proposed (%)', '#Keypoints (per image)']


def markdown_table(results: dict) -> str:
    """The Markdown report: header lines, then one row per evaluated method. With ground truth
    the first three columns are the paper's Table 1 (Method, Keypoint Recall, Inlier Ratio);
    without (real sequences) the columns are proposed / verified matches per pair and their
    ratio. Timing columns close both."""
    methods: dict = results['methods']
    verif = results.get('verification', 'none')
    has_gt = results.get('ground_truth', True)
    lines = [
        f'# semfeat-eval: {results["mode"]}', '',
        f'- data: {results.get("source", "")}',
        f'- pairs: {results.get("n_pairs", 0)}, seed: {results.get("seed")}, '
        + (f'eps: {_num(results.get("eps_px"))} px, ' if has_gt else
           f'RANSAC threshold: {_num(results.get("ransac_px"))} px, ')
        + f'geometric verification: {verif}',
        f'- valid region: {results.get("mask", "whole frame")}', '',
        ('Keypoint Recall = correct matches / GT-matchable keypoints; Inlier Ratio = correct / '
         'proposed matches (before verification); definitions in docs/METRICS.md.' if has_gt
         else 'No ground truth: verified = accepted by geometric verification, an upper bound '
         'on the correct matches; definitions in docs/METRICS.md.'), '',
    ]
    cols = (['Method', *(_GT_COLUMNS if has_gt else _NO_GT_COLUMNS), 'Extract (ms/pair)',
             'Match (ms/pair)'])
    row_of = _gt_row if has_gt else _no_gt_row
    lines.append('| ' + ' | '.join(cols) + ' |')
    lines.append('|' + '|'.join([':---'] + ['---:'] * (len(cols) - 1)) + '|')
    for entry in methods.values():
        s = entry.get('summary')
        if s is None:
            continue
        row = [entry['label'], *row_of(s), _num(s.get('extract_ms')), _num(s.get('match_ms'))]
        lines.append('| ' + ' | '.join(row) + ' |')
    skipped = {n: e for n, e in methods.items() if e.get('summary') is None}
    if skipped:
        lines += ['', 'Skipped (not run, no numbers faked):']
        lines += [f'- {e["label"]} (`{n}`): {e.get("skipped", "unknown reason")}'
                  for n, e in skipped.items()]
    seg = results.get('segmentation')
    if seg:
        lines += ['', '## Segmentation', '']
        for key, s in seg.items():
            lines.append(f'- {key}: mIoU {_pct(s.get("miou"))} %, pixel accuracy '
                         f'{_pct(s.get("pixel_accuracy"))} % over {s.get("n_images", 0)} images')
    notes = results.get('notes') or []
    if notes:
        lines += ['', '## Notes', ''] + [f'- {n}' for n in notes]
    return '\n'.join(lines) + '\n'


def _plt():
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def plot_bars(results: dict, out_dir: str | Path) -> list[Path]:
    """Bar charts: recall / inlier ratio (before and after verification), homography accuracy,
    timing; and the MMA curve. Returns the written PNG paths."""
    plt = _plt()
    out = Path(out_dir)
    ran = {n: e for n, e in results['methods'].items() if e.get('summary') is not None}
    if not ran:
        return []
    labels = [e['label'] for e in ran.values()]
    summ = [e['summary'] for e in ran.values()]
    x = np.arange(len(ran))
    paths: list[Path] = []

    def val(s: dict, key: str) -> float:
        v = s.get(key)
        return float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) else 0.0

    has_gt = results.get('ground_truth', True)
    if has_gt:
        groups = [('keypoint_recall', 'Keypoint Recall'), ('inlier_ratio', 'Inlier Ratio'),
                  ('inlier_ratio_verified', 'Inlier Ratio (verified)'),
                  ('gt_keypoint_recall', 'GT-keypoint Recall')]
        scale, ylabel = 100.0, '%'
        title = f'Matching quality ({results["mode"]}, eps {results.get("eps_px")} px)'
    else:
        groups = [('n_matches', 'proposed'), ('n_verified', 'verified')]
        scale, ylabel = 1.0, 'matches per pair'
        title = f'Matches without ground truth ({results["mode"]})'
    groups = [g for g in groups if any(g[0] in s for s in summ)]
    fig, ax = plt.subplots(figsize=(max(6.0, 1.4 * len(ran) + 2), 4.2))
    w = 0.8 / max(len(groups), 1)
    for k, (key, name) in enumerate(groups):
        ax.bar(x + (k - (len(groups) - 1) / 2) * w, [scale * val(s, key) for s in summ], w,
               label=name)
    ax.set_xticks(x, labels, rotation=20, ha='right')
    ax.set_ylabel(ylabel)
    if has_gt:
        ax.set_ylim(0, 100)
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out / 'bars_matching.png')
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    if any('homography_accuracy' in s for s in summ):
        fig, ax = plt.subplots(figsize=(max(6.0, 1.4 * len(ran) + 2), 4.2))
        w = 0.8 / len(HOMOGRAPHY_THRESHOLDS)
        for k, t in enumerate(HOMOGRAPHY_THRESHOLDS):
            vals = [100 * float((s.get('homography_accuracy') or {}).get(str(t), 0.0))
                    for s in summ]
            ax.bar(x + (k - 1) * w, vals, w, label=f'<= {t} px')
        ax.set_xticks(x, labels, rotation=20, ha='right')
        ax.set_ylabel('% of pairs')
        ax.set_ylim(0, 100)
        ax.set_title('Homography accuracy (mean corner error)')
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(out / 'bars_homography.png')
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)

    fig, ax = plt.subplots(figsize=(max(6.0, 1.4 * len(ran) + 2), 4.2))
    ax.bar(x - 0.2, [val(s, 'extract_ms') for s in summ], 0.4, label='extraction (A+B)')
    ax.bar(x + 0.2, [val(s, 'match_ms') for s in summ], 0.4, label='matching')
    ax.set_xticks(x, labels, rotation=20, ha='right')
    ax.set_ylabel('ms per pair')
    ax.set_title('Time per pair')
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out / 'bars_time.png')
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    if not any(s.get('mma') for s in summ):
        return paths
    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    for lab, s in zip(labels, summ):
        mma = s.get('mma')
        if mma and all(isinstance(v, (int, float)) for v in mma):
            ax.plot(MMA_THRESHOLDS, [100 * v for v in mma], marker='o', label=lab)
    ax.set_xlabel('threshold (px)')
    ax.set_ylabel('MMA (%)')
    ax.set_ylim(0, 100)
    ax.set_title('Mean matching accuracy')
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    paths.append(out / 'mma.png')
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    return paths


def draw_matches(image_a: np.ndarray, image_b: np.ndarray, kpts_a: np.ndarray,
                 kpts_b: np.ndarray, matches: np.ndarray, correct: np.ndarray,
                 path: str | Path, title: str = '', *, max_lines: int = 200, seed: int = 0,
                 max_width: int = 1600, min_width: int = 960,
                 good_name: str = 'correct') -> Path:
    """Side-by-side figure (A | B) of the matches: ``correct`` green, the others red (at most
    ``max_lines``, a seeded random subset; the title gives the full counts, ``good_name``
    naming the green ones). RGB inputs; the figure is resized to a width within
    ``[min_width, max_width]`` px."""
    ha, wa = image_a.shape[:2]
    hb, wb = image_b.shape[:2]
    h = max(ha, hb)
    canvas = np.zeros((h, wa + wb, 3), np.uint8)
    canvas[:ha, :wa] = image_a if image_a.ndim == 3 else image_a[:, :, None]
    canvas[:hb, wa:] = image_b if image_b.ndim == 3 else image_b[:, :, None]
    scale = min(1.0, max_width / canvas.shape[1])
    if canvas.shape[1] < min_width:
        scale = min_width / canvas.shape[1]
    if scale != 1.0:
        interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_NEAREST
        canvas = cv2.resize(canvas, None, fx=scale, fy=scale, interpolation=interp)
    canvas = (canvas.astype(np.float32) * 0.75).astype(np.uint8)
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    correct = np.asarray(correct, bool)
    idx = np.arange(len(matches))
    if len(idx) > max_lines:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_lines, replace=False))
    for k in idx:
        pa = (np.asarray(kpts_a[matches[k, 0]]) + 0.5) * scale - 0.5
        pb = (np.asarray(kpts_b[matches[k, 1]]) + [wa + 0.5, 0.5]) * scale - 0.5
        color = (0, 220, 0) if correct[k] else (230, 0, 0)
        p1 = (int(round(pa[0])), int(round(pa[1])))
        p2 = (int(round(pb[0])), int(round(pb[1])))
        cv2.line(canvas, p1, p2, color, 1, cv2.LINE_AA)
        cv2.circle(canvas, p1, 3, color, -1, cv2.LINE_AA)
        cv2.circle(canvas, p2, 3, color, -1, cv2.LINE_AA)
    n_ok = int(correct.sum())
    text = f'{title}  {good_name} {n_ok} / {len(matches)}'
    if len(idx) < len(matches):
        text += f' (showing {len(idx)})'
    canvas = np.concatenate([np.zeros((26, canvas.shape[1], 3), np.uint8), canvas], axis=0)
    cv2.putText(canvas, text, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1,
                cv2.LINE_AA)
    path = Path(path)
    cv2.imwrite(str(path), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    return path


def write_outputs(results: dict, out_dir: str | Path,
                  seg_figures: Sequence[tuple[str, np.ndarray, Sequence[str]]] = ()) -> dict:
    """Write results.json, results.md, the charts and the confusion matrices; returns the
    written paths by kind."""
    from semfeat_ros.evaluation.segmentation import plot_confusion

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, object] = {'json': write_json(results, out / 'results.json')}
    md = out / 'results.md'
    md.write_text(markdown_table(results), encoding='utf-8')
    written['markdown'] = md
    written['charts'] = plot_bars(results, out)
    written['confusion'] = [plot_confusion(cm, names, out / f'confusion_{key}.png',
                                           title=f'{key}: confusion (row-normalised)')
                            for key, cm, names in seg_figures]
    return written
