"""`volcap eval colour`: every colour method on the same correspondences, scored as both papers do.

Capture frame sets of a bag are cleaned (``volcap_filter``, the clean plate learnt from the bag),
registered to colour at full resolution, smoothed, and matched between cameras with the
calibration (``correspondence``). Frame sets alternate between fitting and scoring (fit on the
1st, 3rd, ...; score on the 2nd, 4th, ...; one frame set is used for both and the report says
so), so chart-free methods are scored on pixels they were not fitted to.

- Paper 001 Tables 1-3: for every camera pair with at least ``eval_min_fraction`` of the pixels
  in correspondence, mean CIEDE2000 (sRGB -> Lab D65) and PSNR (peak 255) of the corrected
  colours at corresponding pixels; over pairs the mean, the mean weighted by correspondence
  count and the standard deviation. The same over every pair with at least ``fit_min_fraction``
  (``methods_all_pairs``): on a ring of stands the cross-stand pairs, where seams show in the
  fused model, are below the 1 % of the paper's protocol.
- Paper 000 Table 1: per camera the mean R, G, B and I difference (0-255) of the board's chart
  patches to the reference chart, before and after each method (needs the bag's board views;
  not for the neural methods, whose mapping depends on the pixel position, which the chart
  samples do not keep).

With ``neural`` (a ``volcap harmonise`` output folder) two more methods are scored: ``neural``,
the per-camera networks D of paper 001, and ``neural_live``, their exported region LUTs (the
same interpolation as the ``color_corrector`` node's integer kernel, in float: the kernel is
within a level of it).

Methods are fitted on pairs with at least ``fit_min_fraction`` (lower than the scoring
threshold: on a 4-stand rig only same-stand pairs reach 1 %, and the thinner cross-stand pairs
are what connects the stands).
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Callable

import colour as color_science
import numpy as np
from tqdm import tqdm

from volcap_calib.color import component_differences, fit_model
from volcap_calib.run import chart_samples, load_board
from volcap_color.baselines import (
    Mapping,
    PixelMapping,
    apply_mapping,
    brown_lowe,
    fit_finlayson,
    fit_reinhard,
    fit_vandermonde,
    identity,
    moulon,
    propagate,
)
from volcap_color.chart_free import chart_free_fit, identity_models
from volcap_color.config import HarmoniseConfig
from volcap_color.correspondence import (
    Matches,
    View,
    cameras_in,
    find_correspondences,
    merge_matches,
    split_frame_sets,
)
from volcap_color.model_choice import SATURATED_CHROMA, ModelChoice, choose_chart_free_model, chroma, split_matches
from volcap_core.calibration import Calibration, CameraCalibration
from volcap_core.color import LUMINANCE, ColorModel, delta_e2000, linear_to_lab, srgb_to_lab, srgb_to_linear
from volcap_core.errors import BadInput
from volcap_pipeline.harmonise import SurfaceConfig
from volcap_pipeline.replay import capture_views
from volcap_studio.render import ColorResponse
from volcap_studio.session import GroundTruth

from .color_figures import write_color_figures
from .config import ColorEvalConfig  # noqa: F401 (re-exported: its home before config.py)

METHODS = ('original', 'reinhard', 'vandermonde', 'finlayson', 'brown_lowe', 'moulon', 'paper_diagonal',
           'volcap_chart', 'volcap_chart_free', 'volcap_chart_harmonised')


def as_8bit(rgb: np.ndarray) -> np.ndarray:
    """Colours as an 8-bit image holds them (what every method is scored on)."""
    return np.round(np.clip(rgb, 0.0, 1.0) * 255.0) / 255.0


def pair_scores(matches: dict[tuple[str, str], Matches], mappings: dict[str, Mapping], max_per_pair: int,
                seed: int = 0) -> dict[str, dict]:
    """Per pair: mean CIEDE2000 and PSNR (dB, peak 255) of the mapped colours, corrected images
    being 8-bit; at most ``max_per_pair`` random correspondences are scored."""
    rng = np.random.default_rng(seed)
    out = {}
    for (a, b), m in matches.items():
        sel = np.arange(len(m)) if len(m) <= max_per_pair else rng.choice(len(m), max_per_pair, replace=False)
        ca = as_8bit(apply_mapping(mappings[a], m.colors_a[sel], m.pixels_a[sel]))
        cb = as_8bit(apply_mapping(mappings[b], m.colors_b[sel], m.pixels_b[sel]))
        mse = float(np.mean((ca - cb) ** 2))
        out[f'{a}-{b}'] = {'de2000': float(delta_e2000(ca, cb).mean()),
                           'psnr': float(10 * np.log10(1.0 / max(mse, 1e-12))), 'n': len(m)}
    return out


TruthFn = Callable[[str, np.ndarray, np.ndarray], np.ndarray]   # (camera, colours, pixels) -> true colours


def _scored_rows(matches: dict[tuple[str, str], Matches], max_per_pair: int, seed: int):
    """(camera, colours, pixels) of both sides of every pair's scored correspondences (the same
    random subset ``pair_scores`` scores)."""
    rng = np.random.default_rng(seed)
    for (a, b), m in matches.items():
        sel = np.arange(len(m)) if len(m) <= max_per_pair else rng.choice(len(m), max_per_pair, replace=False)
        yield a, m.colors_a[sel], m.pixels_a[sel].astype(np.float64)
        yield b, m.colors_b[sel], m.pixels_b[sel].astype(np.float64)


def chroma_kept(matches: dict[tuple[str, str], Matches], mapping: dict[str, Mapping], max_per_pair: int,
                seed: int = 0) -> dict:
    """Mean chroma (CIELAB C*ab) of the saturated pixels (C*ab >= ``SATURATED_CHROMA`` as the
    cameras recorded them) before and after the mapping: a method that buys consistency by
    greying colours out shows here, where pairwise scores cannot see it."""
    before, after = [], []
    for camera, colors, pixels in _scored_rows(matches, max_per_pair, seed):
        recorded = chroma(srgb_to_lab(colors))
        keep = recorded >= SATURATED_CHROMA
        if keep.any():
            before.append(recorded[keep])
            after.append(chroma(srgb_to_lab(as_8bit(apply_mapping(mapping[camera], colors[keep], pixels[keep])))))
    if not before:
        return {'chroma_before': None, 'chroma_after': None, 'saturated_pixels': 0}
    return {'chroma_before': float(np.concatenate(before).mean()), 'chroma_after': float(np.concatenate(after).mean()),
            'saturated_pixels': int(sum(map(len, before)))}


def truth_scores(matches: dict[tuple[str, str], Matches], mapping: dict[str, Mapping], truth: TruthFn,
                 max_per_pair: int, seed: int = 0) -> dict:
    """Mean CIEDE2000 of the mapped colours to the scene's true colours, allowing one colour
    transform shared by every camera (a rig harmonised to any common look is not wrong), in
    two strengths: ``truth_de2000`` one 3x3 matrix in linear light, ``truth_de2000_exposure``
    one exposure gain (so a colour cast shared by all cameras counts against the method).
    ``truth_per_camera``: per camera, its pixels' mean CIEDE2000 under the shared 3x3 and its
    ``exposure``, the least-squares factor of the mapped luminance over the true one (1: as
    bright as the truth; a camera the method made 5 % too bright reads 1.05): which camera a
    method gets wrong, and whether by brightness. Pixels clipped in the truth are left out."""
    mapped, true, cameras = [], [], []
    for camera, colors, pixels in _scored_rows(matches, max_per_pair, seed):
        t = truth(camera, colors, pixels)
        ok = np.all((t > 0.002) & (t < 0.998), axis=1)
        mapped.append(srgb_to_linear(as_8bit(apply_mapping(mapping[camera], colors[ok], pixels[ok]))))
        true.append(srgb_to_linear(t[ok]))
        cameras.append(np.full(int(ok.sum()), camera, dtype=object))
    if not mapped or not sum(map(len, mapped)):
        return {'truth_de2000': None, 'truth_de2000_exposure': None, 'truth_per_camera': {}}
    m, t, camera_of = np.vstack(mapped), np.vstack(true), np.concatenate(cameras)
    M = np.linalg.lstsq(m, t, rcond=None)[0]
    gain = float((m * t).sum() / max((m * m).sum(), 1e-12))
    lab_t = linear_to_lab(t)

    def de(x):
        return color_science.delta_E(linear_to_lab(x), lab_t, method='CIE 2000')
    shared = de(m @ M)
    y_mapped, y_true = (m @ M) @ LUMINANCE, t @ LUMINANCE
    per_camera = {}
    for camera in sorted(set(camera_of)):
        k = camera_of == camera
        per_camera[camera] = {'de2000': float(shared[k].mean()), 'pixels': int(k.sum()),
                              'exposure': float((y_mapped[k] * y_true[k]).sum() / max((y_true[k] ** 2).sum(), 1e-12))}
    return {'truth_de2000': float(shared.mean()), 'truth_de2000_exposure': float(de(m * gain).mean()),
            'truth_per_camera': per_camera}


def synthetic_truth(bag: str | Path, sizes: dict[str, tuple[int, int]]) -> TruthFn | None:
    """True colours of a synthetic bag's cameras (each camera's recorded response inverted to
    the ideal camera's), or None for a bag without ground truth."""
    try:
        gt = GroundTruth(bag)
    except FileNotFoundError:
        return None
    responses = {c: gt.color_response(c) for c in sizes}
    return lambda camera, colors, pixels: responses[camera].true_colors(colors, pixels, sizes[camera])


