"""Temporal filtering of one camera's cleaned depth and colour where the scene holds still.

Each fused frame is made from scratch, so the sensor's noise (4-5 mm per pixel at 2 m), the
marching-cubes edge of the weight threshold and the colour noise all show as shimmer on a subject
that stands still. Per output pixel a running mean of depth (and colour) is kept: the mean of
the frames since the pixel last moved, up to ``1 / alpha`` of them, then an exponential average
with weight ``alpha``. A pixel restarts at its new value when

- it has no depth now or had none (holes, the subject's edge);
- its change is beyond ``pixel_sigmas`` of the time-of-flight noise sigma(z) (a step, an arm);
- the *mean* change over a ``window`` x ``window`` neighbourhood, in units of that noise, is
  beyond ``motion_sigmas`` standard errors of such a mean: single pixels cannot tell 2 mm of
  motion from 5 mm of noise, a 15 x 15 patch can (its mean's noise is 15 times smaller), so a
  turning body restarts while a still one averages;
- its colour changed beyond ``color_levels`` (texture sliding over a surface that stays put, as
  on a body turning about its own axis).

Measured by ``bench/stability.py``: docs/benchmarks.md.
"""
from __future__ import annotations

import cv2
import numpy as np

PIXEL_SIGMAS = 3.0
MOTION_SIGMAS = 3.0
COLOR_LEVELS = 10.0      # 8-bit levels of colour change (largest channel) that mean the texture moved
MIN_SUPPORT = 9          # pixels with depth in both frames that a window needs to judge motion


class TemporalFilter:
    """Running mean of depth (metres) and colour (uint8 RGB) per pixel where the scene holds still."""

    def __init__(self, alpha: float, window: int, noise_base: float, noise_quad: float):
        self.alpha = float(alpha)
        self.max_count = max(1.0, 1.0 / self.alpha)
        self.window = int(window) | 1
        self.noise_base, self.noise_quad = np.float32(noise_base), np.float32(noise_quad)
        self._depth = self._count = self._color = None

    def reset(self) -> None:
        self._depth = self._count = self._color = None

    def update(self, depth: np.ndarray, color: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth, colour, still): the filtered frame and the (depth-grid) pixels that were averaged.
        ``depth`` (h, w) float32 metres, 0 = none; ``color`` (H, W, 3) uint8 at the colour size
        (a multiple of the depth grid's)."""
        if self._depth is None or self._depth.shape != depth.shape or self._color.shape != color.shape:
            self._depth = depth.copy()
            self._count = (depth > 0).astype(np.float32)
            self._color = color.astype(np.float32)
            return depth, color, np.zeros(depth.shape, bool)
        # Only the region with depth now or before can change: the rest of the frame passes as it is.
        rows, cols = np.nonzero(np.any((depth > 0) | (self._depth > 0), axis=1))[0], \
            np.nonzero(np.any((depth > 0) | (self._depth > 0), axis=0))[0]
        if not len(rows):
            self._color = color.astype(np.float32)
            return depth, color, np.zeros(depth.shape, bool)
        pad = self.window // 2
        y0, y1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, depth.shape[0])
        x0, x1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, depth.shape[1])
        region = np.s_[y0:y1, x0:x1]
        z, prev, n = depth[region], self._depth[region], self._count[region]
        both = (z > 0) & (prev > 0)
        sigma = self.noise_base + self.noise_quad * z * z
        r = np.where(both, (z - prev) / np.where(both, sigma, np.float32(1.0)), np.float32(0.0))
        k = (self.window, self.window)
        support = cv2.boxFilter(both.view(np.uint8).astype(np.float32), -1, k, normalize=False,
                                borderType=cv2.BORDER_CONSTANT)
        mean = cv2.boxFilter(r, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT) / np.maximum(support, 1.0)
        # the difference's variance per pixel: the new frame's noise and what is left in the mean's
        spread = np.sqrt((1.0 + 1.0 / np.maximum(n, 1.0)) / np.maximum(support, 1.0))
        still = both & (np.abs(r) <= PIXEL_SIGMAS) & (support >= MIN_SUPPORT) & (np.abs(mean) <= MOTION_SIGMAS * spread)

        sy, sx = color.shape[0] // depth.shape[0], color.shape[1] // depth.shape[1]
        with_color = (sy * depth.shape[0], sx * depth.shape[1]) == color.shape[:2]
        if with_color:
            cregion = np.s_[y0 * sy:y1 * sy, x0 * sx:x1 * sx]
            c, cprev = color[cregion].astype(np.float32), self._color[cregion]
            slid = np.abs(c - cprev).max(axis=2) > COLOR_LEVELS
            # a depth pixel holds still only where all its colour pixels do
            still &= ~slid.reshape(y1 - y0, sy, x1 - x0, sx).any(axis=(1, 3))

        count = np.where(still, np.minimum(n + 1.0, self.max_count), (z > 0).astype(np.float32))
        w = np.where(still, np.float32(1.0) / np.maximum(count, 1.0), np.float32(1.0))
        out_z = np.where(still, prev + w * (z - prev), z).astype(np.float32)
        self._depth[region], self._count[region] = out_z, count
        depth_out = depth.copy()
        depth_out[region] = out_z
        still_full = np.zeros(depth.shape, bool)
        still_full[region] = still
        if not with_color:
            return depth_out, color, still_full
        # Outside the region the colour state is left as it was: a pixel there had no depth
        # before, so it cannot count as still when it comes in, and its old colour is not used.
        wc = np.repeat(np.repeat(w, sy, axis=0), sx, axis=1) if (sy > 1 or sx > 1) else w
        out_c = cprev + wc[..., None] * (c - cprev)
        self._color[cregion] = out_c
        color_out = color.copy()
        color_out[cregion] = np.clip(out_c + 0.5, 0.0, 255.0).astype(np.uint8)
        return depth_out, color_out, still_full
