"""``volcap eval colour`` and ``volcap colour-fit``."""
from __future__ import annotations

import json
from dataclasses import replace

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
    report, extras = evaluate_colour(args.bag, calibration, samples, _eval_config(args), not args.quiet)
    if why:
        report['table1_skipped'] = why
    print(format_report(report))
    if why:
        print(f'chart table left out: {why}')
    if args.json:
        atomic_write(args.json, lambda f: f.write(json.dumps(report, indent=2)), binary=False)
        print(f'wrote {args.json}')
    if args.figures:
        for p in write_colour_figures(args.figures, report, extras['views'], extras['mappings'], extras['models']):
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
    e.set_defaults(func=cmd_eval_colour)

    f = sub.add_parser('colour-fit', help='per-camera colour models from correspondences between the cameras')
    common(f)
    f.add_argument('--out', required=True, help='calibration.yaml to write (the input with new colour models)')
    f.add_argument('--model', default='affine_3x4', choices=('gain', 'gain_offset', 'matrix_3x3', 'affine_3x4'))
    f.add_argument('--reference', default='mean',
                   help='mean (no camera favoured), chart (on top of the calibration\'s chart models, anchored to '
                        'the bag\'s board views) or a camera name')
    f.set_defaults(func=cmd_colour_fit)
