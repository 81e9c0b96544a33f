"""Our chart-free colour harmonisation (ours, beside paper 001's baselines in ``baselines``): one
global weighted least-squares problem over every camera's model (gains, gains + offsets, 3x3 or
3x4 on linear RGB, where exposure, white balance and crosstalk are linear), with the mean model or
one camera fixed as the reference, iteratively reweighted against view-dependent highlights and
mismatches. Which family a rig gets is ``model_choice``'s."""
from __future__ import annotations

import numpy as np

from volcap_core.color import ColorModel, srgb_to_linear
from volcap_core.errors import BadInput

from .baselines import usable
from .config import CHART_FREE_MODELS, SELECTABLE_MODELS  # noqa: F401 (re-exported)
from .correspondence import Matches


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
        ok = np.nonzero(usable(m.colors_a, m.colors_b))[0]
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


