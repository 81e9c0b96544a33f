"""The `volcap eval ...` verbs: every stage scored against ground truth or real data.

The only command-line module, with ``demo_cli``, that may import ``volcap_eval`` (the
import-linter contract "production code never imports the evaluation"): production commands
drive ``volcap_pipeline``; these score what it made.
"""
from __future__ import annotations

from pathlib import Path

from volcap_core.errors import BadInput
from volcap_core.files import write_json
from volcap_core.settings import add_arguments, config_from_args
from volcap_eval.config import ColorEvalConfig

from .color_cli import _correspondence, common_arguments, harmonise_arguments, harmonise_config, surface_config


def cmd_eval_depth(args) -> int:
    from volcap_eval.depth import METHODS, evaluate_depth, format_report, write_report
    methods = tuple(args.methods.split(',')) if args.methods else METHODS
    report = evaluate_depth(args.bag, methods=methods, max_frames=args.frames,
                            figures=Path(args.figures) if args.figures else None, progress=not args.quiet)
    print(format_report(report))
    if args.json:
        write_report(report, Path(args.json))
        print(f'wrote {args.json}')
    return 0


def cmd_eval_registration(args) -> int:
    from volcap_eval.depth import write_report
    from volcap_eval.registration import check_registration
    report = check_registration(args.bag, Path(args.out), camera=args.camera)
    print(f"{report['camera']}: depth edges lie {report['median_offset_px']:.2f} px (median) from colour edges "
          f"over {report['edge_pixels']} edge pixels; best global shift {report['best_shift_px']} px "
          f"(median there {report['median_offset_at_best_shift_px']:.2f} px); overlay {args.out}")
    if args.json:
        write_report(report, Path(args.json))
    return 0


def cmd_eval_calib(args) -> int:
    from volcap_eval.calib import evaluate_calibration, format_report
    report = evaluate_calibration(args.calibration, args.bag, args.board, args.figures, not args.quiet)
    print(format_report(report))
    if args.json:
        write_json(args.json, report)
        print(f'wrote {args.json}')
    return 0


def cmd_eval_chart(args) -> int:
    from volcap_eval.chart import evaluate_charts
    report, lines = evaluate_charts(args.photos, args.method or None, args.figures)
    print('\n'.join(lines))
    if args.json:
        write_json(args.json, report)
        print(f'wrote {args.json}')
    return BadInput.exit_code if report['failed'] else 0     # a photo without a chart: the user's to fix


def _print_report(report: dict, args) -> int:
    from volcap_eval.color import format_report
    print(format_report(report))
    if 'table1_skipped' in report:
        print(f'chart table left out: {report["table1_skipped"]}')
    if args.json:
        write_json(args.json, report)
        print(f'wrote {args.json}')
    for f in report.get('figures', []):
        print(f'wrote {f}')
    return 0


def cmd_eval_color(args) -> int:
    from volcap_eval.color import run
    cfg = config_from_args(ColorEvalConfig, args, correspondence=_correspondence(args))
    report = run(args.bag, args.calibration, cfg,
                 board_file=args.board, chart=not args.no_chart, neural=args.neural, figures=args.figures,
                 progress=not args.quiet)
    return _print_report(report, args)


def cmd_eval_color_frames(args) -> int:
    from volcap_eval.color import evaluate_frames_color
    from volcap_eval.color_figures import write_color_figures
    harmonise = (args.harmonise, harmonise_config(args, seed=args.seed)) if args.harmonise else None
    report, extras = evaluate_frames_color(args.folder, args.intrinsics, args.views, args.seed,
                                           config_from_args(ColorEvalConfig, args), not args.quiet,
                                           harmonise, surface_config(args))
    if args.figures:
        report['figures'] = [str(p) for p in write_color_figures(args.figures, report, extras['views'],
                                                                 extras['mappings'], extras['models'])]
    return _print_report(report, args)


def cmd_eval_fusion(args) -> int:
    from volcap_core.calibration import Calibration
    from volcap_eval.fusion import evaluate_fusion, format_seams
    calibration = Calibration.load(args.calibration) if args.calibration else None
    report = evaluate_fusion(args.dir, args.bag, progress=not args.quiet, max_frames=args.frames,
                             seams=not args.no_seams, calibration=calibration)
    print(f'{report["frames"]} frames: accuracy {report["accuracy_mm"]:.2f} mm (mean distance to the subject), '
          f'completeness {100 * report["completeness"]:.1f} % of the observable surface within '
          f'{report["completeness_threshold_mm"]:.0f} mm ({100 * report["completeness_all"]:.1f} % of all of it)')
    if report['completeness_feet'] is not None:
        print(f'  lowest {100 * report["feet_m"]:.0f} cm of the subject (feet, floor contact): completeness '
              f'{100 * report["completeness_feet"]:.1f} %')
    if report.get('seams'):
        print(f'  {format_seams(report["seams"])}')
    if args.json:
        write_json(args.json, report)
        print(f'wrote {args.json}')
    return 0


def cmd_eval_stability(args) -> int:
    from volcap_eval.stability import evaluate_stability
    from volcap_fusion.stability import format_stability
    if args.first < 0 or (args.frames is not None and args.frames < 2):
        raise BadInput('--first must be 0 or more and --frames 2 or more')
    report = evaluate_stability(args.dir, args.bag, args.first, args.frames, progress=not args.quiet)
    print(f'{format_stability(report)} ({report["scored"]})')
    if args.json:
        write_json(args.json, report)
        print(f'wrote {args.json}')
    return 0


