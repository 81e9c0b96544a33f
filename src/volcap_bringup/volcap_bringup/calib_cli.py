"""``volcap board``, ``volcap calibrate``, ``volcap eval calib`` and ``volcap eval chart``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from volcap_core.files import atomic_write


def _board(path: str | None):
    from volcap_calib.board import BoardConfig
    return BoardConfig.from_yaml(path) if path else BoardConfig.from_yaml()


def calibrator_from_bag(bag: str | Path, board, cfg, all_frames: bool = False, progress: bool = True):
    """A Calibrator fed with every frame set of the bag's calibration phase (or of the whole bag)."""
    from tqdm import tqdm
    from volcap_calib.calibrate import CameraFrame, Calibrator
    from volcap_core.topics import CALIBRATION_PHASE
    from volcap_driver.bag_io import BagReader
    from volcap_driver.frames import frame_sets, read_rig
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    calibrator = Calibrator(rig, board, cfg)
    sets = frame_sets(bag, phases=None if all_frames else (CALIBRATION_PHASE,))
    bar = tqdm(sets, desc='board views', unit='set', disable=not progress)
    for fs in bar:
        status = calibrator.add(fs.index, {n: CameraFrame(f.color, f.color_model, f.depth, f.depth_model)
                                           for n, f in fs.cameras.items()})
        bar.set_postfix(seen=sum('corners' in s for s in status.values()), observations=len(calibrator.observations))
    if calibrator.views == 0:
        raise ValueError(f'{bag} has no frame sets in the {CALIBRATION_PHASE!r} phase'
                         + ('' if all_frames else '; pass --all-frames to use every frame set'))
    return calibrator


def _config(args):
    from volcap_calib.calibrate import CalibrationConfig
    from volcap_calib.extrinsics import SolverConfig
    return CalibrationConfig(reference=args.reference, use_depth=not args.no_depth,
                             colour_method=args.colour_method or None,
                             solver=SolverConfig(depth_weight=0.0 if args.no_depth else 1.0))


def cmd_board(args) -> int:
    from volcap_calib.board import write_board
    board = _board(args.config)
    out = write_board(args.out, board, dpi=args.dpi)
    x0, y0, x1, y1 = board.extent
    print(f'wrote {out}: {(x1 - x0) * 1000:.0f} x {(y1 - y0) * 1000:.0f} mm at {args.dpi} dpi '
          f'({board.squares_x}x{board.squares_y} ChArUco {board.dictionary}, 24-patch chart)')
    return 0


def cmd_calibrate(args) -> int:
    from volcap_calib.evaluate import colour_report, colour_summary
    from volcap_calib.extrinsics import CalibrationError
    from volcap_calib.report import colour_figure, poses_figure
    calibrator = calibrator_from_bag(args.bag, _board(args.board), _config(args), args.all_frames, not args.quiet)
    try:
        outcome = calibrator.solve()
    except CalibrationError as e:
        print(f'calibration failed, {args.out} left as it was: {e}')
        return 1
    calibration = outcome.calibration
    icp = _icp_refinement(args.bag, calibration, args.icp_frame) if args.icp else None
    calibration.save(args.out)
    out = Path(args.out)
    report_dir = Path(args.report) if args.report else out.parent
    stem = out.stem
    colour = colour_report(calibration, calibrator)
    report = {'calibration': str(out), 'reference': calibration.reference, 'frame_sets': calibrator.views,
              'cameras': {c: outcome.extrinsics.cameras[c].to_dict() for c in calibration.cameras},
              'colour': colour, 'colour_average': colour_summary(colour), 'colour_errors': outcome.colour_errors}
    if icp is not None:
        report['icp'] = icp
    json_path = atomic_write(report_dir / f'{stem}_report.json',
                             lambda f: f.write(json.dumps(report, indent=2)), binary=False)
    poses_figure(report_dir / f'{stem}_poses.png', outcome.extrinsics.T_world_color, outcome.extrinsics.T_world_target,
                 report['cameras'])
    if colour:
        colour_figure(report_dir / f'{stem}_colour.png', colour)
    print(f'wrote {out} ({len(calibration.cameras)} cameras, {len(calibrator.observations)} board observations '
          f'in {calibrator.views} frame sets); report {json_path}')
    for c, rep in outcome.extrinsics.cameras.items():
        col = colour.get(c)
        depth = f'{rep.depth_rms_mm:5.2f} mm' if rep.depth_rms_mm is not None else '   -    '
        col_txt = (f'  colour {col["method"]:<18} dE2000 {col["patch_de2000_before"]:5.2f} -> '
                   f'{col["patch_de2000_after"]:4.2f}') if col else '  colour -'
        print(f'  {c}: {rep.views:2d} views  reproj {rep.reproj_rms_px:.3f} px  depth {depth}{col_txt}')
    for c, why in outcome.colour_errors.items():
        print(f'  {c}: no colour model: {why}')
    for c, rep in (icp or {}).get('cameras', {}).items():
        print(f'  {c}: ICP {"moved" if rep["accepted"] else "kept  "} {rep["rotation_deg"]:.3f} deg '
              f'{rep["translation_mm"]:5.2f} mm, inlier RMSE {rep["rmse_before_mm"]:.2f} -> {rep["rmse_after_mm"]:.2f} mm'
              + (f' ({rep["reason"]})' if rep['reason'] else ''))
    return 0


