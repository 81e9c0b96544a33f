"""Paper 001's neural harmonisation against its targets (issue 29), on 2 cores or a GPU:

- real texture (``volcap eval color-frames ../shared/data/rgbd_box --harmonise``, 8 views,
  seeds 0, 1, 2): wall time of the harmonisation, E's RMS on held-out pixels of every camera,
  the neural method (networks D and their live region LUTs) against the true colours
  (CIEDE2000, one 3x3 shared), pairwise against the true colours' floor, saturated chroma
  against the truth's, beside the chart-free gain model and the paper's baselines;
- the floor of E's held-out RMS there: E fitted to one view alone (``--single-view-floor``),
  and beside it the same held-out pixels predicted from their image neighbours (no field);
- what the views allow there (``--cross-view-floor``, no training): E's held-out pixels
  scored against the one colour per surface point closest to every view's true colour, each
  camera's exposure taken out (``cross_view_floor``);
- what a perfect harmoniser scores against rgbd_box's truth (``--exposure-floor``, no training):
  the views are frames of one hand-held camera whose exposure changed, the truth keeps each
  frame's, a harmoniser gives them one (``exposure_floor``);
- the synthetic studio (8 cameras, seeds 7 and 0; rendered and calibrated from its board
  views, so the reference is anchored to the chart): ``volcap harmonise`` with the demo's
  short settings, then ``volcap eval color`` on frame sets it never saw: neural against
  every baseline and our chart-free model, pairwise and on the truth;
- the live form: ``ImageCorrector`` on a region LUT per 1280x720 frame against D on every
  pixel with torch.

    python bench/neural.py [--out bench_out/neural] [--frames-seeds 0 1 2] [--studio-seeds 7 0]
        [--field hashgrid|paper] [--surface fused|views] [--single-view-floor 0] [--cross-view-floor 0 1 2]
        [--exposure-floor 0 1 2] [--crosstalk chart|truth] [--chart-fit matte|sheen]

``--crosstalk truth``: the studio with each camera's true crosstalk in place of the charts'
estimate (the anchor still the charts'), to bound what a better estimate would give.

``--chart-fit sheen``: the studio calibrated with ``bench/chart_models.py``'s sheen prototype
(one gloss per camera and view, in the view's light, taken off the chart patches before each
camera's colour model is fitted) in place of the shipped matte fit; every method that takes the
chart models (``volcap_chart``, the neural anchor and crosstalk) takes these. Give it its own
``--out`` (the calibration is made once per folder; an existing bag there is used as it is).

``--surface``: where E's and D's training pixels lie (``volcap harmonise --surface``; fused, the
default, or each view's own depth); ``bench/neural_fused_surface.py`` runs both side by side.

Each run's full report is written beside ``bench_neural.json``; figures: the colour methods and
images of each run (``figures/``).
"""
import argparse
import contextlib
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from color_stage import median_ms  # bench/ is on the path when run as a script
from stability import commit

from volcap_color.apply import ImageCorrector, RegionLut
from volcap_color.config import HarmoniseConfig
from volcap_color.neural import surface_summary
from volcap_core import transport
from volcap_pipeline.harmonise import SurfaceConfig

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'data'
BASELINES = ('reinhard', 'vandermonde', 'finlayson', 'brown_lowe', 'moulon')


def _row(rows: dict, name: str) -> dict:
    s = rows.get(name) or {}
    return {k: s.get(k) for k in ('de2000_mean', 'psnr_mean', 'truth_de2000', 'truth_de2000_exposure',
                                  'chroma_before', 'chroma_after', 'truth_per_camera')}


def _exposures(m: dict, name: str) -> str:
    """The range of a method's per-camera exposure against the truth (``truth_scores``)."""
    per = (m.get(name) or {}).get('truth_per_camera') or {}
    if not per:
        return '-'
    e = [v['exposure'] for v in per.values()]
    return f'{min(e):.3f}-{max(e):.3f}'


