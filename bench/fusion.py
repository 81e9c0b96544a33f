"""TSDF fusion timings at rig sizes (8 cameras; cleaned depth registered to colour 1280x720 at
full size, as `volcap run` asks of the filters, from 640x576 raw depth), against bare Open3D in
the same run:

- ours: ``TsdfFusion.fuse`` (rectification for lens distortion, crop, capture box, the kept
  volume emptied, integration, marching cubes, box cut);
- bare: ``bare_open3d_fusion`` on the same views (the textbook calls: block coordinates,
  integrate, extract; no distortion handling), into a volume allocated beforehand (not timed),
  and the same with a fresh 40 000-block volume per frame set as the Open3D examples do.

Ours and bare are timed in pairs on the same frame set, ``--repeat`` pairs per voxel size; the
ratio is the median of the pairs' ratios (with its quartiles).

With ``--run``, `volcap run` end to end at 10 mm and 4 mm voxels: fused frame sets per second
and latency from a frame set entering the graph to its mesh reaching the renderer probe.

    python bench/fusion.py BAG CALIBRATION [--repeat 15] [--run]
"""
import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from color_stage import median_ms

from volcap_core import transport
from volcap_core.bag_reader import BagReader
from volcap_core.calibration import Calibration
from volcap_core.camera import depth_to_millimetres
from volcap_core.frames import frame_sets, read_rig
from volcap_core.topics import CAPTURE, CLEAN_PLATE
from volcap_filter.pipeline import DepthCleaner, DepthFilterConfig
from volcap_filter.registration import DepthRegistration
from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion, bare_open3d_fusion

VOXELS = (0.01, 0.006, 0.004)
RUN_RATES = {0.01: 0.04, 0.004: 0.04}    # playback rates at which the graph fused every set on 2 cores


def capture_views(bag: str, calibration: Calibration, count: int) -> list[list[CameraView]]:
    """``count`` capture frame sets cleaned as the depth_filter nodes of `volcap run` do (full size)."""
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    cleaners, sets = {}, []
    for fs in frame_sets(bag, phases=(CLEAN_PLATE, CAPTURE)):
        views = []
        for name, f in fs.cameras.items():
            if name not in cleaners:
                size = (f.color_model.width, f.color_model.height)
                cleaners[name] = DepthCleaner(DepthRegistration(f.depth_model, f.color_model,
                                                                rig.camera(name).T_color_depth, size),
                                              DepthFilterConfig())
            cleaner = cleaners[name]
            if fs.phase == CLEAN_PLATE:
                cleaner.learn_background(f.color, f.depth)
                continue
            result = cleaner.process(f.color, f.depth)
            depth_mm = depth_to_millimetres(result.depth)
            views.append(CameraView(name, depth_mm, cleaner.output_model, f.color, f.color_model,
                                    calibration.T_world_color(name)))
        if views:
            sets.append(views)
        if len(sets) == count:
            return sets
    raise ValueError(f'{bag} has fewer than {count} capture frame sets')


