"""Flying-pixel filters on raw depth images (the sensor's own pixel grid).

A time-of-flight pixel whose footprint straddles a depth step reports a mix of the surfaces it
sees: a point floating between foreground and background. Two detectors:

- ``paper_flying_pixels``: Eq. 5 of paper 000 as published, the baseline. Over a 3x3 window,
  ``DepthError = p_i - 1/n sum_j (p_i - p_j)^2`` with depths in millimetres, and the centre is
  removed when the mean squared difference exceeds its depth (``DepthError < 0``). Neighbours
  are the two horizontal ones or all eight; invalid (zero) neighbours are left out of the mean,
  since the paper does not say how it treats them and counting them as 0 mm would remove the
  rim of every hole.
- ``flying_pixels`` (ours): a pixel is real surface when it continues the surface of its
  neighbours in at least three of the four axes (default): along a direction, the next pixel must be
  within one surface step (what a surface at the largest measurable incidence angle produces,
  plus noise) and the pixel must lie on the line through the next two (second difference
  within the time-of-flight noise sigma(z) = base + quad z^2 and a curvature allowance). A
  mixed pixel continues neither side of its step, and a row of them along a straight edge
  continues only itself (one axis), so both fail; a true boundary pixel continues its own
  surface along the edge and into its side (three axes) and is kept. Next to a depth step the test is one-sided and
  strict, since mixing only ever pulls a pixel from its surface towards the other one. Then
  connected components of kept pixels smaller than ``min_component_px`` (interference speckle,
  stray clusters) are removed.

Depth a driver has registered to the colour camera (Azure Kinect ``depth_to_rgb``, Orbbec
``depth_registration``) is 640x576 spread over 1280x720: every 4-6 px a row and a column stay
empty, so every pixel borders a hole and both tests would remove all of it. ``fill_lattice_gaps``
bridges such gaps (at most ``max_gap`` px between two pixels of one surface) for the tests only;
the holes stay holes in the output.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from volcap_core.errors import BadInput
from volcap_core.settings import setting, validate


@numba.njit(cache=True)
def _paper_eq5(depth_mm, horizontal, threshold):
    h, w = depth_mm.shape
    out = np.zeros((h, w), np.bool_)
    for v in range(h):
        for u in range(w):
            p = depth_mm[v, u]
            if not p > 0.0:
                continue
            acc, n = 0.0, 0
            for dv in range(-1, 2):
                if horizontal and dv != 0:
                    continue
                y = v + dv
                if y < 0 or y >= h:
                    continue
                for du in range(-1, 2):
                    x = u + du
                    if (dv == 0 and du == 0) or x < 0 or x >= w:
                        continue
                    q = depth_mm[y, x]
                    if q > 0.0:
                        acc += (p - q) * (p - q)
                        n += 1
            if n > 0 and p - acc / n < threshold:
                out[v, u] = True
    return out


def paper_flying_pixels(depth_m: np.ndarray, directions: str = 'all', threshold_mm: float = 0.0) -> np.ndarray:
    """Paper 000 Eq. 5 on a depth image in metres: bool mask of the pixels it removes."""
    if directions not in ('all', 'horizontal'):
        raise BadInput(f"directions must be 'all' or 'horizontal', got {directions!r}")
    depth_mm = np.ascontiguousarray(depth_m, np.float32) * np.float32(1000.0)
    return _paper_eq5(depth_mm, directions == 'horizontal', float(threshold_mm))


@dataclass
class FlyingPixelConfig:
    noise_base: float = setting(0.0008, 'ToF depth noise sigma at 0 m (m); sigma(z) = base + quad z^2', 0.0, 0.05)
    noise_quad: float = setting(0.0010, 'ToF depth noise growth (m per m^2)', 0.0, 0.05)
    noise_sigmas: float = setting(3.0, 'second-difference tolerance on smooth surfaces, in sigmas', 0.5, 20.0)
    edge_sigmas: float = setting(1.0, 'one-sided tolerance for pixels at a depth step, in sigmas', 0.1, 20.0)
    curvature: float = setting(0.004, 'second-difference allowance per metre of depth for curved surfaces', 0.0, 0.1)
    max_incidence_deg: float = setting(75.0, 'steeper surfaces than this incidence angle count as depth steps',
                                       30.0, 89.0)
    min_axes: int = setting(3, 'axes (of 4) along which a pixel must continue a surface', 1, 4)
    min_component_px: int = setting(30, 'connected pieces of depth smaller than this are removed (0 = off)', 0, 10000)

    def validate(self) -> None:
        validate(self)


@numba.njit(cache=True, inline='always')
def _continues(zp, y, x, dy, dx, p, limit, lo, hi):
    """Whether the pixel continues the surface of its next two pixels on either side along
    (dy, dx); branch-free so that the row loop stays fast on noisy depth."""
    ok = False
    zero = np.float32(0.0)
    for sgn in (1, -1):
        z1, z2 = zp[y + sgn * dy, x + sgn * dx], zp[y + 2 * sgn * dy, x + 2 * sgn * dx]
        e = p - (z1 + z1) + z2
        ok |= (z1 > zero) & (z2 > zero) & (abs(p - z1) <= limit) & (abs(z1 - z2) <= limit) & (e >= lo) & (e <= hi)
    return np.int32(ok)


@numba.njit(cache=True, fastmath=True)
def _support(zp, slope, base, quad, k_sym, k_edge, curv, min_axes, keep, at_step):
    """``zp`` is the depth padded by 2 zero pixels on every side; ``keep`` and ``at_step``
    (pixel next to a depth step or hole) are unpadded outputs."""
    h, w = keep.shape
    # float32 throughout: the depth is float32 and mixed precision costs vector width.
    zero, root2, step_sigmas, root6 = np.float32(0.0), np.float32(1.4142135), np.float32(4.3), np.float32(2.4494897)
    slope, base, quad = np.float32(slope), np.float32(base), np.float32(quad)
    k_sym, k_edge, curv = np.float32(k_sym), np.float32(k_edge), np.float32(curv)
    for v in range(h):
        y = v + 2
        for u in range(w):
            x = u + 2
            p = zp[y, x]
            if not p > zero:   # invalid areas are large and contiguous: a well-predicted branch
                keep[v, u] = False
                at_step[v, u] = False
                continue
            sigma = base + quad * p * p
            step = slope * p + step_sigmas * sigma
            jump = root2 * step
            # At a depth step a mixed pixel lies behind the near surface or in front of the far
            # one, so there the test is one-sided and strict; a hole may hide either.
            far_step, near_step = False, False
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    q = zp[y + dy, x + dx]
                    far_step |= (q <= zero) | (q - p > jump)
                    near_step |= (q > zero) & (p - q > jump)
            at_step[v, u] = far_step | near_step
            s = root6 * sigma + curv * p
            lo = -(k_edge if near_step else k_sym) * s
            hi = (k_edge if far_step else k_sym) * s
            n = (_continues(zp, y, x, 0, 1, p, step, lo, hi) + _continues(zp, y, x, 1, 0, p, step, lo, hi)
                 + _continues(zp, y, x, 1, 1, p, jump, lo, hi) + _continues(zp, y, x, 1, -1, p, jump, lo, hi))
            keep[v, u] = n >= min_axes


@numba.njit(cache=True)
def _drop_small(labels, n_labels, keep, at_step, z, slope, base, quad, min_px):
    """Clear ``keep`` on pieces of surface smaller than ``min_px``. ``labels`` are components of
    the kept pixels away from steps; a kept pixel at a step survives only beside a large
    component at its own depth (so a speckle blob does not survive by touching the wall)."""
    h, w = labels.shape
    size = np.zeros(n_labels, np.int32)
    for v in range(h):
        for u in range(w):
            size[labels[v, u]] += 1
    size[0] = 0
    for v in range(h):
        for u in range(w):
            if not keep[v, u]:
                continue
            if not at_step[v, u]:
                keep[v, u] = size[labels[v, u]] >= min_px
                continue
            p = z[v, u]
            jump = 1.4142135 * (slope * p + 4.3 * (base + quad * p * p))
            ok = False
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    y, x = v + dy, u + dx
                    if 0 <= y < h and 0 <= x < w and size[labels[y, x]] >= min_px and abs(z[y, x] - p) <= jump:
                        ok = True
            keep[v, u] = ok


@numba.njit(cache=True)
def _fill_gaps(z, slope, base, quad, max_gap, out):
    h, w = z.shape
    for v in range(h):
        for u in range(w):
            out[v, u] = z[v, u]
            if z[v, u] > 0.0:
                continue
            for dy, dx in ((0, 1), (1, 0)):
                a, da, b, db = 0.0, 0, 0.0, 0
                for k in range(1, max_gap + 1):
                    y, x = v - k * dy, u - k * dx
                    if y < 0 or x < 0:
                        break
                    if z[y, x] > 0.0:
                        a, da = z[y, x], k
                        break
                for k in range(1, max_gap + 1):
                    y, x = v + k * dy, u + k * dx
                    if y >= h or x >= w:
                        break
                    if z[y, x] > 0.0:
                        b, db = z[y, x], k
                        break
                if da == 0 or db == 0 or da + db > max_gap + 1:
                    continue
                m = 0.5 * (a + b)
                # the two sides must be one surface: within a surface step per pixel of span
                if abs(a - b) <= (slope * m + 4.3 * (base + quad * m * m)) * (da + db):
                    out[v, u] = a + (b - a) * da / (da + db)
                    break


def fill_lattice_gaps(depth_m: np.ndarray, focal_px: float, cfg: FlyingPixelConfig | None = None,
                      max_gap: int = 2) -> np.ndarray:
    """Depth with holes of at most ``max_gap`` px between two pixels of one surface (along a row
    or a column) filled by linear interpolation. Two passes: the first fills the empty rows and
    columns of a driver's upsampled depth, the second the pixels where they cross."""
    cfg = cfg or FlyingPixelConfig()
    z = np.ascontiguousarray(depth_m, np.float32)
    slope = float(np.tan(np.radians(cfg.max_incidence_deg)) / focal_px)
    for _ in range(2):
        out = np.empty_like(z)
        _fill_gaps(z, slope, cfg.noise_base, cfg.noise_quad, max_gap, out)
        z = out
    return z


