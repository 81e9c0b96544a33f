"""Calibration report: the paper's Table 1 colour differences before and after correction, and
its figures: camera poses (top and side views, with the board views) and per-camera colour
errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from volcap_core.calibration import Calibration
from volcap_core.color import ColorModel, delta_e2000
from volcap_core.figures import save_figure

from .calibrate import Calibrator
from .color import component_differences


def poses_figure(path: str | Path, T_world_color: dict[str, np.ndarray], T_world_target: dict[int, np.ndarray],
                 reports: dict[str, dict], title: str = 'camera poses',
                 T_gt: dict[str, np.ndarray] | None = None) -> Path:
    """Top (x-z) and side (x-y) views of the rig in the world frame; each camera is drawn as its
    centre and viewing direction, labelled with its reprojection RMS."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    for ax, (i, j, names) in zip(axes, ((0, 2, ('x', 'z')), (0, 1, ('x', 'y')))):
        for c, T in T_world_color.items():
            o, d = T[:3, 3], T[:3, 2] * 0.35
            ax.plot(o[i], o[j], 'o', color='tab:blue')
            ax.arrow(o[i], o[j], d[i], d[j], head_width=0.04, color='tab:blue', length_includes_head=True)
            rms = reports.get(c, {}).get('reproj_rms_px')
            ax.annotate(f'{c}' + (f'\n{rms:.2f} px' if rms is not None else ''), (o[i], o[j]), fontsize=8,
                        xytext=(4, 4), textcoords='offset points')
            if T_gt is not None and c in T_gt:
                ax.plot(T_gt[c][i, 3], T_gt[c][j, 3], 'x', color='tab:red')
        for T in T_world_target.values():
            ax.plot(T[i, 3], T[j, 3], 's', color='tab:orange', ms=4)
        ax.set_xlabel(f'{names[0]} (m)')
        ax.set_ylabel(f'{names[1]} (m)')
        ax.set_aspect('equal', adjustable='datalim')
        ax.grid(alpha=0.3)
        if j == 1:
            ax.invert_yaxis()   # optical y points down
    axes[0].set_title(f'{title}: top view (world = reference colour frame)')
    axes[1].set_title('front view; squares: board views' + ('; x: ground truth' if T_gt else ''))
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def color_figure(path: str | Path, color: dict[str, dict]) -> Path:
    """Per camera: mean |R|, |G|, |B|, |I| difference to the reference and patch CIEDE2000,
    before and after correction."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    names = list(color)
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5))
    width = 0.2
    for k, (ch, col) in enumerate(zip('RGBI', ('tab:red', 'tab:green', 'tab:blue', 'grey'))):
        axes[0].bar(x + (k - 1.5) * width, [color[c]['before_abs'][ch] for c in names], width, color=col, alpha=0.35)
        axes[0].bar(x + (k - 1.5) * width, [color[c]['after_abs'][ch] for c in names], width, color=col,
                    label=f'|{ch}|')
    axes[0].set_title('mean |difference| to the chart (8-bit levels); light: before, dark: after')
    axes[1].bar(x - 0.2, [color[c]['patch_de2000_before'] for c in names], 0.4, label='before', color='grey')
    axes[1].bar(x + 0.2, [color[c]['patch_de2000_after'] for c in names], 0.4, label='after', color='tab:green')
    axes[1].axhline(2.0, ls='--', color='k', lw=0.8)
    axes[1].set_title('mean CIEDE2000 on the 24 patches')
    for ax in axes:
        ax.set_xticks(x, [f'{c}\n{color[c]["method"]}' for c in names], fontsize=7)
        ax.legend(fontsize=8)
        ax.grid(axis='y', alpha=0.3)
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def chart_figure(path: str | Path, image: np.ndarray, centres: np.ndarray, measured: np.ndarray,
                 corrected: np.ndarray, reference: np.ndarray, de_before: np.ndarray, de_after: np.ndarray,
                 title: str) -> Path:
    """A ColorChecker photo with the found patches numbered, and per patch three stripes
    (as photographed | corrected | reference) labelled with CIEDE2000 before -> after."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(14, 5), gridspec_kw={'width_ratios': [1.4, 1]})
    axes[0].imshow(image)
    for n, (x, y) in enumerate(centres):
        axes[0].text(x, y, str(n), color='white', ha='center', va='center', fontsize=8,
                     bbox={'facecolor': 'black', 'alpha': 0.5, 'pad': 1, 'lw': 0})
    axes[0].set_title(title)
    axes[0].axis('off')
    cell_w, cell_h = 13, 15   # three 3-wide stripes with 1-wide gaps; a text line under them
    swatch = np.ones((4 * cell_h, 6 * cell_w, 3))
    for n in range(24):
        r, c = divmod(n, 6)
        for k, rgb in enumerate((measured[n], corrected[n], reference[n])):
            x = c * cell_w + 1 + 4 * k
            swatch[r * cell_h + 1:r * cell_h + 11, x:x + 3] = rgb
        axes[1].text(c * cell_w + 6, r * cell_h + 11, f'{de_before[n]:.1f}->{de_after[n]:.1f}', ha='center',
                     va='top', fontsize=7)
    axes[1].imshow(swatch, interpolation='nearest')
    axes[1].set_title(f'photo | corrected | reference; CIEDE2000 mean {de_before.mean():.2f} -> {de_after.mean():.2f}')
    axes[1].axis('off')
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def color_report(calibration: Calibration, calibrator: Calibrator) -> dict:
    """Per camera: paper Table 1 differences (signed as published, and absolute) before and after
    the calibration's colour model, and mean CIEDE2000 on the patches; plus the averages."""
    illumination = calibrator.illumination()
    out = {}
    for c, cam in calibration.cameras.items():
        measured, target, _ = calibrator.color_samples(c, illumination)
        if cam.color is None or not len(measured):
            continue
        corrected = ColorModel.from_dict(cam.color).apply(measured)
        before, after = component_differences(measured, target), component_differences(corrected, target)
        out[c] = {'method': cam.color['method'], 'before': before['signed'], 'after': after['signed'],
                  'before_abs': before['abs'], 'after_abs': after['abs'],
                  'patch_de2000_before': float(delta_e2000(measured, target).mean()),
                  'patch_de2000_after': float(delta_e2000(corrected, target).mean()), 'samples': len(measured)}
    return out


def color_summary(color: dict) -> dict:
    """Averages over cameras, as the paper's Table 1 'Average' column."""
    if not color:
        return {}
    keys = ('R', 'G', 'B', 'I')
    avg = {part: {k: float(np.mean([v[part][k] for v in color.values()])) for k in keys}
           for part in ('before', 'after', 'before_abs', 'after_abs')}
    avg['abs_reduction'] = {k: avg['before_abs'][k] / max(avg['after_abs'][k], 1e-9) for k in keys}
    avg['patch_de2000_before'] = float(np.mean([v['patch_de2000_before'] for v in color.values()]))
    avg['patch_de2000_after'] = float(np.mean([v['patch_de2000_after'] for v in color.values()]))
    avg['max_patch_de2000_after'] = float(max(v['patch_de2000_after'] for v in color.values()))
    return avg