def time_fusion(sets: list[list[CameraView]], voxel: float, repeat: int) -> dict:
    """Ours and bare on the same frame set, one after the other, ``repeat`` times: the ratio is
    the median of these pairs, so a machine that speeds up or slows down during the run (2-core
    timings drift by +-20 %) shifts both sides of each pair alike."""
    cfg = FusionConfig(voxel_size=voxel)
    fusion = TsdfFusion(cfg)
    for views in sets:                                        # warm-up: maps, JIT, the kept volume
        fusion.fuse(views)
        bare_open3d_fusion(views, cfg, fusion.new_volume())
    ours, bare, stages = [], [], []
    for k in range(repeat):
        views = sets[k % len(sets)]
        t0 = time.perf_counter()
        stages.append(fusion.fuse(views).timings_ms)
        ours.append((time.perf_counter() - t0) * 1e3)
        volume = fusion.new_volume()                          # allocation outside the timing
        t0 = time.perf_counter()
        bare_open3d_fusion(views, cfg, volume)
        bare.append((time.perf_counter() - t0) * 1e3)
    cycle = iter(range(10**9))
    bare_fresh = median_ms(lambda: bare_open3d_fusion(sets[next(cycle) % len(sets)], cfg), max(3, repeat // 3))
    ratios = np.asarray(ours) / np.asarray(bare)
    return {'voxel_mm': voxel * 1000, 'ours_ms': float(np.median(ours)), 'bare_ms': float(np.median(bare)),
            'bare_fresh_volume_ms': bare_fresh, 'ratio_vs_bare': float(np.median(ratios)),
            'ratio_vs_bare_quartiles': [float(q) for q in np.percentile(ratios, [25, 75])],
            'ratio_vs_bare_fresh_volume': float(np.median(ours)) / bare_fresh,
            'ours_integrate_ms': float(np.median([s['integrate'] for s in stages])),
            'ours_extract_ms': float(np.median([s['extract'] for s in stages]))}


def time_run(bag: str, calibration: str, voxel: float, rate: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'run'
        subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', 'run', bag, '--calibration', calibration,
                        '--out', str(out), '--voxel', str(voxel), '--rate', str(rate), '--quiet'],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        metrics = json.loads((out / 'metrics.json').read_text())
    probe = metrics['probe']
    return {'voxel_mm': voxel * 1000, 'playback_rate': rate, 'frame_sets': metrics['capture_frame_sets_in_bag'],
            'fused': metrics['frames_written'], 'mesh_rate_hz': probe['mesh_rate_hz'],
            'latency_ms_median': probe['latency_ms_median'], 'latency_ms_p95': probe['latency_ms_p95'],
            'mesh_message_mb_median': probe['mesh_message_mb_median']}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('bag')
    p.add_argument('calibration')
    p.add_argument('--repeat', type=int, default=15, help='ours/bare pairs timed per voxel size')
    p.add_argument('--sets', type=int, default=3, help='capture frame sets cycled through')
    p.add_argument('--run', action='store_true', help='also time volcap run end to end')
    args = p.parse_args()
    transport.configure()
    sets = capture_views(args.bag, Calibration.load(args.calibration), args.sets)
    print(f'{len(sets[0])} cameras, cleaned depth {sets[0][0].depth_mm.shape[1]}x{sets[0][0].depth_mm.shape[0]}, '
          f'colour {sets[0][0].color.shape[1]}x{sets[0][0].color.shape[0]}')
    print('voxel   ours ms  (integrate, extract)   bare ms  ratio (quartiles)   bare+fresh volume ms  ratio')
    for voxel in VOXELS:
        r = time_fusion(sets, voxel, args.repeat)
        q1, q3 = r['ratio_vs_bare_quartiles']
        print(f'{r["voxel_mm"]:4.0f} mm {r["ours_ms"]:8.1f}  '
              f'({r["ours_integrate_ms"]:6.1f}, {r["ours_extract_ms"]:6.1f})'
              f'   {r["bare_ms"]:9.1f}  {r["ratio_vs_bare"]:5.2f} ({q1:.2f}-{q3:.2f})   '
              f'{r["bare_fresh_volume_ms"]:20.1f}  {r["ratio_vs_bare_fresh_volume"]:5.2f}')
    if args.run:
        for voxel, rate in RUN_RATES.items():
            r = time_run(args.bag, args.calibration, voxel, rate)
            print(f'volcap run {r["voxel_mm"]:.0f} mm at rate {rate}: {r["fused"]}/{r["frame_sets"]} frame sets fused, '
                  f'{r["mesh_rate_hz"] or 0:.2f} meshes/s, latency median {r["latency_ms_median"]:.0f} ms '
                  f'(p95 {r["latency_ms_p95"]:.0f}), mesh message {r["mesh_message_mb_median"]:.1f} MB')


if __name__ == '__main__':
    main()