def flying_pixels(depth_m: np.ndarray, focal_px: float, cfg: FlyingPixelConfig | None = None) -> np.ndarray:
    """Our flying-pixel and outlier detector: bool mask of valid pixels to remove."""
    cfg = cfg or FlyingPixelConfig()
    cfg.validate()
    z = np.ascontiguousarray(depth_m, np.float32)
    slope = float(np.tan(np.radians(cfg.max_incidence_deg)) / focal_px)
    keep = np.empty(z.shape, np.bool_)
    at_step = np.empty(z.shape, np.bool_)
    _support(np.pad(z, 2), slope, cfg.noise_base, cfg.noise_quad, cfg.noise_sigmas, cfg.edge_sigmas, cfg.curvature,
             cfg.min_axes, keep, at_step)
    if cfg.min_component_px > 0:
        # Pixels at steps are left out of the labelling, so surfaces at different depths stay
        # apart and plain connectivity finds the stray islands (speckle, clusters of mixed pixels).
        n, labels = cv2.connectedComponents((keep & ~at_step).view(np.uint8), connectivity=4, ltype=cv2.CV_32S)
        _drop_small(labels, n, keep, at_step, z, slope, cfg.noise_base, cfg.noise_quad, cfg.min_component_px)
    return (z > 0) & ~keep
