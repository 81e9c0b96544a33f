"""Rig calibration from frame sets of the moving board: the one entry point shared by the
``calibration_service`` node and ``volcap calibrate``.

``Calibrator.add`` takes one synchronised frame set, detects the board in every camera, poses
it and keeps only what the solve needs (corners, a few depth points, the 24 patch colours, and
each camera's latest depth frame for the floor), so a long calibration session costs little
memory. ``Calibrator.solve`` runs the joint extrinsic
solve and the per-camera colour fits and returns a ``Calibration``, with the studio frame
fitted to the floor in the cameras' latest depth (``studio_frame``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from volcap_core.calibration import Calibration, CameraCalibration, StudioFrame
from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput
from volcap_core.poses import transform_points
from volcap_core.rig import Rig

from .board import BoardConfig, reference_srgb8
from .chart import quad_mean
from .color import ColorFit, fit_camera_color, illuminated_reference, view_illumination
from .config import CalibrationConfig  # noqa: F401 (re-exported: its home before config.py)
from .coverage import Coverage, advice_for, rig_coverage
from .detect import BoardDetector, DetectionError
from .extrinsics import (
    CalibrationError,
    ExtrinsicResult,
    Observation,
    check_against_depth,
    depth_points,
    solve_rig,
    target_depth_points,
    target_pose,
)
from .studio_frame import fit_studio_frame


@dataclass
class BoardView:
    """One camera's image of the board (and its depth, for the depth-to-plane residuals and the floor)."""
    color: np.ndarray                  # (H, W, 3) uint8 RGB
    color_model: CameraModel
    depth: np.ndarray | None = None    # (h, w) float32 metres, depth camera geometry
    depth_model: CameraModel | None = None


@dataclass
class CalibrationOutcome:
    calibration: Calibration
    extrinsics: ExtrinsicResult
    color: dict[str, ColorFit]
    color_errors: dict[str, str]
    weak: dict[str, str] = field(default_factory=dict)   # camera -> predicted error over the target
    coverage: Coverage | None = None