def real_texture(seed: int, out: Path, cfg: HarmoniseConfig, surface: SurfaceConfig = SurfaceConfig()) -> dict:
    from volcap_eval.color import ColorEvalConfig, evaluate_frames_color
    models = out / f'frames_seed{seed}'
    t0 = time.perf_counter()
    report, _ = evaluate_frames_color(SHARED / 'rgbd_box', count=8, seed=seed, cfg=ColorEvalConfig(),
                                      progress=False, harmonise=(models, replace(cfg, seed=seed)), surface=surface)
    wall = time.perf_counter() - t0
    (out / f'frames_seed{seed}.json').write_text(json.dumps(report, indent=1, default=float))
    manifest = json.loads((models / 'manifest.json').read_text())
    rows = report['methods_all_pairs']
    return {'seed': seed, 'harmonise_seconds': manifest['seconds']['total'], 'eval_wall_seconds': wall,
            'field_seconds': manifest['field']['seconds'],
            'mapper_seconds': sum(r['seconds'] for r in manifest['mappers'].values()),
            'field_held_out_rms': manifest['field_error']['rms_levels'],
            'field_held_out_median': manifest['field_error']['median_levels'],
            'field_held_out_rms_best_95': manifest['field_error']['rms_best_95_levels'],
            'grid_cell_mm': manifest['grid_cell_mm'], 'registration': manifest['registration'],
            'export_error_mean_levels': float(np.mean([e['mean_levels'] for e in manifest['export_error'].values()])),
            'texture': manifest['texture'], 'surface': surface_summary(manifest),
            'methods': {n: _row(rows, n) for n in ('original', *BASELINES, 'volcap_chart_free', 'neural',
                                                   'neural_live', 'true_colours')}}


def single_view_floor(seed: int, out: Path, cfg: HarmoniseConfig, camera: int = 2, epochs: int = 120) -> dict:
    """What E reaches on one view alone: the same field fitted to one camera's pixels only
    (no other view to disagree with, ten times the steps), scored on its held-out pixels. The
    images' own noise, sub-cell texture and their colour-to-depth misregistration at object
    edges stay; disagreement between views does not."""
    from volcap_color.neural import harmonise
    from volcap_eval.color import distorted_frame_views
    views, _ = distorted_frame_views(SHARED / 'rgbd_box', SHARED / 'rgbd_box' / 'intrinsics.K.txt', 8, seed)
    view = views[camera]
    harm = harmonise([[view]], [view.name], replace(cfg, seed=seed, field_epochs=epochs, mapper_points=1000,
                                                    mapper_epochs=1), out / f'single_view_seed{seed}', progress=False)
    e = harm.report['field_error']
    return {'seed': seed, 'camera': view.name, 'epochs': epochs, 'rms_levels': e['rms_levels'],
            'median_levels': e['median_levels'], 'rms_best_95_levels': e['rms_best_95_levels']}


