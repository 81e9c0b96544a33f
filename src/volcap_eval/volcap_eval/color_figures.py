"""Figures of the colour evaluation: per-method bars of the pairwise scores, and the cameras'
images before and after our methods side by side (as paper 001 Fig. 17)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from volcap_color.apply import ImageCorrector
from volcap_color.correspondence import View
from volcap_core.figures import save_figure, write_png

GRID_WIDTH = 320          # pixels per camera tile


def bars_figure(path: str | Path, report: dict) -> Path:
    """Mean (with standard deviation over pairs) CIEDE2000 and PSNR of every method, over the
    paper's pairs (every pair when none reaches its overlap), and the scores against the true
    colours where they are known."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    key = 'methods' if any(s['pairs'] for s in report['methods'].values()) else 'methods_all_pairs'
    methods = report[key]
    names = [n for n, s in methods.items() if s['pairs']]
    panels = [('de2000_mean', 'de2000_std', 'pairwise CIEDE2000 (lower is better)'),
              ('psnr_mean', 'psnr_std', 'pairwise PSNR dB (higher is better)')]
    if any(methods[n].get('truth_de2000') is not None for n in names):
        panels.append(('truth_de2000', None, 'CIEDE2000 to the true colours (lower is better)'))
    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 4.8))
    for ax, (mean_key, std_key, label) in zip(axes, panels):
        means = [np.nan if methods[n].get(mean_key) is None else methods[n][mean_key] for n in names]
        stds = [methods[n][std_key] for n in names] if std_key else None
        colors = ['tab:green' if n.startswith(('volcap', 'neural')) else 'tab:grey' if n == 'original' else
                  'tab:olive' if n == 'true_colours' else 'tab:blue' for n in names]
        ax.bar(np.arange(len(names)), means, yerr=stds, color=colors, capsize=3)
        ax.set_xticks(np.arange(len(names)), names, rotation=40, ha='right', fontsize=8)
        ax.set_title(label)
        ax.grid(axis='y', alpha=0.3)
        for i, v in enumerate(means):
            ax.annotate(f'{v:.2f}', (i, v), ha='center', va='bottom', fontsize=7, xytext=(0, 2), textcoords='offset points')
    pairs = max(methods[n]['pairs'] for n in names) if names else 0
    fig.suptitle(f'colour methods over {pairs} camera pairs' +
                 (' (every pair: none reaches the paper\'s overlap)' if key == 'methods_all_pairs' else ''))
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def image_grid(path: str | Path, views: list[View], rows: dict[str, dict]) -> Path:
    """One row per method (its per-camera mapping or ColourModel), one column per camera; each
    row labelled with its method name."""
    tiles = []
    for name, per_camera in rows.items():
        row = []
        for v in views:
            h = int(round(v.color.shape[0] * GRID_WIDTH / v.color.shape[1]))
            small = cv2.resize(v.color, (GRID_WIDTH, h), interpolation=cv2.INTER_AREA)
            img = ImageCorrector(per_camera[v.name])(small)
            cv2.putText(img, v.name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
            row.append(img)
        strip = np.hstack(row)
        label = np.zeros((26, strip.shape[1], 3), np.uint8)
        cv2.putText(label, name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        tiles += [label, strip]
    write_png(Path(path), np.vstack(tiles))
    return Path(path)


def write_color_figures(out_dir: str | Path, report: dict, views: list[View], mappings: dict, models: dict,
                        region_luts: dict | None = None) -> list[Path]:
    """colour_methods.png (bars) and colour_images.png (original, our methods and, given its
    region LUTs, the neural method's live form per camera)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = {'original': mappings['original']}
    for name in ('volcap_chart', 'volcap_chart_free', 'volcap_chart_harmonised'):
        if name in mappings:
            rows[name] = models.get(name) or mappings[name]
    if region_luts:
        rows['neural_live'] = region_luts
    return [bars_figure(out_dir / 'colour_methods.png', report), image_grid(out_dir / 'colour_images.png', views, rows)]


