"""Paper 001's comparison methods over correspondences: pixel mappings and the correspondence graph
they propagate along, the pairwise transfers (Reinhard, De Marchi's Vandermonde, Finlayson's
root-polynomial) and the global baselines (Brown-Lowe gain compensation, Moulon)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import colour as color_science
import numpy as np
from scipy.optimize import linprog
from scipy.sparse.csgraph import shortest_path

from volcap_core.color import ColorModel, srgb_to_linear

from .apply import pixel_centres
from .config import CHART_FREE_MODELS, SELECTABLE_MODELS  # noqa: F401 (re-exported)
from .correspondence import Matches

Mapping = Callable[[np.ndarray], np.ndarray]


def pair_colors(matches: dict[tuple[str, str], Matches], a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
    """Colours of a and b at their common surface points, whichever order the pair was matched in."""
    if (a, b) in matches:
        m = matches[(a, b)]
        return m.colors_a, m.colors_b
    m = matches[(b, a)]
    return m.colors_b, m.colors_a


def usable(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rows where neither colour is clipped (no channel at 0 or 255): clipping breaks every model."""
    lo, hi = 1.5 / 255, 253.5 / 255
    return (x > lo).all(1) & (x < hi).all(1) & (y > lo).all(1) & (y < hi).all(1)


