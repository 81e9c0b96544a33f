"""TSDF fusion of one frame set (paper 000, Figs. 16 and 18): every camera's cleaned depth and
corrected colour integrated into an empty Open3D tensor VoxelBlockGrid, then the coloured mesh
extracted by marching cubes.

Open3D integrates with a pinhole model. The cameras here (Azure Kinect class) have lens
distortion, and the cleaned depth is registered to the distorted colour image, so each
camera's depth and colour are first remapped onto undistorted pinhole grids (``Rectifier``).
Only blocks inside the capture box are allocated, and the mesh is cut to the box, so walls a
camera sees never reach the output. The graph fuses in the studio frame, where the box stands
on the floor (the filter removes the floor itself with the clean plate).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numba
import numpy as np
import open3d as o3d
import open3d.core as o3c

from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput
from volcap_core.poses import convergence_point, invert, transform_points

from .config import FusionConfig, open3d_device  # noqa: F401 (FusionConfig re-exported)

DEPTH_SCALE = 10_000.0   # depth units per metre handed to Open3D (0.1 mm; 6.5 m at most)
FLOOR_SLACK = 0.02       # the capture box reaches this far below a studio floor (m)


@dataclass
class CameraView:
    """One camera of a frame set: cleaned depth registered to its colour camera, and colour.
    Both grids share the colour optical frame, at their own resolutions."""
    name: str
    depth_mm: np.ndarray           # (h, w) uint16 millimetres, 0 = no depth
    depth_model: CameraModel
    color: np.ndarray              # (H, W, 3) uint8 RGB
    color_model: CameraModel
    T_world_camera: np.ndarray     # (4, 4) colour optical frame -> world

    def __post_init__(self):
        if self.depth_mm.dtype != np.uint16 or self.depth_mm.ndim != 2:
            raise BadInput(f'{self.name}: depth must be (h, w) uint16 millimetres, got {self.depth_mm.dtype} '
                             f'{self.depth_mm.shape}')
        if self.depth_mm.shape != (self.depth_model.height, self.depth_model.width):
            raise BadInput(f'{self.name}: depth is {self.depth_mm.shape[1]}x{self.depth_mm.shape[0]} but its '
                             f'camera_info says {self.depth_model.width}x{self.depth_model.height}')
        if self.color.dtype != np.uint8 or self.color.shape != (self.color_model.height, self.color_model.width, 3):
            raise BadInput(f'{self.name}: colour must be {self.color_model.width}x{self.color_model.height} RGB '
                             f'uint8, got {self.color.dtype} {self.color.shape}')
        T = np.asarray(self.T_world_camera, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise BadInput(f'{self.name}: pose must be a finite 4x4 matrix')


@dataclass
class FusedModel:
    """The fused surface of one time step, in the frame of the fused views' poses (the studio
    frame in the graph)."""
    vertices: np.ndarray           # (N, 3) float32
    colors: np.ndarray             # (N, 3) uint8
    triangles: np.ndarray          # (M, 3) int32
    cameras: list[str] = field(default_factory=list)
    timings_ms: dict = field(default_factory=dict)
    # of the cameras' depth (a sample of it): the share outside the capture volume or beyond
    # depth_max, which the model cannot hold
    depth_left_out: float | None = None
    capture_volume: str = ''       # where the box came from: fixed, floor, converging cameras, data
    # voxels both steps saw, of them carried and in blocks that moved; restarted: the last step
    # was not used (the first, a new take, a camera or the box moved); empty: the carry is off
    carried: dict = field(default_factory=dict)

    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        return raycasting_scene(self.vertices, self.triangles)

    def legacy_mesh(self) -> o3d.geometry.TriangleMesh:
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices.astype(np.float64)),
                                         o3d.utility.Vector3iVector(self.triangles))
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.colors.astype(np.float64) / 255.0)
        return mesh


def raycasting_scene(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An Open3D ray-casting / distance scene of one triangle mesh."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32)))
    return scene


def surface_depth(scene: o3d.t.geometry.RaycastingScene, camera: CameraModel, T_world_camera: np.ndarray
                  ) -> np.ndarray:
    """(H, W) float32 depth (m, along the optical axis) of the scene's nearest surface through
    every pixel of ``camera`` at ``T_world_camera`` (a pose in the scene's frame), 0 where a
    ray meets nothing. The rays are the camera's own (``pixel_rays``, lens distortion
    included), so the depth lies on that camera's pixel grid."""
    T = np.asarray(T_world_camera, np.float64)
    rays = camera.pixel_rays().reshape(-1, 3)          # z = 1: a hit's distance is its depth
    cast = np.empty((len(rays), 6), np.float32)
    cast[:, :3] = T[:3, 3]
    cast[:, 3:] = rays @ T[:3, :3].T
    t = scene.cast_rays(o3c.Tensor(cast))['t_hit'].numpy()
    return np.where(np.isfinite(t), t, 0.0).astype(np.float32).reshape(camera.height, camera.width)


