"""The calibration service's session, without ROS: board views gathered per rig (a new set of
cameras starts over), the joint solve on request, and the calibration file written only on
success. Thread-safe: views are added from the detection worker while a solve may be asked for."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from volcap_core.calibration import Calibration
from volcap_core.errors import BadInput
from volcap_core.rig import Rig
from volcap_core.settings import color_transport_setting, setting, tf_prefix_setting
from volcap_core.topics import CALIBRATION_PHASE, camera_names

from .board import BoardConfig
from .calibrate import BoardView, Calibrator
from .config import CalibrationConfig
from .coverage import Coverage


@dataclass
class CalibrationServiceConfig:
    output: str = setting('calibration.yaml', 'calibration file written on success')
    cameras: tuple[str, ...] = setting(tuple(camera_names(8)), 'camera namespaces to listen to (the rig '
                                       'description says which of them are calibrated)', read_only=True)
    rig_file: str = setting('', 'rig description YAML (`volcap rig`; empty: /volcap/rig, else the cameras\' '
                            'camera_info with /tf_static)', read_only=True)
    tf_prefix: str = tf_prefix_setting()
    color_transport: str = color_transport_setting()
    board_file: str = setting('', 'board YAML (empty: the volcap board)', read_only=True)
    collect_phase: str = setting(CALIBRATION_PHASE, 'gather frame sets only in this announced phase '
                                 '(empty: always)')
    solve: CalibrationConfig = field(default_factory=CalibrationConfig)    # reference, use_depth, colour, target
    queue_size: int = setting(16, 'frame sets waiting for detection before the oldest is dropped', 1, 1000,
                              read_only=True)
    drain_timeout_s: float = setting(60.0, 'how long a calibrate call waits for queued frame sets to be detected',
                                     0.0, 3600.0)
    sync_tolerance_ms: float = setting(0.0, 'stamp tolerance of a frame set, ms (0: just under half the frame '
                                       'period the stamps show)', 0.0, 100.0,
                                       read_only=True)


@dataclass
class Solved:
    calibration: Calibration
    message: str            # one line for the service response and the log
    weak: dict[str, str]    # cameras whose predicted pose error exceeds the target -> why


class CalibrationSession:
    def __init__(self, cfg: CalibrationServiceConfig, board: BoardConfig):
        self.cfg = cfg
        self.board = board
        self.rig: Rig | None = None
        self.calibrator: Calibrator | None = None
        self.frame_sets = 0
        self._lock = threading.Lock()

    def set_rig(self, rig: Rig) -> str:
        """Use ``rig``; returns '' or a warning. A rig with other cameras starts the views over;
        one with cameras the service does not listen to is refused (ValueError)."""
        unheard = [c for c in rig.names if c not in self.cfg.cameras]
        if unheard:
            raise BadInput(f'rig cameras {unheard} are not in the cameras parameter; restart with them listed')
        with self._lock:
            same = self.rig is not None and rig.names == self.rig.names
            changed = self.rig is not None and not same
            self.rig = rig
            if not same:
                self.calibrator = Calibrator(rig, self.board, self._solver_config())
                self.frame_sets = 0
        return 'the rig changed: views gathered so far were dropped' if changed else ''

    def collecting(self, phase: str | None) -> bool:
        """Whether frame sets captured in the announced ``phase`` are gathered."""
        wanted = self.cfg.collect_phase
        return not wanted or phase is None or phase == wanted

    @property
    def ready(self) -> bool:
        return self.calibrator is not None

    def add(self, frames: dict[str, BoardView]) -> None:
        """One frame set's cameras (board detection happens here)."""
        with self._lock:
            if self.calibrator is not None and frames:
                self.calibrator.add(self.frame_sets, frames)
                self.frame_sets += 1

    def counts(self) -> tuple[int, int]:
        """(board observations, frame sets) gathered."""
        with self._lock:
            return (len(self.calibrator.observations), self.calibrator.views) if self.calibrator else (0, 0)

    def solve(self) -> Solved:
        """Solve with every view so far and write ``output`` (atomically). Raises
        CalibrationError (naming the cameras) or OSError; the file is then unchanged."""
        if self.calibrator is None:
            raise BadInput('no rig description yet')
        t0 = time.monotonic()
        with self._lock:
            calibrator = self.calibrator
            outcome = calibrator.solve()
        calibration = outcome.calibration
        output = Path(self.cfg.output)
        calibration.save(output)
        worst = max(calibration.cameras.items(), key=lambda kv: kv[1].reproj_rms_px or 0.0)
        message = (f'calibrated {len(calibration.cameras)} cameras from {calibrator.views} frame sets in '
                   f'{time.monotonic() - t0:.1f} s; worst reprojection {worst[0]} {worst[1].reproj_rms_px:.3f} px; '
                   f'wrote {output}')
        if outcome.color_errors:
            message += '; no colour model for ' + ', '.join(f'{c} ({why})' for c, why in outcome.color_errors.items())
        if outcome.weak:
            message += ('; WEAK: ' + ', '.join(f'{c} ({why})' for c, why in outcome.weak.items()) + '; '
                        + ' '.join(calibration.extra.get('advice', [])))
        return Solved(calibration, message, outcome.weak)

    def coverage(self) -> Coverage | None:
        """How the board views gathered so far link the cameras (None before the rig is known)."""
        with self._lock:
            return self.calibrator.coverage() if self.calibrator else None

    def _solver_config(self) -> CalibrationConfig:
        return self.cfg.solve
