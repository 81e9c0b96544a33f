"""Colour models as the calibration file stores them, and the sRGB / CIELAB conversions every
stage shares.

A model maps a camera's sRGB colours onto the reference: the paper's diagonal matrix works on
the encoded values as published (paper 000 Eqs. 6-10); the others work on linear RGB (sRGB
decoding), where a camera's gain, white balance and crosstalk are linear: a 3x3 matrix, an
affine 3x4, Finlayson's root-polynomial (colour-science) and a per-channel gamma before a 3x3.
Fitting them is volcap_calib's job; applying them is everyone's.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from .color_models import METHODS
from .errors import BadInput

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])     # Y of linear sRGB (ITU-R BT.709)
ROOT_DEGREE = {'root_polynomial_2': 2, 'root_polynomial_3': 3}


@cache
def _colour():
    """colour-science, imported on first use: it loads matplotlib (1.4 s of every node's start on
    2 cores), and a node that applies a compiled model never needs it."""
    import colour
    return colour


@cache
def _d65_and_srgb_to_xyz() -> tuple[np.ndarray, np.ndarray]:
    c = _colour()
    return c.CCS_ILLUMINANTS['CIE 1931 2 Degree Standard Observer']['D65'], c.RGB_COLOURSPACES['sRGB'].matrix_RGB_to_XYZ


# The sRGB transfer functions are called directly, not through colour.cctf_*: same result, a
# quarter of the cost inside the Lab refinement's least-squares loop.
def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    return _colour().models.eotf_sRGB(np.clip(rgb, 0.0, 1.0))


def linear_to_srgb(rgb: np.ndarray) -> np.ndarray:
    return _colour().models.eotf_inverse_sRGB(np.clip(rgb, 0.0, 1.0))


@cache
def _d65_white_xyz() -> np.ndarray:
    d65, _ = _d65_and_srgb_to_xyz()
    return _colour().xyY_to_XYZ(np.array([d65[0], d65[1], 1.0]))


# CIE 1976 lightness: the cube root above (6/29)^3, the linear segment below it
_LAB_EPSILON, _LAB_KAPPA = 216.0 / 24389.0, 24389.0 / 27.0


def linear_to_lab(linear: np.ndarray) -> np.ndarray:
    """CIELAB (D65) of linear sRGB values (clipped to [0, 1], as the encoded image would be).

    colour-science's matrix and white point, the CIE formula in plain numpy: ``colour.XYZ_to_Lab``
    costs ~7 ms a call whatever its size (its domain-range machinery), which made it most of the
    chart fit's time (thousands of small calls); equal to it within 1e-10 (test_calib.py)."""
    _, srgb_to_xyz = _d65_and_srgb_to_xyz()
    xyz = np.clip(np.asarray(linear, np.float64), 0.0, 1.0) @ (srgb_to_xyz.T / _d65_white_xyz())
    f = np.where(xyz > _LAB_EPSILON, np.cbrt(xyz), (_LAB_KAPPA * xyz + 16.0) / 116.0)
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    return np.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)], axis=-1)


def srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """CIELAB (D65) of sRGB values in [0, 1]."""
    return linear_to_lab(srgb_to_linear(rgb))


def delta_e2000(rgb_a: np.ndarray, rgb_b: np.ndarray) -> np.ndarray:
    return _colour().delta_E(srgb_to_lab(rgb_a), srgb_to_lab(rgb_b), method='CIE 2000')


def model_features(method: str, linear: np.ndarray, exponents=None) -> np.ndarray:
    if method == 'gamma_3x3':
        return np.clip(linear, 0.0, None) ** np.asarray(exponents if exponents is not None else (1.0, 1.0, 1.0))
    if method == 'matrix_3x3':
        return linear
    if method == 'affine_3x4':
        return np.concatenate([linear, np.ones(linear.shape[:-1] + (1,))], axis=-1)
    if method in ROOT_DEGREE:
        return _colour().characterisation.polynomial_expansion_Finlayson2015(linear, ROOT_DEGREE[method])
    raise BadInput(f'unknown colour model {method!r}; choose from {METHODS}')