def image_floor(seed: int, camera: int = 2) -> dict:
    """What the image itself says about the same held-out pixels as ``single_view_floor``: each
    predicted by the mean of its four neighbours that are not held out, scored as E is
    (``neural.field_error``). No field: the bound that the texture and the cameras' noise set on
    predicting a pixel from the pixels around it."""
    from volcap_color.neural import _held_out_split
    from volcap_color.neural_samples import view_samples
    from volcap_eval.color import distorted_frame_views
    views, _ = distorted_frame_views(SHARED / 'rgbd_box', SHARED / 'rgbd_box' / 'intrinsics.K.txt', 8, seed)
    view = views[camera]
    h, w = view.depth.shape
    pixels = view_samples(view, None, np.random.default_rng(seed), 0)
    held, _ = _held_out_split(pixels, [view.name], seed)    # harmonise splits with cfg.seed = seed
    x = np.rint(pixels.xy[held, 0] * w - 0.5).astype(int)
    y = np.rint(pixels.xy[held, 1] * h - 0.5).astype(int)
    known = np.ones((h + 2, w + 2), bool)
    known[[0, -1]] = known[:, [0, -1]] = False       # a border of unknown pixels
    known[y + 1, x + 1] = False
    image = np.zeros((h + 2, w + 2, 3), np.float64)
    image[1:-1, 1:-1] = view.color
    total, count = np.zeros((len(held), 3)), np.zeros((len(held), 1))
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        k = known[y + 1 + dy, x + 1 + dx][:, None]
        total += k * image[y + 1 + dy, x + 1 + dx]
        count += k
    sq = (total / np.maximum(count, 1) - view.color[y, x]) ** 2
    pixel = np.sqrt(sq.mean(1))
    return {'seed': seed, 'camera': view.name, 'rms_levels': float(np.sqrt(sq.mean())),
            'median_levels': float(np.median(pixel)), 'pixels': len(held)}


def exposure_floor(seed: int) -> dict:
    """What a perfect harmoniser scores against rgbd_box's truth. The eight views are frames of
    one hand-held camera whose exposure changed between them, and the truth (the undistorted
    image) keeps each frame's own; a harmoniser gives them one exposure. Each frame's exposure
    in the true images is solved from the fitted half of the correspondences (the median log
    ratio of luminance per pair, least squares over the pairs, geometric mean 1); the true
    colours with those exposures divided out are then scored as every method is, on the scored
    half (``volcap_eval.color.truth_scores``, one 3x3 shared)."""
    from volcap_color.correspondence import find_correspondences, merge_matches
    from volcap_color.model_choice import split_matches
    from volcap_core.color import LUMINANCE, ColorModel, srgb_to_linear
    from volcap_eval.color import ColorEvalConfig, distorted_frame_views, truth_mapping, truth_scores
    folder, cfg = SHARED / 'rgbd_box', ColorEvalConfig()
    views, responses = distorted_frame_views(folder, folder / 'intrinsics.K.txt', 8, seed)
    cameras, sizes = [v.name for v in views], {v.name: (v.camera.width, v.camera.height) for v in views}
    fit, scored = split_matches(merge_matches([find_correspondences(views, cfg.correspondence)], cfg.fit_min_fraction),
                                seed=cfg.seed)

    def truth(camera, colors, pixels):
        return responses[camera].true_colors(colors, pixels, sizes[camera])
    rows, rhs = [], []
    for (a, b), m in fit.items():
        ya = srgb_to_linear(truth(a, m.colors_a, m.pixels_a.astype(np.float64))) @ LUMINANCE
        yb = srgb_to_linear(truth(b, m.colors_b, m.pixels_b.astype(np.float64))) @ LUMINANCE
        ok = (ya > 0.01) & (yb > 0.01) & (ya < 0.9) & (yb < 0.9)
        if ok.sum() < 50:
            continue
        row = np.zeros(len(cameras))
        row[cameras.index(a)], row[cameras.index(b)] = 1.0, -1.0
        rows.append(row * np.sqrt(ok.sum()))
        rhs.append(np.median(np.log(ya[ok] / yb[ok])) * np.sqrt(ok.sum()))
    # only differences are constrained: lstsq's minimum-norm solution holds the mean log exposure at 0
    log_e = np.linalg.lstsq(np.vstack(rows), np.array(rhs), rcond=None)[0]
    exposure = dict(zip(cameras, np.exp(log_e)))
    equalised = {c: truth_mapping(truth, c, sizes[c]).followed_by(ColorModel('matrix_3x3', np.eye(3) / exposure[c]))
                 for c in cameras}
    scores = truth_scores(scored, equalised, truth, cfg.max_scored_per_pair, cfg.seed)
    return {'seed': seed, 'exposures': {c: float(v) for c, v in exposure.items()},
            'truth_de2000': scores['truth_de2000']}


