"""``volcap eval colour``, ``volcap colour-fit`` and ``volcap harmonise``."""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

from volcap_core.files import atomic_write

from .calib_cli import _board, calibrator_from_bag


def _chart_samples(bag, board, cameras, progress: bool) -> tuple[dict | None, str | None]:
    """Each camera's chart patches in the bag's board views (measured, reference under the
    view's light), or None and why."""
    from volcap_calib.calibrate import CalibrationConfig
    try:
        calibrator = calibrator_from_bag(bag, board, CalibrationConfig(), progress=progress)
    except ValueError as e:
        return None, str(e)
    if not any(calibrator.patches.values()):
        return None, 'no camera saw the chart in the board views'
    illumination = calibrator.illumination()
    return {c: calibrator.colour_samples(c, illumination)[:2] for c in cameras if calibrator.patches.get(c)}, None


def _eval_config(args):
    from volcap_color.evaluate import ColourEvalConfig
    cfg = ColourEvalConfig(frames=args.frames)
    if args.keep_edges:
        cfg = replace(cfg, correspondence=replace(cfg.correspondence, max_gradient=0.0))
    return cfg


def cmd_eval_colour(args) -> int:
    from volcap_color.evaluate import evaluate_colour, format_report
    from volcap_color.figures import write_colour_figures
    from volcap_core.calibration import Calibration
    calibration = Calibration.load(args.calibration)
    samples, why = (None, 'skipped (--no-chart)') if args.no_chart else \
        _chart_samples(args.bag, _board(args.board), list(calibration.cameras), not args.quiet)
    report, extras = evaluate_colour(args.bag, calibration, samples, _eval_config(args), not args.quiet,
                                     neural=args.neural)
    if why:
        report['table1_skipped'] = why
    print(format_report(report))
    if why:
        print(f'chart table left out: {why}')
    if args.json:
        atomic_write(args.json, lambda f: f.write(json.dumps(report, indent=2)), binary=False)
        print(f'wrote {args.json}')
    if args.figures:
        for p in write_colour_figures(args.figures, report, extras['views'], extras['mappings'], extras['models'],
                                      extras['region_luts']):
            print(f'wrote {p}')
    return 0


def cmd_colour_fit(args) -> int:
    from volcap_calib.colour import ColourModel
    from volcap_color.correspondence import find_correspondences
    from volcap_color.evaluate import cameras_in, capture_views, merge_matches
    from volcap_color.methods import chart_free_fit
    from volcap_core.calibration import Calibration
    calibration = Calibration.load(args.calibration)
    cfg = _eval_config(args)
    sets = capture_views(args.bag, calibration, args.frames, not args.quiet)
    cameras = cameras_in(sets, calibration)
    matches = merge_matches([find_correspondences(v, cfg.correspondence) for v in sets], cfg.fit_min_fraction)
    if not matches:
        raise ValueError(f'no camera pair of {args.bag} has {cfg.fit_min_fraction:.1%} of its pixels in correspondence')
    base, anchor = None, None
    if args.reference == 'chart':
        missing = [c for c in cameras if calibration.cameras[c].colour is None]
        if missing:
            raise ValueError(f'--reference chart needs chart colour models; {", ".join(missing)} have none')
        base = {c: ColourModel.from_dict(calibration.cameras[c].colour) for c in cameras}
        anchor, why = _chart_samples(args.bag, _board(args.board), cameras, not args.quiet)
        if anchor is None:
            raise ValueError(f'--reference chart needs the bag\'s board views: {why}')
    models = chart_free_fit(matches, cameras, args.model, args.reference, base=base, anchor=anchor)
    source = 'chart_harmonised' if base else 'chart_free'
    for c, m in models.items():
        previous = calibration.cameras[c].colour
        entry = {**m.to_dict(), 'source': source,
                 'fit': {'bag': str(args.bag), 'model': args.model, 'reference': args.reference,
                         'pairs': sum(c in p for p in matches), 'frame_sets': len(sets)}}
        if previous is not None:
            entry['previous'] = previous     # the chart fit, with its patch errors
        calibration.cameras[c].colour = entry
    calibration.save(args.out)
    print(f'{source} {args.model} models for {len(models)} cameras from {len(matches)} camera pairs '
          f'({sum(len(m) for m in matches.values())} correspondences); wrote {args.out}')
    return 0


