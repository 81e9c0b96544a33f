"""Paper 001's E trained on the fused surface instead of each view's own depth: a candidate for
issue 29, measured beside the default on real texture (rgbd_box, 8 views, seeds 0, 1, 2).

By default every pixel's surface point comes from its own view's depth, and the views' depths
disagree with each other by 2.6-3.0 mm at the median (a pixel footprint is 0.65 mm there), so
one point of the box is a different place in E's hash grid for every view. Here the training
views are first fused (an Open3D TSDF of their depth, 2 mm voxels), each view's depth is
replaced by the fused surface ray-cast into it, and pixels where the two differ by more than
2 cm or the ray cast finds nothing are left out of E's and D's training (and of E's held-out
score, so that column scores a different set of pixels than the default's). Everything else is
the default run of ``bench/neural.py``'s real texture.

    python bench/neural_fused_surface.py [--seeds 0 1 2] [--out bench_out/neural_fused_surface]

It patches ``volcap_color.neural.training_samples`` for the candidate's runs; the harmonisation
itself is unchanged.
"""
import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c

sys.path.insert(0, str(Path(__file__).resolve().parent))
import neural as neural_bench  # noqa: E402 (bench/ is on the path)
from stability import commit  # noqa: E402

import volcap_color.neural as neural  # noqa: E402
from volcap_color.config import HarmoniseConfig  # noqa: E402
from volcap_color.correspondence import View  # noqa: E402

VOXEL_M = 0.002
TRUNC_VOXELS = 4.0
AGREE_M = 0.02


def fused_views(views: list[View]) -> tuple[list[View], list[dict]]:
    """The views with their depth replaced by the TSDF of all of them ray-cast into each (0 where
    it finds nothing or differs from the view's own depth by more than ``AGREE_M``), and per
    view the share of its pixels kept and the median |difference| (mm)."""
    grid = o3d.t.geometry.VoxelBlockGrid(attr_names=('tsdf', 'weight'), attr_dtypes=(o3c.float32, o3c.float32),
                                         attr_channels=((1), (1)), voxel_size=VOXEL_M, block_resolution=8,
                                         block_count=100_000)
    posed = []
    for v in views:
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(v.depth, np.float32)))
        K, extrinsic = o3c.Tensor(v.camera.K), o3c.Tensor(np.linalg.inv(v.T_world_camera))
        blocks = grid.compute_unique_block_coordinates(depth, K, extrinsic, 1.0, 3.0, TRUNC_VOXELS)
        grid.integrate(blocks, depth, K, extrinsic, 1.0, 3.0, TRUNC_VOXELS)
        posed.append((v, blocks, K, extrinsic))
    out, stats = [], []
    for v, blocks, K, extrinsic in posed:
        cast = grid.ray_cast(blocks, K, extrinsic, v.camera.width, v.camera.height, ['depth'], 1.0, 0.1, 3.0, 1.0,
                             TRUNC_VOXELS, 8)
        surface = cast['depth'].numpy()[..., 0].astype(np.float32)
        keep = (v.depth > 0) & (surface > 0) & (np.abs(surface - v.depth) <= AGREE_M)
        stats.append({'view': v.name, 'kept': float(keep.sum() / max(1, (v.depth > 0).sum())),
                      'median_difference_mm': float(1000 * np.median(np.abs(surface - v.depth)[keep]))})
        out.append(View(v.name, v.color, np.where(keep, surface, 0).astype(np.float32), v.camera, v.T_world_camera))
    return out, stats


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
    ap.add_argument('--out', default='bench_out/neural_fused_surface')
    args = ap.parse_args()
    out = Path(args.out)
    default_samples = neural.training_samples
    stats = {}

    def on_fused_surface(sets, cameras, total, seed):
        fused = []
        for views in sets:
            views, s = fused_views(views)
            fused.append(views)
            stats.setdefault('views', []).extend(s)
        return default_samples(fused, cameras, total, seed)

    rows = []
    try:
        measure(args, out, rows, stats, on_fused_surface, default_samples)
    finally:
        neural.training_samples = default_samples
    path = out / 'neural_fused_surface.json'
    path.write_text(json.dumps({'commit': commit(), 'rows': rows}, indent=2, default=float))
    print(f'wrote {path}')


def measure(args, out: Path, rows: list, stats: dict, on_fused_surface, default_samples) -> None:
    for seed in args.seeds:
        for name in ('default (each view\'s depth)', 'fused surface'):
            neural.training_samples = on_fused_surface if name == 'fused surface' else default_samples
            stats.clear()
            folder = out / ('fused' if name == 'fused surface' else 'default')
            folder.mkdir(parents=True, exist_ok=True)
            r = neural_bench.real_texture(seed, folder, replace(HarmoniseConfig(), seed=seed))
            m = r['methods']
            row = {'seed': seed, 'samples': name, 'harmonise_seconds': r['harmonise_seconds'],
                   'field_held_out_rms': r['field_held_out_rms'], 'field_held_out_median': r['field_held_out_median'],
                   'truth': m['neural']['truth_de2000'], 'truth_live': m['neural_live']['truth_de2000'],
                   'pairwise': m['neural']['de2000_mean'], 'floor': m['true_colours']['de2000_mean'],
                   'chroma': m['neural']['chroma_after'], 'chroma_truth': m['true_colours']['chroma_after'],
                   'views': list(stats.get('views', []))}
            rows.append(row)
            kept = (f"; {100 * np.mean([v['kept'] for v in row['views']]):.0f} % of the pixels kept, the views "
                    f"{np.median([v['median_difference_mm'] for v in row['views']]):.1f} mm from the fused surface"
                    if row['views'] else '')
            print(f"seed {seed}, {name}: truth {row['truth']:.3f} (live {row['truth_live']:.3f}; target <= 1.6), "
                  f"pairwise {row['pairwise']:.2f} (floor {row['floor']:.2f}), chroma {row['chroma']:.1f} "
                  f"(truth {row['chroma_truth']:.1f}), E held-out {row['field_held_out_rms']:.2f} levels (median "
                  f"{row['field_held_out_median']:.1f}), harmonise {row['harmonise_seconds']:.0f} s{kept}", flush=True)


if __name__ == '__main__':
    main()
