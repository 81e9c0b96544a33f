"""``volcap board`` and ``volcap calibrate`` (the calibration evaluations are in ``eval_cli``)."""
from __future__ import annotations

from volcap_calib.config import CalibrateConfig
from volcap_core.errors import WeakCalibration
from volcap_core.settings import add_arguments, config_from_args


def cmd_board(args) -> int:
    from volcap_calib.board import write_board
    from volcap_calib.run import load_board
    board = load_board(args.config)
    out = write_board(args.out, board, dpi=args.dpi)
    x0, y0, x1, y1 = board.extent
    print(f'wrote {out}: {(x1 - x0) * 1000:.0f} x {(y1 - y0) * 1000:.0f} mm at {args.dpi} dpi '
          f'({board.squares_x}x{board.squares_y} ChArUco {board.dictionary}, 24-patch chart)')
    return 0


def cmd_calibrate(args) -> int:
    from volcap_calib.extrinsics import CalibrationError
    from volcap_calib.run import run
    cfg = config_from_args(CalibrateConfig, args, bag=args.bag, out=args.out, report_dir=args.report,
                           board_file=args.board, progress=not args.quiet)
    try:
        report = run(cfg)
    except CalibrationError as e:
        raise CalibrationError(f'calibration failed, {args.out} left as it was: {e}') from e
    print('\n'.join(report.lines()))
    if report.outcome.weak and not args.accept_weak:
        print(f'{args.out} written but flagged weak (exit {WeakCalibration.exit_code}): show the board as advised and '
              'calibrate again, or pass --accept-weak to use it as it is')
        return WeakCalibration.exit_code
    return 0


def add_parsers(sub) -> None:
    b = sub.add_parser('board', help='print the calibration board (PNG or PDF at true scale)')
    b.add_argument('--out', required=True, help='board.png or board.pdf')
    b.add_argument('--config', help='board YAML (default: the volcap board)')
    b.add_argument('--dpi', type=int, default=300)
    b.set_defaults(func=cmd_board)

    c = sub.add_parser('calibrate', help='extrinsic and colour calibration from a bag of board views')
    c.add_argument('bag')
    c.add_argument('--out', default='calibration.yaml')
    c.add_argument('--report', help='folder for the report JSON and PNGs (default: beside --out)')
    c.add_argument('--board', help='board YAML (default: the volcap board)')
    add_arguments(c, CalibrateConfig)
    c.add_argument('--accept-weak', action='store_true',
                   help='exit 0 even when a camera is weak (its predicted pose error, times --weak-margin, beyond '
                        '--max-rot-err-deg / --max-trans-err-mm)')
    c.add_argument('--quiet', action='store_true')
    c.set_defaults(func=cmd_calibrate)

