"""The rig pipeline, offline: frame sets fused into models without the graph.

- ``raw_fusion``: a bag's frame set fused straight from the raw streams (nothing removed, raw
  colour), the "before" of paper 000's Figs. 16 and 18 in `volcap run`'s raw-vs-clean figure.
- ``fuse_folder`` (`volcap fuse-frames FOLDER`): the ``frame-NNNNNN.{color.png,depth.png,pose.txt}``
  layout (one moving camera, e.g. ``../shared/data/rgbd_box``) fused with ``TsdfFusion``, beside
  a bare Open3D integration of the same frames (``bare_open3d_fusion``) for comparison, with how
  much of the measured depth each mesh keeps.
"""
from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from volcap_core.camera import CameraModel, depth_to_millimetres
from volcap_core.errors import BadInput
from volcap_core.files import write_json
from volcap_fusion.sequence import write_ply
from volcap_fusion.tsdf import (
    CameraView,
    FusedModel,
    FusionConfig,
    TsdfFusion,
    bare_open3d_fusion,
    sampled_depth_points,
)


def raw_fusion(bag: str | Path, stamp_ns: int, T_world_color: dict[str, np.ndarray], cfg: FusionConfig,
               on_floor: bool = False, tolerance_ns: int = 20_000_000) -> FusedModel:
    """The frame set of ``bag`` at ``stamp_ns`` fused as it left the cameras (the "before" of
    paper 000, Figs. 16 and 18): raw depth registered to colour with nothing removed, raw colour.
    ``T_world_color`` places the cameras in the output frame (``on_floor``: the studio frame)."""
    from volcap_core.bag_reader import BagReader
    from volcap_core.frames import frame_sets, read_rig
    from volcap_core.topics import CAPTURE
    from volcap_filter.registration import DepthRegistration
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    for fs in frame_sets(bag, phases=(CAPTURE,)):
        if abs(fs.stamp_ns - stamp_ns) > tolerance_ns:
            continue
        views = []
        for name, f in fs.cameras.items():
            if name not in T_world_color:
                continue
            c = f.color_model
            registered = DepthRegistration(f.depth_model, c, rig.camera(name).T_color_depth,
                                           (c.width, c.height)).register(f.depth).depth
            depth_mm = depth_to_millimetres(registered)
            views.append(CameraView(name, depth_mm, c, f.color, c, T_world_color[name]))
        return TsdfFusion(cfg).fuse(views, on_floor)
    raise BadInput(f'{bag} has no capture frame set at {stamp_ns} ns')


# posed RGB-D frame folders ------------------------------------------------------------------
def read_frames_folder(folder: str | Path, intrinsics: str | Path, stride: int = 1
                       ) -> tuple[CameraModel, CameraModel, list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]]:
    """(depth model, colour model, [(name, depth mm, rgb, T_world_camera)]) of a frame folder."""
    folder = Path(folder)
    K = np.loadtxt(intrinsics)
    if K.shape != (3, 3):
        raise BadInput(f'{intrinsics}: expected a 3x3 intrinsic matrix')
    names = sorted(p.name[:-len('.color.png')] for p in folder.glob('frame-*.color.png'))[::stride]
    if not names:
        raise FileNotFoundError(f'{folder} has no frame-NNNNNN.color.png')
    frames = []
    for name in names:
        color = cv2.imread(str(folder / f'{name}.color.png'), cv2.IMREAD_COLOR)
        depth = cv2.imread(str(folder / f'{name}.depth.png'), cv2.IMREAD_UNCHANGED)
        if color is None or depth is None or depth.dtype != np.uint16:
            raise BadInput(f'{folder / name}: colour PNG and 16-bit depth PNG expected')
        pose = np.loadtxt(folder / f'{name}.pose.txt')
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise BadInput(f'{folder / name}.pose.txt: expected a finite 4x4 camera-to-world matrix')
        frames.append((name, depth, cv2.cvtColor(color, cv2.COLOR_BGR2RGB), pose))
    h, w = frames[0][1].shape
    depth_model = CameraModel(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    ch, cw = frames[0][2].shape[:2]
    color_model = depth_model if (ch, cw) == (h, w) else depth_model.scaled(cw, ch)
    return depth_model, color_model, frames


def fuse_frames(folder: str | Path, intrinsics: str | Path, cfg: FusionConfig, stride: int = 1
                ) -> tuple[FusedModel, FusedModel, list[CameraView]]:
    """(ours, bare Open3D, the views) for a frame folder. Each frame is one camera of a static
    rig: all are fused into one volume. The bare integration is not cut to our capture box, so
    the comparison sees whatever the box leaves out."""
    depth_model, color_model, frames = read_frames_folder(folder, intrinsics, stride)
    views = [CameraView(n, d, depth_model, c, color_model, T) for n, d, c, T in frames]
    return TsdfFusion(cfg).fuse(views), bare_open3d_fusion(views, cfg), views


def depth_kept(model: FusedModel, views: list[CameraView], within: float = 0.02) -> float:
    """The share of the views' depth points (every ``DEPTH_SAMPLE_STRIDE``-th pixel each way,
    all ranges) within ``within`` metres of the mesh: how much of what the cameras measured
    the model holds."""
    points = np.vstack([sampled_depth_points(v) for v in views]).astype(np.float32)
    if not len(points) or not len(model.triangles):
        return 0.0
    distance = model.raycasting_scene().compute_distance(o3d.core.Tensor(points)).numpy()
    return float(np.mean(distance <= within))


def surface_distance(a: FusedModel, b: FusedModel) -> dict:
    """Symmetric vertex-to-surface distances between two meshes (mm)."""
    ab = b.raycasting_scene().compute_distance(o3d.core.Tensor(a.vertices.astype(np.float32))).numpy()
    ba = a.raycasting_scene().compute_distance(o3d.core.Tensor(b.vertices.astype(np.float32))).numpy()
    both = np.concatenate([ab, ba]) * 1000
    return {'mean_mm': float(both.mean()), 'median_mm': float(np.median(both)),
            'p95_mm': float(np.percentile(both, 95)), 'ours_to_bare_mean_mm': float(ab.mean() * 1000),
            'bare_to_ours_mean_mm': float(ba.mean() * 1000)}


def fuse_folder(folder: str | Path, intrinsics: str | Path, cfg: FusionConfig, out: str | Path, stride: int = 1
                ) -> dict:
    """`volcap fuse-frames`: the folder fused into ``out`` (PLY), compared with a bare Open3D
    integration; a render of both (PNG) and the report (JSON) are written beside it."""
    from .render import render_rows
    t0 = time.monotonic()
    ours, bare, views = fuse_frames(folder, intrinsics, cfg, stride=stride)
    out = Path(out)
    write_ply(out, ours)
    comparison = surface_distance(ours, bare)
    poses = [v.T_world_camera for v in views]
    render = render_rows([('volcap', ours), ('bare Open3D', bare)], poses, out.with_suffix('.png'))
    report = {'frames': len(poses), 'voxel_size': cfg.voxel_size, 'vertices': len(ours.vertices),
              'triangles': len(ours.triangles), 'bare_vertices': len(bare.vertices),
              'capture_volume': ours.capture_volume, 'depth_left_out': ours.depth_left_out,
              'depth_within_2cm': depth_kept(ours, views), 'bare_depth_within_2cm': depth_kept(bare, views),
              'distance_to_bare_open3d': comparison, 'seconds': time.monotonic() - t0, 'render': str(render)}
    write_json(out.with_suffix('.json'), report)
    return report
