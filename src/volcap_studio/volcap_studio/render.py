"""Ray-cast rendering of the synthetic studio (Open3D RaycastingScene), so ground truth is exact.

Colour: Lambert + Blinn-Phong shading of procedural albedo under point lights, then a per-camera
response (vignetting, lens blur, exposure, white balance, sensor noise, channel crosstalk,
gamma). Depth: a time-of-flight model on the depth camera's own rays - distance-dependent noise,
dropouts at grazing angles and on dark surfaces, mixed (flying) pixels from the amplitude-
weighted depth of sub-pixel samples at discontinuities, and interference speckle.
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import cv2
import numpy as np
import open3d as o3d

from volcap_core.camera import CameraModel, depth_to_millimetres
from volcap_core.color import LUMINANCE
from volcap_core.poses import invert, transform_points
from volcap_core.sampling import sample_bilinear
from volcap_studio.config import ToFModel  # noqa: F401 (re-exported: its home before config.py)
from volcap_studio.scene import Light, SceneObject

LUMA = LUMINANCE.astype(np.float32)


@dataclass
class Hits:
    """Ray-cast result. ``t`` and ``obj`` cover every ray; the surface attributes only the rays
    that hit (their indices in ``idx``), so sparse scenes cost little to shade."""
    t: np.ndarray          # (N,) ray parameter (= camera z for z=1 camera rays), inf on miss
    obj: np.ndarray        # (N,) object index, -1 on miss
    idx: np.ndarray        # (M,) rays that hit
    points: np.ndarray     # (M, 3) studio frame
    normals: np.ndarray    # (M, 3) unit, facing the ray origin
    albedo: np.ndarray     # (M, 3) linear RGB
    specular: np.ndarray   # (M,) Blinn-Phong weight
    shininess: np.ndarray  # (M,)
    material: np.ndarray   # (M,) index into the hit object's materials


class SceneRaycaster:
    """One RaycastingScene over posed scene objects (object indices start at ``first_index``)."""

    def __init__(self, objects: list[SceneObject], first_index: int = 0):
        self.objects = objects
        self.first_index = first_index
        self.scene = o3d.t.geometry.RaycastingScene()
        self._vertex_normals, self._triangles = [], []
        self._lut = np.full(len(objects) + 1, -1, np.int64)
        for i, obj in enumerate(objects):
            mesh = o3d.geometry.TriangleMesh(obj.mesh)
            mesh.transform(obj.pose)
            gid = self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
            if gid >= len(self._lut):
                self._lut = np.concatenate([self._lut, np.full(gid + 1 - len(self._lut), -1)])
            self._lut[gid] = i
            self._vertex_normals.append(np.asarray(mesh.vertex_normals, dtype=np.float32))
            self._triangles.append(np.asarray(mesh.triangles))

    def cast(self, origin: np.ndarray, directions: np.ndarray, t_max: np.ndarray | None = None) -> Hits:
        """Cast rays from ``origin`` (3,) along ``directions`` (N, 3); hits at or beyond
        ``t_max`` (N,) are ignored (something nearer is already known there)."""
        n = len(directions)
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = directions
        if not self.objects:
            return _no_hits(n)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans['t_hit'].numpy()
        hit = np.isfinite(t) if t_max is None else np.isfinite(t) & (t < t_max)
        idx = np.flatnonzero(hit)
        local_obj = self._lut[ans['geometry_ids'].numpy()[idx]]
        obj = np.full(n, -1, np.int64)
        obj[idx] = local_obj + self.first_index
        prim = ans['primitive_ids'].numpy()[idx]
        uv = ans['primitive_uvs'].numpy()[idx]
        dirs = rays[idx, 3:]
        points = rays[idx, :3] + dirs * t[idx, None]
        m = len(idx)
        normals = np.zeros((m, 3), np.float32)
        albedo = np.zeros((m, 3), np.float32)
        specular = np.zeros(m, np.float32)
        shininess = np.ones(m, np.float32)
        material = np.zeros(m, np.int64)
        for i, obj_i in enumerate(self.objects):
            sel = np.flatnonzero(local_obj == i)
            if sel.size == 0:
                continue
            tri = self._triangles[i][prim[sel]]
            vn = self._vertex_normals[i]
            u, v = uv[sel, 0:1], uv[sel, 1:2]
            nrm = (1 - u - v) * vn[tri[:, 0]] + u * vn[tri[:, 1]] + v * vn[tri[:, 2]]
            normals[sel] = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            local = transform_points(invert(obj_i.pose), points[sel].astype(np.float64))
            mat_idx = obj_i.triangle_material[prim[sel]]
            material[sel] = mat_idx
            for k, mat in enumerate(obj_i.materials):
                in_mat = mat_idx == k
                if in_mat.any():
                    albedo[sel[in_mat]] = mat.albedo(local[in_mat])
                    specular[sel[in_mat]] = mat.specular
                    shininess[sel[in_mat]] = mat.shininess
        # Two-sided surfaces: the normal faces the viewer.
        normals[np.einsum('ij,ij->i', normals, dirs) > 0] *= -1
        t_all = np.full(n, np.inf, np.float32)
        t_all[idx] = t[idx]
        return Hits(t_all, obj, idx, points, normals, albedo, specular, shininess, material)


def _no_hits(n: int) -> Hits:
    e3 = np.zeros((0, 3), np.float32)
    e1 = np.zeros(0, np.float32)
    return Hits(np.full(n, np.inf, np.float32), np.full(n, -1, np.int64), np.zeros(0, np.int64),
                e3, e3, e3, e1, e1, np.zeros(0, np.int64))


def shade(hits: Hits, eye: np.ndarray, lights: list[Light], ambient: float) -> np.ndarray:
    """(M, 3) linear RGB radiance of the hit rays towards ``eye``: ambient + Lambert + Blinn-Phong."""
    p, n = hits.points, hits.normals
    view = eye.astype(np.float32) - p
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    diffuse = np.full((len(p), 3), ambient, np.float32)
    spec = np.zeros((len(p), 3), np.float32)
    glossy = hits.specular > 0
    for light in lights:
        to_l = np.asarray(light.position, np.float32) - p
        d2 = np.einsum('ij,ij->i', to_l, to_l)
        to_l /= np.sqrt(d2)[:, None]
        irradiance = np.asarray(light.color, np.float32)[None, :] / (1.0 + 0.25 * d2[:, None])
        ndl = np.clip(np.einsum('ij,ij->i', n, to_l), 0.0, None)
        diffuse += irradiance * ndl[:, None]
        lit = glossy & (ndl > 0)
        half = to_l[lit] + view[lit]
        half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
        ndh = np.clip(np.einsum('ij,ij->i', n[lit], half), 0.0, None)
        spec[lit] += irradiance[lit] * (hits.specular[lit] * ndh ** hits.shininess[lit])[:, None]
    return hits.albedo * diffuse + spec


@dataclass
class ColorResponse:
    """How one colour camera turns scene radiance into 8-bit sRGB-like values."""
    gain: float = 1.0
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    crosstalk: tuple = ((1, 0, 0), (0, 1, 0), (0, 0, 1))
    gamma: float = 2.2
    vignetting: tuple[float, float] = (0.0, 0.0)  # 1 - a r^2 - b r^4, r = 1 at the image corner
    read_noise: float = 0.002
    shot_noise: float = 0.008
    blur_sigma_px: float = 0.5

    @classmethod
    def random(cls, rng: np.random.Generator) -> 'ColorResponse':
        M = np.eye(3) + rng.uniform(-0.06, 0.06, (3, 3)) * (1 - np.eye(3))
        M /= M.sum(axis=1, keepdims=True)
        return cls(gain=float(rng.uniform(0.75, 1.3)),
                   white_balance=tuple(float(v) for v in (rng.uniform(0.8, 1.2), 1.0, rng.uniform(0.8, 1.2))),
                   crosstalk=tuple(tuple(float(v) for v in row) for row in M),
                   gamma=float(rng.uniform(2.0, 2.4)),
                   vignetting=(float(rng.uniform(0.1, 0.3)), float(rng.uniform(0.0, 0.1))))

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: (list(map(list, v)) if k == 'crosstalk' else list(v) if isinstance(v, tuple) else v)
                for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> 'ColorResponse':
        return cls(**{k: (tuple(map(tuple, v)) if k == 'crosstalk' else tuple(v) if isinstance(v, list) else v)
                      for k, v in d.items()})

    def vignette(self, width: int, height: int) -> np.ndarray:
        return _vignette(width, height, *self.vignetting)

    def apply(self, radiance: np.ndarray, rng: np.random.Generator, noise: bool = True) -> np.ndarray:
        """(H, W, 3) linear radiance -> (H, W, 3) uint8."""
        h, w = radiance.shape[:2]
        x = radiance * self.vignette(w, h)
        if self.blur_sigma_px > 0:
            x = cv2.GaussianBlur(x, (0, 0), self.blur_sigma_px)
        x = x * np.float32(self.gain) * np.asarray(self.white_balance, np.float32)
        if noise:
            sigma = np.sqrt(self.read_noise ** 2 + self.shot_noise ** 2 * np.clip(x, 0, None))
            x = x + sigma * rng.standard_normal(x.shape, dtype=np.float32)
        x = cv2.transform(x, np.asarray(self.crosstalk, np.float32))
        x = np.clip(x, 0.0, 1.0) ** np.float32(1.0 / self.gamma)
        return np.round(x * 255.0).astype(np.uint8)

    def true_colors(self, rgb: np.ndarray, pixels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """What the ideal camera (``IDEAL_RESPONSE``: unit gain and white balance, no crosstalk
        or vignetting, gamma 2.2) records where this camera recorded ``rgb`` (N, 3 in [0, 1]) at
        ``pixels`` (N, 2) of its ``size`` (width, height) image: the response inverted, noise
        and blur aside; clipped values stay clipped."""
        x = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0) ** self.gamma
        x = x @ np.linalg.inv(np.asarray(self.crosstalk, np.float64)).T
        x = x / (self.gain * np.asarray(self.white_balance))
        width, height = size
        u = pixels[:, 0] - (width - 1) / 2
        v = pixels[:, 1] - (height - 1) / 2
        r2 = (u ** 2 + v ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
        a, b = self.vignetting
        x = x / (1.0 - a * r2 - b * r2 ** 2)[:, None]
        return np.clip(x, 0.0, 1.0) ** (1.0 / IDEAL_RESPONSE.gamma)


IDEAL_RESPONSE = ColorResponse(gamma=2.2, read_noise=0.0, shot_noise=0.0, blur_sigma_px=0.0)


@functools.lru_cache(maxsize=16)
def _vignette(width: int, height: int, a: float, b: float) -> np.ndarray:
    """(H, W, 1) float32 radial fall-off 1 - a r^2 - b r^4, r = 1 at the corners (made once per camera)."""
    u, v = np.meshgrid(np.arange(width) - (width - 1) / 2, np.arange(height) - (height - 1) / 2)
    r2 = (u ** 2 + v ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    out = (1.0 - a * r2 - b * r2 ** 2).astype(np.float32)[:, :, None]
    out.flags.writeable = False
    return out


@dataclass
class DepthRender:
    depth_mm: np.ndarray   # uint16 what the sensor reports, 0 = invalid
    clean: np.ndarray      # float32 metres, noise-free z of the surface at each pixel centre, 0 = none
    flying: np.ndarray     # bool: a mixed pixel whose reported depth lies on no surface
    speckle: np.ndarray    # bool: interference outliers
    dropped: np.ndarray    # bool: a surface within range that the sensor did not report
    objects: np.ndarray    # int64 object index at each pixel centre, -1 = none


class CameraRaycast:
    """One camera's rays through a scene split into static objects (rendered once and cached)
    and moving ones (subject, board: cast per frame, kept where nearer than the background)."""

    def __init__(self, static: SceneRaycaster, cam: CameraModel, T_world_cam: np.ndarray, rays_cam: np.ndarray):
        self.cam = cam
        self.R = T_world_cam[:3, :3].astype(np.float32)
        self.origin = T_world_cam[:3, 3].astype(np.float32)
        self.rays_cam = rays_cam.astype(np.float32)
        self.dirs = self.rays_cam.reshape(-1, 3) @ self.R.T
        self.unit_dirs = self.dirs / np.linalg.norm(self.dirs, axis=1, keepdims=True)
        self.static = static.cast(self.origin, self.dirs)
        self._static_radiance = None

    def _dynamic(self, dynamic: SceneRaycaster | None) -> Hits | None:
        return None if dynamic is None else dynamic.cast(self.origin, self.dirs, t_max=self.static.t)

    def color(self, dynamic: SceneRaycaster | None, lights: list[Light], ambient: float, response: 'ColorResponse',
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) uint8 image and (H, W) object index at each pixel centre."""
        if self._static_radiance is None:
            self._static_radiance = np.zeros((len(self.dirs), 3), np.float32)
            self._static_radiance[self.static.idx] = shade(self.static, self.origin, lights, ambient)
        radiance, obj = self._static_radiance, self.static.obj
        fg = self._dynamic(dynamic)
        if fg is not None and fg.idx.size:
            radiance = radiance.copy()
            radiance[fg.idx] = shade(fg, self.origin, lights, ambient)
            obj = np.where(fg.obj >= 0, fg.obj, obj)
        h, w = self.cam.height, self.cam.width
        return response.apply(radiance.reshape(h, w, 3), rng), obj.reshape(h, w)

    def depth(self, dynamic: SceneRaycaster | None, full: SceneRaycaster, tof: 'ToFModel',
              rng: np.random.Generator) -> DepthRender:
        h, w = self.cam.height, self.cam.width
        z, obj = self.static.t.copy(), self.static.obj.copy()
        cos_inc, ir = np.zeros(h * w, np.float32), np.zeros(h * w, np.float32)
        for hits in (self.static, self._dynamic(dynamic)):
            if hits is None or not hits.idx.size:
                continue
            z[hits.idx], obj[hits.idx] = hits.t[hits.idx], hits.obj[hits.idx]
            cos_inc[hits.idx] = np.abs(np.einsum('ij,ij->i', hits.normals, self.unit_dirs[hits.idx]))
            ir[hits.idx] = hits.albedo @ LUMA
        z, cos_inc, ir = z.reshape(h, w), cos_inc.reshape(h, w), ir.reshape(h, w)
        in_range = np.isfinite(z) & (z >= tof.min_range) & (z <= tof.max_range)
        clean = np.where(in_range, z, 0.0).astype(np.float32)
        p_dark = np.clip((tof.dark_albedo - ir) / tof.dark_albedo, 0.0, 1.0) * 0.9
        dropped = in_range & ((cos_inc < tof.grazing_cos) | (rng.random((h, w), dtype=np.float32) < p_dark))
        noise = rng.standard_normal((h, w), dtype=np.float32) * tof.sigma(clean)
        measured = np.where(in_range & ~dropped, clean + noise, 0.0).astype(np.float32)
        flying = self._mixed_pixels(z, measured, full, tof, rng)
        dropped &= ~flying   # a mixed pixel reports a depth even where its centre surface would not
        speckle = _speckle(measured, flying, tof, rng)
        depth_mm = depth_to_millimetres(measured)
        return DepthRender(depth_mm, clean, flying, speckle & (depth_mm > 0), dropped, obj.reshape(h, w))

    def _mixed_pixels(self, z, measured, full: SceneRaycaster, tof: 'ToFModel', rng) -> np.ndarray:
        """Where the 3x3 neighbourhood spans a depth step, the pixel footprint sees several
        surfaces and the sensor reports their amplitude-weighted depth; ``measured`` is updated
        in place and the pixels whose reported depth lies on no surface are returned."""
        h, w = z.shape
        # A step between surfaces (or against empty space), not the range gate cutting through a
        # continuous surface; the threshold grows with depth so that oblique floors are not steps.
        surface = np.where(np.isfinite(z), z, 100.0).astype(np.float32)
        kernel = np.ones((3, 3), np.uint8)
        step = cv2.dilate(surface, kernel) - cv2.erode(surface, kernel)
        cand_v, cand_u = np.nonzero((step > tof.edge_threshold * (1.0 + surface)) & (surface < tof.max_range + 0.5))
        flying = np.zeros((h, w), bool)
        if cand_v.size == 0:
            return flying
        s = tof.subsamples
        offs = (np.arange(s) + 0.5) / s - 0.5
        du, dv = np.meshgrid(offs, offs)
        sub_px = np.stack([cand_u[:, None] + du.ravel(), cand_v[:, None] + dv.ravel()], axis=2).reshape(-1, 2)
        # Camera rays vary smoothly over the image: interpolating the pixel-centre rays is exact
        # to ~1e-7 and far cheaper than undistorting every sub-sample.
        sub_rays = sample_bilinear(self.rays_cam, sub_px) @ self.R.T
        sh = full.cast(self.origin, sub_rays)
        zs = sh.t.reshape(-1, s * s)
        ok = np.isfinite(zs) & (zs >= tof.min_range) & (zs <= tof.max_range)
        amp = np.zeros(len(sub_rays), np.float32)
        unit = sub_rays[sh.idx] / np.linalg.norm(sub_rays[sh.idx], axis=1, keepdims=True)
        amp[sh.idx] = (sh.albedo @ LUMA) * np.abs(np.einsum('ij,ij->i', sh.normals, unit))
        amp = amp.reshape(-1, s * s)
        wgt = np.where(ok, amp / np.where(ok, zs, 1.0) ** 2, 0.0)
        wsum = wgt.sum(axis=1)
        has = wsum > 0
        mixed = np.where(has, (wgt * np.where(ok, zs, 0.0)).sum(axis=1) / np.where(has, wsum, 1.0), 0.0)
        gap = np.where(ok, np.abs(zs - mixed[:, None]), np.inf).min(axis=1)
        is_flying = has & (gap > np.maximum(0.01, 3 * tof.sigma(mixed))) & (rng.random(len(mixed)) < tof.flying_keep)
        fv, fu, zf = cand_v[is_flying], cand_u[is_flying], mixed[is_flying]
        measured[fv, fu] = zf + rng.standard_normal(zf.shape) * tof.sigma(zf)
        flying[fv, fu] = True
        return flying


def _speckle(measured: np.ndarray, flying: np.ndarray, tof: 'ToFModel', rng) -> np.ndarray:
    """Occasional multi-camera interference: a few small blobs of grossly wrong depth."""
    if rng.random() >= tof.speckle_prob:
        return np.zeros(measured.shape, bool)
    valid_v, valid_u = np.nonzero(measured > 0)
    if valid_v.size == 0:
        return np.zeros(measured.shape, bool)
    picks = rng.choice(valid_v.size, size=min(tof.speckle_blobs, valid_v.size), replace=False)
    labels = np.zeros(measured.shape, np.uint8)        # blob k drawn as k + 1
    for k, i in enumerate(picks):
        cv2.circle(labels, (int(valid_u[i]), int(valid_v[i])), int(rng.integers(1, 3)), k + 1, -1)
    offsets = np.concatenate([[0.0], rng.uniform(-0.3, 0.3, len(picks))]).astype(np.float32)
    speckle = (labels > 0) & (measured > 0) & ~flying
    measured[speckle] += offsets[labels[speckle]]
    return speckle
