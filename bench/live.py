"""Live benchmark: the graph as `volcap live` runs it, fed 8 cameras at 30 fps by a bag looped at
real time with fresh stamps, a renderer stand-in receiving every mesh.

    .venv/bin/python bench/live.py BAG CALIBRATION [--seconds 60] [--voxels 0.01,0.006] [--composed]
        [--split-stages] [--every N]

Per voxel size (and with ``--composed``, also every node in one process; with ``--split-stages``,
also each camera's depth_filter and color_corrector as two processes instead of one
camera_pipeline), after a warm-up:
- delivered meshes/s at the renderer, latency p50/p95 from capture stamp to the mesh's arrival,
  the share of meshes fused from all cameras, the admission the controller settled on, drops
  per stage per second (the stages' own, and admitted frames that never reached them);
- the **compute bound**: each stage's own CPU time per delivered mesh (process CPU while it
  handles admitted frames, summed over cameras, as the stages report it in the same run) and the
  meshes/s the machine's cores would sustain doing only that work; delivered / bound;
- where the rest of the machine went: each process's CPU seconds per second (psutil), the
  frame source (bag_player, standing in for the drivers) and the receiving of frames that are
  not admitted included;
- latency and resident memory over the run, the graph's and each process's own (growth per
  minute over the steady part): run with ``--seconds 1800 --voxels 0.01`` for the 30-minute soak.
Writes bench_out/live.json and live.png.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]


def process_label(proc: psutil.Process) -> str:
    """``module[/namespace]`` of a node process (``python -m volcap_x.y_node -r __ns:=/cam3``)."""
    args = proc.cmdline()
    module = args[args.index('-m') + 1].split('.')[-1] if '-m' in args else proc.name()
    ns = next((a.split(':=/')[1] for a in args if a.startswith('__ns:=/')), '')
    return f'{module}/{ns}' if ns else module


def memory_sampler(stop: threading.Event, samples: list, per_process: dict, period_s: float = 5.0) -> None:
    """Resident memory of this process and every volcap process it started, every ``period_s``:
    the sum in ``samples`` and each process's own series in ``per_process`` (label -> samples)."""
    me = psutil.Process()
    t0 = time.monotonic()
    while not stop.wait(period_s):
        t = time.monotonic() - t0
        rss = me.memory_info().rss
        per_process.setdefault('live (this process)', []).append((t, rss / 1e6))
        for child in me.children(recursive=True):
            try:
                child_rss = child.memory_info().rss
                per_process.setdefault(f'{process_label(child)} [{child.pid}]', []).append((t, child_rss / 1e6))
            except psutil.Error:
                continue
            rss += child_rss
        samples.append((t, rss / 1e6))


