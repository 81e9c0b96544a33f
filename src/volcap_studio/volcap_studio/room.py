"""A room scanned by one moving RGB-D camera, as a posed frame folder (the ``rgbd_box`` layout:
``frame-NNNNNN.{color.png,depth.png,pose.txt}`` and ``intrinsics.K.txt``).

The opposite of the studio: the camera stands inside the scene and turns round, looking out
at walls, floor and furniture, so its optical axes never converge on a subject. It is the case
``volcap fuse-frames`` must hold whole.

    write_room_frames('room', RoomConfig(frames=36))
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from volcap_core.files import atomic_write
from volcap_core.poses import look_at


@dataclass
class RoomConfig:
    frames: int = 36
    size: tuple[float, float, float] = (5.0, 4.0, 2.6)   # x, y, height (m)
    width: int = 640
    height: int = 480
    focal: float = 525.0
    depth_noise_m: float = 0.002
    seed: int = 0


def room_mesh(cfg: RoomConfig) -> tuple[o3d.t.geometry.RaycastingScene, np.ndarray]:
    """The room (walls, floor, ceiling, a table, a cabinet and a box) as a ray-casting scene and
    (T, 3) uint8 colours per triangle: every surface its own colour, with a checker pattern
    written into neighbouring triangles so that colour varies along each surface."""
    sx, sy, sz = cfg.size
    parts = []
    room = o3d.geometry.TriangleMesh.create_box(sx, sy, sz).translate((-sx / 2, -sy / 2, 0))
    room = o3d.geometry.TriangleMesh(room.vertices, o3d.utility.Vector3iVector(np.asarray(room.triangles)[:, ::-1]))
    parts.append((room.subdivide_midpoint(3), (200, 190, 170)))
    for size, centre, colour in (((1.2, 0.8, 0.75), (1.0, 0.6, 0.0), (140, 90, 50)),
                                 ((0.5, 1.4, 1.9), (-2.2, -1.0, 0.0), (60, 110, 160)),
                                 ((0.4, 0.4, 0.3), (1.1, 0.5, 0.75), (200, 40, 40))):
        box = o3d.geometry.TriangleMesh.create_box(*size).translate(
            (centre[0] - size[0] / 2, centre[1] - size[1] / 2, centre[2]))
        parts.append((box.subdivide_midpoint(2), colour))
    scene = o3d.t.geometry.RaycastingScene()
    colours = []
    for mesh, colour in parts:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        shade = np.where(np.arange(len(mesh.triangles)) % 4 < 2, 1.0, 0.75)
        colours.append(np.clip(np.outer(shade, colour), 0, 255).astype(np.uint8))
    return scene, np.vstack(colours)


def camera_poses(cfg: RoomConfig) -> list[np.ndarray]:
    """T_world_camera (optical frame) of each frame: one turn round near the room's middle,
    at standing height, looking out and slightly down."""
    rng = np.random.default_rng(cfg.seed)
    out = []
    for k in range(cfg.frames):
        yaw = 2 * np.pi * k / cfg.frames
        eye = np.array([0.3 * np.cos(yaw / 2), 0.2 * np.sin(yaw), 1.5]) + rng.normal(0, 0.02, 3)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), -0.35])
        out.append(look_at(eye, target))
    return out


def write_room_frames(out: str | Path, cfg: RoomConfig = RoomConfig()) -> Path:
    """Render the room from every pose into ``out`` (created); returns it."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene, colours = room_mesh(cfg)
    K = np.array([[cfg.focal, 0, (cfg.width - 1) / 2], [0, cfg.focal, (cfg.height - 1) / 2], [0, 0, 1]])
    rng = np.random.default_rng(cfg.seed + 1)
    atomic_write(out / 'intrinsics.K.txt', lambda f: np.savetxt(f, K, fmt='%.6f'), binary=False)
    for k, T in enumerate(camera_poses(cfg)):
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(K), o3d.core.Tensor(np.linalg.inv(T)), cfg.width, cfg.height)
        hit = scene.cast_rays(rays)
        t = hit['t_hit'].numpy()
        direction = rays.numpy()[..., 3:]
        z = t * (direction @ T[:3, 2])      # the hit's distance along the optical axis
        z = z + rng.normal(0, cfg.depth_noise_m, z.shape)
        depth = np.where(np.isfinite(z) & (z > 0), np.round(z * 1000), 0).astype(np.uint16)
        ids = hit['primitive_ids'].numpy()
        rgb = colours[np.where(ids < len(colours), ids, 0)]
        name = f'frame-{k:06d}'
        for suffix, image in (('color.png', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)), ('depth.png', depth)):
            ok, png = cv2.imencode('.png', image)
            atomic_write(out / f'{name}.{suffix}', lambda f, data=png: f.write(data.tobytes()))
        atomic_write(out / f'{name}.pose.txt', lambda f, pose=T: np.savetxt(f, pose, fmt='%.9f'), binary=False)
    return out