def summarise(scores: dict[str, dict]) -> dict:
    """Paper 001's columns: mean, correspondence-weighted mean and standard deviation over pairs."""
    if not scores:
        return {'de2000_mean': None, 'de2000_wmean': None, 'de2000_std': None, 'psnr_mean': None,
                'psnr_wmean': None, 'psnr_std': None, 'pairs': 0}
    n = np.array([s['n'] for s in scores.values()], float)
    out = {}
    for key in ('de2000', 'psnr'):
        v = np.array([s[key] for s in scores.values()])
        out.update({f'{key}_mean': float(v.mean()), f'{key}_wmean': float((v * n).sum() / n.sum()),
                    f'{key}_std': float(v.std())})
    out['pairs'] = len(scores)
    return out


def chart_table(samples: dict[str, tuple[np.ndarray, np.ndarray]], mapping: dict[str, Mapping]) -> dict:
    """Paper 000 Table 1 for one method: per camera the signed and absolute R, G, B, I
    differences (0-255) of the mapped chart patches to the reference, and their CIEDE2000."""
    out = {}
    for c, (measured, target) in samples.items():
        if c not in mapping or not len(measured) or isinstance(mapping[c], PixelMapping):
            continue
        after = as_8bit(mapping[c](measured))
        d = component_differences(after, target)
        out[c] = {'signed': d['signed'], 'abs': d['abs'], 'patch_de2000': float(delta_e2000(after, target).mean())}
    return out


