"""Scoring a calibration: camera poses against ground truth, reprojection of the board views
with the rig fixed, and the paper's Table 1 colour differences before and after correction."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from volcap_core.calibration import Calibration
from volcap_core.camera import CameraModel
from volcap_core.poses import from_rotvec_t, invert, rotation_angle_deg, to_rotvec_t

from .calibrate import Calibrator
from .colour import ColourModel, component_differences, delta_e2000
from .extrinsics import Observation, corner_residuals


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


def colour_report(calibration: Calibration, calibrator: Calibrator) -> dict:
    """Per camera: paper Table 1 differences (signed as published, and absolute) before and after
    the calibration's colour model, and mean CIEDE2000 on the patches; plus the averages."""
    illumination = calibrator.illumination()
    out = {}
    for c, cam in calibration.cameras.items():
        measured, target, _ = calibrator.colour_samples(c, illumination)
        if cam.colour is None or not len(measured):
            continue
        corrected = ColourModel.from_dict(cam.colour).apply(measured)
        before, after = component_differences(measured, target), component_differences(corrected, target)
        out[c] = {'method': cam.colour['method'], 'before': before['signed'], 'after': after['signed'],
                  'before_abs': before['abs'], 'after_abs': after['abs'],
                  'patch_de2000_before': float(delta_e2000(measured, target).mean()),
                  'patch_de2000_after': float(delta_e2000(corrected, target).mean()), 'samples': len(measured)}
    return out


def colour_summary(colour: dict) -> dict:
    """Averages over cameras, as the paper's Table 1 'Average' column."""
    if not colour:
        return {}
    keys = ('R', 'G', 'B', 'I')
    avg = {part: {k: float(np.mean([v[part][k] for v in colour.values()])) for k in keys}
           for part in ('before', 'after', 'before_abs', 'after_abs')}
    avg['abs_reduction'] = {k: avg['before_abs'][k] / max(avg['after_abs'][k], 1e-9) for k in keys}
    avg['patch_de2000_before'] = float(np.mean([v['patch_de2000_before'] for v in colour.values()]))
    avg['patch_de2000_after'] = float(np.mean([v['patch_de2000_after'] for v in colour.values()]))
    avg['max_patch_de2000_after'] = float(max(v['patch_de2000_after'] for v in colour.values()))
    return avg
