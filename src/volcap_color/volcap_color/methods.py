"""Multi-camera colour harmonisation from correspondences: our chart-free fit and the baselines
paper 001 compares against, each as a per-camera mapping sRGB (N, 3) in [0, 1] -> sRGB.

- ``chart_free_fit``: ours. One global weighted least-squares problem over every camera's model
  (gains, gains + offsets, 3x3 or 3x4 on linear RGB, where exposure, white balance and crosstalk
  are linear), with the mean model or one camera fixed as the reference and iteratively
  reweighted against view-dependent highlights and mismatches.
- Pairwise transfers (Reinhard et al. mean/std in l-alpha-beta; De Marchi et al.'s Vandermonde
  polynomial; Finlayson et al.'s root-polynomial, both from colour-science) propagated as paper
  001 does: a graph of the cameras with edges weighted by their number of correspondences, the
  most central camera as reference, every other camera fitted to its predecessor on the
  shortest path (already corrected).
- Global baselines: Brown & Lowe's gain compensation (their linear system, per channel, as in
  OpenCV's stitching module) and Moulon et al.'s per-channel gain/offset from histogram
  quantiles under an L-infinity objective (a linear programme).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import colour as color_science
import numpy as np
from scipy.optimize import linprog
from scipy.sparse.csgraph import shortest_path

from volcap_core.color import ColorModel, srgb_to_lab, srgb_to_linear
from volcap_core.errors import BadInput

from .apply import pixel_centres
from .config import CHART_FREE_MODELS, SELECTABLE_MODELS  # noqa: F401 (re-exported)
from .correspondence import Matches

Mapping = Callable[[np.ndarray], np.ndarray]
DARK_L = 25.0          # CIELAB L* below which a correspondence counts as dark
SATURATED_CHROMA = 25.0     # CIELAB C*ab (as recorded) above which a colour counts as saturated
CONTRAST_KEPT = 0.98   # share of the simplest model's lightness spread a richer chosen model must keep


@dataclass
class PixelMapping:
    """A mapping that also depends on where the pixel is (the neural D and its live form):
    ``apply(rgb, xy)`` with xy the pixel centre over the image size, in [0, 1]."""
    apply: Callable[[np.ndarray, np.ndarray], np.ndarray]
    size: tuple[int, int]          # (width, height) of the camera's image

    def __call__(self, rgb: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """sRGB (N, 3) at pixel coordinates (N, 2; x y, integers at pixel centres)."""
        return self.apply(rgb, pixel_centres(pixels[:, 0], pixels[:, 1], *self.size))


def apply_mapping(mapping: Mapping | PixelMapping, rgb: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    return mapping(rgb, pixels) if isinstance(mapping, PixelMapping) else mapping(rgb)


def identity(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, np.float64)


def _pair_colors(matches: dict[tuple[str, str], Matches], a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
    """Colours of a and b at their common surface points, whichever order the pair was matched in."""
    if (a, b) in matches:
        m = matches[(a, b)]
        return m.colors_a, m.colors_b
    m = matches[(b, a)]
    return m.colors_b, m.colors_a


def _usable(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rows where neither colour is clipped (no channel at 0 or 255): clipping breaks every model."""
    lo, hi = 1.5 / 255, 253.5 / 255
    return (x > lo).all(1) & (x < hi).all(1) & (y > lo).all(1) & (y < hi).all(1)


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
        src, dst = _pair_colors(matches, c, p)
        ok = _usable(src, dst)
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


# --- ours: global chart-free fit --------------------------------------------------------------
def _features(model: str, linear: np.ndarray, channel: int) -> np.ndarray:
    """The inputs that output ``channel`` of ``model`` depends on."""
    ones = np.ones((len(linear), 1))
    if model == 'gain':
        return linear[:, channel:channel + 1]
    if model == 'gain_offset':
        return np.hstack([linear[:, channel:channel + 1], ones])
    if model == 'matrix_3x3':
        return linear
    if model == 'affine_3x4':
        return np.hstack([linear, ones])
    raise BadInput(f'unknown chart-free model {model!r}; choose from {CHART_FREE_MODELS}')


def _identity_row(model: str, channel: int) -> np.ndarray:
    if model == 'gain':
        return np.array([1.0])
    if model == 'gain_offset':
        return np.array([1.0, 0.0])
    row = np.zeros(3 if model == 'matrix_3x3' else 4)
    row[channel] = 1.0
    return row