@dataclass
class ColorModel:
    """corrected = features(camera colour) @ matrix.T (linear RGB), or the paper's diagonal on sRGB.

    ``gamma_3x3`` raises each linearised channel to its own exponent first: a camera whose tone
    curve is not quite sRGB (gamma 2.0-2.4) is then linear again before the matrix. ``post``, a
    3x4 affine map applied to the corrected linear RGB, is the harmonisation a chart-free fit
    adds on top of a chart model (volcap_color)."""
    method: str
    matrix: np.ndarray   # (3, K)
    exponents: tuple[float, float, float] | None = None   # gamma_3x3 only
    post: np.ndarray | None = None                         # (3, 4), not for the paper's diagonal

    def __post_init__(self):
        if self.method not in METHODS:
            raise BadInput(f'unknown colour model {self.method!r}; choose from {METHODS}')
        self.matrix = np.asarray(self.matrix, dtype=np.float64)
        if self.exponents is not None and (len(self.exponents) != 3 or not all(
                np.isfinite(e) and e > 0 for e in self.exponents)):
            raise BadInput(f'exponents must be 3 positive numbers, got {self.exponents}')
        features = 3 if self.method == 'paper_diagonal' else \
            model_features(self.method, np.full((1, 3), 0.5), self.exponents).shape[1]
        if self.matrix.shape != (3, features) or not np.all(np.isfinite(self.matrix)):
            raise BadInput(f'a {self.method} model needs a finite 3x{features} matrix, got {self.matrix.shape}')
        if self.post is not None:
            self.post = np.asarray(self.post, dtype=np.float64)
            if self.post.shape != (3, 4) or self.method == 'paper_diagonal' or not np.all(np.isfinite(self.post)):
                raise BadInput('post must be a finite 3x4 affine map on a linear-RGB model')

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        """sRGB (..., 3) in [0, 1] -> corrected sRGB in [0, 1]."""
        rgb = np.asarray(rgb, dtype=np.float64)
        if self.method == 'paper_diagonal':
            return np.clip(rgb @ self.matrix.T, 0.0, 1.0)
        return linear_to_srgb(self.apply_linear(srgb_to_linear(rgb)))

    def apply_linear(self, linear: np.ndarray) -> np.ndarray:
        """Linear camera RGB -> corrected linear RGB (unclipped); not for the paper's diagonal."""
        out = model_features(self.method, linear, self.exponents) @ self.matrix.T
        return out if self.post is None else out @ self.post[:, :3].T + self.post[:, 3]

    def apply_image(self, image: np.ndarray) -> np.ndarray:
        """uint8 RGB image -> corrected uint8 RGB image (a 256^3 table would be the live form)."""
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise BadInput(f'expected an (H, W, 3) uint8 image, got {image.dtype} {image.shape}')
        if self.method == 'paper_diagonal':
            return cv2.transform(image, self.matrix.astype(np.float32))
        out = self.apply(image.reshape(-1, 3) / 255.0)
        return np.round(out * 255.0).astype(np.uint8).reshape(image.shape)

    def to_dict(self) -> dict:
        d = {'method': self.method, 'matrix': [[float(v) for v in row] for row in self.matrix]}
        if self.exponents is not None:
            d['exponents'] = [float(v) for v in self.exponents]
        if self.post is not None:
            d['post'] = [[float(v) for v in row] for row in self.post]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> 'ColorModel':
        if not isinstance(d, dict) or 'method' not in d or 'matrix' not in d:
            raise BadInput(f'a colour model is a mapping with method and matrix, got {d!r:.80}')
        exponents, post = d.get('exponents'), d.get('post')
        return cls(d['method'], np.asarray(d['matrix'], dtype=np.float64),
                   tuple(float(v) for v in exponents) if exponents is not None else None,
                   np.asarray(post, dtype=np.float64) if post is not None else None)
