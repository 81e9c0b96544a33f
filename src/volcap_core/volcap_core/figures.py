"""PNG figures, written atomically: images (OpenCV) and matplotlib figures."""
from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np

from .files import atomic_write


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """An RGB (H, W, 3) uint8 image as a PNG."""
    ok, png = cv2.imencode('.png', np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise OSError(f'could not encode {path}')
    return atomic_write(path, lambda f: f.write(png.tobytes()))


def save_figure(fig, path: str | Path) -> Path:
    """A matplotlib figure as a PNG."""
    buf = io.BytesIO()
    fig.savefig(buf, format='png', dpi=110, bbox_inches='tight')
    return atomic_write(path, lambda f: f.write(buf.getvalue()))
