"""What agreement costs (issue 29): the neural method's colours pulled further toward the
cameras' agreement after D, scored pairwise and against the truth, on the synthetic studio and
(``--frames-seeds``) on rgbd_box's real texture.

For each studio of a ``bench/neural.py`` output folder (its rendered bag, calibration and
trained ``volcap harmonise`` folder): our chart-free fit (``chart_free_fit``, one 3x3 per camera
in linear light, the rig's mean model held at the identity, Cauchy-reweighted) run on the
neural method's harmonised colours of the frame sets the evaluation fits on (the neural method
was trained on the same ones), with its ridge toward the identity at ``--ridges``. Then scored
as ``volcap eval color`` scores every method, on the frame sets it never saw: pairwise
CIEDE2000 (paper 001's protocol) and against the truth (one 3x3 shared; one gain).

A large ridge leaves the neural colours as they are; a small one lets each camera take up
whatever makes the views agree, the shading that changes from view to view included. This is
what a pairwise term in D's training would trade, measured without retraining. On rgbd_box
(``volcap eval color-frames``' split: half of every pair's correspondences fitted, the other
half scored, every pair) the neural method trained by ``bench/neural.py --frames-seeds``.

    python bench/neural_agreement.py [--out bench_out/neural] [--seeds 7 0 3 11]
        [--frames-seeds 0 1 2] [--ridges 1e6 1 0.1 0.01 0.0001]
"""
import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from neural import SHARED  # bench/ is on the path when run as a script
from stability import commit

from volcap_bringup.demo_cli import DemoConfig
from volcap_color.baselines import PixelMapping, apply_mapping
from volcap_color.chart_free import chart_free_fit
from volcap_color.correspondence import cameras_in, find_correspondences, merge_matches, split_frame_sets
from volcap_color.model_choice import split_matches
from volcap_core import transport
from volcap_core.calibration import Calibration
from volcap_eval.color import (
    ColorEvalConfig,
    as_8bit,
    distorted_frame_views,
    neural_mappings,
    pair_scores,
    summarise,
    synthetic_truth,
    truth_scores,
)
from volcap_pipeline.replay import capture_views

RGBD_BOX = SHARED / 'rgbd_box'


def _harmonised(matches: dict, neural: dict[str, PixelMapping]) -> dict:
    """``matches`` with both sides' colours replaced by the neural method's, as 8-bit sRGB (what
    the evaluation scores)."""
    def eight_bit(mapping, colors, pixels):
        return as_8bit(np.asarray(apply_mapping(mapping, colors, pixels.astype(np.float64))))
    return {(a, b): replace(m, colors_a=eight_bit(neural[a], m.colors_a, m.pixels_a),
                            colors_b=eight_bit(neural[b], m.colors_b, m.pixels_b)) for (a, b), m in matches.items()}


def _ridge_rows(label: str, fit: dict, cameras: list[str], neural: dict[str, PixelMapping], scored: dict,
                scored_keys: set[str] | None, truth, cfg: ColorEvalConfig, ridges: list[float]) -> list[dict]:
    """The chart-free 3x3s fitted on the neural colours of ``fit`` at each ridge, scored on
    ``scored`` (pairwise over ``scored_keys``, every pair when None; against the truth)."""
    harmonised = _harmonised(fit, neural)
    rows = []
    for ridge in ridges:
        models = chart_free_fit(harmonised, cameras, model='matrix_3x3', reference='mean', ridge=ridge)
        mappings = {c: neural[c].followed_by(models[c]) for c in cameras}
        pairs = pair_scores(scored, mappings, cfg.max_scored_per_pair, cfg.seed)
        pairwise = summarise({k: v for k, v in pairs.items() if scored_keys is None or k in scored_keys})
        true = truth_scores(scored, mappings, truth, cfg.max_scored_per_pair, cfg.seed)
        off = max(float(np.abs(np.asarray(m.matrix) - np.eye(3)).max()) for m in models.values())
        rows.append({'ridge': ridge, 'pairwise': pairwise['de2000_mean'], 'truth': true['truth_de2000'],
                     'truth_one_gain': true['truth_de2000_exposure'], 'largest_off_identity': off})
        print(f"{label}, ridge {ridge:g}: pairwise {rows[-1]['pairwise']:.2f}, truth "
              f"{rows[-1]['truth']:.2f}, one gain {rows[-1]['truth_one_gain']:.2f}; the 3x3s at most {off:.3f} "
              f"from the identity", flush=True)
    return rows


