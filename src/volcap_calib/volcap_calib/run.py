"""Calibration from a recorded bag (`volcap calibrate`): every board view of the bag's
calibration phase into the joint solve, optional ICP refinement on a capture frame set, the
calibration file and its report (JSON and figures).

    report = run(CalibrateConfig(bag='take1', out='calibration.yaml'))
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from volcap_core.bag_reader import BagReader
from volcap_core.calibration import Calibration
from volcap_core.errors import BadInput
from volcap_core.files import atomic_write
from volcap_core.frames import frame_sets, read_rig
from volcap_core.topics import CALIBRATION_PHASE, CAPTURE, PHASE

from .board import BoardConfig
from .calibrate import BoardView, CalibrationOutcome, Calibrator
from .config import CalibrateConfig, CalibrationConfig  # noqa: F401 (CalibrateConfig re-exported)
from .extrinsics import depth_points
from .icp import refine_with_icp
from .report import color_figure, color_report, color_summary, poses_figure


def load_board(path: str | Path | None) -> BoardConfig:
    """The board of a YAML file, or the volcap board."""
    return BoardConfig.from_yaml(path) if path else BoardConfig.from_yaml()


def calibrator_from_bag(bag: str | Path, board: BoardConfig, cfg: CalibrationConfig, all_frames: bool = False,
                        progress: bool = True) -> Calibrator:
    """A Calibrator fed with every frame set of the bag's calibration phase (or of the whole bag,
    also when the bag announces no phase: a plain recording of the board)."""
    with BagReader(bag) as reader:
        rig = read_rig(reader)
        all_frames = all_frames or PHASE not in reader.topics
    calibrator = Calibrator(rig, board, cfg)
    sets = frame_sets(bag, phases=None if all_frames else (CALIBRATION_PHASE,))
    bar = tqdm(sets, desc='board views', unit='set', disable=not progress)
    for fs in bar:
        status = calibrator.add(fs.index, {n: BoardView(f.color, f.color_model, f.depth, f.depth_model)
                                           for n, f in fs.cameras.items()})
        bar.set_postfix(seen=sum('corners' in s for s in status.values()), observations=len(calibrator.observations))
    if calibrator.views == 0:
        raise BadInput(f'{bag} has no frame sets in the {CALIBRATION_PHASE!r} phase'
                         + ('' if all_frames else '; pass --all-frames to use every frame set'))
    return calibrator


def chart_samples(bag: str | Path, board: BoardConfig, cameras: list[str], progress: bool = True
                  ) -> tuple[dict | None, str | None]:
    """Each camera's chart patches in the bag's board views (measured, reference under the
    view's light), or None and why."""
    try:
        calibrator = calibrator_from_bag(bag, board, CalibrationConfig(), progress=progress)
    except ValueError as e:
        return None, str(e)
    if not any(calibrator.patches.values()):
        return None, 'no camera saw the chart in the board views'
    illumination = calibrator.illumination()
    return {c: calibrator.color_samples(c, illumination)[:2] for c in cameras if calibrator.patches.get(c)}, None


def refine_from_bag(bag: str | Path, calibration: Calibration, frame: int) -> dict:
    """ICP of the subject's depth in capture frame set ``frame`` of the bag; updates
    ``calibration`` in place and returns the report (``skipped`` and why, when it cannot run)."""
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    sets = frame_sets(bag, phases=(CAPTURE,))
    try:
        chosen = next((fs for n, fs in enumerate(sets) if n == frame), None)
    finally:
        sets.close()   # closes the bag
    if chosen is None:
        return {'skipped': f'no capture frame set {frame}'}
    if chosen.missing:
        return {'skipped': f'capture frame set {frame} lacks {chosen.missing}'}
    points = {c: depth_points(f.depth, f.depth_model, rig.camera(c).T_color_depth) for c, f in chosen.cameras.items()}
    T, reports = refine_with_icp({c: cam.T_world_color for c, cam in calibration.cameras.items()}, points,
                                 calibration.reference)
    for c, cam in calibration.cameras.items():
        cam.T_world_color = T[c]
    calibration.method += '+icp'
    return {'frame_set': chosen.index, 'cameras': {c: r.to_dict() for c, r in reports.items()}}


@dataclass
class CalibrateReport:
    calibration: Calibration
    outcome: CalibrationOutcome
    observations: int
    frame_sets: int
    color: dict
    icp: dict | None
    files: dict[str, Path] = field(default_factory=dict)
    target: tuple[float, float, float] = (0.1, 2.0, 2.0)     # deg, mm, margin the weak test used

    def lines(self) -> list[str]:
        out = [f'wrote {self.files["calibration"]} ({len(self.calibration.cameras)} cameras, {self.observations} '
               f'board observations in {self.frame_sets} frame sets); report {self.files["report"]}']
        studio = self.calibration.studio
        if studio.details.get('source') == 'floor':
            out.append(f'  studio frame: floor fitted to {studio.details["floor_points"]} depth points, RMS '
                       f'{studio.details["floor_rms_mm"]:.1f} mm; cameras {min(studio.details["camera_height_m"]):.2f}-'
                       f'{max(studio.details["camera_height_m"]):.2f} m above it')
        else:
            out.append(f'  studio frame: NO FLOOR SEEN: {studio.details.get("note", "")}')
        for c, rep in self.outcome.extrinsics.cameras.items():
            col = self.color.get(c)
            depth = f'{rep.depth_rms_mm:5.2f} mm' if rep.depth_rms_mm is not None else '   -    '
            col_txt = (f'  colour {col["method"]:<18} dE2000 {col["patch_de2000_before"]:5.2f} -> '
                       f'{col["patch_de2000_after"]:4.2f}') if col else '  colour -'
            predicted = (f'  predicted {rep.rot_sigma_deg:.3f} deg {rep.trans_sigma_mm:5.2f} mm'
                         if rep.rot_sigma_deg is not None else '')
            flag = '  WEAK' if c in self.outcome.weak else ''
            out.append(f'  {c}: {rep.views:2d} views  reproj {rep.reproj_rms_px:.3f} px  depth {depth}{predicted}'
                       f'{flag}{col_txt}')
        for c, why in self.outcome.color_errors.items():
            out.append(f'  {c}: no colour model: {why}')
        if not self.outcome.weak and not self.outcome.color_errors:
            deg, mm, margin = self.target
            out.append(f'calibration within the target: every camera predicted within {deg:g} deg / {mm:g} mm '
                       f'with a {margin:g}x margin')
        elif not self.outcome.weak:
            deg, mm, margin = self.target
            out.append(f'poses within the target ({deg:g} deg / {mm:g} mm, {margin:g}x margin); colour: see above')
        if self.outcome.weak:
            out.append(f'WEAK CALIBRATION: {", ".join(self.outcome.weak)} may miss the target (predicted error, '
                       'with its margin, beyond it); '
                       + ' '.join(self.outcome.calibration.extra.get('advice', [])))
        if self.icp and 'skipped' in self.icp:
            out.append(f'ICP skipped: {self.icp["skipped"]}; the board solution is kept')
        for c, rep in (self.icp or {}).get('cameras', {}).items():
            out.append(f'  {c}: ICP {"moved" if rep["accepted"] else "kept  "} {rep["rotation_deg"]:.3f} deg '
                       f'{rep["translation_mm"]:5.2f} mm, inlier RMSE {rep["rmse_before_mm"]:.2f} -> '
                       f'{rep["rmse_after_mm"]:.2f} mm' + (f' ({rep["reason"]})' if rep['reason'] else ''))
        return out


def run(cfg: CalibrateConfig) -> CalibrateReport:
    """Calibrate from the bag and write the calibration and its report. Raises CalibrationError
    (naming the cameras) when the views do not determine the rig: the output is then untouched."""
    calibrator = calibrator_from_bag(cfg.bag, load_board(cfg.board_file), cfg.solve, cfg.all_frames,
                                     cfg.progress)
    outcome = calibrator.solve()
    calibration = outcome.calibration
    icp = refine_from_bag(cfg.bag, calibration, cfg.icp_frame) if cfg.icp else None
    if icp is not None and 'skipped' not in icp:      # the floor placed by the refined poses
        calibration.studio = calibrator.studio_frame({c: cam.T_world_color for c, cam in calibration.cameras.items()},
                                                     calibration.reference)
    out = Path(cfg.out)
    calibration.save(out)
    report_dir = Path(cfg.report_dir) if cfg.report_dir else out.parent
    color = color_report(calibration, calibrator)
    report = {'calibration': str(out), 'reference': calibration.reference, 'frame_sets': calibrator.views,
              'studio': calibration.studio.to_dict(),
              'cameras': {c: outcome.extrinsics.cameras[c].to_dict() for c in calibration.cameras},
              'colour': color, 'colour_average': color_summary(color), 'colour_errors': outcome.color_errors,
              'weak_cameras': outcome.weak, 'coverage': outcome.coverage.to_dict()}
    if icp is not None:
        report['icp'] = icp
    files = {'calibration': out,
             'report': atomic_write(report_dir / f'{out.stem}_report.json',
                                    lambda f: f.write(json.dumps(report, indent=2)), binary=False),
             'poses': poses_figure(report_dir / f'{out.stem}_poses.png', outcome.extrinsics.T_world_color,
                                   outcome.extrinsics.T_world_target, report['cameras'])}
    if color:
        files['color'] = color_figure(report_dir / f'{out.stem}_colour.png', color)
    return CalibrateReport(calibration, outcome, len(calibrator.observations), calibrator.views, color, icp, files,
                           (cfg.solve.max_rot_err_deg, cfg.solve.max_trans_err_mm, cfg.solve.weak_margin))