def patch_colors(image: np.ndarray, camera: CameraModel, T_cam_board: np.ndarray, board: BoardConfig,
                 inner: float = 0.6, min_side_px: float = 12.0, max_angle_deg: float = 70.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(24, 3) sRGB in [0, 1] of each chart patch, robust (inter-quartile) mean of its central
    part, and (24, 2) the patch centres in the image; NaN rows for patches out of view, too
    small, or seen too obliquely."""
    out = np.full((board.chart.rows * board.chart.columns, 3), np.nan)
    centres_px = np.full((len(out), 2), np.nan)
    normal = T_cam_board[:3, 2]
    corners = board.patch_corners()
    centres = corners.mean(axis=1)
    for p, (quad, centre) in enumerate(zip(corners, centres)):
        inner_quad = centre + (quad - centre) * inner
        pts_cam = transform_points(T_cam_board, inner_quad)
        if np.any(pts_cam[:, 2] <= 0):
            continue
        ray = transform_points(T_cam_board, centre[None])[0]
        cos = abs(normal @ ray) / np.linalg.norm(ray)
        if cos < np.cos(np.radians(max_angle_deg)):
            continue
        px = camera.project(pts_cam)
        side = min(np.linalg.norm(px - np.roll(px, 1, axis=0), axis=1)) / inner
        if side < min_side_px:
            continue
        mean = quad_mean(image, px)
        if mean is None:
            continue
        out[p] = mean / 255.0
        centres_px[p] = px.mean(axis=0)
    return out, centres_px


class Calibrator:
    def __init__(self, rig: Rig, board: BoardConfig, cfg: CalibrationConfig = CalibrationConfig()):
        if cfg.reference and cfg.reference not in rig.names:
            raise BadInput(f'reference camera {cfg.reference!r} is not in the rig ({", ".join(rig.names)})')
        self.rig, self.board, self.cfg = rig, board, cfg
        self.detector = BoardDetector(board, cfg.solver.min_corners)
        self.observations: list[Observation] = []
        self.rejected: dict[str, dict[int, str]] = {c: {} for c in rig.names}
        self.patches: dict[str, list[tuple[int, np.ndarray]]] = {c: [] for c in rig.names}
        self.patch_pixels: dict[str, list[np.ndarray]] = {c: [] for c in rig.names}
        self.models: dict[str, CameraModel] = {}
        self.views = 0
        self.floor_depth: dict[str, BoardView] = {}   # latest frame with depth per camera, for the floor
        self._grid_region = (0.0, 0.0, *board.grid_size)   # depth is sampled on the ChArUco grid

    def add(self, view: int, frames: dict[str, BoardView]) -> dict[str, str]:
        """Detect and pose the board in one frame set; returns each camera's outcome in words."""
        self.views += 1
        status = {}
        for name, frame in frames.items():
            if name not in self.rejected:
                status[name] = 'not in the rig'
                continue
            if frame.depth is not None and frame.depth_model is not None:
                self.floor_depth[name] = frame      # a reference: points are made once, at the solve
            try:
                status[name] = self._add_camera(view, name, frame)
            except (DetectionError, ValueError) as e:
                self.rejected[name][view] = str(e)
                status[name] = str(e)
        return status

    def _add_camera(self, view: int, name: str, frame: BoardView) -> str:
        model = frame.color_model
        if frame.color.shape[:2] != (model.height, model.width):
            raise BadInput(f'colour image is {frame.color.shape[1]}x{frame.color.shape[0]}, camera_info says '
                             f'{model.width}x{model.height}')
        if self.models.get(name, model) != model:
            raise BadInput('colour intrinsics changed during the calibration session')
        detection = self.detector.detect(frame.color, model)
        T, rms = target_pose(detection, model)
        obs = Observation(name, view, detection, T, rms)
        if self.cfg.use_depth and frame.depth is not None and frame.depth_model is not None:
            obs.plane_points = target_depth_points(frame.depth, frame.depth_model,
                                                   self.rig.camera(name).T_color_depth, T, self._grid_region)
            reason = check_against_depth(obs, model, self.cfg.solver)
            if reason:
                raise BadInput(reason)
        self.models[name] = model
        self.observations.append(obs)
        colors, centres = patch_colors(frame.color, model, T, self.board, self.cfg.patch_inner, self.cfg.min_patch_px,
                                       self.cfg.max_chart_angle_deg)
        if np.isfinite(colors).all(axis=1).any():
            self.patches[name].append((view, colors))
            self.patch_pixels[name].append(centres)
        return f'{len(detection)} corners, PnP {rms:.2f} px'

    def studio_frame(self, T_world_color: dict[str, np.ndarray], reference: str) -> StudioFrame:
        """The studio frame: the floor in the cameras' latest depth, placed by the calibrated poses."""
        points = {}
        for c, frame in self.floor_depth.items():
            if c not in T_world_color:
                continue
            try:
                local = depth_points(frame.depth, frame.depth_model, self.rig.camera(c).T_color_depth)
            except ValueError:
                continue    # depth not the size its camera_info says: that frame's detection said so
            points[c] = transform_points(T_world_color[c], local)
        return fit_studio_frame(T_world_color, reference, points)

    def reference(self) -> np.ndarray:
        return reference_srgb8(self.board.chart.reference) / 255.0

    def illumination(self) -> dict[int, np.ndarray]:
        return view_illumination({c: items for c, items in self.patches.items() if items}, self.reference(),
                                 self.patch_xy())

    def patch_xy(self) -> np.ndarray:
        """(24, 2) patch centres on the board relative to the chart centre (m)."""
        centres = self.board.patch_corners().mean(axis=1)[:, :2]
        return centres - centres.mean(axis=0)

    def color_samples(self, camera: str, illumination: dict[int, np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured (N, 3) and target (N, 3) sRGB in [0, 1] (the reference chart under each view's
        illumination) and patch numbers (N,) of every sampled patch of ``camera``."""
        reference, xy = self.reference(), self.patch_xy()
        measured, ref, patch = [], [], []
        for view, colors in self.patches[camera]:
            ok = np.isfinite(colors).all(axis=1)
            measured.append(colors[ok])
            ref.append(illuminated_reference(reference[ok], illumination[view], xy[ok]))
            patch.append(np.nonzero(ok)[0])
        if not measured:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int)
        return np.vstack(measured), np.vstack(ref), np.concatenate(patch)

    def solve(self) -> CalibrationOutcome:
        """Raises CalibrationError naming the cameras that cannot be calibrated."""
        reference = self.cfg.reference or self.rig.names[0]
        models = {c: self.models.get(c) for c in self.rig.names}
        unseen = [c for c, m in models.items() if m is None]
        if unseen:
            raise CalibrationError(f'cameras never saw the board ({self.views} frame sets)',
                                   {c: _why_unseen(self.rejected[c]) for c in unseen})
        try:
            extrinsics = solve_rig(self.observations, models, reference, self.cfg.solver_config(), self.rejected)
        except CalibrationError as e:
            coverage = self.coverage(reference)
            if coverage.advice:
                raise CalibrationError(f'{e}. Next: {" ".join(coverage.advice)}', e.cameras) from e
            raise
        k = self.cfg.weak_margin
        weak = {c: f'predicted error {r.rot_sigma_deg:.3f} deg / {r.trans_sigma_mm:.2f} mm RMS, {k:g}x that beyond '
                   f'the target {self.cfg.max_rot_err_deg} deg / {self.cfg.max_trans_err_mm} mm'
                for c, r in extrinsics.cameras.items()
                if r.rot_sigma_deg is not None and (k * r.rot_sigma_deg > self.cfg.max_rot_err_deg
                                                    or k * r.trans_sigma_mm > self.cfg.max_trans_err_mm)}
        coverage = self.coverage(reference, weak)
        fits, color_errors = {}, {}
        illumination = self.illumination() if any(self.patches.values()) else {}
        for c in self.rig.names:
            measured, ref, patch = self.color_samples(c, illumination)
            if len(np.unique(patch)) < 12:
                color_errors[c] = f'chart seen on {len(np.unique(patch))} of 24 patches, need 12'
                continue
            fits[c] = fit_camera_color(measured, ref, patch, self.cfg.color_methods, self.cfg.color_method or None)
        cams = {}
        for c in self.rig.names:
            rep = extrinsics.cameras[c]
            cams[c] = CameraCalibration(extrinsics.T_world_color[c], self.rig.camera(c).color_frame,
                                        rep.reproj_rms_px, rep.depth_rms_mm, rep.views,
                                        fits[c].to_dict() if c in fits else None,
                                        {'rot_deg': rep.rot_sigma_deg, 'trans_mm': rep.trans_sigma_mm})
        calibration = Calibration(reference, self.rig.camera(reference).color_frame, cams, extrinsics.method,
                                  extra={'board': self.board.to_dict(), 'rig': self.rig.name,
                                         'frame_sets': self.views,
                                         'colour_errors': color_errors,
                                         'weak_cameras': weak, 'advice': coverage.advice})
        calibration.studio = self.studio_frame(extrinsics.T_world_color, reference)
        return CalibrationOutcome(calibration, extrinsics, fits, color_errors, weak, coverage)

    def coverage(self, reference: str | None = None, weak: dict[str, str] | None = None) -> Coverage:
        """The board views' coverage of the rig so far (``weak``: cameras the solve found weak,
        added to those the view graph shows)."""
        coverage = rig_coverage(self.observations, self.rig.names, reference or self.cfg.reference or self.rig.names[0])
        if weak:
            coverage.weak = {**weak, **coverage.weak}
            coverage.advice = advice_for(self.observations, coverage)
        return coverage


def _why_unseen(rejected: dict[int, str]) -> str:
    if not rejected:
        return 'no frames'
    reasons = sorted(set(rejected.values()))
    return f'board not usable in {len(rejected)} frame sets ({"; ".join(reasons[:3])})'
