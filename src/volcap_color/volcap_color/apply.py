"""Colour models compiled for full-rate 8-bit images.

A model from ``volcap_core.color`` is evaluated per pixel in float64 by ``ColourModel.apply``:
exact, but about a second per 1280x720 frame. Live correction instead compiles it once:

- ``paper_diagonal`` works on the encoded values: one ``cv2.transform`` on the uint8 image;
- ``matrix_3x3``, ``affine_3x4`` and ``gamma_3x3`` (with or without a harmonising ``post``
  affine) are a per-channel curve (sRGB decoding, and for gamma_3x3 the channel's exponent),
  one 3x4 matrix, and sRGB encoding: a numba kernel over integer tables (each input channel's
  contribution to all three outputs, in 1/16383 steps of linear light, packed into one int64)
  and a table out (within one level of the exact model, tested);
- everything else (root-polynomial models, or any model given as a callable) is sampled into a
  33^3 3D LUT and interpolated trilinearly;
- a ``RegionLut`` (the live form of a neural mapping D(r, g, b, x, y), ``neural.bake_region_lut``)
  is a 3D LUT at each node of a coarse grid over the image: trilinear in colour, bilinear
  between the four nodes around the pixel.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Callable

import cv2
import numba
import numpy as np
from scipy.ndimage import map_coordinates

from volcap_core.color import ColorModel, linear_to_srgb, srgb_to_linear
from volcap_core.errors import BadInput
from volcap_core.files import atomic_write

ENCODE_STEPS = 16384     # linear [0, 1] -> uint8 table; finer than one sRGB level everywhere
LUT_SIZE = 33
FIELD_BITS = 21          # three output channels packed into one int64 table entry
WEIGHT_BITS = 12         # region LUT: integer interpolation weights sum to 2^12 (255 * 2^12 < 2^21)
CHUNKS = 4               # work items per call (two per core on the 2-core target)


@numba.njit(parallel=True, cache=True)
def _linear_kernel(flat, packed, encode, out):
    # packed[c, v] holds, for input channel c at level v, its integer contribution to all three
    # outputs, one 21-bit field each: three table loads and two adds give the pixel's three
    # output indices at once (twice as fast as nine separate loads).
    n = flat.shape[0] // 3
    step = (n + CHUNKS - 1) // CHUNKS
    mask = (1 << FIELD_BITS) - 1
    for chunk in numba.prange(CHUNKS):
        for p in range(chunk * step, min(n, (chunk + 1) * step)):
            s = packed[0, flat[3 * p]] + packed[1, flat[3 * p + 1]] + packed[2, flat[3 * p + 2]]
            out[3 * p] = encode[0, s & mask]
            out[3 * p + 1] = encode[1, (s >> FIELD_BITS) & mask]
            out[3 * p + 2] = encode[2, (s >> (2 * FIELD_BITS)) & mask]


@numba.njit(parallel=True, cache=True)
def _lut_kernel(image, lut, out):
    h, w = image.shape[0], image.shape[1]
    cells = lut.shape[0] - 1
    scale = np.float32(cells / 255.0)
    for y in numba.prange(h):
        for x in range(w):
            fr, fg, fb = image[y, x, 0] * scale, image[y, x, 1] * scale, image[y, x, 2] * scale
            r, g, b = min(int(fr), cells - 1), min(int(fg), cells - 1), min(int(fb), cells - 1)
            dr, dg, db = fr - r, fg - g, fb - b
            # the 8 corner weights once, then each output channel is one weighted sum
            a00, a01 = (1 - dg) * (1 - db), (1 - dg) * db
            a10, a11 = dg * (1 - db), dg * db
            w0, w1, w2, w3 = (1 - dr) * a00, (1 - dr) * a01, (1 - dr) * a10, (1 - dr) * a11
            w4, w5, w6, w7 = dr * a00, dr * a01, dr * a10, dr * a11
            c0, c1 = lut[r, g, b], lut[r, g, b + 1]
            c2, c3 = lut[r, g + 1, b], lut[r, g + 1, b + 1]
            c4, c5 = lut[r + 1, g, b], lut[r + 1, g, b + 1]
            c6, c7 = lut[r + 1, g + 1, b], lut[r + 1, g + 1, b + 1]
            for k in range(3):
                v = (w0 * c0[k] + w1 * c1[k] + w2 * c2[k] + w3 * c3[k] + w4 * c4[k] + w5 * c5[k] + w6 * c6[k]
                     + w7 * c7[k])
                out[y, x, k] = min(max(int(v + np.float32(0.5)), 0), 255)


@numba.njit(parallel=True, cache=True)
def _region_lut_kernel(image, packed, col_node, col_weight, row_node, row_weight, out):
    # packed[r, g, b, node_y, node_x] holds the three output levels, one 21-bit field each, and
    # the 32 weights (8 colour corners x 4 image nodes) are integers summing to about
    # 2^WEIGHT_BITS: each corner is one load and one integer multiply-add for all three channels
    # (three times fewer loads than float tables, which made this kernel load-bound).
    h, w = image.shape[0], image.shape[1]
    cells = packed.shape[0] - 1
    scale = np.float32(cells / 255.0)
    one = np.float32(1.0)
    unit = np.float32(1 << WEIGHT_BITS)
    half = np.float32(0.5)
    mask = (1 << FIELD_BITS) - 1
    rounding = 1 << (WEIGHT_BITS - 1)
    for y in numba.prange(h):
        iy, wy = row_node[y], row_weight[y]
        for x in range(w):
            ix, wx = col_node[x], col_weight[x]
            s00, s01 = (one - wy) * (one - wx) * unit, (one - wy) * wx * unit
            s10, s11 = wy * (one - wx) * unit, wy * wx * unit
            fr, fg, fb = image[y, x, 0] * scale, image[y, x, 1] * scale, image[y, x, 2] * scale
            r, g, b = min(int(fr), cells - 1), min(int(fg), cells - 1), min(int(fb), cells - 1)
            dr, dg, db = fr - r, fg - g, fb - b
            acc = 0
            for corner in range(8):
                cr, cg, cb = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
                wc = (dr if cr else one - dr) * (dg if cg else one - dg) * (db if cb else one - db)
                t = packed[r + cr, g + cg, b + cb]
                acc += (t[iy, ix] * int(wc * s00 + half) + t[iy, ix + 1] * int(wc * s01 + half)
                        + t[iy + 1, ix] * int(wc * s10 + half) + t[iy + 1, ix + 1] * int(wc * s11 + half))
            out[y, x, 0] = min(((acc & mask) + rounding) >> WEIGHT_BITS, 255)
            out[y, x, 1] = min((((acc >> FIELD_BITS) & mask) + rounding) >> WEIGHT_BITS, 255)
            out[y, x, 2] = min((((acc >> (2 * FIELD_BITS)) & mask) + rounding) >> WEIGHT_BITS, 255)


def pixel_centres(x: np.ndarray, y: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 2) float32 positions of pixels (x, y) as position-dependent mappings take them: the
    pixel centre over the image size, in [0, 1] whatever the resolution."""
    return np.stack([(np.asarray(x, np.float64) + 0.5) / width, (np.asarray(y, np.float64) + 0.5) / height],
                    axis=1).astype(np.float32)