def _icp_refinement(bag, calibration, frame: int) -> dict:
    """ICP of the subject's depth in one capture frame set of the bag; updates ``calibration``."""
    from volcap_calib.extrinsics import depth_points
    from volcap_calib.icp import refine_with_icp
    from volcap_core.topics import CAPTURE
    from volcap_driver.bag_io import BagReader
    from volcap_driver.frames import frame_sets, read_rig
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    sets = frame_sets(bag, phases=(CAPTURE,))
    try:
        chosen = next((fs for n, fs in enumerate(sets) if n == frame), None)
    finally:
        sets.close()   # closes the bag
    if chosen is None:
        print(f'ICP skipped: {bag} has no capture frame set {frame}; the board solution is kept')
        return {'skipped': f'no capture frame set {frame}'}
    if chosen.missing:
        print(f'ICP skipped: capture frame set {frame} lacks {chosen.missing}; the board solution is kept')
        return {'skipped': f'capture frame set {frame} lacks {chosen.missing}'}
    points = {c: depth_points(f.depth, f.depth_model, rig.camera(c).T_color_depth) for c, f in chosen.cameras.items()}
    T, reports = refine_with_icp({c: cam.T_world_color for c, cam in calibration.cameras.items()}, points,
                                 calibration.reference)
    for c, cam in calibration.cameras.items():
        cam.T_world_color = T[c]
    calibration.method += '+icp'
    return {'frame_set': chosen.index, 'cameras': {c: r.to_dict() for c, r in reports.items()}}


def cmd_eval_calib(args) -> int:
    from volcap_calib.calibrate import CalibrationConfig
    from volcap_calib.evaluate import colour_report, colour_summary, extrinsic_report
    from volcap_calib.extrinsics import sed_baseline
    from volcap_calib.report import colour_figure, poses_figure
    from volcap_core.calibration import Calibration
    from volcap_driver.synth.session import GroundTruth
    calibration = Calibration.load(args.calibration)
    gt = GroundTruth(args.bag)
    cfg = CalibrationConfig(reference=calibration.reference)
    calibrator = calibrator_from_bag(args.bag, _board(args.board), cfg, False, not args.quiet)
    T_gt = {c: gt.T_world_color(c) for c in calibration.cameras}
    T_est = {c: cam.T_world_color for c, cam in calibration.cameras.items()}
    missing = [c for c in calibration.cameras if c not in calibrator.models]
    if missing:
        raise ValueError(f'cameras {missing} never saw the board in {args.bag}')
    ours = extrinsic_report(T_est, calibrator, T_gt, calibration.reference)
    baseline = sed_baseline(calibrator.observations, calibrator.models, calibration.reference)
    base = extrinsic_report(baseline.T_world_color, calibrator, T_gt, calibration.reference)
    colour = colour_report(calibration, calibrator)
    result = {**ours, 'baseline_gradient_descent': base, 'colour': colour, 'colour_average': colour_summary(colour),
              'protocol': 'poses in the reference camera colour frame (the calibration world) against the '
                          'ground truth; reprojection with each board view posed once for the whole rig'}
    print(f'{"camera":<8}{"rot deg":>9}{"trans mm":>10}{"reproj px":>11}   |  paper SED gradient descent'
          f'{"rot":>7}{"trans":>8}{"reproj":>8}')
    for c, v in ours['cameras'].items():
        b = base['cameras'][c]
        print(f'{c:<8}{v["rot_err_deg"]:9.3f}{v["trans_err_mm"]:10.2f}{v["reproj_rms_px"]:11.3f}   |  '
              f'{"":27}{b["rot_err_deg"]:7.3f}{b["trans_err_mm"]:8.2f}{b["reproj_rms_px"]:8.2f}')
    print(f'max     {ours["max_rot_err_deg"]:9.3f}{ours["max_trans_err_mm"]:10.2f}{ours["max_reproj_rms_px"]:11.3f}   |  '
          f'{"":27}{base["max_rot_err_deg"]:7.3f}{base["max_trans_err_mm"]:8.2f}{base["max_reproj_rms_px"]:8.2f}')
    if colour:
        print('colour (paper Table 1, mean reference - camera, 8-bit; |abs| in brackets; patch CIEDE2000)')
        for c, v in colour.items():
            print(f'  {c} {v["method"]:<18} before ' + ' '.join(f'{k} {v["before"][k]:6.2f} ({v["before_abs"][k]:5.2f})' for k in 'RGBI')
                  + f'  dE {v["patch_de2000_before"]:5.2f}')
            print(f'  {c} {"":<18} after  ' + ' '.join(f'{k} {v["after"][k]:6.2f} ({v["after_abs"][k]:5.2f})' for k in 'RGBI')
                  + f'  dE {v["patch_de2000_after"]:5.2f}')
    if args.json:
        atomic_write(args.json, lambda f: f.write(json.dumps(result, indent=2)), binary=False)
        print(f'wrote {args.json}')
    if args.figures:
        fig_dir = Path(args.figures)
        poses_figure(fig_dir / 'calib_eval_poses.png', T_est, {}, ours['cameras'], 'estimated vs ground truth', T_gt)
        if colour:
            colour_figure(fig_dir / 'calib_eval_colour.png', colour)
    return 0


