"""Registration of raw depth into the colour camera (z-buffered, hole-free at any resolution).

Each raw depth pixel is lifted with the depth camera's undistorted ray, moved by the factory
depth-to-colour extrinsic and projected through the colour lens (rational Brown-Conrady, as
OpenCV). Forward-warping single pixels leaves holes wherever the output is denser than the
depth image, so neighbouring depth pixels are joined into triangles (two per 2x2 quad) and
rasterised with a z-buffer, like a depth mesh; quads that span a depth step are not joined,
so no surface is invented between foreground and background.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput


@dataclass
class Registered:
    depth: np.ndarray   # (h, w) float32 metres in the colour optical frame (z), 0 = no depth
    uv: np.ndarray      # (H, W, 2) float32 output pixel of each raw depth pixel, NaN where none
    z: np.ndarray       # (H, W) float32 colour-frame z of each raw depth pixel, 0 where none


@numba.njit(cache=True, inline='always')
def _distort(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@numba.njit(cache=True)
def _project(depth, rays, R, t, fx, fy, cx, cy, dist, r2_max, uv, zc):
    h, w = depth.shape
    k1, k2, p1, p2, k3, k4, k5, k6 = dist
    for v in range(h):
        for u in range(w):
            d = depth[v, u]
            uv[v, u, 0] = np.nan
            uv[v, u, 1] = np.nan
            zc[v, u] = 0.0
            if not d > 0.0:
                continue
            px, py, pz = rays[v, u, 0] * d, rays[v, u, 1] * d, d
            qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
            qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
            qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
            if qz <= 1e-6:
                continue
            x, y = qx / qz, qy / qz
            # Beyond the lens' calibrated field the rational polynomial can fold back into the image.
            if x * x + y * y > r2_max:
                continue
            xd, yd = _distort(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
            uv[v, u, 0] = fx * xd + cx
            uv[v, u, 1] = fy * yd + cy
            zc[v, u] = qz


@numba.njit(cache=True, inline='always')
def _joined(za, zb, zc, step_abs, step_rel):
    lo = min(za, min(zb, zc))
    hi = max(za, max(zb, zc))
    return lo > 0.0 and hi - lo <= step_abs + step_rel * lo


@numba.njit(cache=True)
def _raster_triangle(out, ax, ay, az, bx, by, bz, cx, cy, cz):
    h, w = out.shape
    x0 = max(int(np.ceil(min(ax, min(bx, cx)))), 0)
    x1 = min(int(np.floor(max(ax, max(bx, cx)))), w - 1)
    y0 = max(int(np.ceil(min(ay, min(by, cy)))), 0)
    y1 = min(int(np.floor(max(ay, max(by, cy)))), h - 1)
    if x0 > x1 or y0 > y1:
        return
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    if abs(area) < 1e-12:
        return
    eps = -1e-6 * abs(area)
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            w0 = ((bx - x) * (cy - y) - (by - y) * (cx - x)) / area
            w1 = ((cx - x) * (ay - y) - (cy - y) * (ax - x)) / area
            w2 = 1.0 - w0 - w1
            if w0 * abs(area) < eps or w1 * abs(area) < eps or w2 * abs(area) < eps:
                continue
            # Depth is interpolated in 1/z, which is linear in image space for a plane.
            z = 1.0 / (w0 / az + w1 / bz + w2 / cz)
            if out[y, x] == 0.0 or z < out[y, x]:
                out[y, x] = z


@numba.njit(cache=True)
def _rasterise(uv, zc, out, step_abs, step_rel):
    h, w = zc.shape
    oh, ow = out.shape
    for v in range(h):
        for u in range(w):
            z = zc[v, u]
            if z <= 0.0:
                continue
            # Every pixel also lands on its own nearest output pixel, so isolated points survive.
            x, y = int(np.floor(uv[v, u, 0] + 0.5)), int(np.floor(uv[v, u, 1] + 0.5))
            if 0 <= x < ow and 0 <= y < oh and (out[y, x] == 0.0 or z < out[y, x]):
                out[y, x] = z
            if v + 1 >= h or u + 1 >= w:
                continue
            z01, z10, z11 = zc[v, u + 1], zc[v + 1, u], zc[v + 1, u + 1]
            if _joined(z, z01, z10, step_abs, step_rel):
                _raster_triangle(out, uv[v, u, 0], uv[v, u, 1], z, uv[v, u + 1, 0], uv[v, u + 1, 1], z01,
                                 uv[v + 1, u, 0], uv[v + 1, u, 1], z10)
            if _joined(z11, z01, z10, step_abs, step_rel):
                _raster_triangle(out, uv[v + 1, u + 1, 0], uv[v + 1, u + 1, 1], z11, uv[v, u + 1, 0],
                                 uv[v, u + 1, 1], z01, uv[v + 1, u, 0], uv[v + 1, u, 1], z10)


class DepthRegistration:
    """Maps one camera's raw depth images into its colour camera at ``output`` resolution.

    ``T_color_depth`` is the factory extrinsic (metres). With ``registered=True`` the depth is
    already in the colour geometry (driver-side registration) and is only resampled.
    """

    def __init__(self, depth: CameraModel, color: CameraModel, T_color_depth: np.ndarray,
                 output_size: tuple[int, int] | None = None, registered: bool = False,
                 step_abs: float = 0.02, step_rel: float = 0.03):
        self.depth_model = depth
        self.color_model = color
        w, h = output_size or (color.width // 2, color.height // 2)
        self.output = color.scaled(w, h)
        self.registered = registered
        self.step_abs, self.step_rel = float(step_abs), float(step_rel)
        T = np.asarray(T_color_depth, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise BadInput('T_color_depth must be a finite 4x4 matrix')
        self.R, self.t = T[:3, :3].copy(), T[:3, 3].copy()
        if registered:   # only resampled: the output pixel of each input pixel centre
            sx, sy = self.output.width / depth.width, self.output.height / depth.height
            u, v = np.meshgrid((np.arange(depth.width) + 0.5) * sx - 0.5, (np.arange(depth.height) + 0.5) * sy - 0.5)
            self._grid_uv = np.stack([u, v], axis=2).astype(np.float32)
            return
        self.rays = depth.pixel_rays().astype(np.float64)
        self._dist = np.zeros(8)
        self._dist[:len(self.output.dist)] = self.output.dist
        # Squared radius of the output image's corners in normalised coordinates, with a margin.
        corners = np.array([[0, 0], [self.output.width - 1, 0], [0, self.output.height - 1],
                            [self.output.width - 1, self.output.height - 1]], np.float64)
        self._r2_max = float((self.output.undistort_pixels(corners) ** 2).sum(axis=1).max() * 1.21)

    def project(self, depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Output-pixel position (H, W, 2) and colour-frame z (H, W) of every raw depth pixel."""
        self._check(depth_m)
        h, w = depth_m.shape
        uv = np.empty((h, w, 2), np.float32)
        zc = np.empty((h, w), np.float32)
        o = self.output
        _project(np.ascontiguousarray(depth_m, np.float32), self.rays, self.R, self.t, o.fx, o.fy, o.cx, o.cy,
                 self._dist, self._r2_max, uv, zc)
        return uv, zc

    def register(self, depth_m: np.ndarray) -> Registered:
        """Registered depth (output geometry) plus where each raw pixel went."""
        if self.registered:
            self._check(depth_m)
            out = cv2.resize(depth_m, (self.output.width, self.output.height), interpolation=cv2.INTER_NEAREST)
            valid = depth_m > 0
            uv = np.where(valid[:, :, None], self._grid_uv, np.float32(np.nan))
            return Registered(out.astype(np.float32), uv, np.where(valid, depth_m, 0).astype(np.float32))
        uv, zc = self.project(depth_m)
        out = np.zeros((self.output.height, self.output.width), np.float32)
        _rasterise(uv, zc, out, self.step_abs, self.step_rel)
        return Registered(out, uv, zc)

    def _check(self, depth_m: np.ndarray) -> None:
        expected = (self.depth_model.height, self.depth_model.width)
        if depth_m.shape != expected:
            raise BadInput(f'depth image is {depth_m.shape[1]}x{depth_m.shape[0]}, its camera_info says '
                             f'{expected[1]}x{expected[0]}')