@dataclass
class RegionLut:
    """A colour mapping that varies over the image: ``table[r, g, b, j, i]`` (0-255) is the
    mapped colour of (r, g, b) = (0..N-1) / (N-1) at image position x = i / (nx-1),
    y = j / (ny-1), positions being pixel centres over the image size."""
    table: np.ndarray            # (N, N, N, ny, nx, 3) float32

    def __post_init__(self):
        self.table = np.ascontiguousarray(self.table, np.float32)
        t = self.table
        if t.ndim != 6 or t.shape[0] != t.shape[1] or t.shape[1] != t.shape[2] or t.shape[5] != 3 \
                or min(t.shape[:5]) < 2:
            raise BadInput(f'a region LUT is (N, N, N, ny, nx, 3) with every size >= 2, got {t.shape}')
        if not np.isfinite(t).all():
            raise BadInput('the region LUT has non-finite entries')

    @property
    def grid(self) -> tuple[int, int]:
        return self.table.shape[4], self.table.shape[3]

    def nodes(self, size: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel along one image axis of ``size``: the node before it and the weight of the next."""
        u = (np.arange(size) + 0.5) / size * (count - 1)
        node = np.minimum(u.astype(np.int64), count - 2)
        return node, (u - node).astype(np.float32)

    def apply_points(self, rgb: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """The same interpolation in float64 for sRGB (N, 3) in [0, 1] at normalised pixel
        positions (N, 2): scoring samples instead of whole images."""
        n = self.table.shape[0] - 1
        nx, ny = self.grid
        coords = np.concatenate([np.clip(rgb, 0, 1).T * n, (np.clip(xy[:, 1], 0, 1) * (ny - 1))[None],
                                 (np.clip(xy[:, 0], 0, 1) * (nx - 1))[None]])
        return np.stack([map_coordinates(c, coords, order=1, mode='nearest') for c in self._channels],
                        axis=1) / 255.0

    @cached_property
    def _channels(self) -> list[np.ndarray]:
        # contiguous float64 planes, made once: scoring calls apply_points for every camera pair
        return [np.ascontiguousarray(self.table[..., k], np.float64) for k in range(3)]

    def save(self, path: str | Path, **metadata) -> Path:
        buf = io.BytesIO()
        np.savez_compressed(buf, table=self.table, **{k: np.asarray(v) for k, v in metadata.items()})
        return atomic_write(path, lambda f: f.write(buf.getvalue()))

    @classmethod
    def load(cls, path: str | Path) -> RegionLut:
        try:
            with np.load(path) as z:
                return cls(z['table'])
        except (OSError, KeyError, ValueError, EOFError) as e:
            raise BadInput(f'{path}: not a region LUT ({e})') from e


def _packed_tables(matrix: np.ndarray, decode: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer tables of ``output_k = sum_c matrix[k, c] decode[c, v_c] + matrix[k, 3]`` in steps of
    1 / (ENCODE_STEPS - 1) of linear light, packed for ``_linear_kernel``, and per output channel
    the uint8 sRGB encoding of each packed field value (offset and clipping folded in)."""
    top = ENCODE_STEPS - 1
    terms = np.round(matrix[:, :3, None] * decode[None, :, :] * top).astype(np.int64)    # (k, c, v)
    bias = -np.minimum(terms.min(axis=2), 0)                                              # keep fields >= 0
    fields = terms + bias[:, :, None]
    size = int(fields.max(axis=2).sum(axis=1).max()) + 1
    if size >= 1 << FIELD_BITS:
        raise BadInput(f'colour model gains too large for the packed tables ({size} steps)')
    packed = np.zeros((3, 256), np.int64)
    for k in range(3):
        packed += fields[k] << (FIELD_BITS * k)
    srgb = np.round(linear_to_srgb(np.linspace(0.0, 1.0, ENCODE_STEPS)) * 255.0).astype(np.uint8)
    encode = np.empty((3, size), np.uint8)
    for k in range(3):
        index = np.arange(size) - bias[k].sum() + int(round(matrix[k, 3] * top))
        encode[k] = srgb[np.clip(index, 0, top)]
    return packed, encode


def lut_from_function(correct: Callable[[np.ndarray], np.ndarray], size: int = LUT_SIZE) -> np.ndarray:
    """(size, size, size, 3) float32 table in 0-255 of ``correct`` (sRGB (N, 3) in [0, 1] ->
    sRGB in [0, 1]) on a regular grid indexed [r, g, b]."""
    axis = np.linspace(0.0, 1.0, size)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing='ij'), axis=-1).reshape(-1, 3)
    return (np.clip(correct(grid), 0.0, 1.0) * 255.0).astype(np.float32).reshape(size, size, size, 3)


