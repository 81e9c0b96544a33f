"""Chart-free colour models for a rig (`volcap colour-fit`): correspondences between the
cameras of a few capture frame sets, one linear model per camera making them agree, written
into the calibration as each camera's colour model (the chart fit kept as ``previous``)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volcap_core.calibration import Calibration
from volcap_core.color import ColorModel
from volcap_core.errors import BadInput

from .chart_free import chart_free_fit, identity_models
from .config import ColorFitConfig  # noqa: F401 (re-exported: its home before config.py)
from .correspondence import View, cameras_in, find_correspondences, merge_matches
from .model_choice import ModelChoice, choose_chart_free_model


@dataclass
class ColorFitReport:
    calibration: Calibration           # the input calibration with the new colour models
    source: str                        # chart_free or chart_harmonised
    cameras: list[str]
    pairs: int
    correspondences: int
    choice: ModelChoice

    def line(self) -> str:
        return (f'{self.source} {self.choice.model} models for {len(self.cameras)} cameras from {self.pairs} camera '
                f'pairs ({self.correspondences} correspondences; {self.choice.why})')


def run(cfg: ColorFitConfig, sets: list[list[View]], calibration: Calibration,
        anchor: dict[str, tuple[np.ndarray, np.ndarray]] | None = None, source_bag: str = '') -> ColorFitReport:
    """Fit on ``sets`` (views of capture frame sets posed by ``calibration``) and store the models
    in ``calibration``. ``reference='chart'`` needs the chart models in the calibration and
    ``anchor``, each camera's chart samples (measured, reference)."""
    cfg.validate()
    cameras = cameras_in(sets, calibration)
    matches = merge_matches([find_correspondences(v, cfg.correspondence) for v in sets], cfg.fit_min_fraction)
    if not matches:
        raise BadInput(f'no camera pair has {cfg.fit_min_fraction:.1%} of its pixels in correspondence')
    base = None
    if cfg.reference == 'chart':
        missing = [c for c in cameras if calibration.cameras[c].color is None]
        if missing:
            raise BadInput(f'reference chart needs chart colour models; {", ".join(missing)} have none')
        if anchor is None:
            raise BadInput('reference chart needs the chart samples of the board views')
        base = {c: ColorModel.from_dict(calibration.cameras[c].color) for c in cameras}
    choice = choose_chart_free_model(matches, cameras, cfg.reference, base, anchor) if cfg.model == 'auto' else \
        ModelChoice(cfg.model, why='chosen by the caller')
    models = identity_models(cameras, base) if choice.model == 'identity' else \
        chart_free_fit(matches, cameras, choice.model, cfg.reference, base=base, anchor=anchor)
    source = 'chart_harmonised' if base else 'chart_free'
    for c, m in models.items():
        previous = calibration.cameras[c].color
        entry = {**m.to_dict(), 'source': source,
                 'fit': {'bag': str(source_bag), 'model': choice.model, 'why': choice.why, 'reference': cfg.reference,
                         'pairs': sum(c in p for p in matches), 'frame_sets': len(sets)}}
        if previous is not None:
            entry['previous'] = previous     # the chart fit, with its patch errors
        calibration.cameras[c].color = entry
    return ColorFitReport(calibration, source, list(models), len(matches), sum(len(m) for m in matches.values()),
                          choice)
