"""The studio frame (``volcap_studio``): gravity-aligned, REP 103 (+Z up, metres), origin on the
floor below the point the cameras converge on, +X horizontal towards the reference camera (the
side a subject faces, which glTF calls the front: +Z there).

The floor is the large horizontal plane every camera's depth sees below it: planes are peeled
off the cameras' depth points (world frame) by RANSAC (Open3D ``segment_plane``), and the first
one that faces up (within ``max_tilt_deg`` of the cameras' mean up direction, -y of an optical
frame), lies below every camera and holds enough points is refined by least squares on its
inliers. Without such a plane (no depth, no floor in view) the frame falls back to the cameras'
mean up through the convergence point, and says so (``source: cameras``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from volcap_core.calibration import STUDIO_FRAME, StudioFrame
from volcap_core.poses import convergence_point

from .extrinsics import fit_plane


@dataclass
class FloorConfig:
    points_per_camera: int = 20_000     # depth points each camera contributes (a random subset)
    distance: float = 0.015             # RANSAC inlier distance (m): ToF noise on a floor 2-4 m away
    max_tilt_deg: float = 30.0          # floor normal against the cameras' mean up
    min_share: float = 0.05             # of all points, on the plane
    min_camera_height: float = 0.3      # every camera at least this far above the floor (m)
    max_planes: int = 6                 # planes peeled off before giving up (walls, stands, board)


def cameras_up(T_world_color: dict[str, np.ndarray]) -> np.ndarray:
    """Mean up direction of the cameras in the world frame (an optical frame's y points down)."""
    up = -np.sum([np.asarray(T)[:3, 1] for T in T_world_color.values()], axis=0)
    return up / np.linalg.norm(up)


def find_floor(points: np.ndarray, up: np.ndarray, centres: np.ndarray, cfg: FloorConfig,
               seed: int = 0) -> tuple[np.ndarray, float, float, int] | None:
    """(unit normal facing up, offset d of n.x = d, RMS of the inliers in m, inliers) of the
    floor among ``points``, or None."""
    o3d.utility.random.seed(seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    total = len(points)
    for _ in range(cfg.max_planes):
        if len(cloud.points) < max(3, cfg.min_share * total):
            return None
        (a, b, c, d), inliers = cloud.segment_plane(cfg.distance, 3, 1000)
        n = np.array([a, b, c])
        d = -d / np.linalg.norm(n)
        n /= np.linalg.norm(n)
        if n @ up < 0:
            n, d = -n, -d
        heights = centres @ n - d
        if (len(inliers) >= cfg.min_share * total and np.degrees(np.arccos(min(1.0, n @ up))) <= cfg.max_tilt_deg
                and heights.min() >= cfg.min_camera_height):
            on_plane = np.asarray(cloud.points)[inliers]
            n2, d2 = fit_plane(on_plane)
            if n2 @ n < 0:
                n2, d2 = -n2, -d2
            rms = float(np.sqrt(np.mean((on_plane @ n2 - d2) ** 2)))
            return n2, d2, rms, len(inliers)
        cloud = cloud.select_by_index(inliers, invert=True)
    return None


def fit_studio_frame(T_world_color: dict[str, np.ndarray], reference: str,
                     depth_points_world: dict[str, np.ndarray] | None = None,
                     cfg: FloorConfig | None = None) -> StudioFrame:
    """The studio frame from the calibrated cameras and (optionally) their depth points in the
    world frame."""
    cfg = cfg or FloorConfig()
    up = cameras_up(T_world_color)
    centres = np.array([np.asarray(T)[:3, 3] for T in T_world_color.values()])
    rng = np.random.default_rng(0)
    chunks = []
    for pts in (depth_points_world or {}).values():
        pts = np.asarray(pts, float)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) > cfg.points_per_camera:
            pts = pts[rng.choice(len(pts), cfg.points_per_camera, replace=False)]
        chunks.append(pts)
    points = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    floor = find_floor(points, up, centres, cfg) if len(points) >= 100 else None
    try:
        aim = convergence_point(list(T_world_color.values()))
    except ValueError:
        aim = centres.mean(axis=0)
    if floor is not None:
        n, d, rms, inliers = floor
        origin = aim - (aim @ n - d) * n
        details = {'source': 'floor', 'floor_rms_mm': round(rms * 1000, 2), 'floor_points': int(inliers),
                   'floor_tilt_deg': round(float(np.degrees(np.arccos(min(1.0, n @ up)))), 2)}
    else:
        n, origin = up, aim
        details = {'source': 'cameras',
                   'note': 'no floor in the depth: up is the cameras\' mean up, the origin their aim point'}
    toward = np.asarray(T_world_color[reference])[:3, 3] - origin
    x = toward - (toward @ n) * n
    if np.linalg.norm(x) < 1e-6:       # reference camera straight above the origin
        x = np.asarray(T_world_color[reference])[:3, 0] - (np.asarray(T_world_color[reference])[:3, 0] @ n) * n
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(n, x), n, origin
    heights = centres @ n - origin @ n
    details['camera_height_m'] = [round(float(h), 3) for h in heights]
    return StudioFrame(T, STUDIO_FRAME, details)