def cross_view_floor(seed: int, surface: SurfaceConfig = SurfaceConfig(), radius_mm: float = 0.75) -> dict:
    """What the other views say about E's held-out pixels, with every colour response known:
    on rgbd_box the true (undistorted) images, each held-out pixel of a camera predicted from
    the training pixels of the other cameras at its surface point (the nearest of each within
    ``radius_mm`` on the surface E trains on, averaged in linear light), each camera's exposure
    against the other's taken out by a least-squares gain per channel. No field: the bound that
    the views' disagreement (the hand-held camera's shading and exposure from frame to frame,
    colour-to-depth registration, depth noise) sets on any one colour per surface point seen
    through a per-camera response, with the same split as E (``neural._held_out_split``). Beside
    it the same pixels predicted from their own camera's nearest training pixels on the
    surface, within the same radius (what ``image_floor`` measures, through the surface).

    The one colour closest to every view (``one_colour``: the mean of the views there, the
    held-out pixel's own included) is the best any field of one colour per point can do for
    these pixels with the views' poses as given; E's small rigid correction of each view
    (``register_views``) could take some of the disagreement away, so it is an estimate, not a
    proof. ``radius_mm`` 0.75: half the pixel footprint on the box (about 1.5 mm), so a match
    is the same place; at 2 mm the nearest pixel's offset adds texture edges to the
    disagreement (19.6-19.7 levels against 18.0 on seeds 0-2) and 98 % of the pixels match
    against 89-90 %. The levels are the true images', not the recorded ones E is scored on
    (their gains are within about +-30 %)."""
    from scipy.spatial import cKDTree

    from volcap_color.neural import _held_out_split, error_spread
    from volcap_color.neural_samples import training_samples
    from volcap_core.color import linear_to_srgb, srgb_to_linear
    from volcap_eval.color import distorted_frame_views, spread_frames
    from volcap_pipeline.harmonise import surface_of
    from volcap_pipeline.rig import read_frames_folder
    folder = SHARED / 'rgbd_box'
    views, _ = distorted_frame_views(folder, folder / 'intrinsics.K.txt', 8, seed)
    _, _, frames = read_frames_folder(folder, folder / 'intrinsics.K.txt')
    # the frames distorted_frame_views took, in its order: their true colours, linear
    truth = [srgb_to_linear(frames[i][2] / 255.0) for i in spread_frames(len(frames), len(views))]
    cameras = [v.name for v in views]
    source = surface_of(surface)
    placed = source(views)[0] if source is not None else views
    pixels = training_samples([placed], cameras, None, seed)       # as harmonise: every pixel with depth
    held, rest = _held_out_split(pixels, cameras, seed)
    h, w = views[0].depth.shape
    xy = np.rint(pixels.xy * (w, h) - 0.5).astype(int)
    lin = np.zeros((len(pixels), 3))
    for c in range(len(cameras)):
        mine = pixels.camera == c
        lin[mine] = truth[c][xy[mine, 1], xy[mine, 0]]
    trees = {c: cKDTree(pixels.points[rest[pixels.camera[rest] == c]]) for c in range(len(cameras))}
    rest_of = {c: rest[pixels.camera[rest] == c] for c in range(len(cameras))}
    radius = radius_mm / 1000
    cross_sq, bound_sq, own_sq, matched, total = [], [], [], 0, 0
    for i in range(len(cameras)):
        mine = held[pixels.camera[held] == i]
        total += len(mine)
        target = lin[mine]
        # own camera: the nearest training pixel on the surface
        d, k = trees[i].query(pixels.points[mine], distance_upper_bound=radius)
        ok = np.isfinite(d)
        own_sq.append(((linear_to_srgb(lin[rest_of[i][k[ok]]]) - linear_to_srgb(target[ok])) * 255) ** 2)
        # the other cameras: each one's nearest, its exposure against camera i taken out
        acc, count = np.zeros_like(target), np.zeros((len(mine), 1))
        for j in range(len(cameras)):
            if j == i:
                continue
            d, k = trees[j].query(pixels.points[mine], distance_upper_bound=radius)
            ok = np.isfinite(d)
            if ok.sum() < 100:
                continue
            theirs = lin[rest_of[j][k[ok]]]
            gain = (theirs * target[ok]).sum(0) / np.maximum((theirs ** 2).sum(0), 1e-12)
            acc[ok] += theirs * gain
            count[ok] += 1
        ok = count[:, 0] > 0
        matched += int(ok.sum())
        cross_sq.append(((linear_to_srgb(acc[ok] / count[ok]) - linear_to_srgb(target[ok])) * 255) ** 2)
        # the one colour closest to every view there, the held-out pixel's own included
        best = (acc[ok] + target[ok]) / (count[ok] + 1)
        bound_sq.append(((linear_to_srgb(best) - linear_to_srgb(target[ok])) * 255) ** 2)
    summary = lambda sq: error_spread(np.concatenate(sq))      # noqa: E731
    return {'seed': seed, 'surface': surface.surface, 'radius_mm': radius_mm, 'held_out': total,
            'matched_share': matched / max(1, total), 'other_views': summary(cross_sq),
            'one_colour': summary(bound_sq), 'own_view': summary(own_sq)}