def identity_models(cameras: list[str], base: dict[str, ColorModel] | None = None) -> dict[str, ColorModel]:
    """Every camera left as it is (as its ``base`` model leaves it)."""
    base = base or {}
    return {c: _to_color_model('gain', [_identity_row('gain', k) for k in range(3)], base.get(c)) for c in cameras}


def _to_color_model(model: str, rows: list[np.ndarray], base: ColorModel | None = None) -> ColorModel:
    if model in ('matrix_3x3', 'affine_3x4'):
        M = np.array(rows) if model == 'affine_3x4' else np.hstack([np.array(rows), np.zeros((3, 1))])
    else:
        M = np.zeros((3, 4))
        for k, r in enumerate(rows):
            M[k, k] = r[0]
            if model == 'gain_offset':
                M[k, 3] = r[1]
    if base is not None:
        return ColorModel(base.method, base.matrix, base.exponents, M)
    return ColorModel('matrix_3x3', M[:, :3]) if model == 'matrix_3x3' else ColorModel('affine_3x4', M)


def chart_free_fit(matches: dict[tuple[str, str], Matches], cameras: list[str], model: str = 'affine_3x4',
                   reference: str = 'mean', base: dict[str, ColorModel] | None = None,
                   anchor: dict[str, tuple[np.ndarray, np.ndarray]] | None = None, anchor_weight: float = 0.05,
                   iterations: int = 6, max_per_pair: int = 200_000, ridge: float = 1e-4,
                   seed: int = 0) -> dict[str, ColorModel]:
    """Per-camera linear-RGB models making corresponding pixels agree (see the module docstring).

    Per output channel the unknowns of all cameras are solved at once from the normal equations
    of sum over pairs and matches of w (a_i . f(x_i) - a_j . f(x_j))^2. ``reference`` fixes the
    gauge: 'mean' (the cameras' mean model is the identity, so no camera is favoured), a camera
    name (that camera is left as it is) or 'chart': each camera's ``anchor`` chart samples
    (measured, reference sRGB) must also map onto the chart reference, with ``anchor_weight``
    times that camera's correspondence weight, so the harmonised rig keeps the chart's absolute
    colour. With ``base`` models the fit is on their corrected colours and is returned as their
    ``post`` map. Weights come from a Cauchy loss on the previous iteration's residuals; a small
    ridge towards the identity keeps a camera with few matches near where it started. Cameras
    without any correspondence get the identity."""
    if model not in CHART_FREE_MODELS:
        raise BadInput(f'unknown chart-free model {model!r}; choose from {CHART_FREE_MODELS}')
    if reference not in ('mean', 'chart') and reference not in cameras:
        raise BadInput(f'reference must be "mean", "chart" or one of {cameras}, got {reference!r}')
    if reference == 'chart' and not (anchor and all(len(anchor.get(c, ((),))[0]) for c in cameras)):
        raise BadInput('reference "chart" needs chart samples of every camera')
    base = base or {}

    def linear(c, rgb):
        lin = srgb_to_linear(rgb)
        return base[c].apply_linear(lin) if c in base else lin
    rng = np.random.default_rng(seed)
    idx = {c: i for i, c in enumerate(cameras)}
    pairs = []
    for (a, b), m in matches.items():
        ok = np.nonzero(_usable(m.colors_a, m.colors_b))[0]
        if len(ok) > max_per_pair:
            ok = rng.choice(ok, max_per_pair, replace=False)
        if len(ok):
            pairs.append((idx[a], idx[b], linear(a, m.colors_a[ok]), linear(b, m.colors_b[ok])))
    n = len(cameras)
    connected = {i for a, b, *_ in pairs for i in (a, b)}
    rows = [[_identity_row(model, k) for k in range(3)] for _ in range(n)]
    if not pairs:
        return {c: _to_color_model(model, rows[idx[c]], base.get(c)) for c in cameras}
    charts = {idx[c]: (linear(c, anchor[c][0]), srgb_to_linear(anchor[c][1])) for c in cameras} \
        if reference == 'chart' else {}
    p = len(_identity_row(model, 0))
    # per pair and output channel, both cameras' features, built once (one array for all three
    # channels where the model's inputs do not depend on the channel)
    shared = model in ('matrix_3x3', 'affine_3x4')
    features = [[(_features(model, xa, k), _features(model, xb, k)) for k in range(1 if shared else 3)]
                for _, _, xa, xb in pairs]
    features = [f * 3 if shared else f for f in features]
    weights = [np.ones(len(xa)) for _, _, xa, _ in pairs]
    for _ in range(iterations):
        for k in range(3):
            N = np.zeros((n * p, n * p))
            rhs = np.zeros(n * p)
            load = np.zeros(n)      # each camera's total correspondence weight
            for (a, b, _, _), w, per_channel in zip(pairs, weights, features):
                Fa, Fb = per_channel[k]
                sa, sb = slice(a * p, (a + 1) * p), slice(b * p, (b + 1) * p)
                Faa, Fbb, Fab = (Fa * w[:, None]).T @ Fa, (Fb * w[:, None]).T @ Fb, (Fa * w[:, None]).T @ Fb
                N[sa, sa] += Faa
                N[sb, sb] += Fbb
                N[sa, sb] -= Fab
                N[sb, sa] -= Fab.T
                load[a] += np.trace(Faa)
                load[b] += np.trace(Fbb)
            scale = load.sum()
            e = _identity_row(model, k)
            lam = ridge * scale / (n * p)
            for i in range(n):
                s = slice(i * p, (i + 1) * p)
                N[s, s] += lam * np.eye(p)
                rhs[s] += lam * e
                if i in charts:
                    F = _features(model, charts[i][0], k)
                    wc = anchor_weight * max(load[i], scale / n) / max(np.trace(F.T @ F), 1e-12)
                    N[s, s] += wc * F.T @ F
                    rhs[s] += wc * F.T @ charts[i][1][:, k]
            big = 1e3 * scale / (n * p)
            if reference == 'mean':
                S = np.tile(np.eye(p), (1, n))          # sum of all cameras' rows = n * identity row
                N += big * S.T @ S
                rhs += big * S.T @ (n * e)
            elif reference != 'chart':
                s = slice(idx[reference] * p, (idx[reference] + 1) * p)
                N[s, s] += big * np.eye(p)
                rhs[s] += big * e
            sol = np.linalg.solve(N, rhs).reshape(n, p)
            for i in range(n):
                rows[i][k] = sol[i] if i in connected or i in charts else _identity_row(model, k)
        residuals = []
        for (a, b, _, _), per_channel in zip(pairs, features):
            ya = np.stack([per_channel[k][0] @ rows[a][k] for k in range(3)], 1)
            yb = np.stack([per_channel[k][1] @ rows[b][k] for k in range(3)], 1)
            residuals.append(np.linalg.norm(ya - yb, axis=1))
        sigma = 1.4826 * np.median(np.concatenate(residuals)) + 1e-6
        weights = [1.0 / (1.0 + (r / (2.0 * sigma)) ** 2) for r in residuals]
    return {c: _to_color_model(model, rows[idx[c]], base.get(c)) for c in cameras}