def one_run(bag: str, calibration: str, voxel: float, seconds: float, warmup: float, composed: bool,
            source_nice: int = 0, split_stages: bool = False, every: int = 0) -> dict:
    from volcap_bringup.live import LiveConfig, latency_ms, run_live, summary_figures
    from volcap_bringup.live_controller import LiveController
    cfg = LiveConfig(calibration, bag=bag, voxel_size=voxel, seconds=seconds, warmup_s=warmup, composed=composed,
                     probe=True, source_nice=source_nice, split_stages=split_stages, every=every)
    stop, memory, per_process = threading.Event(), [], {}
    sampler = threading.Thread(target=memory_sampler, args=(stop, memory, per_process), daemon=True)
    sampler.start()
    last = [0.0]

    def show(s):
        if time.monotonic() - last[0] >= 10:
            last[0] = time.monotonic()
            print(f'  t={s["t_s"]:5.0f} s  {LiveController.line(s)}', flush=True)
    try:
        result = run_live(cfg, on_summary=show)
    finally:
        stop.set()
    figures = summary_figures(result['summaries'], warmup)
    window = result.get('window_s') or 0.0
    meshes = result['meshes']
    start_ns = meshes[0][0] if meshes else 0
    in_window = meshes[len(meshes) - (result['meshes_in_window'] or 0):]     # the meshes after the warm-up
    lat = latency_ms(in_window) if in_window else np.array([])
    after = [s for s in result['summaries'] if s['t_s'] >= warmup]
    work = [s['work_ms_per_set'] for s in after if s.get('work_ms_per_set')]
    work_ms = {k: float(np.median([w[k] for w in work])) for k in work[0]} if work else {}
    cores = psutil.cpu_count()
    bound = cores * 1000 / sum(work_ms.values()) if work_ms else None
    delivered = (result['meshes_in_window'] / window) if window else None
    cpu = {n: v / window for n, v in result.get('cpu_s', {}).items()} if window else {}
    grouped = {}
    for name, v in cpu.items():
        key = name.split('/')[0]
        grouped[key] = grouped.get(key, 0.0) + v
    return {
        'voxel_size': voxel, 'mode': result['mode'] + (', split stages' if split_stages else '')
        + (f', player nice {source_nice}' if source_nice else ''),
        'seconds_measured': window, 'cameras': len(result['cameras']),
        'delivered_meshes_per_s': delivered,
        'latency_ms_p50': float(np.percentile(lat, 50)) if lat.size else None,
        'latency_ms_p95': float(np.percentile(lat, 95)) if lat.size else None,
        'complete_share': figures['complete_share'], 'input_sets_per_s': figures['input_fps'],
        'admit_every_median': figures.get('admit_every_median'), 'drops_per_s': figures.get('drops_per_s'),
        'work_ms_per_set': work_ms, 'cores': cores, 'compute_bound_meshes_per_s': bound,
        'delivered_over_bound': delivered / bound if bound and delivered is not None else None,
        'cpu_cores_used_by_process_group': grouped,
        'memory_mb': memory, 'memory_mb_per_process': per_process,
        'latency_series': [((a - start_ns) / 1e9, (a - s) / 1e6) for a, s, _ in meshes],
        'mesh_mb_median': float(np.median([b for *_, b in meshes]) / 1e6) if meshes else None,
        'node_exit_codes': result['node_exit_codes'],
    }


def growth_per_minute(series: list[tuple[float, float]]) -> float | None:
    """Slope of a least-squares line through (seconds, value), per minute, over the steady part of
    the run (30-85 % of it: the graph's start-up and teardown left out)."""
    if len(series) < 4:
        return None
    t, v = np.array(series).T
    span = t[-1] - t[0]
    keep = (t >= t[0] + 0.3 * span) & (t <= t[0] + 0.85 * span)
    if keep.sum() < 3:
        return None
    return float(np.polyfit(t[keep], v[keep], 1)[0] * 60)