def _true_crosstalk(bag: Path, models: dict):
    """``chart_crosstalk`` that answers each camera's true crosstalk (the studio's ground truth)
    for the chart models of ``models``: E's responses, the reference and D take it in place of the
    charts' estimate; the anchor still comes from the charts."""
    from unittest import mock

    from volcap_studio.session import GroundTruth
    truth = {c: np.asarray(v['color_response']['crosstalk'], float) for c, v in GroundTruth(bag).doc['cameras'].items()}
    camera_of = {id(m): c for c, m in models.items()}
    return mock.patch('volcap_color.neural.chart_crosstalk', lambda model: truth[camera_of[id(model)]])


def _sheen_chart_fit():
    """`volcap calibrate`'s chart fit with ``bench/chart_models.py``'s sheen prototype in place of
    the matte ``view_illumination`` (patched here only). Returns (the patch, the offsets it used)."""
    from unittest import mock

    import chart_models

    from volcap_calib.calibrate import Calibrator
    used = {}

    def illumination(calibrator):
        E, used['offsets'] = chart_models._illumination_with_offsets(calibrator, sheen=True)
        return E

    def color_samples(calibrator, camera, illumination):
        return chart_models._samples(calibrator, camera, illumination, used['offsets'])
    patch = contextlib.ExitStack()
    patch.enter_context(mock.patch.object(Calibrator, 'illumination', illumination))
    patch.enter_context(mock.patch.object(Calibrator, 'color_samples', color_samples))
    return patch, used


