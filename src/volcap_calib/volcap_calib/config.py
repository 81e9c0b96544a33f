"""The calibration's settings, one definition each, importable without OpenCV or the solver: the
``calibration_service`` node's parameters, `volcap calibrate`'s options and the docs tables all
come from these declarations."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from volcap_core.color_models import METHODS
from volcap_core.settings import setting, validate


@dataclass
class SolverConfig:
    min_corners: int = 6
    pixel_sigma: float = 0.5           # px; reprojection residuals are divided by this
    depth_sigma: float = 0.004         # m; depth-to-plane residuals are divided by this
    depth_weight: float = 1.0          # 0 = reprojection only
    depth_points: int = setting(1000, 'depth samples of the board per view in the joint solve (1000 against 60 took '
                                'the worst camera of synthetic studios from 5.7 to 2.3 mm; more gained nothing and '
                                'made the predicted error overconfident: bench/calib_studios.py)', 0, 100_000)
    robust_scale: float = 3.0          # soft-L1 knee, in sigmas
    max_pose_disagreement_deg: float = 5.0   # PnP vs depth-derived pose of one observation
    max_pose_disagreement_m: float = 0.05
    max_reproj_rms_px: float = 1.5     # a camera above this after the solve is inconsistent
    max_depth_rms_mm: float = 20.0


@dataclass
class CalibrationConfig:
    reference: str = setting('', 'camera whose colour frame is the world (empty: the rig\'s first)')
    solver: SolverConfig = field(default_factory=SolverConfig)
    use_depth: bool = setting(True, 'add depth-to-board-plane residuals to the solve', option='--depth')
    color_methods: tuple[str, ...] = METHODS
    color_method: str = setting('', 'force a colour model (empty: the best leave-one-patch-out model)',
                                choices=('', *METHODS), option='--colour-method')
    min_patch_px: float = 12.0           # shortest patch side in the image to sample it
    patch_inner: float = 0.6             # fraction of the patch (per side) that is averaged
    max_chart_angle_deg: float = 70.0    # chart seen more obliquely than this is not sampled
    # The rig's target. The prediction is an RMS, so among several cameras one comes out beyond it:
    # on synthetic studios the worst camera reached 2.2x the largest prediction (bench/calib_studios.py).
    max_rot_err_deg: float = setting(0.1, 'target rotation error of every camera (deg)', 0.0, 10.0)
    max_trans_err_mm: float = setting(2.0, 'target translation error of every camera (mm)', 0.0, 1000.0)
    weak_margin: float = setting(2.0, 'a camera is weak when this many times its predicted RMS pose error exceeds '
                                 'the target', 0.1, 10.0)

    def __post_init__(self):
        if self.reference is None:      # older callers said None for "the first"
            self.reference = ''
        if self.color_method is None:
            self.color_method = ''

    def validate(self) -> None:
        validate(self)

    def solver_config(self) -> SolverConfig:
        """The solver's settings, without depth residuals unless ``use_depth``."""
        return self.solver if self.use_depth else dataclasses.replace(self.solver, depth_weight=0.0)


@dataclass
class CalibrateConfig:
    """`volcap calibrate BAG`: the bag's board views solved into ``out``."""
    bag: str | Path
    out: str | Path = 'calibration.yaml'
    report_dir: str | Path | None = None     # default: beside ``out``
    board_file: str | Path | None = None
    solve: CalibrationConfig = field(default_factory=CalibrationConfig)
    all_frames: bool = setting(False, 'use every frame set, not only the calibration phase')
    icp: bool = setting(False, 'refine the poses by ICP of the subject\'s depth in a capture frame set of the bag')
    icp_frame: int = setting(0, 'which capture frame set ICP uses (0: the first)', 0, 1_000_000)
    progress: bool = True

    def validate(self) -> None:
        validate(self)