@dataclass
class PixelMapping:
    """A mapping that also depends on where the pixel is (the neural D and its live form):
    ``apply(rgb, xy)`` with xy the pixel centre over the image size, in [0, 1]."""
    apply: Callable[[np.ndarray, np.ndarray], np.ndarray]
    size: tuple[int, int]          # (width, height) of the camera's image

    def __call__(self, rgb: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """sRGB (N, 3) at pixel coordinates (N, 2; x y, integers at pixel centres)."""
        return self.apply(rgb, pixel_centres(pixels[:, 0], pixels[:, 1], *self.size))

    def followed_by(self, model: ColorModel) -> PixelMapping:
        """This mapping, then ``model`` (sRGB in, sRGB out)."""
        return PixelMapping(lambda rgb, xy: model.apply(np.asarray(self.apply(rgb, xy))), self.size)


def apply_mapping(mapping: Mapping | PixelMapping, rgb: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    return mapping(rgb, pixels) if isinstance(mapping, PixelMapping) else mapping(rgb)


def identity(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, np.float64)


# --- the correspondence graph ----------------------------------------------------------------
def propagation_tree(matches: dict[tuple[str, str], Matches], cameras: list[str]) -> tuple[str, dict[str, str | None]]:
    """(reference, parent of each camera) as in paper 001: edges weighted by correspondence
    count (a strong edge is short), reference = the camera of largest closeness centrality,
    parents along the shortest paths from it. Cameras with no path keep parent None."""
    idx = {c: i for i, c in enumerate(cameras)}
    n = len(cameras)
    W = np.zeros((n, n))
    most = max((len(m) for m in matches.values()), default=1)
    for (a, b), m in matches.items():
        W[idx[a], idx[b]] = W[idx[b], idx[a]] = most / max(len(m), 1)
    dist = shortest_path(W, directed=False)
    reach = np.isfinite(dist)
    closeness = np.array([(reach[i].sum() - 1) / dist[i][reach[i]].sum() if dist[i][reach[i]].sum() > 0 else 0.0
                          for i in range(n)])
    root = int(np.argmax(closeness))
    _, pred = shortest_path(W, directed=False, indices=root, return_predecessors=True)
    parents = {cameras[root]: None}
    for c in cameras:
        p = pred[idx[c]]
        if c != cameras[root]:
            parents[c] = cameras[p] if p >= 0 else None
    return cameras[root], parents


def propagate(matches: dict[tuple[str, str], Matches], cameras: list[str],
              fit: Callable[[np.ndarray, np.ndarray], Mapping]) -> dict[str, Mapping]:
    """A pairwise transfer ``fit(source, target) -> mapping`` applied along the propagation tree:
    each camera is fitted to its parent's corrected colours, nearest the reference first."""
    root, parents = propagation_tree(matches, cameras)
    mappings: dict[str, Mapping] = {root: identity}

    def depth(c):
        d = 0
        while parents.get(c):
            c, d = parents[c], d + 1
        return d
    for c in sorted(cameras, key=depth):
        p = parents.get(c)
        if c == root:
            continue
        if p is None:
            mappings[c] = identity
            continue
        src, dst = pair_colors(matches, c, p)
        ok = usable(src, dst)
        mappings[c] = fit(src[ok], mappings[p](dst[ok]))
    return mappings


# --- pairwise transfers -----------------------------------------------------------------------
_RGB_TO_LMS = np.array([[0.3811, 0.5783, 0.0402], [0.1967, 0.7244, 0.0782], [0.0241, 0.1288, 0.8444]])


_LMS_TO_LAB = np.diag([1 / np.sqrt(3), 1 / np.sqrt(6), 1 / np.sqrt(2)]) @ np.array([[1, 1, 1], [1, 1, -2], [1, -1, 0]])


def _to_lalphabeta(rgb: np.ndarray) -> np.ndarray:
    lms = np.maximum(srgb_to_linear(rgb) @ _RGB_TO_LMS.T, 1e-6)
    return np.log10(lms) @ _LMS_TO_LAB.T


def _from_lalphabeta(lab: np.ndarray) -> np.ndarray:
    lms = 10.0 ** (lab @ np.linalg.inv(_LMS_TO_LAB).T)
    linear = lms @ np.linalg.inv(_RGB_TO_LMS).T
    return color_science.models.eotf_inverse_sRGB(np.clip(linear, 0.0, 1.0))


def fit_reinhard(source: np.ndarray, target: np.ndarray) -> Mapping:
    """Reinhard et al. 2001: match mean and standard deviation per l-alpha-beta channel."""
    s, t = _to_lalphabeta(source), _to_lalphabeta(target)
    mu_s, mu_t = s.mean(0), t.mean(0)
    gain = t.std(0) / np.maximum(s.std(0), 1e-9)
    return lambda rgb: _from_lalphabeta((_to_lalphabeta(rgb) - mu_s) * gain + mu_t)


def fit_vandermonde(source: np.ndarray, target: np.ndarray, degree: int = 2) -> Mapping:
    """De Marchi et al.: a polynomial of the colour (Vandermonde matrix) by least squares."""
    ccm = color_science.characterisation.matrix_colour_correction_Vandermonde(source, target, degree)
    return lambda rgb: np.clip(color_science.characterisation.apply_matrix_colour_correction_Vandermonde(rgb, ccm, degree),
                               0.0, 1.0)


def fit_finlayson(source: np.ndarray, target: np.ndarray, degree: int = 2) -> Mapping:
    """Finlayson et al. 2015: root-polynomial regression, on linear RGB (exposure invariant there)."""
    ccm = color_science.characterisation.matrix_colour_correction_Finlayson2015(
        srgb_to_linear(source), srgb_to_linear(target), degree)

    def apply(rgb):
        linear = color_science.characterisation.apply_matrix_colour_correction_Finlayson2015(srgb_to_linear(rgb), ccm, degree)
        return color_science.models.eotf_inverse_sRGB(np.clip(linear, 0.0, 1.0))
    return apply


# --- global baselines -------------------------------------------------------------------------
def _gain_offset_mapping(gain: np.ndarray, offset: np.ndarray) -> Mapping:
    return lambda rgb: np.clip(np.asarray(rgb) * gain + offset, 0.0, 1.0)


def brown_lowe(matches: dict[tuple[str, str], Matches], cameras: list[str], sigma_n: float = 10.0,
               sigma_g: float = 0.1) -> dict[str, Mapping]:
    """Brown & Lowe 2007 gain compensation, per channel: minimise over gains g
    sum_ij N_ij ((g_i I_ij - g_j I_ji)^2 / sigma_n^2 + (1 - g_i)^2 / sigma_g^2), I_ij the mean
    of camera i (0-255) over its overlap with j; a linear least-squares system."""
    idx = {c: i for i, c in enumerate(cameras)}
    n = len(cameras)
    gains = np.ones((n, 3))
    for k in range(3):
        rows, rhs = [], []
        for (a, b), m in matches.items():
            w = np.sqrt(len(m))
            Ia, Ib = 255.0 * m.colors_a[:, k].mean(), 255.0 * m.colors_b[:, k].mean()
            r = np.zeros(n)
            r[idx[a]], r[idx[b]] = w * Ia / sigma_n, -w * Ib / sigma_n
            rows.append(r)
            rhs.append(0.0)
            for c in (a, b):
                r = np.zeros(n)
                r[idx[c]] = w / sigma_g
                rows.append(r)
                rhs.append(w / sigma_g)
        if rows:
            gains[:, k] = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    return {c: _gain_offset_mapping(gains[idx[c]], np.zeros(3)) for c in cameras}


def moulon(matches: dict[tuple[str, str], Matches], cameras: list[str], reference: str | None = None,
           quantiles: int = 20, gain_range: tuple[float, float] = (0.5, 2.0)) -> dict[str, Mapping]:
    """Moulon et al. 2013: per camera and channel a gain and offset; for every pair the two
    cameras' histograms of their common region are matched at ``quantiles`` levels, and the
    largest mismatch over all pairs and levels is minimised (L-infinity, a linear programme).
    The reference camera (default: the most central) keeps gain 1, offset 0."""
    reference = reference or propagation_tree(matches, cameras)[0]
    idx = {c: i for i, c in enumerate(cameras)}
    n = len(cameras)
    levels = np.linspace(0.05, 0.95, quantiles)
    gains, offsets = np.ones((n, 3)), np.zeros((n, 3))
    for k in range(3):
        # variables: gain_0..n-1, offset_0..n-1, gamma
        A = []
        for (a, b), m in matches.items():
            qa, qb = np.quantile(m.colors_a[:, k], levels), np.quantile(m.colors_b[:, k], levels)
            for x, y in zip(qa, qb):
                r = np.zeros(2 * n + 1)
                r[idx[a]], r[n + idx[a]], r[idx[b]], r[n + idx[b]] = x, 1.0, -y, -1.0
                A.append(np.r_[r[:-1], -1.0])     #  (g_a x + o_a) - (g_b y + o_b) <= gamma
                A.append(np.r_[-r[:-1], -1.0])    # -(...)                          <= gamma
        if not A:
            continue
        c = np.zeros(2 * n + 1)
        c[-1] = 1.0
        bounds = [gain_range] * n + [(-0.5, 0.5)] * n + [(0, None)]
        r = idx[reference]
        bounds[r], bounds[n + r] = (1.0, 1.0), (0.0, 0.0)
        res = linprog(c, A_ub=np.array(A), b_ub=np.zeros(len(A)), bounds=bounds, method='highs')
        if res.success:
            gains[:, k], offsets[:, k] = res.x[:n], res.x[n:2 * n]
    return {c: _gain_offset_mapping(gains[idx[c]], offsets[idx[c]]) for c in cameras}