def harmonise_config(args):
    from volcap_color.neural_config import HarmoniseConfig
    try:
        nx, ny = (int(v) for v in args.lut_grid.lower().split('x'))
    except ValueError:
        raise ValueError(f'--lut-grid is NXxNY, for example 9x5, not {args.lut_grid!r}') from None
    keys = ('points', 'field_epochs', 'field_batch', 'field_lr', 'field_lr_final', 'mapper_points', 'mapper_epochs',
            'mapper_batch', 'mapper_lr', 'mapper_lr_final', 'background', 'reference', 'lut_colours', 'seed',
            'device', 'precision')
    cfg = HarmoniseConfig(**{k: getattr(args, k) for k in keys}, lut_grid=(nx, ny))
    for k in ('points', 'field_epochs', 'field_batch', 'mapper_points', 'mapper_epochs', 'mapper_batch'):
        if getattr(cfg, k) < 1:
            raise ValueError(f'--{k.replace("_", "-")} must be at least 1')
    if not 0 <= cfg.background <= 4:
        raise ValueError('--background must be between 0 and 4')
    if cfg.lut_colours < 2 or nx < 2 or ny < 2:
        raise ValueError('--lut-colours and both --lut-grid sizes must be at least 2')
    return cfg


def cmd_harmonise(args) -> int:
    from volcap_color.evaluate import cameras_in, capture_views, split_frame_sets
    from volcap_color.figures import training_figure
    from volcap_color.neural import MANIFEST, export_live, harmonise
    from volcap_core.calibration import Calibration
    cfg = harmonise_config(args)
    calibration = Calibration.load(args.calibration)
    t0 = time.perf_counter()
    sets = capture_views(args.bag, calibration, args.frames, not args.quiet)
    cameras = cameras_in(sets, calibration)
    # 'even': the frame sets the colour evaluation fits on, so it scores D on frame sets it never saw
    trained, checked = split_frame_sets(len(sets)) if args.train_sets == 'even' else (list(range(len(sets))),) * 2
    t1 = time.perf_counter()
    harm = harmonise([sets[i] for i in trained], cameras, cfg, args.out, resume=args.resume, progress=not args.quiet)
    t2 = time.perf_counter()
    live = export_live(harm, args.out, [v for i in checked for v in sets[i]], progress=not args.quiet)
    t3 = time.perf_counter()
    manifest = {**harm.report, **live, 'bag': str(args.bag), 'calibration': str(args.calibration),
                'frame_sets': {'read': len(sets), 'trained': trained, 'checked': checked,
                               'checked_held_out': checked != trained},
                'seconds': {'views': t1 - t0, 'training': t2 - t1, 'export': t3 - t2, 'total': t3 - t0}}
    out = Path(args.out)
    atomic_write(out / MANIFEST, lambda f: f.write(json.dumps(manifest, indent=2)), binary=False)
    training_figure(out / 'training.png', manifest)
    err = live['export_error']
    print(f"E: {manifest['field_samples']} samples, {len(manifest['field']['losses'])} epochs, final RMS "
          f"{255 * manifest['field']['losses'][-1] ** 0.5:.2f} levels, {manifest['field']['seconds']:.0f} s "
          f"({manifest['device']}{', bf16' if manifest['bf16'] else ''})")
    for c in cameras:
        m, e = harm.report['mapper_error'].get(c), err.get(c)
        if m and e:
            print(f'{c}: D vs E\'s reference on held-out pixels RMS {m["rms_levels"]:.2f} levels; live LUT vs D '
                  f'mean {e["mean_levels"]:.2f}, '
                  f'p99 {e["p99_levels"]:.0f}, max {e["max_levels"]:.0f} levels')
    print(f'wrote {out}/ (manifest.json, field.pt, <camera>.mapper.pt, <camera>.lut.npz, training.png) '
          f'in {t3 - t0:.0f} s')
    return 0


