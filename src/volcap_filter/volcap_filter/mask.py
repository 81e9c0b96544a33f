"""Foreground masks from colour (paper 000's mask step), learnt from a clean plate or keyed.

``BackgroundModel`` learns per-pixel colour statistics from background-only frames and the
background depth (registered) where it was measured. A pixel is foreground when its colour
leaves the background's colour cone (Horprasert et al.'s brightness / chromaticity distortion:
shadows and exposure drift only scale brightness, so they stay background) or when depth puts a
surface clearly in front of the background. The colour decision draws the boundary (it is
sharper than depth); depth regions in front of the background are added where they touch the
colour decision (a shirt the colour of the wall, a pedestal the grey of the floor). ``chroma_key_mask`` is the green-screen alternative.
"""
from __future__ import annotations

import zipfile
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from volcap_core.errors import BadInput
from volcap_core.files import atomic_write
from volcap_core.settings import setting, validate


@dataclass
class MaskConfig:
    noise_floor: float = setting(3.0, 'colour sigma floor of the clean plate (8-bit levels)', 0.5, 50.0)
    chroma_sigmas: float = setting(6.0, 'chromaticity distortion beyond which a pixel is foreground (sigmas)',
                                   0.5, 100.0)
    min_difference: float = setting(12.0, 'smallest colour difference to the clean plate that can be foreground',
                                    0.0, 255.0)
    shadow_min: float = setting(0.55, 'brightness ratio down to which a darker pixel may be shadow', 0.05, 1.0)
    highlight_max: float = setting(1.25, 'brightness ratio above which a pixel is foreground', 1.0, 5.0)
    depth_margin: float = setting(0.05, 'metres in front of the clean-plate depth that count as foreground',
                                  0.0, 2.0)
    min_area_frac: float = setting(0.0005, 'foreground blobs smaller than this fraction of the image are dropped',
                                   0.0, 0.5)
    min_range: float = setting(0.1, 'range gate near limit (m)', 0.0, 20.0)
    max_range: float = setting(2.5, 'range gate far limit (m)', 0.05, 20.0)

    def validate(self) -> None:
        validate(self)
        if not self.min_range < self.max_range:
            raise BadInput(f'range gate needs 0 <= min_range < max_range, got {self.min_range}, {self.max_range}')
        if not 0.0 < self.shadow_min <= 1.0 <= self.highlight_max:
            raise BadInput('need 0 < shadow_min <= 1 <= highlight_max')


@numba.njit(cache=True)
def _color_foreground(img, mean, inv_sigma, chroma_k, min_diff, shadow_min, highlight_max, out):
    h, w, _ = img.shape
    for v in range(h):
        for u in range(w):
            num, den, diff2 = 0.0, 0.0, 0.0
            for c in range(3):
                e = mean[v, u, c] * inv_sigma[v, u, c]
                x = img[v, u, c] * inv_sigma[v, u, c]
                num += x * e
                den += e * e
                d = float(img[v, u, c]) - mean[v, u, c]
                diff2 += d * d
            alpha = num / den if den > 1e-9 else 1.0
            cd2 = 0.0
            for c in range(3):
                r = (img[v, u, c] - alpha * mean[v, u, c]) * inv_sigma[v, u, c]
                cd2 += r * r
            fg = False
            if diff2 > min_diff * min_diff:
                fg = cd2 > chroma_k * chroma_k or alpha < shadow_min or alpha > highlight_max
            out[v, u] = fg


