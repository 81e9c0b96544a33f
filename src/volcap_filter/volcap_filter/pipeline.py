"""One camera's depth cleaning, stage by stage: flying pixels and range gate on the raw grid,
registration into the colour camera, foreground mask with a depth-aware boundary band,
completion of the holes inside the mask (``flying.complete_inside``), temporal averaging where
the scene holds still (``temporal``), and the coloured point cloud (optionally outlier-filtered)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from volcap_core.errors import BadInput
from volcap_core.settings import setting, validate

from .flying import FlyingPixelConfig, complete_inside, fill_lattice_gaps, fill_sparse_returns, flying_pixels, paper_flying_pixels
from .mask import BackgroundModel, MaskConfig, chroma_key_mask, foreground_mask
from .registration import DepthRegistration, Registered
from .temporal import TemporalFilter

FLYING_METHODS = ('volcap', 'paper_all', 'paper_horizontal', 'none')
MASK_MODES = ('clean_plate', 'chroma', 'none')


@dataclass
class DepthFilterConfig:
    flying_method: str = setting('volcap', 'flying-pixel filter', choices=FLYING_METHODS)
    flying: FlyingPixelConfig = field(default_factory=FlyingPixelConfig)
    mask_mode: str = setting('clean_plate', 'foreground mask', choices=MASK_MODES)
    mask: MaskConfig = field(default_factory=MaskConfig)
    range_gate: bool = setting(True, 'drop depth outside [min_range, max_range]')
    chroma_key: tuple[int, int, int] = setting((0, 177, 64), 'chroma-key colour (R, G, B) for mask_mode chroma',
                                               0, 255)
    chroma_threshold: float = setting(40.0, 'chroma-key distance (Cr, Cb) beyond which a pixel is foreground',
                                      1.0, 255.0)
    boundary_px: int = setting(2, 'mask boundary band (output px) where depth behind the inside is dropped', 0, 20)
    boundary_tolerance: float = setting(0.03, 'how far behind the nearby inside band depth may lie (m)', 0.0, 1.0)
    complete_radius: int = setting(4, 'window radius (output px) over which holes inside the foreground mask get the '
                                   'plane through the depth around them (0 = off)', 0, 16)
    complete_extend: int = setting(2, 'passes after the first that extend the surface from one side towards the mask '
                                   'edge, complete_radius px each (0 = only between depth on three sides)', 0, 8)
    temporal_alpha: float = setting(0.1, 'where the scene holds still, depth and colour are averaged over the frames since '
                                    'it last moved, up to 1/alpha of them (0 = off)', 0.0, 1.0)
    temporal_window: int = setting(15, 'window (px) over which the mean depth change tells motion from noise', 3, 63)
    sor_neighbors: int = setting(0, 'statistical outlier removal neighbours on the cloud (0 = off)', 0, 100)
    sor_std_ratio: float = setting(2.5, 'statistical outlier removal threshold (std ratios)', 0.1, 10.0)

    def validate(self) -> None:
        validate(self)      # every range, the nested configs' too
        if len(self.chroma_key) != 3:
            raise BadInput(f'chroma_key must be three values 0-255, got {self.chroma_key}')
        self.mask.validate()   # its cross-field checks


@dataclass
class CleanResult:
    depth: np.ndarray            # (h, w) float32 metres, colour geometry at output size, 0 = none
    mask: np.ndarray | None      # (H, W) bool foreground at colour resolution (None: no mask)
    flying: np.ndarray           # (Hd, Wd) bool raw pixels the flying-pixel filter removed
    filled: np.ndarray | None    # (Hd, Wd) float32 depth given to raw holes amid sparse returns (0 = none; None: no fill ran)
    registered: Registered       # where each raw pixel went (for scoring against raw-grid truth)
    source_color: np.ndarray     # (H, W, 3) uint8 colour the depth was cleaned with
    timings_ms: dict[str, float]
    _color: np.ndarray | None = None

    @property
    def color(self) -> np.ndarray:
        """(h, w, 3) uint8 colour at the output size, made when first asked for (the point cloud
        asks; the wire and fusion use the source colour: 1 ms a frame not spent)."""
        if self._color is None:
            h, w = self.depth.shape
            src = self.source_color
            self._color = src if src.shape[:2] == (h, w) else cv2.resize(src, (w, h), interpolation=cv2.INTER_AREA)
        return self._color

    def reached_output(self, tolerance: float = 0.02) -> np.ndarray:
        """(Hd, Wd) bool raw pixels whose projection lands on a kept output pixel at their own
        depth (not removed, not hidden behind a nearer surface)."""
        uv, z = self.registered.uv, self.registered.z
        keep = np.zeros(z.shape, bool)
        v, u = np.nonzero(z > 0)
        x = np.floor(uv[v, u, 0] + 0.5).astype(np.int64)
        y = np.floor(uv[v, u, 1] + 0.5).astype(np.int64)
        h, w = self.depth.shape
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        v, u, x, y = v[inside], u[inside], x[inside], y[inside]
        out, zr = self.depth[y, x], z[v, u]
        keep[v, u] = (out > 0) & (np.abs(out - zr) <= tolerance + 0.01 * zr)
        return keep


class DepthCleaner:
    """Cleans one camera's frames; holds its registration, clean plate and temporal state."""

    def __init__(self, registration: DepthRegistration, cfg: DepthFilterConfig | None = None):
        self.registration = registration
        self.cfg = cfg or DepthFilterConfig()
        self.cfg.validate()
        self.background = BackgroundModel()
        self.temporal = TemporalFilter(self.cfg.temporal_alpha, self.cfg.temporal_window, self.cfg.flying.noise_base,
                                       self.cfg.flying.noise_quad) if self.cfg.temporal_alpha > 0 else None
        self._out_rays = registration.output.pixel_rays().astype(np.float32)

    @property
    def output_model(self):
        return self.registration.output

    def learn_background(self, color: np.ndarray, depth_m: np.ndarray) -> None:
        """Add one subject-free frame to the clean plate."""
        self._check(color, depth_m)
        gated = self._gate(sanitise_depth(depth_m))      # a new array (sanitise_depth's)
        filled = self._fill(gated, np.zeros(gated.shape, bool))
        if filled is not None:      # the plate's dark material closed as the subject's will be
            gated += filled
        registered = self.registration.register(gated).depth
        self.background.add(color, registered)

    def process(self, color: np.ndarray, depth_m: np.ndarray) -> CleanResult:
        self._check(color, depth_m)
        t = {}
        t0 = time.perf_counter()
        depth = sanitise_depth(depth_m)
        flying = self._flying(depth)
        gated = self._gate(depth, drop=flying)      # a new array: filled in place below
        filled = self._fill(gated, flying)
        if filled is not None:
            gated += filled
        t['flying'] = _ms(t0)
        t0 = time.perf_counter()
        reg = self.registration.register(gated)
        t['register'] = _ms(t0)
        t0 = time.perf_counter()
        out = self.output_model
        mask = self._mask(color, reg.depth)
        keep = reg.depth > 0
        if mask is not None:
            fg = cv2.resize(mask.view(np.uint8) * np.uint8(255), (out.width, out.height),
                            interpolation=cv2.INTER_AREA) > 127
            keep &= self._boundary_keep(fg, reg.depth)
        clean = np.where(keep, reg.depth, np.float32(0.0))
        t['mask'] = _ms(t0)
        # Depth a driver registered keeps its lattice of empty rows and columns (as in _fill): the
        # completion would fill the lattice inside the mask, unmeasured, so native depth only.
        if mask is not None and self.cfg.complete_radius > 0 and not self.registration.registered:
            t0 = time.perf_counter()
            # a new array (np.where's): completed in place
            complete_inside(clean, fg, out.fx, self.cfg.complete_radius, self.cfg.complete_extend, self.cfg.flying)
            t['complete'] = _ms(t0)
        if self.temporal is not None:
            t0 = time.perf_counter()
            clean, color, _ = self.temporal.update(clean, color)
            t['temporal'] = _ms(t0)
        return CleanResult(clean, mask, flying, filled, reg, color, t)

    def points(self, result: CleanResult) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) float32 points in the colour optical frame and their (N, 3) uint8 colours."""
        valid = result.depth > 0
        xyz = self._out_rays[valid] * result.depth[valid][:, None]
        rgb = result.color[valid]
        if self.cfg.sor_neighbors > 0 and len(xyz) > self.cfg.sor_neighbors:
            xyz, rgb = statistical_outlier_removal(xyz, rgb, self.cfg.sor_neighbors, self.cfg.sor_std_ratio)
        return xyz, rgb

    def _check(self, color: np.ndarray, depth_m: np.ndarray) -> None:
        c = self.registration.color_model
        if color.shape[:2] != (c.height, c.width):
            raise BadInput(f'colour image is {color.shape[1]}x{color.shape[0]}, its camera_info says '
                             f'{c.width}x{c.height}')
        if not np.any(depth_m > 0):
            raise BadInput('depth image has no valid pixel (all zero or NaN)')

    def _flying(self, depth: np.ndarray) -> np.ndarray:
        method = self.cfg.flying_method
        if method == 'none':
            return np.zeros(depth.shape, bool)
        focal = self.registration.depth_model.fx
        # Depth registered by a driver has a lattice of empty rows and columns: bridged for the
        # tests (else every pixel borders a hole), left empty in the output.
        tested = fill_lattice_gaps(depth, focal, self.cfg.flying) if self.registration.registered else depth
        if method == 'volcap':
            found = flying_pixels(tested, focal, self.cfg.flying)
        else:
            found = paper_flying_pixels(tested, method.removeprefix('paper_'))
        return found & (depth > 0)

    def _fill(self, gated: np.ndarray, removed: np.ndarray) -> np.ndarray | None:
        """Depth for the holes amid sparse returns (dark material), with our flying-pixel filter
        (its sparse-return settings), 0 elsewhere; None where no fill runs."""
        # Depth a driver registered keeps its lattice of empty rows and columns in the output
        # (fill_lattice_gaps bridges them for the tests only); the fill cannot tell them from
        # dark material's dropouts there, so it is left to native depth.
        if self.cfg.flying_method != 'volcap' or self.registration.registered or self.cfg.flying.sparse_radius == 0:
            return None
        return fill_sparse_returns(gated, removed, self.registration.depth_model.fx, self.cfg.flying)

    def _gate(self, depth: np.ndarray, drop: np.ndarray | None = None) -> np.ndarray:
        """Depth with ``drop`` pixels and, if the gate is on, out-of-range ones set to 0."""
        if self.cfg.range_gate:
            m = self.cfg.mask
            out_of_range = (depth < m.min_range) | (depth > m.max_range)
            drop = out_of_range if drop is None else drop | out_of_range
        return depth if drop is None else np.where(drop, np.float32(0.0), depth)

    def _mask(self, color: np.ndarray, registered: np.ndarray) -> np.ndarray | None:
        mode = self.cfg.mask_mode
        if mode == 'chroma':
            return chroma_key_mask(color, self.cfg.chroma_key, self.cfg.chroma_threshold, self.cfg.mask.min_area_frac)
        if mode == 'clean_plate' and self.background.frames:
            return foreground_mask(color, registered, self.background, self.cfg.mask)
        return None

    def _boundary_keep(self, fg: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Depth allowed through the mask. In a band from ``boundary_px`` inside the mask's edge
        to one pixel outside it, depth is kept only where it is not behind the nearby inside of
        the mask: background leaking through colour/depth misalignment is dropped, the subject's
        own rim is kept (a plain erosion would cut both)."""
        r = self.cfg.boundary_px
        if r == 0:
            return fg
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        inside = cv2.erode(fg.view(np.uint8), kernel).astype(bool)
        band = cv2.dilate(fg.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~inside
        inside_depth = np.where(inside & (depth > 0), depth, np.float32(0.0))
        wide = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (4 * r + 3, 4 * r + 3))
        reference = cv2.dilate(inside_depth, wide)   # farthest inside surface nearby
        return inside | (band & (depth <= reference + self.cfg.boundary_tolerance) & (reference > 0))


def sanitise_depth(depth_m: np.ndarray) -> np.ndarray:
    """float32 metres with NaN, inf and negative values as 0 (invalid)."""
    d = np.asarray(depth_m, np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0))


def statistical_outlier_removal(xyz: np.ndarray, rgb: np.ndarray, neighbors: int, std_ratio: float):
    import open3d as o3d  # only when the option is on: importing Open3D costs ~1 s at start-up
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz.astype(np.float64)))
    _, idx = pcd.remove_statistical_outlier(nb_neighbors=neighbors, std_ratio=std_ratio)
    idx = np.asarray(idx, np.int64)
    return xyz[idx], rgb[idx]


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0
