"""Scene content of the synthetic studio: subject, room, camera stands, calibration board, lights.

Studio frame: metres, z up, origin on the floor at the capture centre. Every object is a
triangle mesh in its own frame with one material per triangle; albedo is a procedural function
of object-frame position so textures move with the subject. Albedo is linear RGB reflectance.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from volcap_calib.board import BoardConfig
from volcap_core.color import srgb_to_linear
from volcap_core.errors import BadInput
from volcap_core.poses import make_transform
from volcap_core.sampling import sample_bilinear


@dataclass
class Material:
    """Procedural albedo plus a Blinn-Phong specular lobe (the view-dependent part)."""
    kind: str                       # solid | stripes | checker | noise | texture
    colors: tuple = ((0.5, 0.5, 0.5),)   # sRGB in [0, 1]
    period: float = 0.1
    axis: int = 2
    specular: float = 0.0
    shininess: float = 20.0
    texture: np.ndarray | None = None    # float32 linear RGB, for kind == texture
    texture_origin: tuple[float, float] = (0.0, 0.0)
    px_per_m: float = 1.0

    def __post_init__(self):
        self._linear = srgb_to_linear(self.colors)

    def albedo(self, p: np.ndarray) -> np.ndarray:
        lin = self._linear
        if self.kind == 'solid':
            return np.broadcast_to(lin[0], p.shape).copy()
        if self.kind == 'stripes':
            idx = np.floor(p[:, self.axis] / self.period).astype(np.int64) % len(lin)
            return lin[idx]
        if self.kind == 'checker':
            idx = (np.floor(p[:, 0] / self.period) + np.floor(p[:, 1] / self.period)
                   + np.floor(p[:, 2] / self.period)).astype(np.int64) % 2
            return lin[idx]
        if self.kind == 'noise':
            # Smooth pseudo-random variation: a few incommensurate sinusoids (deterministic).
            f = 2 * np.pi / self.period
            n = (np.sin(f * p[:, 0] + 1.3 * np.sin(f * 0.7 * p[:, 2])) * np.cos(f * 1.3 * p[:, 1] + 0.5)
                 + 0.5 * np.sin(f * 2.1 * (p[:, 0] + p[:, 1] + p[:, 2])))
            t = np.clip(0.5 + 0.33 * n, 0.0, 1.0)[:, None]
            return lin[0] * (1 - t) + lin[-1] * t
        if self.kind == 'texture':
            # Front face (z <= 0 in board coordinates) carries the artwork, back and edges grey.
            uv = (p[:, :2] - self.texture_origin) * self.px_per_m - 0.5
            return np.where(p[:, 2:3] <= 1e-4, sample_bilinear(self.texture, uv), lin[0])
        raise BadInput(f'unknown material kind {self.kind!r}')


@dataclass
class SceneObject:
    name: str
    role: str                         # subject | background | board
    mesh: o3d.geometry.TriangleMesh   # object frame
    materials: list[Material]
    triangle_material: np.ndarray     # (T,) index into materials
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))  # T_studio_object


@dataclass
class Light:
    position: tuple[float, float, float]
    color: tuple[float, float, float]  # linear RGB intensity at 1 m


def _parts_to_object(name: str, role: str, parts: list[tuple[o3d.geometry.TriangleMesh, int]],
                     materials: list[Material]) -> SceneObject:
    mesh = o3d.geometry.TriangleMesh()
    tri_mat = []
    for part, mat in parts:
        mesh += part
        tri_mat.append(np.full(len(part.triangles), mat, np.int32))
    mesh.compute_vertex_normals()
    return SceneObject(name, role, mesh, materials, np.concatenate(tri_mat))


def _cylinder(r, h, centre, res=40, scale=(1, 1, 1), tilt=None):
    m = o3d.geometry.TriangleMesh.create_cylinder(radius=r, height=h, resolution=res, split=max(1, int(h / 0.05)))
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) * scale)
    if tilt is not None:
        m.rotate(tilt, center=(0, 0, 0))
    return m.translate(centre)


def _sphere(r, centre, res=40, scale=(1, 1, 1)):
    m = o3d.geometry.TriangleMesh.create_sphere(radius=r, resolution=res)
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) * scale)
    return m.translate(centre)


def _box(size, centre):
    m = o3d.geometry.TriangleMesh.create_box(*size)
    return m.translate(np.asarray(centre) - np.asarray(size) / 2)


def person() -> SceneObject:
    """A person-sized (1.75 m) figure with textured clothes, skin and a glossy hat."""
    mats = [
        Material('noise', ((0.22, 0.30, 0.52), (0.32, 0.40, 0.62)), period=0.08),             # jeans
        Material('solid', ((0.04, 0.035, 0.03),), specular=0.05, shininess=30),              # shoes
        Material('stripes', ((0.80, 0.12, 0.10), (0.92, 0.90, 0.85), (0.15, 0.35, 0.70)),
                 period=0.045, axis=2, specular=0.08, shininess=12),                         # shirt
        Material('noise', ((0.78, 0.57, 0.46), (0.86, 0.66, 0.55)), period=0.05, specular=0.12,
                 shininess=25),                                                               # skin
        Material('checker', ((0.55, 0.10, 0.12), (0.95, 0.80, 0.20)), period=0.04,
                 specular=0.35, shininess=60),                                                # hat
    ]
    arm_l = o3d.geometry.get_rotation_matrix_from_xyz((0.0, np.radians(-18), 0.0))
    arm_r = o3d.geometry.get_rotation_matrix_from_xyz((0.0, np.radians(18), 0.0))
    parts = [
        (_cylinder(0.075, 0.82, (-0.10, 0, 0.49)), 0), (_cylinder(0.075, 0.82, (0.10, 0, 0.49)), 0),
        (_box((0.11, 0.26, 0.08), (-0.10, -0.04, 0.04)), 1), (_box((0.11, 0.26, 0.08), (0.10, -0.04, 0.04)), 1),
        (_cylinder(0.17, 0.55, (0, 0, 1.12), scale=(1, 0.68, 1)), 2),
        (_sphere(0.17, (0, 0, 1.39), scale=(1.1, 0.7, 0.45)), 2),
        (_cylinder(0.045, 0.60, (-0.30, 0, 1.13), tilt=arm_r), 2),
        (_cylinder(0.045, 0.60, (0.30, 0, 1.13), tilt=arm_l), 2),
        (_sphere(0.05, (-0.40, 0, 0.83)), 3), (_sphere(0.05, (0.40, 0, 0.83)), 3),
        (_cylinder(0.05, 0.12, (0, 0, 1.50)), 3),
        (_sphere(0.105, (0, 0, 1.63), scale=(0.9, 1.0, 1.1)), 3),
        (_cylinder(0.10, 0.06, (0, 0, 1.75)), 4),
    ]
    return _parts_to_object('person', 'subject', parts, mats)


def bunny_on_pedestal(bunny_path: str) -> SceneObject:
    """The Stanford bunny, scaled to about 0.45 m, glazed, on a matte 0.8 m pedestal."""
    bunny = o3d.io.read_triangle_mesh(bunny_path)
    if len(bunny.triangles) == 0:
        raise BadInput(f'could not read a mesh from {bunny_path}')
    # The scan is y-up: turn it z-up, scale, stand it on the pedestal.
    bunny.rotate(o3d.geometry.get_rotation_matrix_from_xyz((np.pi / 2, 0, 0)), center=(0, 0, 0))
    bb = bunny.get_axis_aligned_bounding_box()
    bunny.translate(-np.array([*bb.get_center()[:2], bb.min_bound[2]]))
    bunny.scale(0.45 / (bb.max_bound[2] - bb.min_bound[2]), center=(0, 0, 0))
    bunny.translate((0, 0, 0.8))
    mats = [Material('noise', ((0.62, 0.30, 0.16), (0.85, 0.62, 0.35)), period=0.06, specular=0.45, shininess=70),
            Material('noise', ((0.80, 0.80, 0.78), (0.70, 0.72, 0.74)), period=0.2)]
    return _parts_to_object('bunny', 'subject', [(bunny, 0), (_box((0.4, 0.4, 0.8), (0, 0, 0.4)), 1)], mats)


def room(stand_xy: list[tuple[float, float]], half_size: float = 2.6, height: float = 3.0) -> list[SceneObject]:
    floor = _parts_to_object('floor', 'background', [(_box((2 * half_size, 2 * half_size, 0.02), (0, 0, -0.01)), 0)],
                             [Material('checker', ((0.45, 0.43, 0.40), (0.60, 0.58, 0.55)), period=0.5,
                                       specular=0.05, shininess=15)])
    walls = [(_box((2 * half_size, 0.05, height), (0, s * half_size, height / 2)), 0) for s in (-1, 1)]
    walls += [(_box((0.05, 2 * half_size, height), (s * half_size, 0, height / 2)), 0) for s in (-1, 1)]
    walls.append((_box((2 * half_size, 2 * half_size, 0.05), (0, 0, height)), 1))
    walls_obj = _parts_to_object('walls', 'background', walls,
                                 [Material('noise', ((0.72, 0.70, 0.64), (0.80, 0.78, 0.72)), period=0.6),
                                  Material('solid', ((0.30, 0.30, 0.30),))])
    stands = _parts_to_object('stands', 'background',
                              [(_cylinder(0.025, 1.9, (x, y, 0.95), res=16), 0) for x, y in stand_xy],
                              [Material('solid', ((0.15, 0.15, 0.16),), specular=0.3, shininess=40)])
    return [floor, walls_obj, stands]


def board_object(config: BoardConfig, px_per_m: float = 1500.0, thickness: float = 0.005) -> SceneObject:
    """The calibration board as a thin box in board coordinates (artwork on the z = 0 face)."""
    x0, y0, x1, y1 = config.extent
    box = o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, thickness).translate((x0, y0, 0.0))
    art = srgb_to_linear(config.render(px_per_m) / 255.0).astype(np.float32)
    mat = Material('texture', ((0.5, 0.5, 0.5),), texture=art, texture_origin=(x0, y0), px_per_m=px_per_m,
                   specular=0.03, shininess=10)
    return _parts_to_object('board', 'board', [(box, 0)], [mat])


def studio_lights() -> tuple[list[Light], float]:
    """Three ceiling lights of slightly different colour temperature, and the ambient level."""
    lights = [Light((1.2, -1.5, 2.7), (2.4, 2.25, 2.0)),     # warm key
              Light((-1.6, -0.6, 2.6), (1.5, 1.6, 1.8)),     # cool fill
              Light((0.2, 1.8, 2.8), (1.7, 1.7, 1.7))]       # back light
    return lights, 0.18


def subject_pose(frame: int, fps: float, motion: str = 'turn') -> np.ndarray:
    """T_studio_subject at a capture frame: a slow turn (20 deg/s) with a little sway, or (motion
    ``none``) the first frame's pose held."""
    t = frame / fps if motion == 'turn' else 0.0
    yaw = np.radians(20.0) * t
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return make_transform(R, (0.03 * np.sin(2 * np.pi * 0.5 * t), 0.0, 0.0))
