"""One camera's live colour correction, without ROS: which mapping applies (a neural region LUT,
fixed once loaded; else the colour model of the latest usable calibration; else none, and the
image is passed through or dropped), applying it, and the status the color_corrector node
reports."""
from __future__ import annotations

import time
from collections import deque
from pathlib import Path

import numpy as np

from volcap_core.calibration import Calibration
from volcap_core.color import ColorModel
from volcap_core.errors import BadInput

from .apply import ImageCorrector, RegionLut


class CameraCorrection:
    def __init__(self, camera: str, passthrough: bool = True):
        self.camera = camera
        self.passthrough = passthrough
        self.corrector: ImageCorrector | None = None
        self.model_text = 'none'
        self.neural = False
        self.neural_problem = ''
        self.corrected = self.passed = self.skipped = 0
        self.without_model = 0      # images that came while there was no model (passed or dropped)
        self.ms: deque[float] = deque(maxlen=100)    # the latest corrections' times
        self._buffer: np.ndarray | None = None

    def load_neural(self, models_dir: str | Path) -> str:
        """Apply the camera's exported neural mapping (``<camera>.lut.npz`` of a ``volcap
        harmonise`` folder) from now on; later calibrations no longer change it. Returns what
        to log; a missing or unreadable LUT is kept as ``neural_problem`` and the calibration's
        model is used instead."""
        path = Path(models_dir) / f'{self.camera}.lut.npz'
        try:
            lut = RegionLut.load(path)
        except ValueError as e:
            self.neural_problem = f'neural mapping not used, falling back to the calibration: {e}'
            return self.neural_problem
        self.corrector, self.neural = ImageCorrector(lut), True
        n, (nx, ny) = lut.table.shape[0], lut.grid
        self.model_text = f'neural (region LUT {n}^3 x {nx}x{ny}, {path.parent})'
        return f'{self.camera}: colour model {self.model_text}'

    def set_calibration(self, text: str) -> tuple[bool, str]:
        """(used, message) for a calibration published as YAML: its model for this camera replaces
        the current one; an unusable calibration keeps the current model and says why."""
        if self.neural:
            return False, f'{self.camera}: new calibration; keeping the neural mapping'
        try:
            calibration = Calibration.from_yaml(text)
            cam = calibration.cameras.get(self.camera)
            if cam is None:
                raise BadInput(f'the calibration has no camera {self.camera!r} '
                                 f'(it has {", ".join(calibration.cameras)})')
            if cam.color is None:
                raise BadInput(f'the calibration has no colour model for {self.camera}')
            model = ColorModel.from_dict(cam.color)
            corrector = ImageCorrector(model)
        except ValueError as e:
            return False, f'calibration not used, keeping {self.model_text}: {e}'
        self.corrector = corrector
        self.model_text = f'{model.method}{" + harmonisation" if model.post is not None else ""} ({corrector.kind})'
        return True, f'{self.camera}: colour model {self.model_text}'

    def apply(self, rgb: np.ndarray, window: tuple[int, int, int, int, int] | None = None) -> np.ndarray | None:
        """The corrected image (the input itself while there is no model and images pass
        through), or None when it is dropped. The output buffer is reused: publish a copy.
        ``window``: ``rgb`` is a region of the camera's image (``ImageCorrector``)."""
        if self.corrector is None:
            self.without_model += 1
            if not self.passthrough:
                return None
            self.passed += 1
            return rgb
        t0 = time.perf_counter()
        out = self._buffer = self.corrector(rgb, self._buffer, window)
        self.ms.append((time.perf_counter() - t0) * 1e3)
        self.corrected += 1
        return out

    def status(self) -> tuple[str, str, dict]:
        """(level, message, values) for diagnostics."""
        problem = f'; {self.neural_problem}' if self.neural_problem else ''
        if self.corrector is None and not self.without_model:
            # a graph starting: the calibration is published latched and usually lands before
            # the first image; only an image without a model is something to act on
            return 'warn' if problem else 'ok', f'{self.camera}: waiting for a colour model{problem}', \
                {'passed': self.passed, 'skipped': self.skipped}
        if self.corrector is None:
            return 'warn', (f'{self.camera}: no colour model yet; images are '
                            f'{"passed through" if self.passthrough else "dropped"}{problem}'), \
                {'passed': self.passed, 'skipped': self.skipped}
        ms = float(np.median(self.ms)) if self.ms else 0.0
        return 'warn' if problem else 'ok', \
            f'{self.camera}: {self.corrected} frames corrected with {self.model_text}{problem}', \
            {'corrected': self.corrected, 'passed': self.passed, 'skipped': self.skipped, 'median_ms': round(ms, 2)}
