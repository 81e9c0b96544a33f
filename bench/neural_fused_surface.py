"""Where E's and D's training pixels lie, side by side on real texture (rgbd_box, 8 views, seeds
0, 1, 2): each view's own depth (paper 001; ``volcap harmonise --surface views``) against the
training views' fused surface ray-cast back into each (ours, the default; ``--surface fused``,
``volcap_pipeline.harmonise.FusedSurface``).

The views' own depths disagree with each other by 2.6-3.0 mm at the median (a pixel footprint
is 0.65 mm there), so one point of the box is a different place in E's hash grid for every
view. Everything else is ``bench/neural.py``'s real texture run, once per surface.

    python bench/neural_fused_surface.py [--seeds 0 1 2] [--out bench_out/neural_fused_surface]

E's held-out column scores the pixels each run trains on: the fused run leaves out the pixels far
from the surface (edges), so it scores a different set of pixels than the views' run.
"""
import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import neural as neural_bench  # noqa: E402 (bench/ is on the path)
from stability import commit  # noqa: E402

from volcap_color.config import HarmoniseConfig  # noqa: E402
from volcap_pipeline.harmonise import SurfaceConfig  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
    ap.add_argument('--out', default='bench_out/neural_fused_surface')
    args = ap.parse_args()
    out = Path(args.out)
    rows = []
    for seed in args.seeds:
        for surface in ('views', 'fused'):
            folder = out / surface
            folder.mkdir(parents=True, exist_ok=True)
            r = neural_bench.real_texture(seed, folder, replace(HarmoniseConfig(), seed=seed),
                                          SurfaceConfig(surface=surface))
            m = r['methods']
            row = {'seed': seed, 'surface': surface, 'harmonise_seconds': r['harmonise_seconds'],
                   'field_held_out_rms': r['field_held_out_rms'], 'field_held_out_median': r['field_held_out_median'],
                   'truth': m['neural']['truth_de2000'], 'truth_live': m['neural_live']['truth_de2000'],
                   'pairwise': m['neural']['de2000_mean'], 'floor': m['true_colours']['de2000_mean'],
                   'chroma': m['neural']['chroma_after'], 'chroma_truth': m['true_colours']['chroma_after'],
                   'on_surface': r['surface']}
            rows.append(row)
            print(f"seed {seed}, {surface}: truth {row['truth']:.3f} (live {row['truth_live']:.3f}; target <= 1.6), "
                  f"pairwise {row['pairwise']:.2f} (floor {row['floor']:.2f}), chroma {row['chroma']:.1f} "
                  f"(truth {row['chroma_truth']:.1f}), E held-out {row['field_held_out_rms']:.2f} levels (median "
                  f"{row['field_held_out_median']:.1f}), harmonise {row['harmonise_seconds']:.0f} s"
                  f"{neural_bench._on_surface(r)}", flush=True)
    path = out / 'neural_fused_surface.json'
    path.write_text(json.dumps({'commit': commit(), 'rows': rows}, indent=2, default=float))
    print(f'wrote {path}')


if __name__ == '__main__':
    main()
