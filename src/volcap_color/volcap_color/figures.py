"""The training figure of `volcap harmonise` (loss per epoch of E and of every camera's D)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from volcap_core.figures import save_figure


def training_figure(path: str | Path, report: dict) -> Path:
    """Loss per epoch of E and of every camera's D (``volcap harmonise``'s manifest)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    field = report['field']['losses']
    axes[0].semilogy(np.arange(1, len(field) + 1), np.sqrt(field) * 255.0)
    axes[0].set_title(f"E (colour field): {report['field_samples']} samples, {report['field']['seconds']:.0f} s")
    for cam, r in report['mappers'].items():
        axes[1].semilogy(np.arange(1, len(r['losses']) + 1), np.sqrt(r['losses']) * 255.0, label=cam)
    axes[1].set_title(f"D per camera, reference {report['reference']}")
    axes[1].legend(fontsize=7, ncol=2)
    for ax in axes:
        ax.set_xlabel('epoch')
        ax.set_ylabel('sqrt(training loss), levels')
        ax.grid(alpha=0.3, which='both')
    out = save_figure(fig, path)
    plt.close(fig)
    return out
