"""The synthetic 8-camera studio of paper 000: rig layout, session plan and frame rendering.

Four stands (front, right, back, left) at ``stand_radius`` from the capture centre, two Azure
Kinect-class cameras per stand at 1.7 m and 0.7 m, all converging on the subject. Intrinsics
and the depth-to-colour offset start from a real factory calibration and vary a little per
device, as they do between real units.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volcap_calib.board import BoardConfig
from volcap_core.camera import CameraModel
from volcap_core.poses import look_at, make_transform, perturb
from volcap_core.rig import Rig, RigCamera, rig_camera_from_k4a
from volcap_core.topics import CALIBRATION_PHASE, CAPTURE, CLEAN_PLATE, camera_names
from volcap_studio import scene as sc
from volcap_studio.config import (  # noqa: F401 (re-exported: their home before config.py)
    BOARD_LAYOUTS,
    SCENES,
    SynthConfig,
    default_bunny_mesh,
    default_k4a_calibration,
    shared_data_dir,
)
from volcap_studio.render import CameraRaycast, ColorResponse, DepthRender, SceneRaycaster

PHASE_GAP_NS = 1_000_000_000
START_NS = 1_700_000_000_000_000_000


@dataclass
class FramePlan:
    index: int
    phase: str
    stamp_ns: int
    subject_pose: np.ndarray | None = None   # T_studio_subject
    board_pose: np.ndarray | None = None     # T_studio_board


@dataclass
class RenderedFrame:
    color: np.ndarray
    depth: DepthRender
    color_subject: np.ndarray   # bool: colour pixel centre sees the subject
    depth_subject: np.ndarray   # bool: depth pixel centre sees the subject
    color_stamp_ns: int
    depth_stamp_ns: int


def stand_layout(cfg: SynthConfig) -> list[tuple[str, np.ndarray]]:
    """(name, T_studio_color) of the nominal rig: stands evenly round the centre, two heights."""
    n_stands = (cfg.cameras + 1) // 2
    out = []
    for i, name in enumerate(camera_names(cfg.cameras)):
        stand, level = divmod(i, 2)
        angle = -np.pi / 2 + 2 * np.pi * stand / n_stands   # stand 0 in front (-y)
        height = cfg.heights[level]
        eye = (cfg.stand_radius * np.cos(angle), cfg.stand_radius * np.sin(angle), height)
        target = (0.0, 0.0, 1.05 if height > 1.2 else 0.8)
        out.append((name, look_at(eye, target)))
    return out


def make_rig(cfg: SynthConfig, rng: np.random.Generator) -> tuple[Rig, dict[str, np.ndarray]]:
    """The rig (per-device intrinsics and depth-to-colour offsets) and GT T_studio_color."""
    base = rig_camera_from_k4a(cfg.k4a_calibration, 'base')
    cams, poses = [], {}
    for name, T in stand_layout(cfg):
        poses[name] = perturb(T, rng.normal(0, 1.0, 3), rng.normal(0, 0.008, 3))
        color = _vary(base.color, rng, 0.008, 4.0)
        depth = _vary(base.depth, rng, 0.005, 2.0)
        T_cd = perturb(base.T_color_depth, rng.normal(0, 0.15, 3), rng.normal(0, 0.0008, 3))
        cams.append(RigCamera(name, color, depth, T_cd, serial=f'SYNTH{cfg.seed:04d}{len(cams):02d}'))
    return Rig(cams, name='synthetic_studio'), poses


def _vary(cam: CameraModel, rng, focal_rel: float, centre_px: float) -> CameraModel:
    f = 1 + rng.normal(0, focal_rel)
    return CameraModel(cam.width, cam.height, cam.fx * f, cam.fy * f * (1 + rng.normal(0, 0.001)),
                       cam.cx + rng.normal(0, centre_px), cam.cy + rng.normal(0, centre_px), cam.dist)


def board_poses(cfg: SynthConfig, board: BoardConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """T_studio_board for each calibration frame, at two heights and tilts, with a little random
    placement. ``sweep``: the board turned towards every direction in turn (so each camera sees
    it several times, and neighbouring stands see it together). ``pairs``: the way the
    calibration service guides an operator: facing midway between two neighbouring stands, pair
    after pair round the ring, so that every neighbouring pair shares views and the ring closes."""
    x0, y0, x1, y1 = board.extent
    centre_local = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    n_stands = (cfg.cameras + 1) // 2
    out = []
    for k in range(cfg.board_poses):
        if cfg.board_layout == 'pairs':
            yaw = -np.pi / 2 + 2 * np.pi * (k % n_stands + 0.5) / n_stands + rng.normal(0, 0.05)
            high = (k + k // n_stands) % 2 == 0     # each pair high and low in turn
        else:
            yaw = -np.pi / 2 + 2 * np.pi * k / max(cfg.board_poses, 1) + rng.normal(0, 0.05)
            high = k % 2 == 0
        pitch = np.radians(12.0 if high else -8.0) + rng.normal(0, 0.05)
        facing = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
        z = -facing                                  # board z points into the board
        y = np.array([0.0, 0.0, -1.0]) - z * (-z[2])  # "down" in the board plane
        y /= np.linalg.norm(y)
        R = np.stack([np.cross(y, z), y, z], axis=1)
        centre = np.array([0.0, 0.0, 1.35 if high else 0.95]) + 0.25 * facing * np.array([1, 1, 0]) \
            + rng.normal(0, 0.05, 3)
        out.append(make_transform(R, centre - R @ centre_local))
    return out


def session_plan(cfg: SynthConfig, board: BoardConfig, rng: np.random.Generator) -> list[FramePlan]:
    """Clean plate, then the board poses, then the subject capture, at ``fps`` with gaps between."""
    period = int(round(1e9 / cfg.fps))
    plans, t = [], START_NS
    for k in range(cfg.background_frames):
        plans.append(FramePlan(len(plans), CLEAN_PLATE, t))
        t += period
    t += PHASE_GAP_NS
    for T in board_poses(cfg, board, rng):
        plans.append(FramePlan(len(plans), CALIBRATION_PHASE, t, board_pose=T))
        t += period
    t += PHASE_GAP_NS
    for k in range(cfg.frames):
        plans.append(FramePlan(len(plans), CAPTURE, t, subject_pose=sc.subject_pose(k, cfg.fps, cfg.motion)))
        t += period
    return plans


class StudioRenderer:
    """Renders every camera of a planned frame; holds per-camera rays and colour responses."""

    def __init__(self, cfg: SynthConfig, rig: Rig, T_studio_color: dict[str, np.ndarray], board: BoardConfig,
                 rng: np.random.Generator):
        self.cfg, self.rig, self.rng = cfg, rig, rng
        self.T_studio_color = T_studio_color
        self.T_studio_depth = {c.name: T_studio_color[c.name] @ c.T_color_depth for c in rig.cameras}
        self.responses = {c.name: ColorResponse.random(rng) for c in rig.cameras}
        # Poles stand 10 cm behind the cameras mounted on them.
        stand_xy = sorted({tuple(np.round(T[:2, 3] * (1 + 0.1 / np.linalg.norm(T[:2, 3])), 3))
                           for T in T_studio_color.values()})
        self.background = sc.room(stand_xy)
        self.subject = sc.person() if cfg.scene == 'person' else sc.bunny_on_pedestal(cfg.bunny_mesh)
        self.board = sc.board_object(board)
        self.lights, self.ambient = sc.studio_lights()
        static = SceneRaycaster(self.background)
        self.color_views = {c.name: CameraRaycast(static, c.color, T_studio_color[c.name], c.color.pixel_rays())
                            for c in rig.cameras}
        self.depth_views = {c.name: CameraRaycast(static, c.depth, self.T_studio_depth[c.name], c.depth.pixel_rays())
                            for c in rig.cameras}

    def moving_objects(self, plan: FramePlan) -> list[sc.SceneObject]:
        objects = []
        if plan.subject_pose is not None:
            self.subject.pose = plan.subject_pose
            objects.append(self.subject)
        if plan.board_pose is not None:
            self.board.pose = plan.board_pose
            objects.append(self.board)
        return objects

    def render(self, plan: FramePlan) -> dict[str, RenderedFrame]:
        moving = self.moving_objects(plan)
        dynamic = SceneRaycaster(moving, first_index=len(self.background)) if moving else None
        full = SceneRaycaster(self.background + moving)
        # Object index -1 (no hit) picks the trailing False.
        is_subject = np.array([o.role == 'subject' for o in self.background + moving] + [False])
        jitter = self.cfg.stamp_jitter_ms * 1e6
        out = {}
        for cam in self.rig.cameras:
            n = cam.name
            color, color_obj = self.color_views[n].color(dynamic, self.lights, self.ambient, self.responses[n],
                                                         self.rng)
            depth = self.depth_views[n].depth(dynamic, full, self.cfg.tof, self.rng)
            stamp = plan.stamp_ns + int(np.clip(self.rng.normal(0, jitter), -3 * jitter, 3 * jitter))
            out[n] = RenderedFrame(color, depth, is_subject[color_obj], is_subject[depth.objects],
                                 stamp, stamp + int(self.rng.normal(0, 0.1e6)))
        return out



