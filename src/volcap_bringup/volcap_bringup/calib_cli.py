"""``volcap board`` and ``volcap calibrate`` (the calibration evaluations are in ``eval_cli``)."""
from __future__ import annotations


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
    from volcap_calib.run import CalibrateConfig, run
    cfg = CalibrateConfig(args.bag, args.out, args.report, args.board, args.reference, not args.no_depth,
                          args.color_method or None, args.all_frames, args.icp, args.icp_frame, not args.quiet)
    try:
        report = run(cfg)
    except CalibrationError as e:
        print(f'calibration failed, {args.out} left as it was: {e}')
        return 1
    print('\n'.join(report.lines()))
    if report.outcome.weak and not args.accept_weak:
        print(f'{args.out} written but flagged weak (exit 3): show the board as advised and calibrate again, '
              'or pass --accept-weak to use it as it is')
        return 3
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
    c.add_argument('--reference', default=None, help='camera whose colour frame is the world (default: the first)')
    c.add_argument('--color-method', '--colour-method', default='', help='force a colour model instead of the leave-one-out choice')
    c.add_argument('--no-depth', action='store_true', help='reprojection only (no depth-to-plane residuals)')
    c.add_argument('--all-frames', action='store_true', help='use every frame set, not only the calibration phase')
    c.add_argument('--icp', action='store_true',
                   help='refine the poses by ICP of the subject\'s depth in a capture frame set of the bag')
    c.add_argument('--icp-frame', type=int, default=0, help='which capture frame set ICP uses (default: the first)')
    c.add_argument('--accept-weak', action='store_true',
                   help='exit 0 even when a camera\'s predicted pose error exceeds 0.1 deg / 2 mm')
    c.add_argument('--quiet', action='store_true')
    c.set_defaults(func=cmd_calibrate)