def method_mappings(fit: dict[tuple[str, str], Matches], cameras: list[str], calibration: Calibration,
                    chart_samples: dict[str, tuple[np.ndarray, np.ndarray]] | None, cfg: ColorEvalConfig
                    ) -> tuple[dict[str, dict[str, Mapping]], dict[str, str], dict[str, dict[str, ColorModel]],
                               ModelChoice]:
    """Every method's per-camera mapping, the methods left out (with why), our fitted models and
    the chart-free model family used (and why)."""
    out: dict[str, dict[str, Mapping]] = {'original': {c: identity for c in cameras}}
    skipped = {}
    out['reinhard'] = propagate(fit, cameras, fit_reinhard)
    out['vandermonde'] = propagate(fit, cameras, fit_vandermonde)
    out['finlayson'] = propagate(fit, cameras, fit_finlayson)
    out['brown_lowe'] = brown_lowe(fit, cameras)
    out['moulon'] = moulon(fit, cameras)
    if chart_samples and all(len(chart_samples.get(c, ((),))[0]) for c in cameras):
        out['paper_diagonal'] = {c: fit_model('paper_diagonal', *chart_samples[c]).apply for c in cameras}
    else:
        skipped['paper_diagonal'] = 'the bag has no board views of every camera to fit the chart diagonal from'
    missing = [c for c in cameras if calibration.cameras[c].color is None]
    if missing:
        skipped['volcap_chart'] = f'{", ".join(missing)} have no colour model in the calibration'
    models = {}
    if not missing:
        models['volcap_chart'] = {c: ColorModel.from_dict(calibration.cameras[c].color) for c in cameras}
    chart_free = choose_chart_free_model(fit, cameras, cfg.chart_free_reference, seed=cfg.seed) \
        if cfg.chart_free_model == 'auto' else ModelChoice(cfg.chart_free_model, why='chosen by the caller')
    models['volcap_chart_free'] = identity_models(cameras) if chart_free.model == 'identity' else \
        chart_free_fit(fit, cameras, chart_free.model, cfg.chart_free_reference, seed=cfg.seed)
    if 'volcap_chart' in models and 'paper_diagonal' in out:
        harmonised = choose_chart_free_model(fit, cameras, 'chart', models['volcap_chart'], chart_samples,
                                             seed=cfg.seed).model if cfg.chart_free_model == 'auto' else chart_free.model
        harmonised = 'gain' if harmonised == 'identity' else harmonised
        models['volcap_chart_harmonised'] = chart_free_fit(fit, cameras, harmonised, 'chart',
                                                           base=models['volcap_chart'],
                                                           anchor=chart_samples, anchor_weight=cfg.anchor_weight,
                                                           seed=cfg.seed)
    else:
        skipped['volcap_chart_harmonised'] = 'needs the calibration\'s colour models and the bag\'s board views'
    for name, per_camera in models.items():
        out[name] = {c: per_camera[c].apply for c in cameras}
    return out, skipped, models, chart_free