def cmd_eval_chart(args) -> int:
    import cv2
    from volcap_calib.board import reference_srgb8
    from volcap_calib.chart import ChartNotFound, find_colour_checker
    from volcap_calib.colour import METHODS, component_differences, delta_e2000, fit_camera_colour
    from volcap_calib.report import chart_figure
    reference = reference_srgb8() / 255.0
    result, failed = {}, []
    for photo in args.photos:
        bgr = cv2.imread(photo, cv2.IMREAD_COLOR)
        if bgr is None:
            print(f'{photo}: not a readable image')
            failed.append(photo)
            continue
        image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        try:
            chart = find_colour_checker(image, reference)
        except ChartNotFound as e:
            print(f'{photo}: no ColorChecker: {e}')
            failed.append(photo)
            continue
        fit = fit_camera_colour(chart.colours, reference, np.arange(24), method=args.method or None)
        corrected = fit.model.apply(chart.colours)
        de_before, de_after = delta_e2000(chart.colours, reference), delta_e2000(corrected, reference)
        name = Path(photo).stem
        result[name] = {'photo': str(photo), 'patches_found': chart.candidates, 'method': fit.model.method,
                        'model': fit.model.to_dict(), 'de2000_before': float(de_before.mean()),
                        'de2000_after': float(de_after.mean()), 'de2000_after_loo': fit.loo_de2000[fit.model.method],
                        'loo_de2000': fit.loo_de2000, 'table1_before': component_differences(chart.colours, reference),
                        'table1_after': component_differences(corrected, reference),
                        'patch_de2000_before': [float(v) for v in de_before],
                        'patch_de2000_after': [float(v) for v in de_after]}
        print(f'{name}: chart found ({chart.candidates} patches detected, 24 sampled); {fit.model.method}: '
              f'CIEDE2000 {de_before.mean():.2f} -> {de_after.mean():.2f} (leave-one-patch-out '
              f'{fit.loo_de2000[fit.model.method]:.2f}, max {de_after.max():.2f})')
        print('  leave-one-patch-out per model: ' + ', '.join(f'{m} {fit.loo_de2000[m]:.2f}'
                                                             for m in METHODS if m in fit.loo_de2000))
        if args.figures:
            png = chart_figure(Path(args.figures) / f'{name}_chart.png', image, chart.centres, chart.colours,
                               corrected, reference, de_before, de_after, f'{name}: {fit.model.method}')
            print(f'  figure {png}')
    if args.json:
        atomic_write(args.json, lambda f: f.write(json.dumps({'photos': result, 'failed': failed}, indent=2)),
                     binary=False)
        print(f'wrote {args.json}')
    return 1 if failed else 0


def add_parsers(sub, eval_sub) -> None:
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
    c.add_argument('--colour-method', default='', help='force a colour model instead of the leave-one-out choice')
    c.add_argument('--no-depth', action='store_true', help='reprojection only (no depth-to-plane residuals)')
    c.add_argument('--all-frames', action='store_true', help='use every frame set, not only the calibration phase')
    c.add_argument('--icp', action='store_true',
                   help='refine the poses by ICP of the subject\'s depth in a capture frame set of the bag')
    c.add_argument('--icp-frame', type=int, default=0, help='which capture frame set ICP uses (default: the first)')
    c.add_argument('--quiet', action='store_true')
    c.set_defaults(func=cmd_calibrate)

    e = eval_sub.add_parser('calib', help='a calibration against a synthetic bag\'s ground truth, with the paper baseline')
    e.add_argument('calibration')
    e.add_argument('bag')
    e.add_argument('--json', help='write the report here')
    e.add_argument('--figures', help='write PNGs into this folder')
    e.add_argument('--board', help='board YAML (default: the volcap board)')
    e.add_argument('--quiet', action='store_true')
    e.set_defaults(func=cmd_eval_calib)

    ch = eval_sub.add_parser('chart', help='find a ColorChecker Classic in photos and correct it to the reference')
    ch.add_argument('photos', nargs='+')
    ch.add_argument('--method', default='', help='force a colour model instead of the leave-one-out choice')
    ch.add_argument('--json', help='write the report here')
    ch.add_argument('--figures', help='write one PNG per photo into this folder')
    ch.set_defaults(func=cmd_eval_chart)
