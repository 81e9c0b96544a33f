"""Pixel correspondences between cameras from registered depth and the calibration.

Each camera's depth, registered to its colour camera, gives every valid pixel a surface point.
That point is taken into every other camera with the calibrated poses and projected (lens
distortion included). It is a correspondence only where the other camera sees that surface
itself: its own registered depth at the four pixels around the projection agrees with the
point's depth there (the z-buffer test; this rejects occluded points and, because all four
neighbours must agree, points on a silhouette, whose bilinear colour would mix two surfaces).
A round trip then takes the second camera's own surface point at the match back into the
first: a depth error of the first camera moves the match sideways, and the round trip lands
away from the pixel it started at. The colour of the first camera is read at its pixel, that of
the second bilinearly at the sub-pixel projection.

Registered ToF depth is first smoothed (``smooth_depth``): its noise, seen from a camera 90
degrees away, is a sideways error of the match.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from volcap_core.calibration import Calibration
from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput
from volcap_core.sampling import sample_bilinear

from .config import CorrespondenceConfig  # noqa: F401 (re-exported: its home before config.py)


@dataclass
class View:
    """One camera in one frame set: colour and registered depth on the same pixel grid."""
    name: str
    color: np.ndarray            # (H, W, 3) uint8 RGB
    depth: np.ndarray            # (H, W) float32 metres, 0 = no depth
    camera: CameraModel          # intrinsics of that grid
    T_world_camera: np.ndarray   # (4, 4)
    _rays: np.ndarray | None = field(default=None, repr=False)
    _gradient: np.ndarray | None = field(default=None, repr=False)
    _surface: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        h, w = self.depth.shape
        if self.color.shape != (h, w, 3) or (self.camera.height, self.camera.width) != (h, w):
            raise BadInput(f'{self.name}: colour {self.color.shape[:2]}, depth {self.depth.shape} and camera '
                             f'{self.camera.height}x{self.camera.width} must share one pixel grid')

    def rays(self) -> np.ndarray:
        if self._rays is None:
            self._rays = self.camera.pixel_rays().astype(np.float32)
        return self._rays

    def surface(self, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(H', W', 3) points and unit normals (0 where undefined) on every ``stride``-th pixel."""
        if stride not in self._surface:
            points = self.rays()[::stride, ::stride] * self.depth[::stride, ::stride, None]
            self._surface[stride] = (points, _normals(points))
        return self._surface[stride]

    def gradient(self) -> np.ndarray:
        """(H, W) luminance gradient magnitude in levels per pixel (Sobel)."""
        if self._gradient is None:
            grey = cv2.cvtColor(self.color, cv2.COLOR_RGB2GRAY).astype(np.float32)
            gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
            gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
            self._gradient = np.hypot(gx, gy)
        return self._gradient


@dataclass
class Matches:
    """Pixels of camera ``a`` (integer, x y) and where the same surface points are in ``b``
    (sub-pixel), with both cameras' colours there (sRGB in [0, 1])."""
    a: str
    b: str
    pixels_a: np.ndarray     # (N, 2) int32
    pixels_b: np.ndarray     # (N, 2) float32
    colors_a: np.ndarray    # (N, 3) float64
    colors_b: np.ndarray    # (N, 3) float64
    fraction: float          # N over the number of pixels of a

    def __len__(self) -> int:
        return len(self.pixels_a)


def smooth_depth(depth: np.ndarray, diameter: int = 9, sigma_m: float = 0.015, sigma_px: float = 4.0) -> np.ndarray:
    """Edge-preserving average of registered depth (OpenCV's bilateral filter): neighbours more
    than a few ``sigma_m`` away in depth (another surface, or no depth: 0) get no weight."""
    out = cv2.bilateralFilter(np.ascontiguousarray(depth, np.float32), diameter, sigma_m, sigma_px)
    out[depth <= 0] = 0.0
    return out