def studio(seed: int, out: Path, cfg: HarmoniseConfig, surface: SurfaceConfig = SurfaceConfig(),
           crosstalk: str = 'chart', chart_fit: str = 'matte') -> dict:
    from volcap_bringup.demo_cli import DemoConfig
    from volcap_calib.run import CalibrateConfig
    from volcap_calib.run import run as calibrate
    from volcap_color import neural
    from volcap_color.correspondence import cameras_in
    from volcap_core.calibration import Calibration
    from volcap_eval.color import ColorEvalConfig
    from volcap_eval.color import run as evaluate_color
    from volcap_pipeline import harmonise
    from volcap_pipeline.replay import capture_views
    from volcap_studio.session import synthesize
    from volcap_studio.studio import SynthConfig
    demo = DemoConfig()
    bag, calibration = out / f'studio_seed{seed}', out / f'studio_seed{seed}.calibration.yaml'
    if not calibration.exists():
        if not (bag / 'metadata.yaml').exists():
            synthesize(bag, SynthConfig(cameras=8, frames=demo.colour_frames, board_poses=demo.board_poses,
                                        board_layout=demo.board_layout, background_frames=3, seed=seed), overwrite=True)
        if chart_fit == 'sheen':
            patch, used = _sheen_chart_fit()
            with patch:
                calibrate(CalibrateConfig(bag, calibration))
            if not used.get('offsets'):
                raise RuntimeError('--chart-fit sheen did not reach the calibration (Calibrator.illumination is no '
                                   'longer where volcap calibrate fits the charts)')
        else:
            calibrate(CalibrateConfig(bag, calibration))
    rig = Calibration.load(calibration)
    t0 = time.perf_counter()
    sets = capture_views(bag, rig, demo.colour_frames, False)
    models = out / f'studio_seed{seed}.neural'
    short = replace(cfg, seed=seed, **{k: v for k, v in demo.harmonise().items() if k != 'seed'})
    charts = neural.chart_models(rig)
    with _true_crosstalk(bag, charts) if crosstalk == 'truth' else contextlib.nullcontext():
        trained = harmonise.run(sets, cameras_in(sets, rig), short, models, surface, progress=False,
                                views_seconds=0.0, chart_models=charts)
    if crosstalk == 'truth':
        # the patch reached the training: the manifest records the true matrices, not the charts'
        from volcap_studio.session import GroundTruth
        true = GroundTruth(bag).doc['cameras']
        used = trained.manifest['crosstalk'] or {}
        if set(used) != set(true) or any(not np.allclose(used[c], true[c]['color_response']['crosstalk'], atol=1e-4)
                                         for c in used):
            raise RuntimeError('--crosstalk truth did not reach the harmonisation (volcap_color.neural.chart_crosstalk '
                               'is no longer where the training looks it up)')
    harmonise_s = time.perf_counter() - t0
    report = evaluate_color(bag, calibration, ColorEvalConfig(frames=demo.colour_frames), neural=models,
                            progress=False)
    (out / f'studio_seed{seed}.json').write_text(json.dumps(report, indent=1, default=float))
    rows = report['methods']
    return {'seed': seed, 'harmonise_seconds': harmonise_s, 'anchor': trained.manifest['anchor'], 'crosstalk': crosstalk,
            'chart_fit': chart_fit,
            'field_held_out_rms': trained.manifest['field_error']['rms_levels'], 'texture': trained.manifest['texture'],
            'surface': surface_summary(trained.manifest),
            'methods': {n: _row(rows, n) for n in rows}}


def live_form(models: Path) -> dict:
    from volcap_color.neural_models import load_harmonisation
    harm = load_harmonisation(models)
    image = np.random.default_rng(0).integers(0, 256, (720, 1280, 3), dtype=np.uint8)
    cam = harm.cameras[0]
    live = ImageCorrector(RegionLut.load(models / f'{cam}.lut.npz'))
    out = live(image)
    live_ms = median_ms(lambda: live(image, out), repeat=30)
    ys, xs = np.mgrid[0:720, 0:1280]
    xy = np.stack([(xs.reshape(-1) + 0.5) / 1280, (ys.reshape(-1) + 0.5) / 720], axis=1)
    net_ms = median_ms(lambda: harm.map_colors(cam, image.reshape(-1, 3) / 255.0, xy), repeat=3)
    return {'region_lut_ms': live_ms, 'torch_network_ms': net_ms}


def _f(v, d=2):
    return '-' if v is None else f'{v:.{d}f}'


