"""Find a stand-alone ColorChecker Classic (4 x 6 patches) in a photo and read its patches.

For charts that are not on the ChArUco board (a studio's own X-Rite chart, a Passport): no
markers give the pose, so the chart is found from its geometry alone.

1. Square-ish contours of similar size in adaptive thresholds at a few scales: patch candidates.
2. A lattice hypothesis from each candidate and two neighbours at right angles; every candidate
   gets integer lattice coordinates, and a homography from lattice to image is refitted on the
   inliers (perspective is allowed).
3. Each lattice's 6 x 4 window holding the most candidates is a chart hypothesis.
4. Every hypothesis is read in its four orientations and scored by how well a 3x3 linear-RGB
   matrix maps its 24 patch colours to the reference: only the true chart in its true
   orientation fits the neutral row and the hues (a Passport's other page, a ChArUco board's
   black squares or a chessboard do not).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from volcap_core.errors import BadInput

from .color import fit_model, srgb_to_linear

ROWS, COLUMNS = 4, 6


class ChartNotFound(BadInput):
    pass


@dataclass
class ChartReading:
    colors: np.ndarray      # (24, 3) sRGB in [0, 1], reference order (dark skin first)
    centres: np.ndarray      # (24, 2) patch centres in the image (x, y)
    homography: np.ndarray   # (3, 3) chart lattice (column, row) -> image pixels
    candidates: int          # patch candidates on the chart's lattice
    orientation_residual: float


def robust_mean(values: np.ndarray) -> np.ndarray:
    """Mean of the pixels inside every channel's inter-quartile range (specks and edges out)."""
    lo, hi = np.percentile(values, [25, 75], axis=0)
    keep = np.all((values >= lo) & (values <= hi), axis=1)
    return (values[keep] if keep.sum() >= 3 else values).mean(axis=0)


def patch_candidates(image: np.ndarray, min_side_px: float = 10.0) -> np.ndarray:
    """(N, 3) rows (x, y, side) of square-ish blobs, duplicates across thresholds merged."""
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    h, w = gray.shape
    found = []
    for block in (31, 61, 121):
        for offset in (-2, -5, -10):
            binary = cv2.adaptiveThreshold(gray, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, block, offset)
            contours, _ = cv2.findContours(binary, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
            for contour in contours:
                area = cv2.contourArea(contour)
                if area < min_side_px ** 2 or area > 0.05 * h * w:
                    continue
                quad = cv2.approxPolyDP(contour, 0.08 * cv2.arcLength(contour, True), True)
                if len(quad) != 4 or not cv2.isContourConvex(quad):
                    continue
                _, _, bw, bh = cv2.boundingRect(quad)
                if min(bw, bh) / max(bw, bh) < 0.6 or area / (bw * bh) < 0.7:
                    continue
                found.append((*quad.reshape(4, 2).mean(axis=0), np.sqrt(area)))
    if not found:
        return np.empty((0, 3))
    found = np.array(found)
    # The same patch is found at many thresholds, and sometimes a blob inside it: keep, per
    # group of nearby centres, the median centre and the largest side.
    order = np.argsort(-found[:, 2])
    merged, used = [], np.zeros(len(found), bool)
    for i in order:
        if used[i]:
            continue
        near = ~used & (np.linalg.norm(found[:, :2] - found[i, :2], axis=1) < 0.35 * found[i, 2])
        used |= near
        merged.append((*np.median(found[near, :2], axis=0), found[i, 2]))
    return np.array(merged)


def _lattice_from_seed(centres: np.ndarray, sides: np.ndarray, i: int, j: int, k: int):
    """Integer lattice coordinates of all candidates under the affine lattice through centre i
    with steps to j and k, refined to a homography on the inliers; None when it does not hold."""
    origin, a, b = centres[i], centres[j] - centres[i], centres[k] - centres[i]
    basis = np.column_stack([a, b])
    if abs(np.linalg.det(basis)) < 1e-6:
        return None
    pitch = min(np.linalg.norm(a), np.linalg.norm(b))
    similar_size = np.abs(sides / np.median(sides[[i, j, k]]) - 1.0) < 0.35
    uv, H = np.linalg.solve(basis, (centres - origin).T).T, None
    for refit in (True, True, True, False):
        grid = np.round(uv).astype(int)
        predicted = (origin + grid @ basis.T) if H is None else \
            cv2.perspectiveTransform(grid[None].astype(np.float64), H)[0]
        inlier = (np.linalg.norm(predicted - centres, axis=1) < 0.2 * pitch) & similar_size
        if inlier.sum() < 6:
            return None
        if not refit:
            return grid, inlier, H
        H, _ = cv2.findHomography(grid[inlier].astype(np.float64), centres[inlier], 0)
        if H is None:
            return None
        uv = cv2.perspectiveTransform(centres[None].astype(np.float64), np.linalg.inv(H))[0]


def _best_window(grid: np.ndarray, inlier: np.ndarray):
    """The COLUMNS x ROWS or ROWS x COLUMNS window of lattice cells with the most inliers."""
    cells = {tuple(g) for g in grid[inlier]}
    us, vs = grid[inlier, 0], grid[inlier, 1]
    best = (0, None)
    for width, height in ((COLUMNS, ROWS), (ROWS, COLUMNS)):
        for u0 in range(us.min() - width + 1, us.max() + 1):
            for v0 in range(vs.min() - height + 1, vs.max() + 1):
                n = sum((u, v) in cells for u in range(u0, u0 + width) for v in range(v0, v0 + height))
                if n > best[0]:
                    best = (n, (u0, v0, width, height))
    return best


def _orientations(u0: int, v0: int, width: int, height: int):
    """For each rotation of the window, the (24, 2) lattice cells in reference patch order."""
    # Patch p = row * COLUMNS + column in the chart's own frame.
    rc = np.array([(r, c) for r in range(ROWS) for c in range(COLUMNS)])
    if (width, height) == (COLUMNS, ROWS):
        maps = [lambda r, c: (c, r), lambda r, c: (COLUMNS - 1 - c, ROWS - 1 - r)]
    else:
        maps = [lambda r, c: (r, COLUMNS - 1 - c), lambda r, c: (ROWS - 1 - r, c)]
    for f in maps:
        du, dv = f(rc[:, 0], rc[:, 1])
        yield np.column_stack([u0 + du, v0 + dv])


def quad_mean(image: np.ndarray, quad_px: np.ndarray) -> np.ndarray | None:
    """Robust mean (uint8 levels) of the pixels inside a convex quad, None when it leaves the
    image or covers fewer than 9 pixels."""
    h, w = image.shape[:2]
    x0, y0 = np.floor(quad_px.min(axis=0)).astype(int)
    x1, y1 = np.ceil(quad_px.max(axis=0)).astype(int) + 1
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return None
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, np.round(quad_px - (x0, y0)).astype(np.int32), 1)
    values = image[y0:y1, x0:x1][mask.astype(bool)].astype(np.float64)
    return robust_mean(values) if len(values) >= 9 else None