def _normals(points: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals from the cross product of neighbouring points (0 where undefined)."""
    dx = np.zeros_like(points)
    dy = np.zeros_like(points)
    dx[:, 1:-1] = points[:, 2:] - points[:, :-2]
    dy[1:-1] = points[2:] - points[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def _bilinear_depth_ok(depth: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, tol: np.ndarray) -> np.ndarray:
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    ok = np.ones(len(x), bool)
    for dy in (0, 1):
        for dx in (0, 1):
            d = depth[y0 + dy, x0 + dx]
            ok &= (d > 0) & (np.abs(d - z) <= tol)
    return ok


def match_pair(a: View, b: View, cfg: CorrespondenceConfig = CorrespondenceConfig()) -> Matches:
    """Correspondences from camera a's pixels into camera b (see the module docstring)."""
    s = cfg.stride
    points_a, normals_a = a.surface(s)
    v, u = np.nonzero(a.depth[::s, ::s] > 0)
    pts = points_a[v, u].astype(np.float64)
    nrm = normals_a[v, u].astype(np.float64)
    cos_max = np.cos(np.radians(cfg.max_angle_deg))
    view_a = -pts / np.linalg.norm(pts, axis=1, keepdims=True)
    facing = np.abs((nrm * view_a).sum(1)) >= cos_max
    T = np.linalg.inv(b.T_world_camera) @ a.T_world_camera
    pts_b = pts @ T[:3, :3].T + T[:3, 3]
    nrm_b = nrm @ T[:3, :3].T
    in_front = pts_b[:, 2] > 0.05
    keep = facing & in_front
    view_b = -pts_b / np.maximum(np.linalg.norm(pts_b, axis=1, keepdims=True), 1e-9)
    keep &= np.abs((nrm_b * view_b).sum(1)) >= cos_max
    v, u, pts_b = v[keep], u[keep], pts_b[keep]
    empty = Matches(a.name, b.name, np.zeros((0, 2), np.int32), np.zeros((0, 2), np.float32),
                    np.zeros((0, 3)), np.zeros((0, 3)), 0.0)
    if not len(pts_b):
        return empty
    px = b.camera.project(pts_b)
    x, y = px[:, 0], px[:, 1]
    h, w = b.depth.shape
    inside = (x >= 0) & (y >= 0) & (x < w - 1) & (y < h - 1)
    x, y, z, v, u = x[inside], y[inside], pts_b[inside, 2], v[inside], u[inside]
    ok = _bilinear_depth_ok(b.depth, x, y, z, cfg.depth_tolerance_m + cfg.depth_tolerance_rel * z)
    x, y, v, u = x[ok], y[ok], v[ok], u[ok]
    if not len(x):
        return empty
    at_b = np.stack([x, y], 1).astype(np.float32)
    # Round trip: b's own surface point at the match, taken back into a. A depth error of a
    # moves the match sideways in b; b's surface there then lands away from a's pixel.
    back = (sample_bilinear(b.rays(), at_b) * sample_bilinear(b.depth, at_b)).astype(np.float64)
    T_ab = np.linalg.inv(T)
    back_px = a.camera.project(back @ T_ab[:3, :3].T + T_ab[:3, 3])
    ok = np.linalg.norm(back_px - np.stack([u * s, v * s], 1), axis=1) <= cfg.max_round_trip_px
    if cfg.max_gradient > 0:
        # On a texture edge a tenth of a pixel of misregistration, or the two cameras' different
        # pixel footprints, is a large colour difference that no colour model should chase.
        ok &= (a.gradient()[v * s, u * s] <= cfg.max_gradient) & \
            (sample_bilinear(b.gradient(), at_b)[:, 0] <= cfg.max_gradient)
    at_b, v, u = at_b[ok], v[ok] * s, u[ok] * s
    if not len(at_b):
        return empty
    colors_a = a.color[v, u].astype(np.float64) / 255.0
    colors_b = sample_bilinear(b.color, at_b).astype(np.float64) / 255.0   # 8-bit, like a resampled image
    return Matches(a.name, b.name, np.stack([u, v], 1).astype(np.int32), at_b, colors_a, colors_b,
                   len(at_b) * s * s / float(a.depth.size))


def find_correspondences(views: list[View], cfg: CorrespondenceConfig = CorrespondenceConfig()
                         ) -> dict[tuple[str, str], Matches]:
    """Every unordered camera pair (a before b in ``views``) with at least ``min_fraction`` of a's
    pixels in correspondence."""
    out = {}
    for i, a in enumerate(views):
        for b in views[i + 1:]:
            m = match_pair(a, b, cfg)
            if m.fraction >= cfg.min_fraction:
                out[(a.name, b.name)] = m
    return out


def split_frame_sets(count: int) -> tuple[list[int], list[int]]:
    """(fitted, scored) frame set indices: the 1st, 3rd, ... and the 2nd, 4th, ...; one frame set
    is both."""
    fit = list(range(0, count, 2))
    return fit, list(range(1, count, 2)) or fit


def cameras_in(sets: list[list[View]], calibration: Calibration) -> list[str]:
    """The calibration's cameras seen in any of the frame sets (one missing from a set still counts)."""
    seen = {v.name for views in sets for v in views}
    return [c for c in calibration.cameras if c in seen]


def merge_matches(per_set: list[dict[tuple[str, str], Matches]], min_fraction: float) -> dict[tuple[str, str], Matches]:
    """One Matches per pair over several frame sets; the fraction is over all of them."""
    pairs = sorted({p for d in per_set for p in d})
    out = {}
    for p in pairs:
        parts = [d[p] for d in per_set if p in d]
        fraction = sum(m.fraction for m in parts) / len(per_set)
        if fraction < min_fraction:
            continue
        out[p] = Matches(p[0], p[1], *(np.concatenate([getattr(m, k) for m in parts]) for k in
                                       ('pixels_a', 'pixels_b', 'colors_a', 'colors_b')), fraction)
    return out