def _on_surface(r: dict) -> str:
    s = r['surface']
    if s['kept'] is None:
        return f"; pixels on the {s['source']} depth"
    return (f"; pixels on the {s['source']} surface: {s['kept']:.0%} kept, the views {s['median_difference_mm']:.1f} mm "
            f"from it, {s['seconds']:.0f} s")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', default='bench_out/neural')
    p.add_argument('--frames-seeds', type=int, nargs='*', default=[0, 1, 2])
    p.add_argument('--studio-seeds', type=int, nargs='*', default=[7, 0])
    p.add_argument('--field', default='hashgrid', choices=('hashgrid', 'paper'))
    p.add_argument('--surface', default=SurfaceConfig().surface, choices=('fused', 'views'),
                   help='where the training pixels lie (volcap harmonise --surface)')
    p.add_argument('--single-view-floor', type=int, nargs='*', default=[0], metavar='SEED',
                   help='rgbd_box seeds on which to fit E to one view alone, the floor of its held-out RMS')
    p.add_argument('--exposure-floor', type=int, nargs='*', default=[0, 1, 2], metavar='SEED',
                   help='rgbd_box seeds on which to score the true colours with each frame\'s own exposure divided '
                        'out: what a perfect harmoniser scores against the truth (no training, seconds)')
    p.add_argument('--cross-view-floor', type=int, nargs='*', default=[0, 1, 2], metavar='SEED',
                   help='rgbd_box seeds on which to score the one colour per surface point closest to every view '
                        '(the true images; no training, seconds)')
    p.add_argument('--crosstalk', default='chart', choices=('chart', 'truth'),
                   help="studio: the crosstalk E, the reference and D take: the charts' estimate (volcap harmonise) "
                        "or, to bound what a better estimate gives, each camera's true one")
    p.add_argument('--chart-fit', default='matte', choices=('matte', 'sheen'),
                   help="studio: calibrate the charts as volcap calibrate does (matte) or with bench/chart_models.py's "
                        "sheen prototype (give it its own --out)")
    args = p.parse_args()
    transport.configure()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = HarmoniseConfig(field=args.field)
    surface = SurfaceConfig(surface=args.surface)
    device = 'cuda' if torch.cuda.is_available() else 'cpu'
    result = {'device': device, 'threads': torch.get_num_threads(), 'field': args.field, 'surface': args.surface,
              'crosstalk': args.crosstalk,
              'commit': commit(), 'real_texture': [],
              'studio': []}
    for seed in args.frames_seeds:
        r = real_texture(seed, out, cfg, surface)
        result['real_texture'].append(r)
        m = r['methods']
        print(f"rgbd_box seed {seed}: harmonise {r['harmonise_seconds']:.0f} s (E {r['field_seconds']:.0f} s, "
              f"D {r['mapper_seconds']:.0f} s; target <= 600), E held-out RMS {r['field_held_out_rms']:.2f} levels "
              f"(target <= 6; median {r['field_held_out_median']:.1f}, 95 % best {r['field_held_out_rms_best_95']:.1f}; "
              f"{r['grid_cell_mm']:.1f} mm cells); truth CIEDE2000 neural {_f(m['neural']['truth_de2000'])} / live "
              f"{_f(m['neural_live']['truth_de2000'])} (target <= 1.6; gain model "
              f"{_f(m['volcap_chart_free']['truth_de2000'])}, untouched {_f(m['original']['truth_de2000'])}); "
              f"pairwise {_f(m['neural']['de2000_mean'])} (floor {_f(m['true_colours']['de2000_mean'])}, target <= "
              f"floor + 0.3); saturated chroma {_f(m['neural']['chroma_after'], 1)} vs truth's "
              f"{_f(m['true_colours']['chroma_after'], 1)} (target within 10 %); each camera's exposure against the "
              f"truth: neural {_exposures(m, 'neural')}, gain model {_exposures(m, 'volcap_chart_free')}"
              f"{_on_surface(r)}", flush=True)
    result['single_view_floor'] = []
    for seed in args.single_view_floor:
        r = single_view_floor(seed, out, cfg)
        result['single_view_floor'].append(r)
        print(f"rgbd_box seed {seed}, E on {r['camera']} alone ({r['epochs']} epochs): held-out RMS "
              f"{r['rms_levels']:.2f} levels (median {r['median_levels']:.1f}, 95 % best "
              f"{r['rms_best_95_levels']:.1f}): the floor the 8 views' E is held to", flush=True)
        r = image_floor(seed)
        result['single_view_floor'][-1]['image_floor'] = r
        print(f"rgbd_box seed {seed}, the same held-out pixels of {r['camera']} from their 4 image neighbours: RMS "
              f"{r['rms_levels']:.2f} levels (median {r['median_levels']:.1f}): what the image allows", flush=True)
    result['exposure_floor'] = []
    for seed in args.exposure_floor:
        r = exposure_floor(seed)
        result['exposure_floor'].append(r)
        e = r['exposures']
        print(f"rgbd_box seed {seed}, the frames' own exposures in the true images {min(e.values()):.3f}-"
              f"{max(e.values()):.3f} ({', '.join(f'{c} {v:.3f}' for c, v in e.items())}); the true colours with "
              f"them divided out (a perfect harmoniser) score {r['truth_de2000']:.2f} CIEDE2000 against the truth",
              flush=True)
    result['cross_view_floor'] = []
    for seed in args.cross_view_floor:
        r = cross_view_floor(seed, surface)
        result['cross_view_floor'].append(r)
        o, one, own = r['other_views'], r['one_colour'], r['own_view']
        print(f"rgbd_box seed {seed}, E's held-out pixels from the true images on the {r['surface']} surface "
              f"({100 * r['matched_share']:.0f} % with another view within {r['radius_mm']} mm): the other views "
              f"predict them to {o['rms_levels']:.2f} levels RMS (median {o['median_levels']:.1f}); the one colour "
              f"closest to every view there, the pixel's own included, {one['rms_levels']:.2f} (median "
              f"{one['median_levels']:.1f}, 95 % best {one['rms_best_95_levels']:.1f}): what any field of one colour "
              f"per point allows with the views' poses as given; the same camera's nearest pixels "
              f"{own['rms_levels']:.2f} (median {own['median_levels']:.1f})", flush=True)
    for seed in args.studio_seeds:
        r = studio(seed, out, cfg, surface, args.crosstalk, args.chart_fit)
        result['studio'].append(r)
        m = r['methods']
        others = {n: v for n, v in m.items() if n not in ('neural', 'neural_live', 'true_colours')}
        best_pair = min((v['de2000_mean'], n) for n, v in others.items() if v['de2000_mean'] is not None)
        best_truth = min((v['truth_de2000'], n) for n, v in others.items() if v['truth_de2000'] is not None)
        print(f"studio seed {seed}: harmonise (demo's short run) {r['harmonise_seconds']:.0f} s (target <= 180), "
              f"anchor {r['anchor']}, the {args.crosstalk}'s crosstalk, the {args.chart_fit} chart fit; "
              f"neural pairwise {_f(m['neural']['de2000_mean'])} vs best other "
              f"{best_pair[0]:.2f} ({best_pair[1]}); truth {_f(m['neural']['truth_de2000'])} vs best other "
              f"{best_truth[0]:.2f} ({best_truth[1]}); untouched truth {_f(m['original']['truth_de2000'])}; "
              f"true colours' pairwise (the floor) {_f(m['true_colours']['de2000_mean'])}; each camera's exposure "
              f"against the truth: neural {_exposures(m, 'neural')}, chart-free {_exposures(m, 'volcap_chart_free')}"
              f"{_on_surface(r)}", flush=True)
    if args.frames_seeds:
        result['live'] = live_form(out / f'frames_seed{args.frames_seeds[0]}')
        print(f"live form on 1280x720: region LUT {result['live']['region_lut_ms']:.1f} ms, torch D on every pixel "
              f"{result['live']['torch_network_ms']:.0f} ms")
    path = out / 'bench_neural.json'
    path.write_text(json.dumps(result, indent=2, default=float))
    print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
