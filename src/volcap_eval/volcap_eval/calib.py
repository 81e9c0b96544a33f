"""Scoring a calibration: camera poses against ground truth and reprojection of the board views
with the rig fixed."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from volcap_calib.calibrate import CalibrationConfig, Calibrator
from volcap_calib.extrinsics import Observation, corner_residuals, sed_baseline
from volcap_calib.report import color_figure, color_report, color_summary, poses_figure
from volcap_calib.run import calibrator_from_bag, load_board
from volcap_core.calibration import Calibration
from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput
from volcap_core.poses import from_rotvec_t, invert, rotation_angle_deg, to_rotvec_t
from volcap_studio.session import GroundTruth


def pose_errors(T_est: dict[str, np.ndarray], T_gt: dict[str, np.ndarray], reference: str) -> dict[str, dict]:
    """Rotation (deg) and translation (mm) error of every camera, both rigs expressed in the
    reference camera's colour frame (the calibration's world)."""
    gt_ref, est_ref = invert(T_gt[reference]), invert(T_est[reference])
    out = {}
    for c in T_est:
        A, B = est_ref @ T_est[c], gt_ref @ T_gt[c]
        out[c] = {'rot_err_deg': rotation_angle_deg(A[:3, :3], B[:3, :3]),
                  'trans_err_mm': float(np.linalg.norm(A[:3, 3] - B[:3, 3]) * 1000)}
    return out


def rig_reprojection(observations: list[Observation], models: dict[str, CameraModel],
                     T_world_color: dict[str, np.ndarray]) -> dict[str, float]:
    """Per camera RMS reprojection error when each board view is posed once for the whole rig
    (its cameras held at ``T_world_color``): how well a set of extrinsics explains the views."""
    by_view: dict[int, list[Observation]] = {}
    for o in observations:
        by_view.setdefault(o.view, []).append(o)
    sq: dict[str, list[np.ndarray]] = {c: [] for c in models}

    def residuals(x, obs):
        T_wt = from_rotvec_t(x)
        return [corner_residuals(o.detection, invert(T_world_color[o.camera]) @ T_wt, models[o.camera]) for o in obs]

    for obs in by_view.values():
        start = to_rotvec_t(T_world_color[obs[0].camera] @ obs[0].T_cam_target)
        sol = least_squares(lambda x: np.concatenate([r.ravel() for r in residuals(x, obs)]), start, method='lm')
        for o, r in zip(obs, residuals(sol.x, obs)):
            sq[o.camera].append(np.sum(r ** 2, axis=1))
    return {c: float(np.sqrt(np.mean(np.concatenate(v)))) if v else float('nan') for c, v in sq.items()}


def extrinsic_report(T_world_color: dict[str, np.ndarray], calibrator: Calibrator, T_gt: dict[str, np.ndarray],
                     reference: str) -> dict:
    errors = pose_errors(T_world_color, T_gt, reference)
    rms = rig_reprojection(calibrator.observations, calibrator.models, T_world_color)
    cams = {c: {**errors[c], 'reproj_rms_px': rms[c]} for c in T_world_color}
    return {'cameras': cams,
            'max_rot_err_deg': max(v['rot_err_deg'] for v in cams.values()),
            'max_trans_err_mm': max(v['trans_err_mm'] for v in cams.values()),
            'max_reproj_rms_px': max(v['reproj_rms_px'] for v in cams.values())}


def evaluate_calibration(calibration_path: str | Path, bag: str | Path, board_file: str | Path | None = None,
                         figures: str | Path | None = None, progress: bool = True) -> dict:
    """A calibration against a synthetic bag's ground truth, beside the paper's SED gradient
    descent on the same board views, with the colour models' Table 1; ``figures``: PNGs there."""
    calibration = Calibration.load(calibration_path)
    gt = GroundTruth(bag)
    cfg = CalibrationConfig(reference=calibration.reference)
    calibrator = calibrator_from_bag(bag, load_board(board_file), cfg, False, progress)
    T_gt = {c: gt.T_world_color(c) for c in calibration.cameras}
    T_est = {c: cam.T_world_color for c, cam in calibration.cameras.items()}
    missing = [c for c in calibration.cameras if c not in calibrator.models]
    if missing:
        raise BadInput(f'cameras {missing} never saw the board in {bag}')
    ours = extrinsic_report(T_est, calibrator, T_gt, calibration.reference)
    baseline = sed_baseline(calibrator.observations, calibrator.models, calibration.reference)
    base = extrinsic_report(baseline.T_world_color, calibrator, T_gt, calibration.reference)
    color = color_report(calibration, calibrator)
    report = {**ours, 'baseline_gradient_descent': base, 'colour': color, 'colour_average': color_summary(color),
              'protocol': 'poses in the reference camera colour frame (the calibration world) against the '
                          'ground truth; reprojection with each board view posed once for the whole rig'}
    if figures:
        fig_dir = Path(figures)
        report['figures'] = [str(poses_figure(fig_dir / 'calib_eval_poses.png', T_est, {}, ours['cameras'],
                                              'estimated vs ground truth', T_gt))]
        if color:
            report['figures'].append(str(color_figure(fig_dir / 'calib_eval_colour.png', color)))
    return report


def format_report(report: dict) -> str:
    base = report['baseline_gradient_descent']
    lines = [f'{"camera":<8}{"rot deg":>9}{"trans mm":>10}{"reproj px":>11}   |  paper SED gradient descent'
             f'{"rot":>7}{"trans":>8}{"reproj":>8}']
    for c, v in report['cameras'].items():
        b = base['cameras'][c]
        lines.append(f'{c:<8}{v["rot_err_deg"]:9.3f}{v["trans_err_mm"]:10.2f}{v["reproj_rms_px"]:11.3f}   |  '
                     f'{"":27}{b["rot_err_deg"]:7.3f}{b["trans_err_mm"]:8.2f}{b["reproj_rms_px"]:8.2f}')
    lines.append(f'max     {report["max_rot_err_deg"]:9.3f}{report["max_trans_err_mm"]:10.2f}'
                 f'{report["max_reproj_rms_px"]:11.3f}   |  {"":27}{base["max_rot_err_deg"]:7.3f}'
                 f'{base["max_trans_err_mm"]:8.2f}{base["max_reproj_rms_px"]:8.2f}')
    if report['colour']:
        lines.append('colour (paper Table 1, mean reference - camera, 8-bit; |abs| in brackets; patch CIEDE2000)')
        for c, v in report['colour'].items():
            for when, label in (('before', v['method']), ('after', '')):
                lines.append(f'  {c} {label:<18} {when:<6} '
                             + ' '.join(f'{k} {v[when][k]:6.2f} ({v[when + "_abs"][k]:5.2f})' for k in 'RGBI')
                             + f'  dE {v["patch_de2000_" + when]:5.2f}')
    return '\n'.join(lines)