def neural_mappings(models_dir: str | Path, views: list[View], cameras: list[str]
                    ) -> tuple[dict[str, dict[str, PixelMapping]], dict, dict]:
    """The ``neural`` (networks D) and ``neural_live`` (region LUTs) mappings of a ``volcap
    harmonise`` folder, its manifest and the LUTs."""
    from volcap_color.apply import RegionLut
    from volcap_color.neural_models import load_harmonisation
    harm = load_harmonisation(models_dir)
    missing = [c for c in cameras if c not in harm.mappers]
    if missing:
        raise BadInput(f'{models_dir} has no networks for {", ".join(missing)}')
    sizes = {v.name: (v.camera.width, v.camera.height) for v in views}
    luts = {c: RegionLut.load(Path(models_dir) / f'{c}.lut.npz') for c in cameras}
    net = {c: PixelMapping(lambda rgb, xy, c=c: harm.map_colors(c, rgb, xy), sizes[c]) for c in cameras}
    live = {c: PixelMapping(luts[c].apply_points, sizes[c]) for c in cameras}
    return {'neural': net, 'neural_live': live}, harm.report, luts


def evaluate_color(bag: str | Path, calibration: Calibration, chart_samples: dict | None = None,
                   cfg: ColorEvalConfig = ColorEvalConfig(), progress: bool = True,
                   neural: str | Path | None = None) -> tuple[dict, dict]:
    """(report, extras): the report as documented in the README; extras hold the first scored
    frame set's views and every method's mappings, for figures."""
    sets = capture_views(bag, calibration, cfg.frames, progress)
    cameras = cameras_in(sets, calibration)
    per_set = [find_correspondences(views, cfg.correspondence)
               for views in tqdm(sets, desc='correspondences', unit='set', disable=not progress)]
    fit_idx, score_idx = split_frame_sets(len(sets))
    fit = merge_matches([per_set[i] for i in fit_idx], cfg.fit_min_fraction)
    scored_sets = [per_set[i] for i in score_idx]
    scored = merge_matches(scored_sets, cfg.eval_min_fraction)
    thin = merge_matches(scored_sets, cfg.fit_min_fraction)
    scored_keys = {f'{a}-{b}' for a, b in scored}
    mappings, skipped, models, chart_free = method_mappings(fit, cameras, calibration, chart_samples, cfg)
    sizes = {v.name: (v.camera.width, v.camera.height) for views in sets for v in views}
    truth = synthetic_truth(bag, sizes)
    neural_info, luts = None, {}
    if neural is not None:
        extra, manifest, luts = neural_mappings(neural, [v for views in sets for v in views], cameras)
        mappings.update(extra)
        trained = manifest.get('frame_sets', {}).get('trained', [])
        neural_info = {'models': str(neural), 'trained_on': trained, 'reference': manifest['reference'],
                       'scored_sets_trained_on': sorted(set(trained) & set(score_idx)),
                       'export_error': manifest.get('export_error', {})}
    methods, all_pairs, pairs = score_methods(mappings, thin, scored_keys, truth, sizes, cfg, progress)
    table1 = {name: chart_table(chart_samples, m) for name, m in mappings.items()} if chart_samples else {}
    report = {'bag': str(bag), 'cameras': cameras, 'frame_sets': {'fit': fit_idx, 'scored': score_idx,
                                                                  'held_out': score_idx != fit_idx},
              'methods': methods, 'methods_all_pairs': all_pairs, 'skipped': skipped, 'pairs': pairs,
              'correspondences': {'fit_pairs': {f'{a}-{b}': len(m) for (a, b), m in fit.items()},
                                  'scored_pairs': {f'{a}-{b}': len(m) for (a, b), m in scored.items()}},
              'table1': table1, 'neural': neural_info, 'chart_free_model': chart_free.to_dict(),
              'truth': 'synthetic ground truth (each camera\'s response inverted)' if truth else None,
              'models': {name: {c: m.to_dict() for c, m in per.items()} for name, per in models.items()},
              'config': asdict(cfg)}
    return report, {'views': sets[score_idx[0]], 'mappings': mappings, 'models': models, 'region_luts': luts}