class ImageCorrector:
    """Applies one colour model to uint8 RGB images at full rate (see the module docstring)."""

    def __init__(self, model: ColorModel | RegionLut | Callable[[np.ndarray], np.ndarray], lut_size: int = LUT_SIZE):
        self.model = model
        self.kind = 'lut'
        self._nodes: dict[tuple[int, int], tuple] = {}
        if isinstance(model, RegionLut):
            self.kind = 'region_lut'
            levels = np.clip(np.round(model.table), 0, 255).astype(np.int64)
            self._packed = np.ascontiguousarray(levels[..., 0] + (levels[..., 1] << FIELD_BITS)
                                                + (levels[..., 2] << (2 * FIELD_BITS)))
        elif isinstance(model, ColorModel) and model.method == 'paper_diagonal':
            self.kind = 'diagonal'
            self._matrix = model.matrix.astype(np.float32)
        elif isinstance(model, ColorModel) and model.method in ('matrix_3x3', 'affine_3x4', 'gamma_3x3'):
            self.kind = 'linear'
            levels = srgb_to_linear(np.arange(256) / 255.0)
            exponents = np.asarray(model.exponents if model.method == 'gamma_3x3' else (1.0, 1.0, 1.0))
            decode = levels[None, :] ** exponents[:, None]                     # (c, 256)
            matrix = np.zeros((3, 4))
            matrix[:, :model.matrix.shape[1]] = model.matrix
            if model.post is not None:       # affine after affine is one affine
                matrix = model.post[:, :3] @ matrix
                matrix[:, 3] += model.post[:, 3]
            self._packed, self._encode = _packed_tables(matrix, decode)
        else:
            correct = model.apply if isinstance(model, ColorModel) else model
            self._lut = lut_from_function(correct, lut_size)

    def __call__(self, image: np.ndarray, out: np.ndarray | None = None,
                 window: tuple[int, int, int, int, int] | None = None) -> np.ndarray:
        """The corrected image, written into ``out`` (same shape, uint8, contiguous) if given:
        a caller at frame rate reuses one buffer instead of paging in a fresh 2.7 MB each time.
        ``window`` = (x, y, full width, full height, step): ``image`` is a crop of a larger image
        from (x, y), every ``step``-th pixel (the wire's region); the one model that depends on
        the position (the region LUT) then corrects it as it would the whole image."""
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise BadInput(f'expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}')
        if out is None or out.shape != image.shape or out.dtype != np.uint8 or not out.flags.c_contiguous:
            out = np.empty_like(image, order='C')
        if self.kind == 'diagonal':
            return cv2.transform(image, self._matrix, dst=out)
        image = np.ascontiguousarray(image)
        if self.kind == 'linear':
            _linear_kernel(image.reshape(-1), self._packed, self._encode, out.reshape(-1))
        elif self.kind == 'region_lut':
            h, w = image.shape[:2]
            x, y, full_w, full_h, step = window or (0, 0, w, h, 1)
            if (full_w, full_h) not in self._nodes:
                nx, ny = self.model.grid
                self._nodes[(full_w, full_h)] = (*self.model.nodes(full_w, nx), *self.model.nodes(full_h, ny))
            col_node, col_weight, row_node, row_weight = self._nodes[(full_w, full_h)]
            cols, rows = slice(x, x + w * step, step), slice(y, y + h * step, step)
            _region_lut_kernel(image, self._packed, np.ascontiguousarray(col_node[cols]),
                               np.ascontiguousarray(col_weight[cols]), np.ascontiguousarray(row_node[rows]),
                               np.ascontiguousarray(row_weight[rows]), out)
        else:
            _lut_kernel(image, self._lut, out)
        return out