def add_parsers(sub, eval_sub) -> None:
    def common(p):
        p.add_argument('bag')
        p.add_argument('--calibration', required=True, help='calibration.yaml of the rig')
        p.add_argument('--frames', type=int, default=4, help='capture frame sets to use')
        p.add_argument('--keep-edges', action='store_true', help='keep correspondences on texture edges')
        p.add_argument('--board', help='board YAML (default: the volcap board)')
        p.add_argument('--quiet', action='store_true')

    e = eval_sub.add_parser('colour', help='every colour method on the same correspondences (papers 000 and 001)')
    common(e)
    e.add_argument('--json', help='write the report here')
    e.add_argument('--figures', help='write colour_methods.png and colour_images.png into this folder')
    e.add_argument('--no-chart', action='store_true', help='leave out the chart methods and table')
    e.add_argument('--neural', help='a volcap harmonise output folder: score its networks (neural) and live '
                                    'form (neural_live) too')
    e.set_defaults(func=cmd_eval_colour)

    f = sub.add_parser('colour-fit', help='per-camera colour models from correspondences between the cameras')
    common(f)
    f.add_argument('--out', required=True, help='calibration.yaml to write (the input with new colour models)')
    f.add_argument('--model', default='affine_3x4', choices=('gain', 'gain_offset', 'matrix_3x3', 'affine_3x4'))
    f.add_argument('--reference', default='mean',
                   help='mean (no camera favoured), chart (on top of the calibration\'s chart models, anchored to '
                        'the bag\'s board views) or a camera name')
    f.set_defaults(func=cmd_colour_fit)

    from volcap_color.neural_config import HarmoniseConfig
    d = HarmoniseConfig()
    h = sub.add_parser('harmonise', help='train paper 001\'s colour field E and per-camera networks D (torch), '
                                         'and export them for color_corrector')
    common(h)
    h.add_argument('--out', required=True, help='folder for the models (created)')
    h.add_argument('--train-sets', choices=('even', 'all'), default='even',
                   help='train on the 1st, 3rd, ... frame set (the colour evaluation scores the others) or on all')
    h.add_argument('--points', type=int, default=d.points, help='surface samples for E')
    h.add_argument('--field-epochs', type=int, default=d.field_epochs)
    h.add_argument('--field-batch', type=int, default=d.field_batch)
    h.add_argument('--field-lr', type=float, default=d.field_lr)
    h.add_argument('--field-lr-final', type=float, default=d.field_lr_final,
                   help='decay the learning rate exponentially to this by the last epoch (default: constant)')
    h.add_argument('--mapper-points', type=int, default=d.mapper_points, help='pixels per camera for its D')
    h.add_argument('--mapper-epochs', type=int, default=d.mapper_epochs)
    h.add_argument('--mapper-batch', type=int, default=d.mapper_batch)
    h.add_argument('--mapper-lr', type=float, default=d.mapper_lr)
    h.add_argument('--mapper-lr-final', type=float, default=d.mapper_lr_final)
    h.add_argument('--background', type=float, default=d.background,
                   help='pixels without a surface point added to each D, per pixel with one, aimed at the camera\'s '
                        'affine map onto the reference (0: the paper, D sees the subject only)')
    h.add_argument('--reference', default=d.reference, help='camera whose colours D reproduces, or mean (E '
                                                            'averaged over every camera)')
    h.add_argument('--lut-colours', type=int, default=d.lut_colours, help='live form: colour nodes per axis')
    h.add_argument('--lut-grid', default='x'.join(map(str, d.lut_grid)), help='live form: image nodes, NXxNY')
    h.add_argument('--seed', type=int, default=d.seed)
    h.add_argument('--device', choices=('auto', 'cpu', 'cuda'), default=d.device)
    h.add_argument('--precision', choices=('auto', 'bf16', 'fp32'), default=d.precision)
    h.add_argument('--resume', action='store_true', help='carry on from the checkpoint in --out')
    h.set_defaults(func=cmd_harmonise)
