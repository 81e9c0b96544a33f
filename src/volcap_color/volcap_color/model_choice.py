"""Choosing the chart-free model per rig: the families fitted on half the correspondences and
scored on the other half (CIEDE2000, dark pixels, chroma, lightness spread); a richer model must
keep the simplest one's contrast."""
from __future__ import annotations

from dataclasses import dataclass, field

import colour as color_science
import numpy as np

from volcap_core.color import ColorModel, srgb_to_lab

from .chart_free import chart_free_fit
from .config import CHART_FREE_MODELS, SELECTABLE_MODELS  # noqa: F401 (re-exported)
from .correspondence import Matches

DARK_L = 25.0          # CIELAB L* below which a correspondence counts as dark


SATURATED_CHROMA = 25.0     # CIELAB C*ab (as recorded) above which a colour counts as saturated


CONTRAST_KEPT = 0.98   # share of the simplest model's lightness spread a richer chosen model must keep


@dataclass
class ModelChoice:
    model: str                   # a CHART_FREE_MODELS name, or 'identity' when none helps
    scores: dict[str, dict] = field(default_factory=dict)   # candidate -> {'de2000', 'de2000_dark'}
    why: str = ''

    def to_dict(self) -> dict:
        return {'model': self.model, 'scores': self.scores, 'why': self.why}


def split_matches(matches: dict[tuple[str, str], Matches], share: float = 0.5, seed: int = 0
                  ) -> tuple[dict[tuple[str, str], Matches], dict[tuple[str, str], Matches]]:
    """Each pair's correspondences split at random into two disjoint sets (``share`` in the first)."""
    rng = np.random.default_rng(seed)
    first, second = {}, {}
    for key, m in matches.items():
        pick = rng.random(len(m)) < share
        for out, keep in ((first, pick), (second, ~pick)):
            out[key] = Matches(m.a, m.b, m.pixels_a[keep], m.pixels_b[keep], m.colors_a[keep], m.colors_b[keep],
                               m.fraction * float(keep.mean()) if len(m) else 0.0)
    return first, second


def chroma(lab: np.ndarray) -> np.ndarray:
    """CIELAB C*ab of (N, 3) L*a*b* rows."""
    return np.hypot(lab[:, 1], lab[:, 2])


def held_out_scores(matches: dict[tuple[str, str], Matches], models: dict[str, ColorModel] | None) -> dict:
    """How well ``models`` (None: the colours as recorded) make corresponding colours agree, and
    what that does to them, over every pair: mean CIEDE2000 over all correspondences and over
    the dark ones (L* < ``DARK_L``), mean chroma of the saturated colours (C*ab >=
    ``SATURATED_CHROMA`` as recorded, so every model is measured on the same pixels) and the
    standard deviation of L*. Each side is mapped and converted once."""
    pairs = [m for m in matches.values() if len(m)]
    if not pairs:
        return {'de2000': float('nan'), 'de2000_dark': float('nan'), 'chroma': float('nan'),
                'lightness_std': float('nan')}

    def mapped(camera, colors):
        return np.clip(models[camera].apply(colors), 0, 1) if models else colors
    lab_a = srgb_to_lab(np.vstack([mapped(m.a, m.colors_a) for m in pairs]))
    lab_b = srgb_to_lab(np.vstack([mapped(m.b, m.colors_b) for m in pairs]))
    recorded_a = np.vstack([m.colors_a for m in pairs])
    recorded_b = np.vstack([m.colors_b for m in pairs])
    de = color_science.delta_E(lab_a, lab_b, method='CIE 2000')
    dark = srgb_to_lab(np.minimum(recorded_a, recorded_b))[:, 0] < DARK_L
    lab = np.vstack([lab_a, lab_b])
    saturated = chroma(srgb_to_lab(np.vstack([recorded_a, recorded_b]))) >= SATURATED_CHROMA
    return {'de2000': float(de.mean()), 'de2000_dark': float(de[dark].mean()) if dark.any() else float('nan'),
            'chroma': float(chroma(lab[saturated]).mean()) if saturated.any() else float('nan'),
            'lightness_std': float(lab[:, 0].std())}


def choose_chart_free_model(matches: dict[tuple[str, str], Matches], cameras: list[str], reference: str = 'mean',
                            base: dict[str, ColorModel] | None = None,
                            anchor: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                            candidates: tuple[str, ...] = SELECTABLE_MODELS, tolerance: float = 0.05,
                            seed: int = 0) -> ModelChoice:
    """The model family for this rig, chosen on correspondences held out from the fit (half of
    each pair's): among the candidates that keep the colours' contrast (the spread of CIELAB L*
    within ``CONTRAST_KEPT`` of the simplest candidate's), the simplest within ``tolerance``
    (relative) of the best held-out CIEDE2000 that does not make the dark correspondences worse
    than they were; the identity when no candidate improves on the untouched colours (a rig
    already consistent). ``base``, ``anchor``: as ``chart_free_fit`` (the untouched colours are
    then the base models')."""
    fit, check = split_matches(matches, seed=seed)
    scores = {'identity': held_out_scores(check, base)}
    before = scores['identity']
    for model in candidates:
        scores[model] = held_out_scores(check, chart_free_fit(fit, cameras, model, reference, base=base, anchor=anchor,
                                                               seed=seed))

    def flattens(s):
        # Corresponding colours also agree when lightness is pulled together (blacks lifted,
        # highlights pressed): with mis-registered correspondences a flexible model gains
        # held-out CIEDE2000 that way and loses the truth. The simplest candidate (per-channel
        # gains) cannot do that, so its spread is the yardstick.
        return s['lightness_std'] < CONTRAST_KEPT * scores[candidates[0]]['lightness_std']

    def darkens(s):
        return s['de2000_dark'] > before['de2000_dark']
    admissible = candidates[:1] + tuple(m for m in candidates[1:] if not flattens(scores[m]))
    best = min(scores[m]['de2000'] for m in admissible)
    if not best < before['de2000']:
        return ModelChoice('identity', scores, f'no model improves on the untouched colours ({before["de2000"]:.2f})')
    for model in admissible:
        s = scores[model]
        if s['de2000'] <= best * (1 + tolerance) and not darkens(s):
            flattening = [m for m in candidates if m not in admissible]
            return ModelChoice(model, scores, f'simplest within {tolerance:.0%} of the best held-out CIEDE2000 '
                                              f'({best:.2f}) that keeps dark pixels ({before["de2000_dark"]:.2f} -> '
                                              f'{s["de2000_dark"]:.2f})' +
                               (f'; left out for flattening lightness: {", ".join(flattening)}' if flattening else ''))
    model = min(admissible, key=lambda m: scores[m]['de2000'])
    return ModelChoice(model, scores, 'every candidate worsens dark pixels; the best held-out one')
