"""Per-camera colour correction from the board's 24-patch chart (paper 000 Eqs. 6-10 and better).

Measured and reference patch colours are sRGB in [0, 1]. Each model (``volcap_core.color``) is
fitted by linear least squares and then refined in CIELAB, the space the error is judged in.
The default model is the one with the smallest leave-one-patch-out CIEDE2000.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from volcap_core.color import (
    METHODS,
    ColorModel,
    delta_e2000,
    linear_to_lab,
    linear_to_srgb,
    model_features,
    srgb_to_lab,
    srgb_to_linear,
)
from volcap_core.errors import BadInput

# scipy's relative step for '2-point' differences: the square root of the float64 epsilon
FORWARD_STEP = float(np.sqrt(np.finfo(np.float64).eps))


def _linear_fit(method: str, measured: np.ndarray, reference: np.ndarray) -> ColorModel:
    """The closed-form fit: paper Eqs. 9-10, or least squares in linear RGB."""
    if method == 'paper_diagonal':
        # Eqs. 9-10: k = mean(reference) / mean(observed), per channel.
        return ColorModel(method, np.diag(reference.mean(0) / np.maximum(measured.mean(0), 1e-6)))
    linear, target = srgb_to_linear(measured), srgb_to_linear(reference)
    X = model_features(method, linear)
    if len(X) < X.shape[1]:
        raise BadInput(f'{method} needs at least {X.shape[1]} patches, got {len(X)}')
    if method == 'gamma_3x3':
        # Variable projection: the matrix is linear given the exponents, so only 3 are searched.
        def residual(g):
            F = model_features(method, linear, g)
            return (F @ np.linalg.lstsq(F, target, rcond=None)[0] - target).ravel()
        g = least_squares(residual, np.ones(3), bounds=(0.5, 2.0)).x
        M, *_ = np.linalg.lstsq(model_features(method, linear, g), target, rcond=None)
        return ColorModel(method, M.T, tuple(float(v) for v in g))
    M, *_ = np.linalg.lstsq(X, target, rcond=None)
    return ColorModel(method, M.T)


def _refine_in_lab(model: ColorModel, measured: np.ndarray, reference: np.ndarray) -> ColorModel:
    """Least squares in CIELAB from ``model``: linear-RGB least squares lets the bright patches
    dominate, while CIEDE2000 weighs a dark patch's error as much as a bright one's; the Lab
    distance is the smooth stand-in for it (this halves the patch CIEDE2000 of some cameras)."""
    target, linear = srgb_to_lab(reference), srgb_to_linear(measured)
    size, shape = model.matrix.size, model.matrix.shape
    gamma = model.exponents is not None

    def unpack(x):
        return ColorModel(model.method, x[:size].reshape(shape), tuple(float(v) for v in x[size:]) if gamma else None)

    # Only the gamma model's features depend on the parameters: the others' are computed once.
    features = None if gamma else model_features(model.method, linear)

    def corrected(x):
        return unpack(x).apply_linear(linear) if gamma else features @ x[:size].reshape(shape).T

    def residual(x):
        return (linear_to_lab(corrected(x)) - target).ravel()

    def jacobian(x):
        # Forward differences with scipy's '2-point' steps, every perturbed model's colours
        # converted to Lab in one call: colour-science's conversion costs ~7 ms a call whatever
        # its size, and a Jacobian of the cubic root-polynomial took 40 of them (34 of the 39 s
        # its leave-one-patch-out score took; docs/calib.md).
        step = FORWARD_STEP * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
        step = np.where(x + step > upper, -step, step)
        perturbed = x + np.diag(step)
        labs = linear_to_lab(np.stack([corrected(x)] + [corrected(xp) for xp in perturbed]))
        return ((labs[1:] - labs[0]).reshape(len(x), -1) / step[:, None]).T

    x0 = np.concatenate([model.matrix.ravel(), model.exponents if gamma else ()])
    lower = np.concatenate([np.full(size, -np.inf), np.full(3 if gamma else 0, 0.5)])
    upper = np.concatenate([np.full(size, np.inf), np.full(3 if gamma else 0, 2.0)])
    if len(x0) >= residual(x0).size:
        return model   # too few patches to refine this many parameters
    return unpack(least_squares(residual, x0, jac=jacobian, bounds=(lower, upper), x_scale='jac').x)


def fit_model(method: str, measured: np.ndarray, reference: np.ndarray, perceptual: bool = True,
              start: ColorModel | None = None) -> ColorModel:
    """Fit one model; measured and reference are (N, 3) sRGB in [0, 1]. The paper's diagonal is
    fitted as published; the others by least squares in linear RGB, then (``perceptual``) in
    CIELAB, from ``start`` when given (a fit on nearly the same data converges in a few steps)."""
    measured, reference = np.asarray(measured, np.float64), np.asarray(reference, np.float64)
    if measured.shape != reference.shape or measured.ndim != 2 or measured.shape[1] != 3:
        raise BadInput(f'expected matching (N, 3) colours, got {measured.shape} and {reference.shape}')
    if not np.isfinite(measured).all():
        raise BadInput('measured patch colours contain NaN or inf')
    if method == 'paper_diagonal' or not perceptual:
        return _linear_fit(method, measured, reference)
    return _refine_in_lab(start or _linear_fit(method, measured, reference), measured, reference)


def leave_one_patch_out(method: str, measured: np.ndarray, reference: np.ndarray, patch: np.ndarray) -> float:
    """Mean CIEDE2000 of each patch predicted by a model fitted without that patch (every view
    of it held out together); ``patch`` gives each row's patch number."""
    errors = []
    full = fit_model(method, measured, reference)
    for p in np.unique(patch):
        held = patch == p
        model = fit_model(method, measured[~held], reference[~held], start=full)
        errors.append(delta_e2000(model.apply(measured[held]), reference[held]))
    return float(np.mean(np.concatenate(errors)))