# --- choosing the chart-free model --------------------------------------------------------------
@dataclass
class ModelChoice:
    model: str                   # a CHART_FREE_MODELS name, or 'identity' when none helps
    scores: dict[str, dict] = field(default_factory=dict)   # candidate -> {'de2000', 'de2000_dark'}
    why: str = ''

    def to_dict(self) -> dict:
        return {'model': self.model, 'scores': self.scores, 'why': self.why}


def split_matches(matches: dict[tuple[str, str], Matches], share: float = 0.5, seed: int = 0
                  ) -> tuple[dict[tuple[str, str], Matches], dict[tuple[str, str], Matches]]:
    """Each pair's correspondences split at random into two disjoint sets (``share`` in the first)."""
    rng = np.random.default_rng(seed)
    first, second = {}, {}
    for key, m in matches.items():
        pick = rng.random(len(m)) < share
        for out, keep in ((first, pick), (second, ~pick)):
            out[key] = Matches(m.a, m.b, m.pixels_a[keep], m.pixels_b[keep], m.colors_a[keep], m.colors_b[keep],
                               m.fraction * float(keep.mean()) if len(m) else 0.0)
    return first, second


def chroma(lab: np.ndarray) -> np.ndarray:
    """CIELAB C*ab of (N, 3) L*a*b* rows."""
    return np.hypot(lab[:, 1], lab[:, 2])