def truth_mapping(truth: TruthFn, camera: str, size: tuple[int, int]) -> PixelMapping:
    """``camera``'s true colours as a mapping (the `true_colours` row: a perfect harmoniser)."""
    scale = np.asarray(size, np.float64)
    return PixelMapping(lambda rgb, xy: truth(camera, rgb, xy * scale - 0.5), size)


def score_methods(mappings: dict[str, dict[str, Mapping]], matches: dict[tuple[str, str], Matches],
                  scored_keys: set[str], truth: TruthFn | None, sizes: dict[str, tuple[int, int]],
                  cfg: ColorEvalConfig, progress: bool = True) -> tuple[dict, dict, dict]:
    """(summary over the ``scored_keys`` pairs, summary over all pairs, per-pair scores) of every
    method, each summary with the chroma check and, given ``truth``, the scores against it and a
    ``true_colours`` row: every camera mapped to its true colours, the perfect harmoniser, whose
    pairwise scores are the floor the correspondences allow (below it a method is flattening
    colours to agree, not correcting cameras)."""
    if truth is not None:
        mappings = {**mappings, 'true_colours': {c: truth_mapping(truth, c, size) for c, size in sizes.items()}}
    methods, all_pairs, pairs = {}, {}, {}
    for name in tqdm(mappings, desc='scoring methods', unit='method', disable=not progress):
        pairs[name] = pair_scores(matches, mappings[name], cfg.max_scored_per_pair, cfg.seed)
        extra = chroma_kept(matches, mappings[name], cfg.max_scored_per_pair, cfg.seed)
        if truth is not None:
            extra.update(truth_scores(matches, mappings[name], truth, cfg.max_scored_per_pair, cfg.seed))
        methods[name] = {**summarise({p: v for p, v in pairs[name].items() if p in scored_keys}), **extra}
        all_pairs[name] = {**summarise(pairs[name]), **extra}
    return methods, all_pairs, pairs


# real texture -------------------------------------------------------------------------------
def spread_frames(total: int, count: int) -> np.ndarray:
    """The indices of ``count`` frames spread evenly over ``total`` (first and last included):
    the frames ``distorted_frame_views`` takes as its cameras."""
    return np.linspace(0, total - 1, count).round().astype(int)


def distorted_frame_views(folder: str | Path, intrinsics: str | Path, count: int = 8, seed: int = 0
                          ) -> tuple[list[View], dict[str, ColorResponse]]:
    """``count`` frames spread over a posed RGB-D folder (``volcap fuse-frames`` layout) as the
    cameras of one frame set, each recorded through its own random colour response (gain,
    white balance, crosstalk, gamma, vignetting, noise: the synthetic studio's
    ``ColorResponse.random``) applied to the real image taken as linear radiance. The
    responses are the ground truth: inverted, they give back the real image."""
    from volcap_pipeline.rig import read_frames_folder
    depth_model, color_model, frames = read_frames_folder(folder, intrinsics)
    if color_model != depth_model:
        raise BadInput(f'{folder}: colour and depth must share one pixel grid')
    if len(frames) < count:
        raise BadInput(f'{folder} has {len(frames)} frames, {count} asked for')
    rng = np.random.default_rng(seed)
    views, responses = [], {}
    for k, i in enumerate(spread_frames(len(frames), count)):
        _, depth_mm, rgb, T = frames[i]
        name = f'cam{k}'
        responses[name] = ColorResponse.random(rng)
        radiance = srgb_to_linear(rgb / 255.0).astype(np.float32)
        recorded = responses[name].apply(radiance, rng)
        views.append(View(name, recorded, depth_mm.astype(np.float32) / 1000, color_model, T))
    return views, responses