def pinhole(model: CameraModel) -> CameraModel:
    """The undistorted pinhole camera with the same size and intrinsics."""
    return CameraModel(model.width, model.height, model.fx, model.fy, model.cx, model.cy)


@dataclass
class RectifiedView:
    """One camera's depth (uint16, ``DEPTH_SCALE`` units) and colour on undistorted pinhole grids,
    cropped to where there is depth, with the intrinsics of the crops."""
    depth: np.ndarray
    depth_K: np.ndarray
    color: np.ndarray
    color_K: np.ndarray


class Rectifier:
    """Puts one camera's images in the form Open3D integrates: pinhole (Open3D has no lens
    distortion), cropped to the pixels with depth (remapping the whole frame would cost more
    than integrating the subject), depth on a grid ``scale`` times finer.

    Open3D reads the depth of the pixel nearest to each voxel's projection, so on a slanted
    surface the signed distance steps by up to half a pixel's footprint. The finer grid is
    interpolated bilinearly where the source pixels around a sample lie on one surface (within
    ``edge_tolerance`` metres plus 1 %); at a silhouette the nearest pixel is kept, so nothing
    is blended across it. Maps are made once per camera.

    When the depth is registered at the colour camera's own resolution (``scale`` 1, as
    `volcap run` has the filters publish it), depth and colour share one grid: the colour is
    picked in the same pass, and only under pixels with depth, the only ones Open3D reads.
    """

    MARGIN_PX = 4

    def __init__(self, depth_model: CameraModel, color_model: CameraModel, scale: int = 1,
                 edge_tolerance: float = 0.02):
        self.depth_model, self.color_model = depth_model, color_model
        self.target = pinhole(depth_model.scaled(depth_model.width * scale, depth_model.height * scale))
        self.edge_tolerance = edge_tolerance
        self.map_x, self.map_y = cv2.initUndistortRectifyMap(depth_model.K, depth_model.D, None, self.target.K,
                                                             (self.target.width, self.target.height), cv2.CV_32FC1)
        self.shared_grid = scale == 1 and same_grid(depth_model, color_model)
        self.color_map = None
        if any(d != 0.0 for d in color_model.dist) and not self.shared_grid:
            # Integer maps of the nearest pixel. (A CV_16SC2 map straight from
            # initUndistortRectifyMap is the fixed-point form for bilinear remapping: with
            # INTER_NEAREST it picks a neighbouring pixel, not the nearest.)
            map_x, map_y = cv2.initUndistortRectifyMap(color_model.K, color_model.D, None, color_model.K,
                                                       (color_model.width, color_model.height), cv2.CV_32FC1)
            self.color_map = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2, nninterpolation=True)[0]

    def __call__(self, depth_mm: np.ndarray, color: np.ndarray) -> RectifiedView | None:
        """Depth in uint16 millimetres, colour RGB; None when the depth has no valid pixel."""
        roi = self._target_roi(depth_mm > 0)
        if roi is None:
            return None
        x0, y0, x1, y1 = roi
        depth_units = np.zeros((y1 - y0, x1 - x0), np.uint16)
        depth_K = _shifted(self.target.K, x0, y0)
        color_crop = np.zeros((y1 - y0, x1 - x0, 3), np.uint8) if self.shared_grid else _NO_COLOR
        _resample(depth_mm, color, self.map_x, self.map_y, x0, y0, depth_units, color_crop,
                  np.float32(self.edge_tolerance * 1000.0), np.float32(DEPTH_SCALE / 1000.0))
        if self.shared_grid:
            return RectifiedView(depth_units, depth_K, color_crop, depth_K)
        # The colour pixels that see the same rays (both grids share the colour optical frame).
        t, c = self.target, self.color_model
        cx0 = int(np.clip(np.floor(c.fx * (x0 - t.cx) / t.fx + c.cx) - self.MARGIN_PX, 0, c.width - 1))
        cx1 = int(np.clip(np.ceil(c.fx * (x1 - 1 - t.cx) / t.fx + c.cx) + self.MARGIN_PX + 1, cx0 + 1, c.width))
        cy0 = int(np.clip(np.floor(c.fy * (y0 - t.cy) / t.fy + c.cy) - self.MARGIN_PX, 0, c.height - 1))
        cy1 = int(np.clip(np.ceil(c.fy * (y1 - 1 - t.cy) / t.fy + c.cy) + self.MARGIN_PX + 1, cy0 + 1, c.height))
        if self.color_map is None:
            color_crop = np.ascontiguousarray(color[cy0:cy1, cx0:cx1])
        else:
            color_crop = cv2.remap(color, self.color_map[cy0:cy1, cx0:cx1], None, cv2.INTER_NEAREST,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return RectifiedView(depth_units, depth_K, color_crop, _shifted(c.K, cx0, cy0))

    def _target_roi(self, valid: np.ndarray) -> tuple[int, int, int, int] | None:
        """(x0, y0, x1, y1) of the target grid that covers the valid source pixels."""
        rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
        if rows.size == 0:
            return None
        m = self.MARGIN_PX
        sx0, sx1, sy0, sy1 = cols[0] - m, cols[-1] + m, rows[0] - m, rows[-1] + m
        # The source box's outline taken through the undistortion: lens distortion bends straight
        # edges, so points along them, not just the corners.
        edge = np.linspace(0.0, 1.0, 16)
        xs, ys = sx0 + (sx1 - sx0) * edge, sy0 + (sy1 - sy0) * edge
        outline = np.concatenate([np.stack([xs, np.full_like(xs, sy0)], 1), np.stack([xs, np.full_like(xs, sy1)], 1),
                                  np.stack([np.full_like(ys, sx0), ys], 1), np.stack([np.full_like(ys, sx1), ys], 1)])
        xy = self.depth_model.undistort_pixels(outline)
        t = self.target
        u, v = t.fx * xy[:, 0] + t.cx, t.fy * xy[:, 1] + t.cy
        x0, x1 = int(max(np.floor(u.min()) - m, 0)), int(min(np.ceil(u.max()) + m + 1, t.width))
        y0, y1 = int(max(np.floor(v.min()) - m, 0)), int(min(np.ceil(v.max()) + m + 1, t.height))
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def same_grid(a: CameraModel, b: CameraModel) -> bool:
    """Whether two camera models describe the same pixel grid (size, intrinsics and lens, to
    within what a camera_info round trip changes)."""
    if (a.width, a.height) != (b.width, b.height) or len(a.dist) != len(b.dist):
        return False
    return bool(np.allclose(a.K, b.K, rtol=0.0, atol=1e-6) and np.allclose(a.D, b.D, rtol=0.0, atol=1e-9))


_NO_COLOR = np.zeros((0, 0, 3), np.uint8)   # colour output of a pass that picks none


@numba.njit(cache=True)
def _resample(depth_mm, color, map_x, map_y, x0, y0, depth_out, color_out, tolerance_mm, units_per_mm):
    """Depth (uint16 mm) sampled at (map_x, map_y) over the target grid from row y0, column x0,
    into ``depth_out`` in ``DEPTH_SCALE`` units: bilinear where the four source pixels are valid
    and within ``tolerance_mm`` (+1 %) of each other, the nearest pixel otherwise. (Open3D takes
    uint16 depth with uint8 colour; units finer than a millimetre keep the interpolation.) Where
    there is depth and ``color_out`` is not empty, the nearest colour pixel goes to it."""
    h, w = depth_mm.shape
    with_color = color_out.shape[0] > 0
    half = np.float32(0.5)
    x_end, y_end = np.float32(w - 0.5), np.float32(h - 0.5)
    for r in range(depth_out.shape[0]):
        row_x, row_y = map_x[y0 + r], map_y[y0 + r]
        for c in range(depth_out.shape[1]):
            x, y = row_x[x0 + c], row_y[x0 + c]
            if not (x > -half and y > -half and x < x_end and y < y_end):
                continue
            # x, y > -0.5 here, so int() truncation is floor() (and far cheaper)
            ny, nx = int(y + half), int(x + half)
            nearest = depth_mm[ny, nx]
            if nearest == 0:        # no depth here: nothing to interpolate (most of a crop)
                continue
            ix, iy = min(int(x), w - 2), min(int(y), h - 2)
            fx = min(max(x - np.float32(ix), np.float32(0.0)), np.float32(1.0))
            fy = min(max(y - np.float32(iy), np.float32(0.0)), np.float32(1.0))
            a, b = np.float32(depth_mm[iy, ix]), np.float32(depth_mm[iy, ix + 1])
            cc, d = np.float32(depth_mm[iy + 1, ix]), np.float32(depth_mm[iy + 1, ix + 1])
            lo, hi = min(min(a, b), min(cc, d)), max(max(a, b), max(cc, d))
            if lo > 0 and hi - lo <= tolerance_mm + np.float32(0.01) * hi:
                z = (a * (1 - fx) + b * fx) * (1 - fy) + (cc * (1 - fx) + d * fx) * fy
            else:
                z = np.float32(nearest)
            depth_out[r, c] = min(np.float32(65535.0), z * units_per_mm + half)
            if with_color:
                for k in range(3):
                    color_out[r, c, k] = color[ny, nx, k]


def _shifted(K: np.ndarray, x0: int, y0: int) -> np.ndarray:
    """Intrinsics of an image cropped at (x0, y0)."""
    out = K.copy()
    out[0, 2] -= x0
    out[1, 2] -= y0
    return out


class TsdfFusion:
    """Fuses frame sets. Each time step is integrated into an empty volume; with ``carry_decay``
    the voxels that held still since the last step are then averaged with it (``carry``), so
    that volume is kept until the next step. The volumes' memory and the per-camera maps are
    kept between steps: allocating a 40 000-block grid costs more than integrating eight
    cameras into it."""

    def __init__(self, cfg: FusionConfig | None = None):
        self.cfg = cfg or FusionConfig()
        self.cfg.validate()
        self.device = o3c.Device(open3d_device(self.cfg.device))
        self._rectifiers: dict[tuple[CameraModel, CameraModel], Rectifier] = {}
        self._spare: o3d.t.geometry.VoxelBlockGrid | None = None      # the next step's memory
        self._previous: o3d.t.geometry.VoxelBlockGrid | None = None   # the last step's volume (carry)
        self._previous_key: tuple | None = None
        self._previous_wobble = None                                   # carry.BlockWobble of the last step
        self._previous_stamp: int | None = None

    def rectifier(self, view: CameraView) -> Rectifier:
        key = (view.depth_model, view.color_model)
        if key not in self._rectifiers:
            self._rectifiers[key] = Rectifier(*key, self.cfg.depth_upsample, self.cfg.edge_tolerance)
        return self._rectifiers[key]

    def empty_volume(self) -> o3d.t.geometry.VoxelBlockGrid:
        """The kept spare volume with every block removed."""
        if self._spare is None:
            self._spare = self.new_volume()
            return self._spare
        hashmap = self._spare.hashmap()
        active = hashmap.active_buf_indices().to(o3c.int64)
        if active.shape[0]:
            # Re-activated blocks keep their old values: a zero weight makes the next
            # integration overwrite tsdf and colour, and keeps unobserved voxels out of the mesh.
            if self.device.get_type() == o3c.Device.CPU:
                hashmap.value_tensor(1).numpy()[active.numpy()] = 0.0
            else:
                hashmap.value_tensor(1)[active] = 0.0
            hashmap.erase(hashmap.key_tensor()[active])
        return self._spare

    def forget(self) -> None:
        """The next step carries nothing over (a new take, a scene cut)."""
        self._previous_key = None

    def _carry(self, volume: o3d.t.geometry.VoxelBlockGrid, views: list[CameraView],
               box: tuple[np.ndarray, np.ndarray], stamp_ns: int | None) -> dict:
        """Averages the last step into ``volume`` where it held still (``carry.carry_over``) when
        both share the capture box, every camera in both kept its pose and (with stamps) this
        step follows the last within ``carry_max_gap_s``; then ``volume`` becomes the last step
        and the last one's memory the spare."""
        from .carry import carry_over  # torch: loaded only when the carry is on
        key = (np.concatenate(box).tobytes(), {v.name: np.asarray(v.T_world_camera, np.float64).tobytes()
                                               for v in views})
        counts = {'seen_twice': 0, 'carried': 0, 'moved': 0, 'restarted': True}
        last, wobble = self._previous_key, None
        since = self._previous_stamp
        in_time = (stamp_ns is None or since is None
                   or 0 < stamp_ns - since <= self.cfg.carry_max_gap_s * 1e9)
        if (self._previous is not None and last is not None and last[0] == key[0] and in_time
                and all(last[1].get(name, pose) == pose for name, pose in key[1].items())):
            counts['restarted'] = False
            carried, wobble = carry_over(volume, self._previous, self.cfg.carry_decay, self.cfg.carry_reset_mm,
                                         self.cfg.trunc_voxels * self.cfg.voxel_size * 1e3, self._previous_wobble)
            counts |= carried
        self._spare, self._previous, self._previous_key = self._previous, volume, key
        self._previous_wobble = wobble
        self._previous_stamp = stamp_ns
        return counts

    def new_volume(self) -> o3d.t.geometry.VoxelBlockGrid:
        cfg = self.cfg
        return o3d.t.geometry.VoxelBlockGrid(
            attr_names=('tsdf', 'weight', 'color'), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)), voxel_size=cfg.voxel_size, block_resolution=cfg.block_resolution,
            block_count=cfg.block_count, device=self.device)

    def capture_box(self, views: list[CameraView], on_floor: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the capture box in the frame of the views' poses."""
        return self.capture_volume(views, on_floor)[:2]

    def capture_volume(self, views: list[CameraView], on_floor: bool = False
                       ) -> tuple[np.ndarray, np.ndarray, str]:
        """(min, max, source) of the capture box in the frame of the views' poses. ``box_center``
        set: that box. ``on_floor``: that frame is the studio frame (+Z up, z = 0 on the floor),
        and the box stands on the floor (``FLOOR_SLACK`` below it, so soles resting on it are
        kept) around the z axis. Otherwise the box around the point the cameras converge on,
        when they do (it lies in front of every camera, in its image and range); else, or with
        ``capture_volume`` 'data', the bounds of all the views' depth."""
        half = np.asarray(self.cfg.box_size, float) / 2
        if self.cfg.box_center is not None:
            centre = np.asarray(self.cfg.box_center, float)
            return centre - half, centre + half, 'fixed'
        if on_floor:
            centre = np.array([0.0, 0.0, half[2] - FLOOR_SLACK])
            return centre - half, centre + half, 'studio floor'
        centre = None if self.cfg.capture_volume == 'data' else converging_point(views, self.cfg.depth_max)
        if centre is not None:
            return centre - half, centre + half, 'converging cameras'
        points = np.vstack([sampled_depth_points(v, self.cfg.depth_max) for v in views])
        if not len(points):
            return -half, half, 'no depth'
        margin = self.cfg.trunc_voxels * self.cfg.voxel_size
        return points.min(axis=0) - margin, points.max(axis=0) + margin, 'depth bounds'

    def integrate(self, volume: o3d.t.geometry.VoxelBlockGrid, view: CameraView, box: tuple[np.ndarray, np.ndarray]
                  ) -> int:
        """Integrates one camera into ``volume`` within ``box``; returns the number of blocks it touched."""
        cfg = self.cfg
        rectified = self.rectifier(view)(view.depth_mm, view.color)
        if rectified is None:
            return 0
        depth = o3d.t.geometry.Image(o3c.Tensor.from_numpy(rectified.depth)).to(self.device)
        color = o3d.t.geometry.Image(o3c.Tensor.from_numpy(rectified.color)).to(self.device)
        depth_k, color_k = o3c.Tensor(rectified.depth_K), o3c.Tensor(rectified.color_K)
        extrinsic = o3c.Tensor(invert(np.asarray(view.T_world_camera, np.float64)), o3c.float64)
        blocks = volume.compute_unique_block_coordinates(depth, depth_k, extrinsic, DEPTH_SCALE, cfg.depth_max,
                                                         cfg.trunc_voxels)
        blocks = self._inside(blocks, box)
        if blocks.shape[0] == 0:
            return 0
        volume.integrate(blocks, depth, color, depth_k, color_k, extrinsic, DEPTH_SCALE, cfg.depth_max,
                         cfg.trunc_voxels)
        return int(blocks.shape[0])

    def _inside(self, blocks: o3c.Tensor, box: tuple[np.ndarray, np.ndarray]) -> o3c.Tensor:
        # Blocks whose cube touches the box, in block coordinates (floor of metres / block edge).
        edge = self.cfg.voxel_size * self.cfg.block_resolution
        lo, hi = np.floor(box[0] / edge).astype(np.int32), np.floor(box[1] / edge).astype(np.int32)
        if blocks.device.get_type() == o3c.Device.CPU:
            # numpy: each Open3D tensor operation costs ~0.1 ms at a few thousand blocks
            b = blocks.numpy()
            return o3c.Tensor(b[((b >= lo) & (b <= hi)).all(axis=1)])
        lo, hi = o3c.Tensor(lo, device=blocks.device), o3c.Tensor(hi, device=blocks.device)
        return blocks[((blocks >= lo) & (blocks <= hi)).all(dim=1)]

    def extract(self, volume: o3d.t.geometry.VoxelBlockGrid, box: tuple[np.ndarray, np.ndarray], cameras: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices, uint8 colours, triangles) of the zero level set, cut to the capture box."""
        mesh = volume.extract_triangle_mesh(weight_threshold=effective_weight_threshold(self.cfg.weight_threshold,
                                                                                        cameras)).cpu()
        if 'positions' not in mesh.vertex or mesh.vertex.positions.shape[0] == 0 or 'indices' not in mesh.triangle:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.int32)
        vertices = mesh.vertex.positions.numpy()
        colors = mesh.vertex.colors.numpy() if 'colors' in mesh.vertex else np.zeros_like(vertices)
        triangles = mesh.triangle.indices.numpy().astype(np.int32)
        return crop_to_box(vertices, colors_to_uint8(colors), triangles, *box)

    def fuse(self, views: list[CameraView], on_floor: bool = False, stamp_ns: int | None = None) -> FusedModel:
        """One time step: an empty volume, every view integrated, the still part of the last
        step carried over (``carry_decay``), the mesh extracted (in the frame of the views'
        poses; ``on_floor``: see ``capture_box``). ``stamp_ns``, the frame set's stamp: one more
        than ``carry_max_gap_s`` after the last step, or not after it, carries nothing."""
        if not views:
            raise BadInput('no camera to fuse')
        t0 = time.perf_counter()
        *box, source = self.capture_volume(views, on_floor)
        left_out = depth_left_out(views, box, self.cfg.depth_max)
        volume = self.empty_volume()
        seen = sum(self.integrate(volume, view, box) > 0 for view in views)
        t1 = time.perf_counter()
        timings = {'integrate': (t1 - t0) * 1e3}
        carried = self._carry(volume, views, box, stamp_ns) if self.cfg.carry_decay > 0 else {}
        t2 = time.perf_counter()
        if self.cfg.carry_decay > 0:
            timings['carry'] = (t2 - t1) * 1e3
        if seen == 0:
            # An empty stage is a state, not a failure: an empty model the caller reports.
            empty = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.int32)
            return FusedModel(*empty, [v.name for v in views], {**timings, 'extract': 0.0}, left_out, source,
                              carried)
        vertices, colors, triangles = self.extract(volume, box, seen)
        timings['extract'] = (time.perf_counter() - t2) * 1e3
        return FusedModel(vertices, colors, triangles, [v.name for v in views], timings, left_out, source, carried)


DEPTH_SAMPLE_STRIDE = 8     # every 8th pixel each way: the box and the left-out share, at ~0.1 ms a camera


@lru_cache(maxsize=64)
def _sample_rays(model: CameraModel, stride: int) -> np.ndarray:
    rays = model.pixel_rays()[::stride, ::stride].astype(np.float32)
    rays.flags.writeable = False
    return rays


def sampled_depth_points(view: CameraView, depth_max: float | None = None,
                         stride: int = DEPTH_SAMPLE_STRIDE) -> np.ndarray:
    """(N, 3) world points of every ``stride``-th depth pixel each way (within ``depth_max``)."""
    depth = view.depth_mm[::stride, ::stride].astype(np.float32) / 1000
    valid = depth > 0
    if depth_max is not None:
        valid &= depth <= depth_max
    local = _sample_rays(view.depth_model, stride)[valid] * depth[valid, None]
    return transform_points(view.T_world_camera, local)


def depth_left_out(views: list[CameraView], box, depth_max: float) -> float:
    """The share of the views' depth (sampled) beyond ``depth_max`` or outside ``box``."""
    total = kept = 0
    for view in views:
        total += int(np.count_nonzero(view.depth_mm[::DEPTH_SAMPLE_STRIDE, ::DEPTH_SAMPLE_STRIDE]))
        points = sampled_depth_points(view, depth_max)
        kept += int(np.count_nonzero(np.all((points >= box[0]) & (points <= box[1]), axis=1)))
    return 1.0 - kept / total if total else 0.0


def converging_point(views: list[CameraView], depth_max: float) -> np.ndarray | None:
    """The point the cameras converge on, or None when they do not: it must lie in front of
    every camera within ``depth_max`` and inside its image (a ring of cameras round a subject;
    not a camera moved through a room, nor one camera alone)."""
    try:
        point = convergence_point([v.T_world_camera for v in views])
    except ValueError:
        return None
    for v in views:
        local = transform_points(invert(v.T_world_camera), point[None])[0]
        if not 0 < local[2] <= depth_max:
            return None
        u, w = v.depth_model.project(local[None])[0]
        if not (0 <= u < v.depth_model.width and 0 <= w < v.depth_model.height):
            return None
    return point


def effective_weight_threshold(weight_threshold: float, cameras: int) -> float:
    """Open3D meshes voxels whose weight (one per camera that saw them) is above the threshold:
    capped at one below the cameras fused, so fewer cameras than the threshold still mesh."""
    return max(0.0, min(weight_threshold, cameras - 1.0))


def colors_to_uint8(colors: np.ndarray) -> np.ndarray:
    """Open3D's 0-1 vertex colours (it integrates uint8 colour as 0-255 and divides by 255 when
    it extracts the mesh) as uint8."""
    return np.clip(np.round(colors * 255.0), 0, 255).astype(np.uint8)


def crop_to_box(vertices: np.ndarray, colors: np.ndarray, triangles: np.ndarray, box_min, box_max
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh without the triangles that have a vertex outside the box, vertices re-indexed."""
    inside = np.all((vertices >= np.asarray(box_min, np.float32)) & (vertices <= np.asarray(box_max, np.float32)),
                    axis=1)
    if inside.all():
        return vertices, colors, triangles
    keep_tri = inside[triangles].all(axis=1)
    new_index = np.cumsum(inside) - 1
    return vertices[inside], colors[inside], new_index[triangles[keep_tri]].astype(np.int32)


def bare_open3d_fusion(views: list[CameraView], cfg: FusionConfig, volume: o3d.t.geometry.VoxelBlockGrid | None = None
                       ) -> FusedModel:
    """The textbook Open3D integration of the same views, for comparison: each image as it
    comes, pinhole intrinsics (lens distortion ignored), no crop, no capture box; a fresh
    volume unless ``volume`` is given."""
    vbg = volume if volume is not None else TsdfFusion(cfg).new_volume()
    for v in views:
        depth, color = o3d.t.geometry.Image(o3c.Tensor(v.depth_mm)), o3d.t.geometry.Image(o3c.Tensor(v.color))
        depth_k, color_k = o3c.Tensor(v.depth_model.K), o3c.Tensor(v.color_model.K)
        extrinsic = o3c.Tensor(invert(np.asarray(v.T_world_camera, np.float64)))
        blocks = vbg.compute_unique_block_coordinates(depth, depth_k, extrinsic, 1000.0, cfg.depth_max,
                                                      cfg.trunc_voxels)
        vbg.integrate(blocks, depth, color, depth_k, color_k, extrinsic, 1000.0, cfg.depth_max, cfg.trunc_voxels)
    mesh = vbg.extract_triangle_mesh(weight_threshold=effective_weight_threshold(cfg.weight_threshold,
                                                                                   len(views))).cpu()
    if 'indices' not in mesh.triangle:
        return FusedModel(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.int32))
    return FusedModel(mesh.vertex.positions.numpy(), colors_to_uint8(mesh.vertex.colors.numpy()),
                      mesh.triangle.indices.numpy().astype(np.int32), [v.name for v in views])