def held_out_scores(matches: dict[tuple[str, str], Matches], models: dict[str, ColorModel] | None) -> dict:
    """How well ``models`` (None: the colours as recorded) make corresponding colours agree, and
    what that does to them, over every pair: mean CIEDE2000 over all correspondences and over
    the dark ones (L* < ``DARK_L``), mean chroma of the saturated colours (C*ab >=
    ``SATURATED_CHROMA`` as recorded, so every model is measured on the same pixels) and the
    standard deviation of L*. Each side is mapped and converted once."""
    pairs = [m for m in matches.values() if len(m)]
    if not pairs:
        return {'de2000': float('nan'), 'de2000_dark': float('nan'), 'chroma': float('nan'),
                'lightness_std': float('nan')}

    def mapped(camera, colors):
        return np.clip(models[camera].apply(colors), 0, 1) if models else colors
    lab_a = srgb_to_lab(np.vstack([mapped(m.a, m.colors_a) for m in pairs]))
    lab_b = srgb_to_lab(np.vstack([mapped(m.b, m.colors_b) for m in pairs]))
    recorded_a = np.vstack([m.colors_a for m in pairs])
    recorded_b = np.vstack([m.colors_b for m in pairs])
    de = color_science.delta_E(lab_a, lab_b, method='CIE 2000')
    dark = srgb_to_lab(np.minimum(recorded_a, recorded_b))[:, 0] < DARK_L
    lab = np.vstack([lab_a, lab_b])
    saturated = chroma(srgb_to_lab(np.vstack([recorded_a, recorded_b]))) >= SATURATED_CHROMA
    return {'de2000': float(de.mean()), 'de2000_dark': float(de[dark].mean()) if dark.any() else float('nan'),
            'chroma': float(chroma(lab[saturated]).mean()) if saturated.any() else float('nan'),
            'lightness_std': float(lab[:, 0].std())}


def choose_chart_free_model(matches: dict[tuple[str, str], Matches], cameras: list[str], reference: str = 'mean',
                            base: dict[str, ColorModel] | None = None,
                            anchor: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                            candidates: tuple[str, ...] = SELECTABLE_MODELS, tolerance: float = 0.05,
                            seed: int = 0) -> ModelChoice:
    """The model family for this rig, chosen on correspondences held out from the fit (half of
    each pair's): among the candidates that keep the colours' contrast (the spread of CIELAB L*
    within ``CONTRAST_KEPT`` of the simplest candidate's), the simplest within ``tolerance``
    (relative) of the best held-out CIEDE2000 that does not make the dark correspondences worse
    than they were; the identity when no candidate improves on the untouched colours (a rig
    already consistent). ``base``, ``anchor``: as ``chart_free_fit`` (the untouched colours are
    then the base models')."""
    fit, check = split_matches(matches, seed=seed)
    scores = {'identity': held_out_scores(check, base)}
    before = scores['identity']
    for model in candidates:
        scores[model] = held_out_scores(check, chart_free_fit(fit, cameras, model, reference, base=base, anchor=anchor,
                                                               seed=seed))

    def flattens(s):
        # Corresponding colours also agree when lightness is pulled together (blacks lifted,
        # highlights pressed): with mis-registered correspondences a flexible model gains
        # held-out CIEDE2000 that way and loses the truth. The simplest candidate (per-channel
        # gains) cannot do that, so its spread is the yardstick.
        return s['lightness_std'] < CONTRAST_KEPT * scores[candidates[0]]['lightness_std']

    def darkens(s):
        return s['de2000_dark'] > before['de2000_dark']
    admissible = candidates[:1] + tuple(m for m in candidates[1:] if not flattens(scores[m]))
    best = min(scores[m]['de2000'] for m in admissible)
    if not best < before['de2000']:
        return ModelChoice('identity', scores, f'no model improves on the untouched colours ({before["de2000"]:.2f})')
    for model in admissible:
        s = scores[model]
        if s['de2000'] <= best * (1 + tolerance) and not darkens(s):
            flattening = [m for m in candidates if m not in admissible]
            return ModelChoice(model, scores, f'simplest within {tolerance:.0%} of the best held-out CIEDE2000 '
                                              f'({best:.2f}) that keeps dark pixels ({before["de2000_dark"]:.2f} -> '
                                              f'{s["de2000_dark"]:.2f})' +
                               (f'; left out for flattening lightness: {", ".join(flattening)}' if flattening else ''))
    model = min(admissible, key=lambda m: scores[m]['de2000'])
    return ModelChoice(model, scores, 'every candidate worsens dark pixels; the best held-out one')