def evaluate_frames_color(folder: str | Path, intrinsics: str | Path | None = None, count: int = 8, seed: int = 0,
                          cfg: ColorEvalConfig = ColorEvalConfig(), progress: bool = True,
                          harmonise: tuple[str | Path, HarmoniseConfig] | None = None,
                          surface: SurfaceConfig = SurfaceConfig()) -> tuple[dict, dict]:
    """`volcap eval color-frames`: the colour methods on real texture. One frame set of
    ``count`` distorted real views (``distorted_frame_views``); every pair's correspondences
    are split at random, one half fitted, the other scored; the truth is the undistorted image.
    With ``harmonise`` (folder, settings) the neural method is trained on the views too (every
    pixel with depth, as `volcap harmonise --train-sets all`, its pixels on ``surface``) and
    scored as ``neural`` and ``neural_live``."""
    intrinsics = intrinsics or Path(folder) / 'intrinsics.K.txt'
    views, responses = distorted_frame_views(folder, intrinsics, count, seed)
    cameras = [v.name for v in views]
    matches = merge_matches([find_correspondences(views, cfg.correspondence)], cfg.fit_min_fraction)
    fit, scored = split_matches(matches, seed=cfg.seed)
    scored_keys = {f'{a}-{b}' for (a, b), m in scored.items() if 2 * m.fraction >= cfg.eval_min_fraction}
    calibration = Calibration(cameras[0], cameras[0], {c: CameraCalibration(v.T_world_camera) for c, v in
                                                       zip(cameras, views)})
    mappings, skipped, models, chart_free = method_mappings(fit, cameras, calibration, None, cfg)
    sizes = {v.name: (v.camera.width, v.camera.height) for v in views}
    neural_info, luts = None, {}
    if harmonise is not None:
        from volcap_pipeline.harmonise import run as harmonise_views
        out_dir, harmonise_cfg = harmonise
        trained = harmonise_views([views], cameras, harmonise_cfg, out_dir, surface, train_sets='all',
                                  progress=progress, sources={'folder': str(folder), 'seed': seed})
        extra, _, luts = neural_mappings(out_dir, views, cameras)
        mappings.update(extra)
        neural_info = {'models': str(out_dir), 'trained_on': [0], 'reference': harmonise_cfg.reference,
                       'seconds': trained.manifest['seconds'],
                       'scored_sets_trained_on': [], 'export_error': trained.manifest.get('export_error', {})}

    def truth(camera, colors, pixels):
        return responses[camera].true_colors(colors, pixels, sizes[camera])
    methods, all_pairs, pairs = score_methods(mappings, scored, scored_keys, truth, sizes, cfg, progress)
    report = {'folder': str(folder), 'cameras': cameras, 'seed': seed,
              'frame_sets': {'fit': [0], 'scored': [0], 'held_out': False},
              'methods': methods, 'methods_all_pairs': all_pairs, 'skipped': skipped, 'pairs': pairs,
              'correspondences': {'fit_pairs': {f'{a}-{b}': len(m) for (a, b), m in fit.items()},
                                  'scored_pairs': {f'{a}-{b}': len(m) for (a, b), m in scored.items()}},
              'table1': {}, 'neural': neural_info, 'chart_free_model': chart_free.to_dict(),
              'truth': 'the undistorted real images (each view\'s colour response inverted)',
              'responses': {c: r.to_dict() for c, r in responses.items()},
              'models': {name: {c: m.to_dict() for c, m in per.items()} for name, per in models.items()},
              'config': asdict(cfg)}
    return report, {'views': views, 'mappings': mappings, 'models': models, 'region_luts': luts}


