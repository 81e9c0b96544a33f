"""PNG renders of fused models: ray-cast (Open3D RaycastingScene, no display needed) from
virtual cameras around the model, vertex colours interpolated over each triangle and lit by a
headlight so the shape reads as well as the colour."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from volcap_core.errors import BadInput
from volcap_core.figures import write_png
from volcap_fusion.tsdf import FusedModel


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """T_world_camera of an optical-frame camera (z forward, y down) at ``eye`` facing ``target``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def camera_up(poses: list[np.ndarray]) -> np.ndarray:
    """The world's up direction as the rig's cameras see it: their mean -y axis (cameras are
    mounted upright, optical y points down)."""
    up = -np.mean([np.asarray(T)[:3, 1] for T in poses], axis=0)
    return up / np.linalg.norm(up)


def orbit_views(model: FusedModel, up: np.ndarray, count: int = 4, fov_deg: float = 50.0) -> list[np.ndarray]:
    """``count`` cameras evenly around the model's centre, level with it, far enough away that
    the whole model fits a ``fov_deg`` view."""
    lo, hi = np.percentile(model.vertices, 1, axis=0), np.percentile(model.vertices, 99, axis=0)
    centre = (lo + hi) / 2
    distance = 1.15 * np.linalg.norm(hi - lo) / 2 / np.tan(np.radians(fov_deg) / 2)
    up = np.asarray(up, float) / np.linalg.norm(up)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    other = np.cross(up, side)
    views = []
    for k in range(count):
        a = 2 * np.pi * k / count
        eye = centre + distance * (np.cos(a) * side + np.sin(a) * other)
        views.append(look_at(eye, centre, up))
    return views


def render(model: FusedModel, T_world_camera: np.ndarray, width: int = 480, height: int = 640,
           fov_deg: float = 50.0, background: int = 32) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of the model seen from ``T_world_camera``."""
    image = np.full((height, width, 3), background, np.uint8)
    if len(model.triangles) == 0:
        return image
    scene = model.raycasting_scene()
    f = 0.5 * height / np.tan(np.radians(fov_deg) / 2)
    u, v = np.meshgrid(np.arange(width) - (width - 1) / 2, np.arange(height) - (height - 1) / 2)
    dirs = np.stack([u / f, v / f, np.ones_like(u)], axis=-1) @ T_world_camera[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(T_world_camera[:3, 3], dirs.shape), dirs], axis=-1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    tri = hit['primitive_ids'].numpy().astype(np.int64)
    seen = tri != o3d.t.geometry.RaycastingScene.INVALID_ID
    if not seen.any():
        return image
    uv = hit['primitive_uvs'].numpy()[seen]
    corners = model.triangles[tri[seen]]
    weights = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    color = np.einsum('nk,nkc->nc', weights, model.colors[corners].astype(np.float32))
    normal = hit['primitive_normals'].numpy()[seen]
    shade = 0.35 + 0.65 * np.abs(np.sum(normal * dirs[seen], axis=1))
    image[seen] = np.clip(color * shade[:, None], 0, 255).astype(np.uint8)
    return image


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    out = image.copy()
    for color, width in (((0, 0, 0), 4), ((255, 255, 255), 1)):
        cv2.putText(out, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, color, width, cv2.LINE_AA)
    return out


def turntable(model: FusedModel, views: list[np.ndarray], label: str = '', **kwargs) -> np.ndarray:
    """The model from every view, side by side."""
    tiles = [render(model, T, **kwargs) for T in views]
    if label:
        tiles[0] = labelled(tiles[0], label)
    return np.hstack(tiles)


def render_rows(models: list[tuple[str, FusedModel]], poses: list[np.ndarray], path: str | Path,
                frame_on: FusedModel | None = None) -> Path:
    """A PNG with one row per (label, model): the model from four sides, each framed on itself or
    all on ``frame_on``; ``poses`` (the cameras) say which way is up."""
    up = camera_up(poses)
    rows = [turntable(m, orbit_views(m if frame_on is None else frame_on, up), label=label)
            for label, m in models if len(m.triangles)]
    if not rows:
        raise BadInput('nothing to render: every mesh is empty')
    return write_png(path, np.vstack(rows))