def add_parsers(esub) -> None:
    """The verbs under `volcap eval`."""
    ed = esub.add_parser('depth', help='depth cleaning on a synthetic bag: raw, paper Eq. 5 and ours')
    ed.add_argument('bag')
    ed.add_argument('--json', help='write the report here')
    ed.add_argument('--figures', help='write Fig. 13/15 style PNGs into this folder')
    ed.add_argument('--frames', type=int, default=None, help='score only the first N capture frame sets')
    ed.add_argument('--methods', default='', help='comma-separated subset of raw,paper_horizontal,paper_all,volcap')
    ed.add_argument('--quiet', action='store_true')
    ed.set_defaults(func=cmd_eval_depth)
    er = esub.add_parser('registration', help='edge offset of registered depth against colour (real recordings)')
    er.add_argument('bag')
    er.add_argument('--camera', default=None, help='camera name (default: the first in the rig)')
    er.add_argument('--out', default='registration_overlay.png', help='overlay PNG')
    er.add_argument('--json', help='write the measurements here')
    er.set_defaults(func=cmd_eval_registration)

    e = esub.add_parser('calib', help='a calibration against a synthetic bag\'s ground truth, with the paper baseline')
    e.add_argument('calibration')
    e.add_argument('bag')
    e.add_argument('--json', help='write the report here')
    e.add_argument('--figures', help='write PNGs into this folder')
    e.add_argument('--board', help='board YAML (default: the volcap board)')
    e.add_argument('--quiet', action='store_true')
    e.set_defaults(func=cmd_eval_calib)

    ch = esub.add_parser('chart', help='find a ColorChecker Classic in photos and correct it to the reference')
    ch.add_argument('photos', nargs='+')
    ch.add_argument('--method', default='', help='force a colour model instead of the leave-one-out choice')
    ch.add_argument('--json', help='write the report here')
    ch.add_argument('--figures', help='write one PNG per photo into this folder')
    ch.set_defaults(func=cmd_eval_chart)

    e = esub.add_parser('color', aliases=['colour'], help='every colour method on the same correspondences (papers 000 and 001)')
    common_arguments(e)
    e.add_argument('--json', help='write the report here')
    e.add_argument('--figures', help='write colour_methods.png and colour_images.png into this folder')
    e.add_argument('--no-chart', action='store_true', help='leave out the chart methods and table')
    add_arguments(e, ColorEvalConfig, ['chart_free_model'])
    e.add_argument('--neural', help='a volcap harmonise output folder: score its networks (neural) and live '
                                    'form (neural_live) too')
    e.set_defaults(func=cmd_eval_color)

    r = esub.add_parser('color-frames', aliases=['colour-frames'],
                            help='the colour methods on real texture: views of a posed RGB-D folder, each through '
                                 'its own colour response, scored against the undistorted images too')
    r.add_argument('folder', help='frame-NNNNNN.{color.png,depth.png,pose.txt} (e.g. ../shared/data/rgbd_box)')
    r.add_argument('--intrinsics', help='3x3 intrinsic matrix (default FOLDER/intrinsics.K.txt)')
    r.add_argument('--views', type=int, default=8, help='frames used as the cameras of one frame set')
    r.add_argument('--seed', type=int, default=0, help='seed of the colour responses (and of --harmonise)')
    add_arguments(r, ColorEvalConfig, ['chart_free_model'])
    r.add_argument('--json', help='write the report here')
    r.add_argument('--figures', help='write colour_methods.png and colour_images.png into this folder')
    r.add_argument('--quiet', action='store_true')
    r.add_argument('--harmonise', metavar='DIR', help='also train the neural method (volcap harmonise, settings '
                                                      'below) on the views into DIR and score it')
    harmonise_arguments(r, seed=False)
    r.set_defaults(func=cmd_eval_color_frames)

    e = esub.add_parser('fusion', help='fused sequence against the synthetic ground truth')
    e.add_argument('dir', help='a volcap run output folder')
    e.add_argument('bag', help='the synthetic bag it was made from')
    e.add_argument('--json', help='write the report here')
    e.add_argument('--frames', type=int, default=None, help='score only the first N frames')
    e.add_argument('--calibration', help='the colour models the run applied, for the seam score (default: the '
                                         'calibration the run\'s metrics.json names)')
    e.add_argument('--no-seams', action='store_true', help='leave the seam score out')
    e.add_argument('--quiet', action='store_true')
    e.set_defaults(func=cmd_eval_fusion)
    st = esub.add_parser('stability', help='frame-to-frame change of a fused sequence where the subject holds still: '
                                           'surface jitter, colour flicker, surface appearing or vanishing')
    st.add_argument('dir', help='a volcap run output folder')
    st.add_argument('bag', nargs='?', help='the synthetic bag it was made from (scores only the parts its ground '
                                           'truth holds still); without it every point is scored')
    st.add_argument('--first', type=int, default=0, help='first fused frame scored (a real take\'s still part)')
    st.add_argument('--frames', type=int, default=None, help='score only N frames from --first')
    st.add_argument('--json', help='write the report here')
    st.add_argument('--quiet', action='store_true')
    st.set_defaults(func=cmd_eval_stability)