def figure(runs: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    for r in runs:
        label = f'{r["voxel_size"] * 1000:.0f} mm {r["mode"]}'
        if r['latency_series']:
            t, lat = np.array(r['latency_series']).T
            axes[0].plot(t, lat, '.', ms=3, label=label)
        if r['memory_mb']:
            t, mb = np.array(r['memory_mb']).T
            axes[1].plot(t, mb, label=f'{label}: all')
        if len(runs) == 1:            # a soak: each process's own line
            for name, series in r.get('memory_mb_per_process', {}).items():
                t, mb = np.array(series).T
                axes[1].plot(t, mb, linewidth=0.7, label=name.split(' [')[0] if mb[-1] > 400 else None)
    axes[0].set(xlabel='s', ylabel='capture to mesh at the renderer, ms', title='latency per mesh')
    axes[1].set(xlabel='s', ylabel='MB resident (all processes)', title='memory')
    names = [f'{r["voxel_size"] * 1000:.0f} mm\n{r["mode"]}' for r in runs]
    x = np.arange(len(runs))
    axes[2].bar(x - 0.2, [r['delivered_meshes_per_s'] or 0 for r in runs], 0.4, label='delivered')
    axes[2].bar(x + 0.2, [r['compute_bound_meshes_per_s'] or 0 for r in runs], 0.4, label='compute bound')
    axes[2].set_xticks(x, names)
    axes[2].set(ylabel='meshes/s', title='delivered vs compute bound')
    for ax in axes:
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('bag')
    ap.add_argument('calibration')
    ap.add_argument('--seconds', type=float, default=60.0)
    ap.add_argument('--warmup', type=float, default=15.0)
    ap.add_argument('--voxels', default='0.01,0.006')
    ap.add_argument('--composed', action='store_true', help='also run every node in one process (10 mm)')
    ap.add_argument('--every', type=int, default=0,
                    help='admit one frame set in N, fixed (0: the controller chooses from the load); a fixed '
                         'admission compares graphs on the same work')
    ap.add_argument('--split-stages', action='store_true',
                    help='also run each camera as a depth_filter and a color_corrector process (the first voxel size)')
    ap.add_argument('--source-nice', type=int, default=0,
                    help='run the bag player at this niceness (standing in for drivers on cores of their own)')
    ap.add_argument('--out', default=str(REPO / 'bench_out'))
    args = ap.parse_args()
    runs = []
    first = float(args.voxels.split(',')[0])
    plan = [(float(v), False, False) for v in args.voxels.split(',')]
    if args.composed:
        plan.append((first, True, False))
    if args.split_stages:
        plan.append((first, False, True))
    for voxel, composed, split in plan:
        print(f'{voxel * 1000:.0f} mm voxels, {"composed" if composed else "processes"}'
              f'{", split stages" if split else ""}: {args.seconds:.0f} s after the graph is up', flush=True)
        r = one_run(args.bag, args.calibration, voxel, args.seconds, args.warmup, composed, args.source_nice, split,
                    args.every)
        r['memory_mb_per_minute'] = growth_per_minute(r['memory_mb'])
        r['process_mb_per_minute'] = {name: growth_per_minute(series)
                                      for name, series in r['memory_mb_per_process'].items()}
        r['latency_ms_per_minute'] = growth_per_minute(r['latency_series'])
        runs.append(r)

        def f(v, fmt='.2f'):
            return '-' if v is None else format(v, fmt)
        print(f'  delivered {f(r["delivered_meshes_per_s"])} meshes/s from {f(r["input_sets_per_s"], ".1f")} sets/s '
              f'in (admit 1/{f(r["admit_every_median"], ".0f")}); latency p50 {f(r["latency_ms_p50"], ".0f")} ms, '
              f'p95 {f(r["latency_ms_p95"], ".0f")} ms; {100 * (r["complete_share"] or 0):.0f} % from all cameras')
        print(f'  own work per mesh (ms CPU): {r["work_ms_per_set"]}; compute bound '
              f'{f(r["compute_bound_meshes_per_s"])} meshes/s on {r["cores"]} cores; delivered/bound '
              f'{f(r["delivered_over_bound"])}')
        print(f'  cores used by process group: { {k: round(v, 2) for k, v in r["cpu_cores_used_by_process_group"].items()} }')
        print(f'  drops/s: {r["drops_per_s"]}')
        print(f'  growth per minute: memory {f(r["memory_mb_per_minute"], ".1f")} MB, latency '
              f'{f(r["latency_ms_per_minute"], ".1f")} ms', flush=True)
        for name, slope in sorted(r['process_mb_per_minute'].items(), key=lambda kv: -(kv[1] or 0)):
            series = r['memory_mb_per_process'][name]
            print(f'    {name:<40} {series[0][1]:7.0f} -> {series[-1][1]:7.0f} MB resident, '
                  f'{f(slope, "+.2f")} MB/min over the steady part', flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'live.json').write_text(json.dumps(runs, indent=1))
    figure(runs, out / 'live.png')
    print(f'wrote {out / "live.json"} and {out / "live.png"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