def component_differences(measured: np.ndarray, reference: np.ndarray) -> dict:
    """Paper 000 Table 1: mean reference-minus-camera difference of R, G, B and I = (R+G+B)/3 in
    8-bit levels (signed, as published) and the mean absolute difference."""
    d = (np.asarray(reference) - np.asarray(measured)) * 255.0
    d = np.concatenate([d, d.mean(axis=1, keepdims=True)], axis=1)
    keys = ('R', 'G', 'B', 'I')
    return {'signed': dict(zip(keys, map(float, d.mean(0)))), 'abs': dict(zip(keys, map(float, np.abs(d).mean(0))))}


@dataclass
class ColorFit:
    model: ColorModel
    loo_de2000: dict[str, float]     # every candidate's leave-one-patch-out error
    before: dict
    after: dict
    de2000_before: float
    de2000_after: float
    samples: int

    def to_dict(self) -> dict:
        return {**self.model.to_dict(), 'loo_de2000': self.loo_de2000, 'before': self.before, 'after': self.after,
                'patch_de2000_before': self.de2000_before, 'patch_de2000_after': self.de2000_after,
                'samples': self.samples}


def view_illumination(samples: dict[str, list[tuple[int, np.ndarray]]], reference: np.ndarray,
                      patch_xy: np.ndarray, iterations: int = 20) -> dict[int, np.ndarray]:
    """Per-view illumination of the chart, shared by every camera that saw the view.

    The chart is matte, so in one view every camera sees the same radiance: reference albedo
    times the illumination at the board's pose, which changes from view to view (and across the
    chart, lights being near) as the board turns between differently coloured lights. Per view
    and channel it is modelled as a plane over the chart, e0 + ex x + ey y (``patch_xy``: patch
    centres in metres relative to the chart centre). Alternating least squares over per-camera
    3x3 models and these illuminants separates the two; the mean e0 over the views is fixed at
    (1, 1, 1), the level the corrected images are brought to. ``samples`` maps each camera to
    (view, (24, 3) sRGB patch colours with NaN rows for unsampled patches). Returns per view a
    (3, 3) array: rows R, G, B; columns e0, ex, ey."""
    ref = srgb_to_linear(np.asarray(reference, np.float64))
    basis = np.hstack([np.ones((len(patch_xy), 1)), patch_xy])          # (24, 3)
    views = sorted({v for items in samples.values() for v, _ in items})
    E = {v: np.array([[1.0, 0.0, 0.0]] * 3) for v in views}
    rows = {c: [(v, np.isfinite(m).all(axis=1), srgb_to_linear(np.nan_to_num(m))) for v, m in items]
            for c, items in samples.items()}
    for _ in range(iterations):
        lhs = {v: [] for v in views}
        for c, items in rows.items():
            X = np.vstack([m[ok] for _, ok, m in items])
            Y = np.vstack([illumination_at(E[v], basis[ok]) * ref[ok] for v, ok, _ in items])
            M, *_ = np.linalg.lstsq(X, Y, rcond=None)
            for v, ok, m in items:
                lhs[v].append((ok, m[ok] @ M))
        for v in views:
            E_v = np.empty((3, 3))
            A = np.vstack([basis[ok] for ok, _ in lhs[v]])
            R = np.vstack([ref[ok] for ok, _ in lhs[v]])
            P = np.vstack([pred for _, pred in lhs[v]])
            for k in range(3):
                E_v[k] = np.linalg.lstsq(A * R[:, k:k + 1], P[:, k], rcond=None)[0]
            E[v] = E_v
        mean = np.mean([E[v][:, 0] for v in views], axis=0)
        E = {v: E[v] / mean[:, None] for v in views}
    return E


def illumination_at(E_v: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(N, 3) RGB illumination at patches with basis rows (1, x, y)."""
    return basis @ E_v.T


def illuminated_reference(reference: np.ndarray, E_v: np.ndarray, patch_xy: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] of reference patches (N, 3) at ``patch_xy`` (N, 2) under one view's illumination."""
    basis = np.hstack([np.ones((len(patch_xy), 1)), patch_xy])
    return linear_to_srgb(srgb_to_linear(np.asarray(reference, np.float64)) * illumination_at(E_v, basis))


def fit_camera_color(measured: np.ndarray, reference: np.ndarray, patch: np.ndarray,
                     methods: tuple[str, ...] = METHODS, method: str | None = None) -> ColorFit:
    """Fit every candidate, score each by leave-one-patch-out CIEDE2000, keep ``method`` or the best."""
    usable = [m for m in methods if m == 'paper_diagonal' or len(np.unique(patch)) > model_features(m, np.zeros((1, 3))).shape[1]]
    loo = {m: leave_one_patch_out(m, measured, reference, patch) for m in usable}
    chosen = method or min(loo, key=loo.get)
    model = fit_model(chosen, measured, reference)
    corrected = model.apply(measured)
    return ColorFit(model, loo, component_differences(measured, reference), component_differences(corrected, reference),
                    float(delta_e2000(measured, reference).mean()), float(delta_e2000(corrected, reference).mean()),
                    len(measured))