def sample_cells(image: np.ndarray, H: np.ndarray, cells: np.ndarray, inner: float = 0.4) -> np.ndarray:
    """(N, 3) sRGB in [0, 1]: robust mean over the central ``inner`` x ``inner`` pitch of each
    lattice cell; NaN rows for cells off the image."""
    half = inner / 2
    out = np.full((len(cells), 3), np.nan)
    for n, (u, v) in enumerate(cells):
        quad = np.array([[u - half, v - half], [u + half, v - half], [u + half, v + half], [u - half, v + half]])
        mean = quad_mean(image, cv2.perspectiveTransform(quad[None].astype(np.float64), H)[0])
        if mean is not None:
            out[n] = mean / 255.0
    return out


def find_color_checker(image: np.ndarray, reference: np.ndarray, min_patches: int = 12,
                       max_residual: float = 0.1) -> ChartReading:
    """Locate a ColorChecker Classic in an RGB uint8 ``image``; ``reference`` is the (24, 3) sRGB
    [0, 1] chart reference in patch order, used to tell the chart's orientation and to refuse a
    lattice of squares whose colours no 3x3 matrix maps to the chart's (a chessboard): the best
    orientation's linear-RGB RMS residual must stay under ``max_residual`` (a real chart under
    warm light: 0.025)."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise BadInput(f'expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}')
    found = patch_candidates(image)
    if len(found) < min_patches:
        raise ChartNotFound(f'only {len(found)} square patches in the image (need {min_patches})')
    centres, sides = found[:, :2], found[:, 2]
    windows, most = {}, 0   # distinct chart hypotheses: candidates in the window -> lattice
    for i in range(len(found)):
        d = centres - centres[i]
        dist = np.linalg.norm(d, axis=1)
        near = np.flatnonzero((dist > 1.0 * sides[i]) & (dist < 1.8 * sides[i])
                              & (np.abs(sides / sides[i] - 1.0) < 0.3))
        # The two nearest neighbours at roughly right angles span the lattice.
        for j in near:
            perpendicular = [k for k in near if abs(d[j] @ d[k]) < 0.3 * dist[j] * dist[k]]
            if not perpendicular:
                continue
            k = min(perpendicular, key=lambda k: dist[k])
            if d[j, 0] * d[k, 1] - d[j, 1] * d[k, 0] < 0:
                j, k = k, j   # a right-handed lattice, like the image: a mirrored chart is impossible
            lattice = _lattice_from_seed(centres, sides, i, j, k)
            if lattice is None:
                continue
            grid, inlier, _ = lattice
            n, window = _best_window(grid, inlier)
            most = max(most, n)
            if n >= min_patches:
                u0, v0, width, height = window
                in_window = inlier & (grid[:, 0] >= u0) & (grid[:, 0] < u0 + width) \
                    & (grid[:, 1] >= v0) & (grid[:, 1] < v0 + height)
                windows.setdefault(frozenset(np.flatnonzero(in_window)), (grid, window))
            break
    if not windows:
        raise ChartNotFound(f'no 4 x 6 patch lattice: at most {most} patches line up (need {min_patches})')
    # Several lattices of squares may qualify (a ChArUco board's own squares, a Passport's
    # other page): every orientation of every one is scored on colour, and the best kept.
    target = srgb_to_linear(reference)
    readings = []
    for members, (grid, window) in windows.items():
        members = sorted(members)
        H, _ = cv2.findHomography(grid[members].astype(np.float64), centres[members], 0)
        for cells in _orientations(*window):
            colors = sample_cells(image, H, cells)
            if not np.isfinite(colors).all():
                continue
            fitted = fit_model('matrix_3x3', colors, reference, perceptual=False).apply(colors)
            residual = float(np.sqrt(np.mean((srgb_to_linear(fitted) - target) ** 2)))
            centres_px = cv2.perspectiveTransform(cells[None].astype(np.float64), H)[0]
            readings.append(ChartReading(colors, centres_px, H, len(members), residual))
    if not readings:
        raise ChartNotFound('the only 4 x 6 patch lattice runs off the image')
    best = min(readings, key=lambda r: r.orientation_residual)
    if best.orientation_residual > max_residual:
        raise ChartNotFound(f'{best.candidates} squares form a 4 x 6 lattice, but their colours are not a '
                            f'ColorChecker\'s (residual {best.orientation_residual:.3f} > {max_residual})')
    return best
