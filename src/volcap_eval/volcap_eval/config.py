"""The evaluations' settings, importable without the evaluations (the command line reads them)."""
from __future__ import annotations

from dataclasses import dataclass, field

from volcap_color.config import CHART_FREE_MODELS, CaptureSetsConfig, CorrespondenceConfig
from volcap_core.settings import setting


@dataclass
class ColorEvalConfig(CaptureSetsConfig):
    # frames: CaptureSetsConfig's, shared with color-fit and harmonise
    eval_min_fraction: float = 0.01
    fit_min_fraction: float = 0.001
    max_scored_per_pair: int = 50_000
    chart_free_model: str = setting('auto', 'model family of volcap_chart_free (auto: chosen per rig on held-out '
                                    'correspondences)', choices=('auto',) + CHART_FREE_MODELS)
    chart_free_reference: str = 'mean'
    anchor_weight: float = 0.05       # chart term of volcap_chart_harmonised, relative to correspondences
    seed: int = 0
    correspondence: CorrespondenceConfig = field(default_factory=lambda: CorrespondenceConfig(min_fraction=0.0))
