"""Panels of depth cleaning: paper 000 Fig. 13 style (RGB, mask, masked RGB) and raw vs cleaned
depth with the removed flying pixels marked, like its Figs. 14-15."""
from __future__ import annotations

import cv2
import numpy as np

from .pipeline import CleanResult


def depth_colormap(depth_m: np.ndarray, far: float = 4.0) -> np.ndarray:
    """RGB turbo rendering of depth in metres, black where invalid."""
    scaled = (np.clip(depth_m / far, 0, 1) * 255).astype(np.uint8)
    rgb = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)[:, :, ::-1].copy()
    rgb[depth_m <= 0] = 0
    return rgb


def mask_panels(color: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Fig. 13 (a)-(c): original RGB, mask, masked RGB, side by side."""
    m = mask.astype(np.uint8)[:, :, None]
    return np.concatenate([color, np.repeat(m * 255, 3, axis=2), color * m], axis=1)


def depth_panels(raw_m: np.ndarray, result: CleanResult) -> np.ndarray:
    """Raw depth with the flying-pixel filter's removals in orange, and the cleaned output."""
    raw = depth_colormap(raw_m)
    raw[result.flying] = (255, 140, 0)
    clean = depth_colormap(result.depth)
    h = raw.shape[0]
    clean = cv2.resize(clean, (int(round(clean.shape[1] * h / clean.shape[0])), h), interpolation=cv2.INTER_NEAREST)
    return np.concatenate([raw, clean], axis=1)