class BackgroundModel:
    """Clean-plate statistics of one camera: colour mean and spread, and background depth."""

    def __init__(self):
        self._n = 0
        self._sum = self._sum2 = None
        self._depth_far = None
        self._stats = None   # (noise_floor, mean, 1 / sigma), made once per clean plate

    @property
    def frames(self) -> int:
        return self._n

    def add(self, rgb: np.ndarray, depth_m: np.ndarray | None = None) -> None:
        """Add one background-only frame (colour at mask resolution, registered depth at any)."""
        x = rgb.astype(np.float64)
        if self._sum is not None and x.shape != self._sum.shape:
            raise BadInput(f'clean-plate frame is {x.shape[1]}x{x.shape[0]}, earlier ones were '
                             f'{self._sum.shape[1]}x{self._sum.shape[0]}')
        self._sum = x if self._sum is None else self._sum + x
        self._sum2 = x * x if self._sum2 is None else self._sum2 + x * x
        if depth_m is not None:
            d = np.where(np.isfinite(depth_m), depth_m, 0).astype(np.float32)
            # The farthest return seen: a transient object in one frame must not become background.
            self._depth_far = d if self._depth_far is None else np.maximum(self._depth_far, d)
        self._n += 1
        self._stats = None

    def statistics(self, noise_floor: float) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel colour mean and 1 / sigma (float32), cached until a frame is added."""
        if self._n == 0:
            raise BadInput('no clean-plate frames learnt yet')
        if self._stats is None or self._stats[0] != noise_floor:
            mean = self._sum / self._n
            var = np.maximum(self._sum2 / self._n - mean ** 2, 0.0) * (self._n / max(self._n - 1, 1))
            sigma = np.sqrt(np.maximum(var, noise_floor ** 2))
            self._stats = (noise_floor, mean.astype(np.float32), (1.0 / sigma).astype(np.float32))
        return self._stats[1], self._stats[2]

    @property
    def depth(self) -> np.ndarray | None:
        return self._depth_far

    def save(self, path: str) -> None:
        if self._n == 0:
            raise BadInput('no clean-plate frames to save')
        depth = self._depth_far if self._depth_far is not None else np.zeros(0, np.float32)
        atomic_write(path, lambda f: np.savez_compressed(f, n=self._n, sum=self._sum, sum2=self._sum2, depth=depth))

    @classmethod
    def load(cls, path: str) -> 'BackgroundModel':
        """A saved clean plate, checked; a ValueError says what is wrong with the file."""
        model = cls()
        try:
            with np.load(path, allow_pickle=False) as npz:
                n, total, total2, depth = int(npz['n']), npz['sum'], npz['sum2'], npz['depth']
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise BadInput(f'clean plate {path} is unreadable: {type(e).__name__}: {e}') from e
        if n < 1 or total.ndim != 3 or total.shape[2] != 3 or total2.shape != total.shape \
                or not np.all(np.isfinite(total)) or not np.all(np.isfinite(total2)):
            raise BadInput(f'clean plate {path}: expected colour sums of shape (H, W, 3) over >= 1 frames, got '
                             f'{total.shape} over {n}')
        if depth.size and (depth.ndim != 2 or not np.all(np.isfinite(depth))):
            raise BadInput(f'clean plate {path}: expected a finite (H, W) depth, got {depth.shape}')
        model._n, model._sum, model._sum2 = n, total, total2
        model._depth_far = depth if depth.size else None
        return model


def color_foreground(rgb: np.ndarray, model: BackgroundModel, cfg: MaskConfig) -> np.ndarray:
    """Pixels whose colour cannot be the learnt background (before clean-up)."""
    mean, inv_sigma = model.statistics(cfg.noise_floor)
    if rgb.shape != mean.shape:
        raise BadInput(f'colour image is {rgb.shape[1]}x{rgb.shape[0]}, the clean plate is '
                         f'{mean.shape[1]}x{mean.shape[0]}')
    out = np.empty(rgb.shape[:2], np.bool_)
    _color_foreground(np.ascontiguousarray(rgb), mean, inv_sigma, cfg.chroma_sigmas, cfg.min_difference,
                      cfg.shadow_min, cfg.highlight_max, out)
    return out


def depth_foreground(depth_m: np.ndarray, background_m: np.ndarray | None, cfg: MaskConfig) -> np.ndarray:
    """Surfaces inside the range gate and clearly in front of the learnt background depth."""
    in_gate = (depth_m > cfg.min_range) & (depth_m < cfg.max_range)
    if background_m is None:
        return in_gate
    if background_m.shape != depth_m.shape:
        raise BadInput('background depth and depth differ in size')
    return in_gate & ((background_m <= 0) | (depth_m < background_m - cfg.depth_margin))


def foreground_mask(rgb: np.ndarray, depth_m: np.ndarray, model: BackgroundModel, cfg: MaskConfig) -> np.ndarray:
    """Clean-plate foreground at the colour image's resolution; ``depth_m`` is the registered
    depth at any resolution of the same camera (resized here), flying pixels already removed."""
    h, w = rgb.shape[:2]
    fg = color_foreground(rgb, model, cfg)
    if depth_m is not None:
        bg = model.depth if model.depth is not None and model.depth.shape == depth_m.shape else None
        by_depth = depth_foreground(depth_m, bg, cfg).view(np.uint8)
        by_depth = cv2.resize(by_depth, (w, h), interpolation=cv2.INTER_NEAREST) > 0
        # Depth regions join the mask where they touch colour foreground (a pedestal the grey of
        # the floor below a coloured subject), never on their own (no colour change, no subject).
        return clean_mask(fg | by_depth, cfg.min_area_frac, seeds=fg)
    return clean_mask(fg, cfg.min_area_frac)


def clean_mask(fg: np.ndarray, min_area_frac: float, seeds: np.ndarray | None = None) -> np.ndarray:
    """Despeckle a raw foreground decision: open, drop blobs smaller than ``min_area_frac`` of the
    image (and, given ``seeds``, blobs containing no seed pixel), fill enclosed holes."""
    m = cv2.morphologyEx(fg.view(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    out = np.zeros(fg.shape, bool)
    # The rest works on the box around what the opening left (the subject, not the frame: 8.6 ->
    # ~3 ms a 1280x720 frame). Outside it all is background, connected to the image border, so
    # flooding from the box's border finds the same holes as flooding from the image's.
    x, y, w, h = cv2.boundingRect(m)
    if w == 0 or h == 0:
        return out
    box = (slice(y, y + h), slice(x, x + w))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m[box], connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area_frac * fg.size
    keep[0] = False
    if seeds is not None:
        touched = np.zeros(n, bool)
        touched[labels[seeds[box]]] = True
        keep &= touched
    # Holes are the background that a flood from the border does not reach.
    padded = cv2.copyMakeBorder(keep[labels].view(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    cv2.floodFill(padded, None, (0, 0), 2)
    out[box] = padded[1:-1, 1:-1] != 2
    return out


def chroma_key_mask(rgb: np.ndarray, key_rgb: tuple[int, int, int] = (0, 177, 64), threshold: float = 40.0,
                    min_area_frac: float = 0.0005) -> np.ndarray:
    """Foreground = pixels whose chroma (Cr, Cb) is farther than ``threshold`` from the key's."""
    ycrcb = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2YCrCb).astype(np.float32)
    key = cv2.cvtColor(np.uint8([[key_rgb]]), cv2.COLOR_RGB2YCrCb).astype(np.float32)[0, 0]
    dist = np.hypot(ycrcb[:, :, 1] - key[1], ycrcb[:, :, 2] - key[2])
    return clean_mask(dist > threshold, min_area_frac)
