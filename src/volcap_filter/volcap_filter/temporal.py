"""Temporal filtering of one camera's cleaned depth and colour where the scene holds still.

Each fused frame is made from scratch, so the sensor's noise (4-5 mm per pixel at 2 m), the
marching-cubes edge of the weight threshold and the colour noise all show as shimmer on a subject
that stands still. Per output pixel a running mean of depth (and colour) is kept: the mean of
the frames since the pixel last moved, up to ``1 / alpha`` of them, then an exponential average
with weight ``alpha``. A pixel restarts at its new value when

- it had no depth (the subject's edge, a hole);
- it has no depth now, unless it is *held*: a pixel with a history whose colour and
  neighbourhood are still keeps its mean for as many frames as it has averaged, less one each
  time (dark material returns a random few of its pixels each frame, and without the hold its
  surface comes and goes);
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
import numba
import numpy as np

PIXEL_SIGMAS = 3.0
MOTION_SIGMAS = 3.0
COLOR_LEVELS = 10.0      # 8-bit levels of colour change (largest channel) that mean the texture moved
MIN_SUPPORT = 9          # pixels with depth in both frames that a window needs to judge motion


@numba.njit(cache=True, fastmath=True)
def _normalised_change(z, prev, base, quad, r, both):
    """Per pixel: depth in both frames, and the change in units of the ToF noise sigma(z)."""
    h, w = z.shape
    for v in range(h):
        for u in range(w):
            a, b = z[v, u], prev[v, u]
            ok = (a > 0) & (b > 0)
            both[v, u] = np.float32(1.0) if ok else np.float32(0.0)
            r[v, u] = (a - b) / (base + quad * a * a) if ok else np.float32(0.0)


@numba.njit(cache=True, fastmath=True)
def _average(z, prev, count, r, sum_r, support, color, state, out, sy, sx, max_count, with_color, still):
    """The running mean, in place: ``z`` (the frame's depth region) becomes the output, ``prev``
    and ``count`` the new state; with colour, ``state`` (float) and ``out`` (uint8) likewise."""
    h, w = z.shape
    for v in range(h):
        for u in range(w):
            a, b, n, m = z[v, u], prev[v, u], count[v, u], support[v, u]
            ok = False
            # a hole where a pixel with a history had depth: held (below) if nothing moved
            hold = a <= 0 and b > 0 and n >= 2.0 and with_color
            if (a > 0 or hold) and b > 0 and m >= MIN_SUPPORT and (hold or abs(r[v, u]) <= PIXEL_SIGMAS):
                # the mean change's standard error: the new frame's noise and what is left in the mean
                spread = np.sqrt((1.0 + 1.0 / max(n, 1.0)) / m)
                ok = abs(sum_r[v, u] / m) <= MOTION_SIGMAS * spread
            if ok and with_color:
                for y in range(v * sy, v * sy + sy):
                    for x in range(u * sx, u * sx + sx):
                        for k in range(3):
                            if abs(np.float32(color[y, x, k]) - state[y, x, k]) > COLOR_LEVELS:
                                ok = False
            if ok and hold:
                # The sensor missed a still surface (dark material returns a random few of its
                # pixels each frame): its mean stands in, for one frame fewer each time, and the
                # colour state stays. A subject that left shows a new colour and is not held.
                z[v, u] = b
                count[v, u] = n - 1.0
                still[v, u] = True
                for y in range(v * sy, v * sy + sy):       # a hold has colour (the guard above)
                    for x in range(u * sx, u * sx + sx):
                        for k in range(3):
                            out[y, x, k] = np.uint8(min(max(state[y, x, k] + np.float32(0.5), 0.0), 255.0))
                continue
            if ok:
                n = min(n + 1.0, max_count)
                wgt = np.float32(1.0) / n
                z[v, u] = b + wgt * (a - b)
            else:
                n = np.float32(1.0) if a > 0 else np.float32(0.0)
                wgt = np.float32(1.0)
            prev[v, u] = z[v, u]
            count[v, u] = n
            still[v, u] = ok
            if with_color:
                for y in range(v * sy, v * sy + sy):
                    for x in range(u * sx, u * sx + sx):
                        for k in range(3):
                            c = state[y, x, k] + wgt * (np.float32(color[y, x, k]) - state[y, x, k])
                            state[y, x, k] = c
                            out[y, x, k] = np.uint8(min(max(c + np.float32(0.5), 0.0), 255.0))


class TemporalFilter:
    """Running mean of depth (metres) and colour (uint8 RGB) per pixel where the scene holds still."""

    def __init__(self, alpha: float, window: int, noise_base: float, noise_quad: float):
        self.alpha = float(alpha)
        self.max_count = np.float32(max(1.0, 1.0 / self.alpha))
        self.window = int(window) | 1
        self.noise_base, self.noise_quad = np.float32(noise_base), np.float32(noise_quad)
        self._depth = self._count = self._color = None

    def reset(self) -> None:
        self._depth = self._count = self._color = None

    def update(self, depth: np.ndarray, color: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth, colour, still): the filtered frame and the (depth-grid) pixels that were averaged.
        ``depth`` (h, w) float32 metres, 0 = none, is filtered in place (the cleaner's own array);
        ``color`` (H, W, 3) uint8 at the colour size (a whole multiple of the depth grid's, else
        the colour passes unfiltered) is not written: a filtered copy is returned."""
        depth = np.ascontiguousarray(depth, np.float32)
        if self._depth is None or self._depth.shape != depth.shape or self._color.shape != color.shape:
            self._depth = depth.copy()
            self._count = (depth > 0).astype(np.float32)
            self._color = color.astype(np.float32)
            return depth, color, np.zeros(depth.shape, bool)
        # Only the region with depth now or before can change: the rest of the frame passes as it is.
        x, y, w, h = cv2.boundingRect(((depth > 0) | (self._depth > 0)).view(np.uint8))
        still = np.zeros(depth.shape, bool)
        if w == 0 or h == 0:
            return depth, color, still
        pad = self.window // 2
        y0, y1 = max(y - pad, 0), min(y + h + pad, depth.shape[0])
        x0, x1 = max(x - pad, 0), min(x + w + pad, depth.shape[1])
        z, prev = depth[y0:y1, x0:x1], self._depth[y0:y1, x0:x1]
        r = np.empty(z.shape, np.float32)
        both = np.empty(z.shape, np.float32)
        _normalised_change(z, prev, self.noise_base, self.noise_quad, r, both)
        k = (self.window, self.window)
        support = cv2.boxFilter(both, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        sum_r = cv2.boxFilter(r, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        sy, sx = color.shape[0] // depth.shape[0], color.shape[1] // depth.shape[1]
        with_color = (sy * depth.shape[0], sx * depth.shape[1]) == color.shape[:2]
        out = color.copy() if with_color else color
        cy, cx = (np.s_[y0 * sy:y1 * sy], np.s_[x0 * sx:x1 * sx]) if with_color else (np.s_[0:0], np.s_[0:0])
        # Outside the region the colour state is left as it was: a pixel there had no depth
        # before, so it cannot count as still when it comes in, and its old colour is not used.
        _average(z, prev, self._count[y0:y1, x0:x1], r, sum_r, support, color[cy, cx], self._color[cy, cx],
                 out[cy, cx], sy, sx, self.max_count, with_color, still[y0:y1, x0:x1])
        return depth, out, still
