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
  stray clusters) are removed. Dark material returns too sparsely for these tests (no pixel has
  two consecutive neighbours): a return amid holes is kept when returns on its surface surround
  it in the ``sparse_radius`` window, and ``fill_sparse_returns`` closes the holes between such
  returns from the plane through them (issue 30's feet).

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
    sparse_radius: int = setting(4, 'window radius (px) over which a sparse return (dark material) finds its surface '
                                 '(0 = off)', 0, 8)
    sparse_support: int = setting(4, 'returns on its own surface a sparse return needs in that window', 1, 100)
    curved_support: int = setting(10, 'a hole between returns (the sparse fill, the completion\'s first pass) takes '
                                  'the quadric through them instead of the plane where the plane misses them by more '
                                  'than a sigma and this many returns are in reach (0 = planes only)', 0, 100)

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


@numba.njit(cache=True, inline='always')
def _quadrant(dx, dy):
    """The bit of the half-open quadrant (dx, dy) lies in: every neighbour in exactly one."""
    if dx > 0 and dy >= 0:
        return 1
    if dx <= 0 and dy > 0:
        return 2
    if dx < 0 and dy <= 0:
        return 4
    return 8


@numba.njit(cache=True, inline='always')
def _quadrants(bits):
    return (bits & 1) + ((bits >> 1) & 1) + ((bits >> 2) & 1) + ((bits >> 3) & 1)


@numba.njit(cache=True)
def _keep_sparse(zp, r, slope, base, quad, min_support, keep):
    """Keep the valid pixels the tests above could not judge because the sensor returned too few
    around them: dark material (black shoes, hair) returns depth on a random 10-25 % of its
    pixels, so no pixel has the two consecutive neighbours the axis test needs. Such a return is
    kept when its own 3x3 neighbourhood is mostly holes (a mixed pixel sits on a step between two
    returned surfaces, a dense neighbourhood), it is not between a nearer and a farther returned
    neighbour, and the ``(2r+1)^2`` window holds at least ``min_support`` other returns on its
    surface (within a surface step per pixel of distance) in each of the four quadrants around
    it. A row of mixed pixels along an edge fills two or three (the row, the surface on one
    side): with three required, such rows along the synthetic studio's shoes came back (flying
    recall 0.985 -> 0.979). With four, 2 of its ~2950 mixed pixels a frame set come back (3 and
    7 cm off their surface, where a dense surface and dark material meet; recall 0.9854 ->
    0.9847). Counting only sparse returns as support brings those back too, but keeps so few
    shoe returns that the lowest 6 cm fuse 3-6 % instead of 26-28 %. ``zp`` is the depth padded
    by ``r`` zero pixels."""
    h, w = keep.shape
    for v in range(h):
        y = v + r
        for u in range(w):
            x = u + r
            p = zp[y, x]
            if keep[v, u] or not p > 0.0:
                continue
            sigma = base + quad * p * p
            jump = 1.4142135 * (slope * p + 4.3 * sigma)
            near, far, valid = False, False, 0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    q = zp[y + dy, x + dx]
                    if q > 0.0 and (dy != 0 or dx != 0):
                        valid += 1
                        near |= p - q > jump
                        far |= q - p > jump
            if valid > 3 or (near and far):
                continue
            support, bits = 0, 0
            noise = 4.3 * sigma
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    q = zp[y + dy, x + dx]
                    if not q > 0.0 or (dy == 0 and dx == 0):
                        continue
                    if abs(q - p) <= slope * p * max(abs(dy), abs(dx)) + noise:
                        support += 1
                        bits |= _quadrant(dx, dy)
            keep[v, u] = support >= min_support and bits == 15


@numba.njit(cache=True)
def _quadric_at_hole(xs, ys, zs, k, design):
    """(value at the hole, worst residual) of the least-squares quadric z = a + b x + c y + d x^2
    + e x y + f y^2 through the first ``k`` points (x, y offsets from the hole); worst is inf when
    the fit is singular. ``design``: an (at least k, 6) buffer the caller allocates once for
    every hole of an image."""
    a = design[:k]
    for i in range(k):
        x, y = xs[i], ys[i]
        a[i, 0], a[i, 1], a[i, 2], a[i, 3], a[i, 4], a[i, 5] = 1.0, x, y, x * x, x * y, y * y
    ata = a.T @ a
    if abs(np.linalg.det(ata)) < 1e-6:
        return 0.0, np.inf
    coef = np.linalg.solve(ata, a.T @ zs[:k])
    worst = 0.0
    for i in range(k):
        fit = 0.0
        for j in range(6):
            fit += a[i, j] * coef[j]
        worst = max(worst, abs(zs[i] - fit))
    return coef[0], worst


@numba.njit(cache=True)
def _fill_sparse(zp, support, fillable, r, slope, base, quad, min_support, min_quadrants, extrapolate, out,
                 curved=0):
    """``out`` (unpadded, zeros) gets the depth of the ``fillable`` holes from the plane through
    the ``support`` returns around them (``zp`` and ``support`` padded by ``r``), when they lie
    in ``min_quadrants`` of the four quadrants; see ``fill_sparse_returns``. With
    ``extrapolate`` the plane may pass beyond the returns' depth range by one sigma
    (``complete_inside``'s extending passes); else only within it. With ``curved`` (a count of
    returns, 0 = off) a hole with at least that many returns around it whose plane misses one of
    them by more than a sigma takes the least-squares quadric through them where it fits them
    better (``_quadric_at_hole``): the plane of a convex patch (a shoe's toe and top, an ankle)
    lies behind its middle by the patch's sagitta, 5-10 mm over a 9x9 window at 2.5 m, more than
    the 5 mm the fused score allows, or misses its returns by over 3 sigma and fills nothing."""
    h, w = out.shape
    n = (2 * r + 1) * (2 * r + 1)
    xs, ys, zs = np.empty(n), np.empty(n), np.empty(n)
    design = np.empty((n, 6))
    for v in range(h):
        for u in range(w):
            if not fillable[v, u]:
                continue
            y, x = v + r, u + r
            k, bits = 0, 0
            lo, hi = np.inf, 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if support[y + dy, x + dx]:
                        q = zp[y + dy, x + dx]
                        xs[k], ys[k], zs[k] = dx, dy, q
                        k += 1
                        lo, hi = min(lo, q), max(hi, q)
                        bits |= _quadrant(dx, dy)
            if k < min_support or _quadrants(bits) < min_quadrants:
                continue
            m = 0.5 * (lo + hi)
            # one surface across the window: no wider than its steepest measurable incidence spans
            if hi - lo > slope * m * 2 * r + 4.3 * (base + quad * m * m):
                continue
            # least-squares plane z = a + b dx + c dy, evaluated at the hole (a)
            sx, sy, sz, sxx, syy, sxy, sxz, syz = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for i in range(k):
                sx += xs[i]
                sy += ys[i]
                sz += zs[i]
                sxx += xs[i] * xs[i]
                syy += ys[i] * ys[i]
                sxy += xs[i] * ys[i]
                sxz += xs[i] * zs[i]
                syz += ys[i] * zs[i]
            # the normal equations [[k, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]] (a, b, c) =
            # (sz, sxz, syz), solved by Cramer's rule: no allocation per hole
            det = k * (sxx * syy - sxy * sxy) - sx * (sx * syy - sxy * sy) + sy * (sx * sxy - sxx * sy)
            if abs(det) < 1e-9:
                continue
            c0 = (sz * (sxx * syy - sxy * sxy) - sx * (sxz * syy - sxy * syz) + sy * (sxz * sxy - sxx * syz)) / det
            c1 = (k * (sxz * syy - syz * sxy) - sz * (sx * syy - sxy * sy) + sy * (sx * syz - sxz * sy)) / det
            c2 = (k * (sxx * syz - sxy * sxz) - sx * (sx * syz - sxz * sy) + sz * (sx * sxy - sxx * sy)) / det
            # the returns must lie on that plane within the sensor's noise (two surfaces a few
            # centimetres apart pass the range test above, not this one)
            sigma = base + quad * m * m
            worst = 0.0
            for i in range(k):
                worst = max(worst, abs(zs[i] - c0 - c1 * xs[i] - c2 * ys[i]))
            if curved and k >= curved and worst > sigma:
                q0, qworst = _quadric_at_hole(xs, ys, zs, k, design)
                if qworst < worst:
                    c0, worst = q0, qworst
            slack = sigma if extrapolate else 0.0
            if worst <= 3.0 * sigma and lo - slack <= c0 <= hi + slack:
                out[v, u] = c0


def fill_sparse_returns(depth_m: np.ndarray, removed: np.ndarray, focal_px: float,
                        cfg: FlyingPixelConfig | None = None) -> np.ndarray:
    """The depth to give the holes of sparse-return regions (0 elsewhere; add it to the depth).

    Dark material (black shoes, hair) returns depth on a random 10-25 % of its pixels, and the
    fusion cannot close a surface from such a sieve: the lowest 6 cm of the synthetic studio's
    shoes fused 0 %. A hole is filled when its 3x3 neighbourhood is mostly holes, the
    ``sparse_radius`` window around it holds at least ``sparse_support`` sparse returns
    (themselves amid holes) in three of its four quadrants, all on one surface, and the plane
    through them (on a curved patch the quadric, ``curved_support``) fits them within 3 sigma of
    the sensor's noise and passes within their depth range at the hole (interpolated, never
    extrapolated). ``depth_m`` is the depth after the
    flying-pixel filter and ``removed`` its removals: never support, never filled. Dense
    surfaces are untouched."""
    cfg = cfg or FlyingPixelConfig()
    z = np.ascontiguousarray(depth_m, np.float32)
    out = np.zeros_like(z)
    if cfg.sparse_radius == 0:
        return out
    valid = (z > 0).view(np.uint8)
    # Sparse: at most 3 of the 8 neighbours returned (the 3x3 sum counts the pixel itself). Only
    # sparse returns support a fill, so a dense surface beside dark material (the floor behind a
    # shoe) is never extended into it.
    sparse = cv2.boxFilter(valid, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT) - valid <= 3
    support = (valid > 0) & sparse
    r = cfg.sparse_radius
    # only holes with enough support in reach are visited: most holes are empty regions, and the
    # window over each of them was most of the fill's time (bench/filter.py: the fill 1.2 ms a
    # 640x576 studio frame on one core)
    reach = cv2.boxFilter(support.view(np.uint8), cv2.CV_16U, (2 * r + 1, 2 * r + 1), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    fillable = (valid == 0) & sparse & ~np.asarray(removed, bool) & (reach >= cfg.sparse_support)
    slope = float(np.tan(np.radians(cfg.max_incidence_deg)) / focal_px)
    _fill_sparse(np.pad(z, r), np.pad(support, r), fillable, r, slope, cfg.noise_base, cfg.noise_quad,
                 cfg.sparse_support, 3, False, out, cfg.curved_support)     # interpolated, never extrapolated
    return out


def complete_inside(depth_m: np.ndarray, region: np.ndarray, focal_px: float, radius: int, extend: int,
                    cfg: FlyingPixelConfig | None = None) -> int:
    """Gives the holes inside ``region`` depth, in place (``depth_m`` float32); returns how many.

    For cleaned depth in the colour camera's geometry with ``region`` the foreground silhouette:
    a hole there is the subject's surface without depth. ``fill_sparse_returns`` closes dark
    material's sieve only between returns it kept, and at a shoe's sole it keeps none (the floor
    beside them is another surface, so no return there has its surface on every side): the
    lowest 6 cm fused 30 %, and fusing the truth's exact depth on that same sieve only 40 %
    (bench/feet.py --ceiling). The silhouette says where the surface ends. Holes are completed
    from the plane through the depth inside ``region`` around them, the same plane test as
    ``fill_sparse_returns`` over a ``radius`` window: first between depth on three sides
    (interpolated), then ``extend`` passes from depth on any side towards the silhouette's edge,
    each reaching ``radius`` px further (the plane may pass beyond the depth range around it by
    one sigma: a surface turning away towards a rim is not extended). Allowing that range plus
    a sigma gave the same feet (91.2 against 91.0 %) and a turning subject's accuracy 1.38
    against 1.36 mm (seed 3); extending only 2 px or more inside the silhouette, 1.31 mm but
    feet 86.3 %, since a sole's strip ends at the silhouette's edge. Nothing outside ``region``
    is touched, and only its bounding box is visited. OpenCV's inpainting (Telea, Navier-Stokes)
    is no substitute: it takes every pixel outside its mask as known, so the zeros beyond the
    silhouette pull the sole towards 0 m (on the test's shoe: 1.0 m / 0.57 m median error,
    against 1.0 mm here)."""
    cfg = cfg or FlyingPixelConfig()
    if depth_m.dtype != np.float32 or depth_m.shape != region.shape:
        raise BadInput(f'complete_inside needs float32 depth and a region of its shape, got {depth_m.dtype} '
                       f'{depth_m.shape} and {region.shape}')
    region = np.ascontiguousarray(region, bool)
    x, y, w, h = cv2.boundingRect(region.view(np.uint8))
    if radius == 0 or w == 0:
        return 0
    r = radius
    box = (slice(y, y + h), slice(x, x + w))
    inside = region[box]
    zp = np.pad(depth_m[box], r)    # the box only, padded for the window
    core = zp[r:-r, r:-r]
    support = np.pad((core > 0) & inside, r)
    count = 0
    slope = float(np.tan(np.radians(cfg.max_incidence_deg)) / focal_px)
    window = (2 * r + 1, 2 * r + 1)
    for k in range(1 + extend):
        reach = cv2.boxFilter(support.view(np.uint8), cv2.CV_16U, window, normalize=False,
                              borderType=cv2.BORDER_CONSTANT)[r:-r, r:-r]
        fillable = inside & (core <= 0) & (reach >= cfg.sparse_support)
        if not fillable.any():
            break
        # Written straight into the box: the kernel reads depth only where ``support`` is set,
        # never at the holes it fills, so this pass sees none of its own fills.
        _fill_sparse(zp, support, fillable, r, slope, cfg.noise_base, cfg.noise_quad, cfg.sparse_support,
                     3 if k == 0 else 1, k > 0, core, cfg.curved_support if k == 0 else 0)
        fresh = fillable & (core > 0)
        support[r:-r, r:-r] |= fresh        # the next pass grows from this one's fills
        count += int(np.count_nonzero(fresh))
    depth_m[box] = core
    return count


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
    if cfg.sparse_radius > 0:
        _keep_sparse(np.pad(z, cfg.sparse_radius), cfg.sparse_radius, slope, cfg.noise_base, cfg.noise_quad,
                     cfg.sparse_support, keep)
    return (z > 0) & ~keep
