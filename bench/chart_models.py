"""The calibration's chart colour models against each camera's hidden response (issue 29: what
a viewer sees live, and the crosstalk the neural method starts from).

For each studio bag (``bench/neural.py``'s ``studio_seed<N>``, rendered here when absent): the
calibrator's chart patches, as `volcap calibrate` samples them; every camera's chart model fitted
as `volcap calibrate` fits it; then, for 424 colours (the chart's 24 and 400 random, linear
0.01-0.8, at radiance 0.7), the camera's record of them (``ColorResponse`` without noise,
vignetting or blur: the image centre) corrected by its model, against what the studio's ideal
camera (``IDEAL_RESPONSE``) records. One linear scale per camera takes the exposure out (the
models bring images to the chart's mean light, not the ideal camera's level), so the scores are
colour only:

- ``de``: mean CIEDE2000 of the corrected colours from the ideal camera's;
- ``chroma``: their mean chroma over the ideal's, on colours of chroma above 30 (1: true);
- ``crosstalk_bias``: the mean off-diagonal of the model's crosstalk (``chart_crosstalk``, what
  the neural method takes) minus the true one.

Three chart fits, all alternating least squares over per-view illumination and per-camera
models: ``matte``, the shipped ``view_illumination`` (the chart seen as matte); and two
prototypes, here only, that add one linear offset per (camera, view), taken off that view's
patches before the camera's model is fitted (a gloss or flare term: the synthetic board has a
broad specular lobe): ``matte_offset``, any offset (3 parameters), and ``matte_sheen``, the
view's light times a scale of at least 0 (1 parameter). The offset is not applied to the images
the model later corrects.

    .venv/bin/python bench/chart_models.py [--out bench_out/neural] [--studio-seeds 7 0]

Writes <out>/chart_models.json.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RADIANCE = 0.7
VARIANTS = ('matte', 'matte_offset', 'matte_sheen')


def _bag(out: Path, seed: int) -> Path:
    """bench/neural.py's studio session for ``seed`` (its calibration is not needed here)."""
    from volcap_bringup.demo_cli import DemoConfig
    from volcap_studio.session import synthesize
    from volcap_studio.studio import SynthConfig
    bag = out / f'studio_seed{seed}'
    if not (bag / 'metadata.yaml').exists():
        demo = DemoConfig()
        synthesize(bag, SynthConfig(cameras=8, frames=demo.colour_frames, board_poses=demo.board_poses,
                                    board_layout=demo.board_layout, background_frames=3, seed=seed), overwrite=True)
    return bag


def _illumination_with_offsets(calibrator, iterations: int = 30, sheen: bool = False):
    """``view_illumination``'s alternating fit with one additive linear offset per (camera, view):
    returns the per-view illumination and the offsets. ``sheen``: each offset is the view's light
    (its illuminant colour, e0) times one scale of at least 0, as the camera records it: a
    neutral gloss, 1 parameter per (camera, view) instead of 3."""
    from volcap_calib.color import illumination_at
    from volcap_core.color import srgb_to_linear
    samples = {c: items for c, items in calibrator.patches.items() if items}
    ref = srgb_to_linear(np.asarray(calibrator.reference(), np.float64))
    xy = calibrator.patch_xy()
    basis = np.hstack([np.ones((len(xy), 1)), xy])
    views = sorted({v for items in samples.values() for v, _ in items})
    E = {v: np.array([[1.0, 0.0, 0.0]] * 3) for v in views}
    rows = {c: [(v, np.isfinite(m).all(axis=1), srgb_to_linear(np.nan_to_num(m))) for v, m in items]
            for c, items in samples.items()}
    offsets = {(c, v): np.zeros(3) for c, items in rows.items() for v, _, _ in items}
    for _ in range(iterations):
        seen = {v: [] for v in views}
        for c, items in rows.items():
            X = np.vstack([m[ok] - offsets[(c, v)] for v, ok, m in items])
            Y = np.vstack([illumination_at(E[v], basis[ok]) * ref[ok] for v, ok, _ in items])
            M, *_ = np.linalg.lstsq(X, Y, rcond=None)
            for v, ok, m in items:
                target = illumination_at(E[v], basis[ok]) * ref[ok]
                excess = (m[ok] @ M - target).mean(axis=0)         # (m - o) M = target, in the reference's space
                if sheen:
                    light = E[v][:, 0]
                    excess = max(0.0, float(excess @ light / (light @ light))) * light
                offsets[(c, v)] = np.linalg.solve(M.T, excess)
                seen[v].append((ok, (m[ok] - offsets[(c, v)]) @ M))
        for v in views:
            A = np.vstack([basis[ok] for ok, _ in seen[v]])
            R = np.vstack([ref[ok] for ok, _ in seen[v]])
            P = np.vstack([p for _, p in seen[v]])
            E[v] = np.array([np.linalg.lstsq(A * R[:, k:k + 1], P[:, k], rcond=None)[0] for k in range(3)])
        mean = np.mean([E[v][:, 0] for v in views], axis=0)
        E = {v: E[v] / mean[:, None] for v in views}
    return E, offsets