def format_report(report: dict) -> str:
    """Markdown: the pairwise table (paper 001) and the chart table averages (paper 000)."""
    def f(v, d=2):
        return '-' if v is None else f'{v:.{d}f}'
    cfg = report['config']
    lines = []
    for key, title in (('methods', f"Pairs with >= {cfg['eval_min_fraction']:.0%} of the pixels in correspondence "
                                   '(paper 001 protocol):'),
                       ('methods_all_pairs', f"Every pair with >= {cfg['fit_min_fraction']:.1%} (across stands too):")):
        truth = report.get('truth') is not None
        lines += [title, '', '| method | CIEDE2000 mean | weighted | std | PSNR mean | weighted | std | pairs | '
                  'chroma of saturated pixels |' + (' truth CIEDE2000 (3x3) | truth (exposure) |' if truth else ''),
                  '|---|---|---|---|---|---|---|---|---|' + ('---|---|' if truth else '')]
        for name, s in report[key].items():
            lines.append(f"| {name} | {f(s['de2000_mean'])} | {f(s['de2000_wmean'])} | {f(s['de2000_std'])} | "
                         f"{f(s['psnr_mean'])} | {f(s['psnr_wmean'])} | {f(s['psnr_std'])} | {s['pairs']} | "
                         f"{f(s.get('chroma_before'), 1)} -> {f(s.get('chroma_after'), 1)} |"
                         + (f" {f(s.get('truth_de2000'))} | {f(s.get('truth_de2000_exposure'))} |" if truth else ''))
        lines.append('')
    per_camera = {name: s['truth_per_camera'] for name, s in report['methods'].items() if s.get('truth_per_camera')}
    if per_camera:
        cameras = sorted({c for per in per_camera.values() for c in per})
        lines += ['Each camera against the truth (CIEDE2000 under the shared 3x3 / exposure: its luminance over the '
                  "truth's, 1 = as bright):", '', '| method | ' + ' | '.join(cameras) + ' |',
                  '|---|' + '---|' * len(cameras)]
        for name, per in per_camera.items():
            lines.append(f'| {name} | ' + ' | '.join(f"{per[c]['de2000']:.2f} / {per[c]['exposure']:.3f}" if c in per
                                                      else '-' for c in cameras) + ' |')
        lines.append('')
    if 'true_colours' in report['methods']:
        lines.append('true_colours: every camera mapped to its true colours (a perfect harmoniser); its pairwise '
                     'scores are the floor these correspondences allow: below it a method agrees by flattening colours')
    choice = report.get('chart_free_model')
    if choice:
        lines.append(f"volcap_chart_free model: {choice['model']} ({choice['why']})")
    for name, why in report['skipped'].items():
        lines.append(f'{name} left out: {why}')
    if report['table1']:
        lines += ['', 'Chart patches (paper 000 Table 1), mean over cameras, 0-255:', '',
                  '| method | R | G | B | I | abs R | abs G | abs B | abs I | patch CIEDE2000 |',
                  '|---|---|---|---|---|---|---|---|---|---|']
        for name, cams in report['table1'].items():
            if not cams:
                continue
            sig = {k: np.mean([c['signed'][k] for c in cams.values()]) for k in 'RGBI'}
            ab = {k: np.mean([c['abs'][k] for c in cams.values()]) for k in 'RGBI'}
            de = np.mean([c['patch_de2000'] for c in cams.values()])
            lines.append(f'| {name} | ' + ' | '.join(f'{sig[k]:.2f}' for k in 'RGBI') + ' | '
                         + ' | '.join(f'{ab[k]:.2f}' for k in 'RGBI') + f' | {de:.2f} |')
    held = 'held-out frame sets' if report['frame_sets']['held_out'] else \
        'the frame set the methods were fitted on' + (' (half of each pair\'s correspondences, held out from the fit)'
                                                      if 'folder' in report else '')
    lines += ['', f"Scored on {held}: {report['frame_sets']['scored']}."]
    neural = report.get('neural')
    if neural:
        lines.append(f"neural: trained on frame sets {neural['trained_on']}, reference {neural['reference']}"
                     + (f"; WARNING: also trained on scored frame sets {neural['scored_sets_trained_on']}"
                        if neural['scored_sets_trained_on'] else ''))
    return '\n'.join(lines)


def run(bag: str | Path, calibration_path: str | Path, cfg: ColorEvalConfig | None = None,
        board_file: str | Path | None = None, chart: bool = True, neural: str | Path | None = None,
        figures: str | Path | None = None, progress: bool = True) -> dict:
    """`volcap eval colour`: the report (``table1_skipped`` says why the chart table is left out,
    ``figures`` lists the PNGs written when ``figures`` is a folder)."""
    calibration = Calibration.load(calibration_path)
    samples, why = (None, 'skipped (--no-chart)') if not chart else \
        chart_samples(bag, load_board(board_file), list(calibration.cameras), progress)
    report, extras = evaluate_color(bag, calibration, samples, cfg or ColorEvalConfig(), progress, neural=neural)
    if why:
        report['table1_skipped'] = why
    if figures:
        report['figures'] = [str(p) for p in write_color_figures(figures, report, extras['views'],
                                                                 extras['mappings'], extras['models'],
                                                                 extras['region_luts'])]
    return report
