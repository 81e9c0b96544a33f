"""``volcap color-fit`` and ``volcap harmonise`` (``colour-fit`` is an alias; the colour evaluations are in
``eval_cli``)."""
from __future__ import annotations

import time

from volcap_core.errors import BadInput


def _correspondence(args):
    from volcap_color.correspondence import CorrespondenceConfig
    return CorrespondenceConfig(min_fraction=0.0, **({'max_gradient': 0.0} if args.keep_edges else {}))


def cmd_color_fit(args) -> int:
    from volcap_calib.run import chart_samples, load_board
    from volcap_color import fit
    from volcap_color.correspondence import cameras_in
    from volcap_core.calibration import Calibration
    from volcap_pipeline.replay import capture_views
    calibration = Calibration.load(args.calibration)
    sets = capture_views(args.bag, calibration, args.frames, not args.quiet)
    anchor = None
    if args.reference == 'chart':
        anchor, why = chart_samples(args.bag, load_board(args.board), cameras_in(sets, calibration), not args.quiet)
        if anchor is None:
            raise BadInput(f'--reference chart needs the bag\'s board views: {why}')
    cfg = fit.ColorFitConfig(model=args.model, reference=args.reference, correspondence=_correspondence(args))
    report = fit.run(cfg, sets, calibration, anchor, source_bag=str(args.bag))
    report.calibration.save(args.out)
    print(f'{report.line()}; wrote {args.out}')
    return 0


def harmonise_config(args):
    from volcap_color.neural_config import HarmoniseConfig
    try:
        nx, ny = (int(v) for v in args.lut_grid.lower().split('x'))
    except ValueError:
        raise BadInput(f'--lut-grid is NXxNY, for example 9x5, not {args.lut_grid!r}') from None
    keys = ('points', 'field_epochs', 'field_batch', 'field_lr', 'field_lr_final', 'mapper_points', 'mapper_epochs',
            'mapper_batch', 'mapper_lr', 'mapper_lr_final', 'background', 'reference', 'lut_colors', 'seed',
            'device', 'precision')
    cfg = HarmoniseConfig(**{k: getattr(args, k) for k in keys}, lut_grid=(nx, ny))
    cfg.validate()
    return cfg


def cmd_harmonise(args) -> int:
    from volcap_color import neural
    from volcap_color.correspondence import cameras_in
    from volcap_core.calibration import Calibration
    from volcap_pipeline.replay import capture_views
    cfg = harmonise_config(args)
    calibration = Calibration.load(args.calibration)
    t0 = time.perf_counter()
    sets = capture_views(args.bag, calibration, args.frames, not args.quiet)
    report = neural.run(sets, cameras_in(sets, calibration), cfg, args.out, args.train_sets, args.resume,
                        not args.quiet, {'bag': str(args.bag), 'calibration': str(args.calibration)},
                        time.perf_counter() - t0)
    print('\n'.join(report.lines()))
    return 0


def harmonise_arguments(h, seed: bool = True) -> None:
    """The training settings of ``volcap harmonise`` (HarmoniseConfig), shared by ``eval color-frames``
    (whose own ``--seed`` seeds the training too: ``seed=False``)."""
    from volcap_color.neural_config import HarmoniseConfig
    d = HarmoniseConfig()
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
    h.add_argument('--lut-colors', '--lut-colours', type=int, default=d.lut_colors, help='live form: colour nodes per axis')
    h.add_argument('--lut-grid', default='x'.join(map(str, d.lut_grid)), help='live form: image nodes, NXxNY')
    if seed:
        h.add_argument('--seed', type=int, default=d.seed)
    h.add_argument('--device', choices=('auto', 'cpu', 'cuda'), default=d.device)
    h.add_argument('--precision', choices=('auto', 'bf16', 'fp32'), default=d.precision)


def common_arguments(p) -> None:
    """The bag, calibration and correspondence arguments of every command that reads a rig's
    capture frame sets (``color-fit``, ``harmonise``, ``eval color``)."""
    p.add_argument('bag')
    p.add_argument('--calibration', required=True, help='calibration.yaml of the rig')
    p.add_argument('--frames', type=int, default=4, help='capture frame sets to use')
    p.add_argument('--keep-edges', action='store_true', help='keep correspondences on texture edges')
    p.add_argument('--board', help='board YAML (default: the volcap board)')
    p.add_argument('--quiet', action='store_true')


def add_parsers(sub) -> None:
    f = sub.add_parser('color-fit', aliases=['colour-fit'], help='per-camera colour models from correspondences between the cameras')
    common_arguments(f)
    f.add_argument('--out', required=True, help='calibration.yaml to write (the input with new colour models)')
    f.add_argument('--model', default='auto', choices=('auto', 'gain', 'gain_offset', 'matrix_3x3', 'affine_3x4'),
                   help='auto: the simplest model that fits without hurting dark pixels (none for a consistent rig)')
    f.add_argument('--reference', default='mean',
                   help='mean (no camera favoured), chart (on top of the calibration\'s chart models, anchored to '
                        'the bag\'s board views) or a camera name')
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