def _samples(calibrator, camera: str, illumination: dict, offsets: dict | None):
    """``Calibrator.color_samples``, the offsets taken off each view's patches first."""
    from volcap_core.color import linear_to_srgb, srgb_to_linear
    if offsets is None:
        return calibrator.color_samples(camera, illumination)
    from volcap_calib.color import illuminated_reference
    reference, xy = calibrator.reference(), calibrator.patch_xy()
    measured, ref, patch = [], [], []
    for view, colors in calibrator.patches[camera]:
        ok = np.isfinite(colors).all(axis=1)
        measured.append(linear_to_srgb(np.clip(srgb_to_linear(colors[ok]) - offsets[(camera, view)], 0, None)))
        ref.append(illuminated_reference(reference[ok], illumination[view], xy[ok]))
        patch.append(np.nonzero(ok)[0])
    return np.vstack(measured), np.vstack(ref), np.concatenate(patch)


def score(model, response: dict, colors: np.ndarray) -> dict:
    from volcap_color.neural import chart_crosstalk
    from volcap_core.color import delta_e2000, linear_to_srgb, srgb_to_lab, srgb_to_linear
    from volcap_studio.render import IDEAL_RESPONSE, ColorResponse
    camera = replace(ColorResponse.from_dict(response), blur_sigma_px=0.0, vignetting=(0.0, 0.0))
    radiance = (colors * RADIANCE).astype(np.float32)[:, None, :]
    recorded = camera.apply(radiance, np.random.default_rng(0), noise=False)[:, 0] / 255.0
    ideal = IDEAL_RESPONSE.apply(radiance, np.random.default_rng(0), noise=False)[:, 0] / 255.0
    ok = ((recorded < 0.995) & (recorded > 0.02)).all(axis=1)     # neither clipped nor in the noise floor
    corrected = srgb_to_linear(np.clip(model.apply(recorded[ok]), 0, 1))
    target = srgb_to_linear(ideal[ok])
    corrected = linear_to_srgb(np.clip(corrected * (corrected * target).sum() / (corrected ** 2).sum(), 0, 1))
    a, b = srgb_to_lab(corrected), srgb_to_lab(ideal[ok])
    chroma_a, chroma_b = np.hypot(a[:, 1], a[:, 2]), np.hypot(b[:, 1], b[:, 2])
    vivid = chroma_b > 30
    off = ~np.eye(3, dtype=bool)
    bias = (chart_crosstalk(model) - np.asarray(response['crosstalk'], float))[off].mean()
    return {'method': model.method, 'de': float(delta_e2000(corrected, ideal[ok]).mean()),
            'chroma': float(chroma_a[vivid].mean() / chroma_b[vivid].mean()), 'crosstalk_bias': float(bias),
            'colours': int(ok.sum())}


def studio(bag: Path) -> dict:
    from volcap_calib.calibrate import CalibrationConfig
    from volcap_calib.color import fit_camera_color
    from volcap_calib.run import calibrator_from_bag, load_board
    from volcap_core.color import srgb_to_linear
    from volcap_studio.session import GroundTruth
    cfg = CalibrationConfig()
    calibrator = calibrator_from_bag(bag, load_board(None), cfg, progress=False)
    responses = {c: v['color_response'] for c, v in GroundTruth(bag).doc['cameras'].items()}
    rng = np.random.default_rng(0)
    colors = np.vstack([srgb_to_linear(np.asarray(calibrator.reference(), float)), rng.uniform(0.01, 0.8, (400, 3))])
    out = {}
    for variant in VARIANTS:
        if variant == 'matte':
            illumination, offsets = calibrator.illumination(), None
        else:
            illumination, offsets = _illumination_with_offsets(calibrator, sheen=variant == 'matte_sheen')
        cams = {}
        for c in calibrator.rig.names:
            measured, ref, patch = _samples(calibrator, c, illumination, offsets)
            fit = fit_camera_color(measured, ref, patch, cfg.color_methods, cfg.color_method or None)
            cams[c] = score(fit.model, responses[c], colors)
        out[variant] = {'cameras': cams, **{k: float(np.mean([v[k] for v in cams.values()]))
                                            for k in ('de', 'chroma', 'crosstalk_bias')}}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--out', default=str(REPO / 'bench_out' / 'neural'))
    ap.add_argument('--studio-seeds', type=int, nargs='+', default=[7, 0])
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for seed in args.studio_seeds:
        results[seed] = studio(_bag(out, seed))
        for variant, r in results[seed].items():
            print(f'seed {seed}  {variant:13s} dE2000 {r["de"]:.2f}  chroma {r["chroma"]:.3f}  '
                  f'crosstalk bias {r["crosstalk_bias"]:+.4f}', flush=True)
            for c, s in r['cameras'].items():
                print(f'    {c} {s["method"]:12s} dE2000 {s["de"]:.2f}  chroma {s["chroma"]:.3f}  '
                      f'bias {s["crosstalk_bias"]:+.4f}')
    (out / 'chart_models.json').write_text(json.dumps(results, indent=1))
    print(f'wrote {out / "chart_models.json"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
