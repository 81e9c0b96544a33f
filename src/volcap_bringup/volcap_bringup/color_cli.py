"""``volcap color-fit`` and ``volcap harmonise`` (``colour-fit`` is an alias; the colour evaluations are in
``eval_cli``)."""
from __future__ import annotations

import time

from volcap_color.config import CaptureSetsConfig, ColorFitConfig
from volcap_core.errors import BadInput
from volcap_core.settings import add_arguments, config_from_args


def _correspondence(args):
    from volcap_color.correspondence import CorrespondenceConfig
    return CorrespondenceConfig(min_fraction=0.0, **({'max_gradient': 0.0} if args.keep_edges else {}))


def cmd_color_fit(args) -> int:
    from volcap_calib.run import chart_samples, load_board
    from volcap_color import fit
    from volcap_color.correspondence import cameras_in
    from volcap_core.calibration import Calibration
    from volcap_pipeline.replay import capture_views
    cfg = config_from_args(ColorFitConfig, args, correspondence=_correspondence(args))
    calibration = Calibration.load(args.calibration)
    sets = capture_views(args.bag, calibration, config_from_args(CaptureSetsConfig, args).frames, not args.quiet)
    anchor = None
    if cfg.reference == 'chart':
        anchor, why = chart_samples(args.bag, load_board(args.board), cameras_in(sets, calibration), not args.quiet)
        if anchor is None:
            raise BadInput(f'--reference chart needs the bag\'s board views: {why}')
    report = fit.run(cfg, sets, calibration, anchor, source_bag=str(args.bag))
    report.calibration.save(args.out)
    print(f'{report.line()}; wrote {args.out}')
    return 0


def harmonise_config(args, **fixed):
    """The training settings given on the command line (``harmonise_arguments``)."""
    from volcap_color.config import HarmoniseConfig
    return config_from_args(HarmoniseConfig, args, **fixed)


def surface_config(args):
    """Where the training pixels lie, as given on the command line (``harmonise_arguments``)."""
    from volcap_pipeline.harmonise import SurfaceConfig
    return config_from_args(SurfaceConfig, args)


def cmd_harmonise(args) -> int:
    from volcap_color import neural
    from volcap_color.correspondence import cameras_in
    from volcap_core.calibration import Calibration
    from volcap_pipeline import harmonise
    from volcap_pipeline.replay import capture_views
    cfg, surface = harmonise_config(args), surface_config(args)
    calibration = Calibration.load(args.calibration)
    t0 = time.perf_counter()
    sets = capture_views(args.bag, calibration, config_from_args(CaptureSetsConfig, args).frames, not args.quiet)
    report = harmonise.run(sets, cameras_in(sets, calibration), cfg, args.out, surface, train_sets=args.train_sets,
                           resume=args.resume, progress=not args.quiet,
                           sources={'bag': str(args.bag), 'calibration': str(args.calibration)},
                           views_seconds=time.perf_counter() - t0, chart_models=neural.chart_models(calibration))
    print('\n'.join(report.lines()))
    return 0


# The training settings `volcap harmonise` and `eval color-frames --harmonise` take; the others
# (the paper's network sizes and encodings) are set in code only.
HARMONISE_OPTIONS = ('field', 'points', 'field_epochs', 'field_batch', 'field_lr', 'field_lr_final', 'mapper_points',
                     'mapper_epochs', 'mapper_batch', 'mapper_lr', 'mapper_lr_final', 'mapper_input', 'mapper_width', 'mapper_layers',
                     'gamut', 'background', 'reference', 'anchor', 'anchor_fit', 'grid_levels', 'grid_log2_table',
                     'grid_cell_mm', 'register_views',
                     'crosstalk_from_chart',
                     'edge_levels', 'lut_colors', 'lut_grid', 'seed', 'device', 'precision')


def harmonise_arguments(h, seed: bool = True) -> None:
    """The training settings of ``volcap harmonise`` (HarmoniseConfig's and SurfaceConfig's own
    declarations), shared by ``eval color-frames`` (whose own ``--seed`` seeds the training too:
    ``seed=False``)."""
    from volcap_color.config import HarmoniseConfig
    from volcap_pipeline.harmonise import SurfaceConfig
    add_arguments(h, HarmoniseConfig, HARMONISE_OPTIONS, exclude=() if seed else ('seed',))
    add_arguments(h, SurfaceConfig)


def common_arguments(p) -> None:
    """The bag, calibration and correspondence arguments of every command that reads a rig's
    capture frame sets (``color-fit``, ``harmonise``, ``eval color``)."""
    p.add_argument('bag')
    p.add_argument('--calibration', required=True, help='calibration.yaml of the rig')
    add_arguments(p, CaptureSetsConfig)
    p.add_argument('--keep-edges', action='store_true', help='keep correspondences on texture edges')
    p.add_argument('--board', help='board YAML (default: the volcap board)')
    p.add_argument('--quiet', action='store_true')


def add_parsers(sub) -> None:
    f = sub.add_parser('color-fit', aliases=['colour-fit'], help='per-camera colour models from correspondences between the cameras')
    common_arguments(f)
    f.add_argument('--out', required=True, help='calibration.yaml to write (the input with new colour models)')
    add_arguments(f, ColorFitConfig, ['model', 'reference'])
    f.set_defaults(func=cmd_color_fit)

    h = sub.add_parser('harmonise', help='train paper 001\'s colour field E and per-camera networks D (torch), '
                                         'and export them for color_corrector')
    common_arguments(h)
    h.add_argument('--out', required=True, help='folder for the models (created)')
    h.add_argument('--train-sets', choices=('even', 'all'), default='even',
                   help='train on the 1st, 3rd, ... frame set (the colour evaluation scores the others) or on all')
    harmonise_arguments(h)
    h.add_argument('--resume', action='store_true', help='carry on from the checkpoint in --out')
    h.set_defaults(func=cmd_harmonise)
