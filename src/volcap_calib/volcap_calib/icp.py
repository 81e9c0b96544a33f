"""Optional last step of the rig calibration: ICP of every camera's depth of the subject against
the other cameras' (Open3D point-to-plane, robust Tukey loss).

The board solve fixes the rig to a few millimetres; what is left shows as doubled surfaces in
the fused model. Here each camera's cloud of one synchronised frame set is registered to the
union of the others (Gauss-Seidel sweeps, the reference camera held fixed as the gauge). Only
the capture volume is used: a sphere around the point the cameras look at, so walls that one
camera sees alone do not pull. A camera's update is kept only when it is small (the board
solution is the prior, ICP a correction) and clearly improves its alignment: on depth noise of
a few millimetres a flat optimum would otherwise let the poses drift.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from volcap_core.errors import BadInput
from volcap_core.poses import rotation_angle_deg, transform_points


@dataclass
class IcpConfig:
    voxel: float = 0.005             # down-sampling of each cloud (m)
    max_distance: float = 0.015      # correspondence search radius (m)
    radius: float = 1.2              # capture volume: sphere around the cameras' look-at point (m)
    sweeps: int = 15                 # Gauss-Seidel sweeps over the cameras, at most
    converged_m: float = 0.0002      # stop when no camera moved more than this in a sweep
    max_rotation_deg: float = 1.0    # larger corrections are refused: the board solve is the prior
    max_translation_m: float = 0.02
    min_fitness: float = 0.2         # share of a camera's points with a partner within max_distance
    min_gain: float = 0.02           # a step must cut the camera's inlier RMSE by this fraction


@dataclass
class IcpCameraReport:
    rmse_before_mm: float
    rmse_after_mm: float
    fitness: float
    rotation_deg: float
    translation_mm: float
    accepted: bool
    reason: str = ''

    def to_dict(self) -> dict:
        return dict(vars(self))


def look_at_centre(T_world_color: dict[str, np.ndarray]) -> np.ndarray:
    """The point nearest (least squares) to every camera's optical axis: the capture centre."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for T in T_world_color.values():
        d, o = T[:3, 2], T[:3, 3]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ o
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _local_cloud(points: np.ndarray, cfg: IcpConfig) -> o3d.geometry.PointCloud:
    """Down-sampled cloud with normals in the camera's own frame (oriented towards it), made
    once: moving it to the world later only rotates the normals."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pc = pc.voxel_down_sample(cfg.voxel)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * cfg.voxel, max_nn=30))
    pc.orient_normals_towards_camera_location(np.zeros(3))
    return pc


def _placed(cloud: o3d.geometry.PointCloud, T: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(cloud).transform(T)


def refine_with_icp(T_world_color: dict[str, np.ndarray], points_color: dict[str, np.ndarray], reference: str,
                    cfg: IcpConfig = IcpConfig()) -> tuple[dict[str, np.ndarray], dict[str, IcpCameraReport]]:
    """``points_color``: each camera's depth points of one frame set in its own colour frame.
    Returns the refined T_world_color (the reference camera's unchanged) and a report per
    camera (every camera but the reference)."""
    if reference not in T_world_color:
        raise BadInput(f'reference camera {reference!r} is not in the calibration')
    missing = sorted(set(T_world_color) - set(points_color))
    if missing:
        raise BadInput(f'no depth points for cameras {missing}')
    centre = look_at_centre(T_world_color)
    clouds = {}
    for c, pts in points_color.items():
        world = transform_points(T_world_color[c], pts)
        clouds[c] = _local_cloud(pts[np.linalg.norm(world - centre, axis=1) < cfg.radius], cfg)
    T = {c: M.copy() for c, M in T_world_color.items()}
    registration = o3d.pipelines.registration
    method = registration.TransformationEstimationPointToPlane(registration.TukeyLoss(k=cfg.max_distance / 2))
    criteria = registration.ICPConvergenceCriteria(max_iteration=50)
    movable = [c for c in T if c != reference]

    def others(c):
        union = o3d.geometry.PointCloud()
        for o in T:
            if o != c:
                union += _placed(clouds[o], T[o])
        return union

    rmse_before = {}
    for _ in range(cfg.sweeps):
        largest = 0.0
        for c in movable:
            target, source = others(c), _placed(clouds[c], T[c])
            before = registration.evaluate_registration(source, target, cfg.max_distance)
            rmse_before.setdefault(c, before.inlier_rmse)
            result = registration.registration_icp(source, target, cfg.max_distance, np.eye(4), method, criteria)
            candidate = result.transformation @ T[c]
            if result.fitness >= cfg.min_fitness and result.inlier_rmse <= (1 - cfg.min_gain) * before.inlier_rmse \
                    and _within_limits(candidate, T_world_color[c], cfg):
                largest = max(largest, np.linalg.norm(candidate[:3, 3] - T[c][:3, 3]))
                T[c] = candidate
        if largest < cfg.converged_m:
            break
    reports = {}
    for c in movable:
        after = registration.evaluate_registration(_placed(clouds[c], T[c]), others(c), cfg.max_distance)
        moved = not np.allclose(T[c], T_world_color[c])
        reason = '' if moved else (f'fitness {after.fitness:.2f} < {cfg.min_fitness}' if after.fitness < cfg.min_fitness
                                   else 'no correction that is small and improves the alignment')
        reports[c] = IcpCameraReport(rmse_before[c] * 1000, after.inlier_rmse * 1000,
                                     after.fitness, rotation_angle_deg(T[c][:3, :3], T_world_color[c][:3, :3]),
                                     float(np.linalg.norm(T[c][:3, 3] - T_world_color[c][:3, 3]) * 1000), moved,
                                     reason)
    return T, reports


def _within_limits(T_new: np.ndarray, T_prior: np.ndarray, cfg: IcpConfig) -> bool:
    return (rotation_angle_deg(T_new[:3, :3], T_prior[:3, :3]) <= cfg.max_rotation_deg
            and np.linalg.norm(T_new[:3, 3] - T_prior[:3, 3]) <= cfg.max_translation_m)
