"""Bilinear sampling of images at many sub-pixel positions (OpenCV remap)."""
from __future__ import annotations

import cv2
import numpy as np


def sample_bilinear(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, C) of an (H, W, C) image (uint8 or float32) at pixel coordinates
    (N, 2) x, y; positions outside repeat the border."""
    n = len(px)
    channels = image.shape[2] if image.ndim == 3 else 1
    if n == 0:
        return np.zeros((0, channels), image.dtype)
    # cv2.remap maps must stay under 32767 rows: lay the lookups out 1024 wide.
    maps = np.zeros((-(-n // 1024) * 1024, 2), np.float32)
    maps[:n] = px
    out = cv2.remap(image, maps.reshape(-1, 1024, 2), None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, channels)[:n]
