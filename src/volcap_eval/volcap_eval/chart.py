"""`volcap eval chart`: find a ColorChecker Classic in stand-alone photos and score the colour
models volcap_calib fits to it (CIEDE2000 before and after, leave-one-patch-out, paper 000 Table 1)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from volcap_calib.board import reference_srgb8
from volcap_calib.chart import ChartNotFound, find_color_checker
from volcap_calib.color import component_differences, fit_camera_color
from volcap_calib.report import chart_figure
from volcap_core.color import METHODS, delta_e2000


def evaluate_charts(photos: list[str | Path], method: str | None = None, figures: str | Path | None = None
                    ) -> tuple[dict, list[str]]:
    """({'photos': {name: scores}, 'failed': [photos]}, the lines to print)."""
    reference = reference_srgb8() / 255.0
    result, failed, lines = {}, [], []
    for photo in photos:
        bgr = cv2.imread(str(photo), cv2.IMREAD_COLOR)
        if bgr is None:
            lines.append(f'{photo}: not a readable image')
            failed.append(str(photo))
            continue
        image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        try:
            chart = find_color_checker(image, reference)
        except ChartNotFound as e:
            lines.append(f'{photo}: no ColorChecker: {e}')
            failed.append(str(photo))
            continue
        fit = fit_camera_color(chart.colors, reference, np.arange(24), method=method)
        corrected = fit.model.apply(chart.colors)
        de_before, de_after = delta_e2000(chart.colors, reference), delta_e2000(corrected, reference)
        name = Path(photo).stem
        result[name] = {'photo': str(photo), 'patches_found': chart.candidates, 'method': fit.model.method,
                        'model': fit.model.to_dict(), 'de2000_before': float(de_before.mean()),
                        'de2000_after': float(de_after.mean()), 'de2000_after_loo': fit.loo_de2000[fit.model.method],
                        'loo_de2000': fit.loo_de2000, 'table1_before': component_differences(chart.colors, reference),
                        'table1_after': component_differences(corrected, reference),
                        'patch_de2000_before': [float(v) for v in de_before],
                        'patch_de2000_after': [float(v) for v in de_after]}
        lines.append(f'{name}: chart found ({chart.candidates} patches detected, 24 sampled); {fit.model.method}: '
                     f'CIEDE2000 {de_before.mean():.2f} -> {de_after.mean():.2f} (leave-one-patch-out '
                     f'{fit.loo_de2000[fit.model.method]:.2f}, max {de_after.max():.2f})')
        lines.append('  leave-one-patch-out per model: ' + ', '.join(f'{m} {fit.loo_de2000[m]:.2f}'
                                                                     for m in METHODS if m in fit.loo_de2000))
        if figures:
            png = chart_figure(Path(figures) / f'{name}_chart.png', image, chart.centres, chart.colors,
                               corrected, reference, de_before, de_after, f'{name}: {fit.model.method}')
            lines.append(f'  figure {png}')
    return {'photos': result, 'failed': failed}, lines
