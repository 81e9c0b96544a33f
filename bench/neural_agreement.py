"""What agreement costs on the synthetic studio (issue 29): the neural method's colours pulled
further toward the cameras' agreement after D, scored pairwise and against the truth.

For each studio of a ``bench/neural.py`` output folder (its rendered bag, calibration and
trained ``volcap harmonise`` folder): one 3x3 per camera in linear light, fitted on the frame
sets the evaluation fits on (the neural method was trained on the same ones) so that every
correspondence's two harmonised colours meet at their mean, pulled toward the identity with
weight ``lambda`` per pixel and with the rig's mean 3x3 held at the identity (no shared drift).
The fit alternates ten times between the pairs' means and each camera's least-squares 3x3.
Then scored as ``volcap eval color`` scores every method, on the frame sets it never saw:
pairwise CIEDE2000 (paper 001's protocol) and against the truth (one 3x3 shared; one gain).

A large ``lambda`` leaves the neural colours as they are; a small one lets each camera take up
whatever makes the views agree, the shading that changes from view to view included. This is
what a pairwise term in D's training would trade, measured without retraining.

    python bench/neural_agreement.py [--out bench_out/neural] [--seeds 7 0 3 11]
        [--lambdas 1e9 0.01 0.003 0.001]
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np
from stability import commit  # bench/ is on the path when run as a script

from volcap_bringup.demo_cli import DemoConfig
from volcap_color.baselines import PixelMapping, apply_mapping
from volcap_color.correspondence import cameras_in, find_correspondences, merge_matches, split_frame_sets
from volcap_core import transport
from volcap_core.calibration import Calibration
from volcap_core.color import linear_to_srgb, srgb_to_linear
from volcap_eval.color import ColorEvalConfig, neural_mappings, pair_scores, summarise, synthetic_truth, truth_scores
from volcap_pipeline.replay import capture_views


def _linear(mapping: PixelMapping, colors: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """The mapping's 8-bit output (as the evaluation scores it), in linear light."""
    out = np.asarray(apply_mapping(mapping, colors, pixels.astype(np.float64)))
    return srgb_to_linear(np.round(np.clip(out, 0.0, 1.0) * 255.0) / 255.0)


def _pulled(mapping: PixelMapping, matrix: np.ndarray) -> PixelMapping:
    """``mapping`` followed by ``matrix`` in linear light."""
    return PixelMapping(lambda rgb, xy: linear_to_srgb(np.clip(
        srgb_to_linear(np.asarray(mapping.apply(rgb, xy))) @ matrix, 0.0, 1.0)), mapping.size)


def fit_agreement(pairs: list, cameras: list[str], weight: float, rounds: int = 10) -> dict[str, np.ndarray]:
    """Per camera the 3x3 (row vectors: colour @ M) that brings each pair's two colours to
    their mean, pulled toward the identity by ``weight`` per pixel, the rig's mean held at it."""
    M = {c: np.eye(3) for c in cameras}
    for _ in range(rounds):
        xs = {c: [] for c in cameras}
        ys = {c: [] for c in cameras}
        for a, b, ca, cb in pairs:
            mean = 0.5 * (ca @ M[a] + cb @ M[b])
            xs[a].append(ca)
            ys[a].append(mean)
            xs[b].append(cb)
            ys[b].append(mean)
        fitted = {}
        for c in cameras:
            if not xs[c]:
                fitted[c] = np.eye(3)
                continue
            x, y = np.vstack(xs[c]), np.vstack(ys[c])
            prior = weight * len(x) * np.eye(3)
            fitted[c] = np.linalg.solve(x.T @ x + prior, x.T @ y + prior)
        centre = np.linalg.inv(sum(fitted.values()) / len(cameras))
        M = {c: m @ centre for c, m in fitted.items()}
    return M


def studio(folder: Path, seed: int, weights: list[float]) -> dict:
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
    neural = neural['neural']
    truth = synthetic_truth(bag, sizes)
    pairs = []
    for (a, b), m in fit.items():
        ca, cb = _linear(neural[a], m.colors_a, m.pixels_a), _linear(neural[b], m.colors_b, m.pixels_b)
        ok = np.all((ca > 0.003) & (ca < 0.97) & (cb > 0.003) & (cb < 0.97), axis=1)   # neither clipped
        pairs.append((a, b, ca[ok], cb[ok]))
    rows = []
    for weight in weights:
        M = fit_agreement(pairs, cameras, weight)
        mappings = {c: _pulled(neural[c], M[c]) for c in cameras}
        pairwise = summarise({k: v for k, v in pair_scores(thin, mappings, cfg.max_scored_per_pair, cfg.seed).items()
                              if k in scored_keys})
        true = truth_scores(thin, mappings, truth, cfg.max_scored_per_pair, cfg.seed)
        rows.append({'lambda': weight, 'pairwise': pairwise['de2000_mean'], 'truth': true['truth_de2000'],
                     'truth_one_gain': true['truth_de2000_exposure'],
                     'largest_off_identity': float(max(np.abs(m - np.eye(3)).max() for m in M.values()))})
        print(f"studio seed {seed}, lambda {weight:g}: pairwise {rows[-1]['pairwise']:.2f}, truth "
              f"{rows[-1]['truth']:.2f}, one gain {rows[-1]['truth_one_gain']:.2f}; the 3x3s at most "
              f"{rows[-1]['largest_off_identity']:.3f} from the identity", flush=True)
    return {'seed': seed, 'rows': rows}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', default='bench_out/neural', help="bench/neural.py's output folder")
    p.add_argument('--seeds', type=int, nargs='*', default=[7, 0, 3, 11])
    p.add_argument('--lambdas', type=float, nargs='*', default=[1e9, 0.01, 0.003, 0.001])
    args = p.parse_args()
    transport.configure()
    out = Path(args.out)
    missing = [s for s in args.seeds if not (out / f'studio_seed{s}.neural' / 'manifest.json').exists()]
    if missing:
        print(f'{out} has no trained studio for seeds {missing}: run bench/neural.py --studio-seeds first',
              file=sys.stderr)
        return 2
    result = {'commit': commit(), 'studio': [studio(out, s, args.lambdas) for s in args.seeds]}
    path = out / 'bench_neural_agreement.json'
    path.write_text(json.dumps(result, indent=2))
    print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