def studio(folder: Path, seed: int, ridges: list[float]) -> dict:
    bag = folder / f'studio_seed{seed}'
    rig = Calibration.load(folder / f'studio_seed{seed}.calibration.yaml')
    cfg = ColorEvalConfig(frames=DemoConfig().colour_frames)
    sets = capture_views(bag, rig, cfg.frames, False)
    cameras = cameras_in(sets, rig)
    per_set = [find_correspondences(views, cfg.correspondence) for views in sets]
    fit_idx, score_idx = split_frame_sets(len(sets))
    fit = merge_matches([per_set[i] for i in fit_idx], cfg.fit_min_fraction)
    scored_sets = [per_set[i] for i in score_idx]
    scored_keys = {f'{a}-{b}' for a, b in merge_matches(scored_sets, cfg.eval_min_fraction)}
    thin = merge_matches(scored_sets, cfg.fit_min_fraction)
    sizes = {v.name: (v.camera.width, v.camera.height) for views in sets for v in views}
    neural = neural_mappings(folder / f'studio_seed{seed}.neural', [v for views in sets for v in views], cameras)[0]
    rows = _ridge_rows(f'studio seed {seed}', fit, cameras, neural['neural'], thin, scored_keys,
                       synthetic_truth(bag, sizes), cfg, ridges)
    return {'seed': seed, 'rows': rows}


def real_texture(folder: Path, seed: int, ridges: list[float]) -> dict:
    """rgbd_box (``volcap eval color-frames``' views, split and scored as it scores them, every
    pair), with the neural method ``bench/neural.py`` trained on it."""
    cfg = ColorEvalConfig()
    views, responses = distorted_frame_views(RGBD_BOX, RGBD_BOX / 'intrinsics.K.txt', 8, seed)
    cameras = [v.name for v in views]
    matches = merge_matches([find_correspondences(views, cfg.correspondence)], cfg.fit_min_fraction)
    fit, scored = split_matches(matches, seed=cfg.seed)
    sizes = {v.name: (v.camera.width, v.camera.height) for v in views}
    neural = neural_mappings(folder / f'frames_seed{seed}', views, cameras)[0]

    def truth(camera, colors, pixels):
        return responses[camera].true_colors(colors, pixels, sizes[camera])
    return {'seed': seed, 'rows': _ridge_rows(f'rgbd_box seed {seed}', fit, cameras, neural['neural'], scored, None,
                                              truth, cfg, ridges)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', default='bench_out/neural', help="bench/neural.py's output folder")
    p.add_argument('--seeds', type=int, nargs='*', default=[7, 0, 3, 11], help='studio seeds')
    p.add_argument('--frames-seeds', type=int, nargs='*', default=[], help='rgbd_box seeds')
    p.add_argument('--ridges', type=float, nargs='*', default=[1e6, 1.0, 0.1, 0.01, 1e-4])
    args = p.parse_args()
    transport.configure()
    out = Path(args.out)
    missing = [f'studio_seed{s}' for s in args.seeds if not (out / f'studio_seed{s}.neural' / 'manifest.json').exists()]
    missing += [f'frames_seed{s}' for s in args.frames_seeds if not (out / f'frames_seed{s}' / 'manifest.json').exists()]
    if missing:
        print(f'{out} has no trained {", ".join(missing)}: run bench/neural.py --studio-seeds / --frames-seeds first',
              file=sys.stderr)
        return 2
    result = {'commit': commit(), 'studio': [studio(out, s, args.ridges) for s in args.seeds],
              'rgbd_box': [real_texture(out, s, args.ridges) for s in args.frames_seeds]}
    path = out / 'bench_neural_agreement.json'
    path.write_text(json.dumps(result, indent=2))
    print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
