"""Write a synthetic studio session as a rosbag2 MCAP bag plus its ground-truth sidecar, and read
the sidecar back.

Layout of ``DIR``: ``metadata.yaml`` and ``DIR_0.mcap`` (the bag), ``ground_truth/ground_truth.yaml``
(rig, T_world_color per camera, colour responses, ToF model, board and subject poses, frame
stamps), ``ground_truth/frames/NNNNNN.npz`` (per camera: clean depth, flying / speckle / dropped
masks and subject masks), ``ground_truth/subject.ply`` and ``ground_truth/preview.png`` (every
camera's colour and depth in the first capture frame, or the last frame when there is none).
The world frame is cam0's colour optical frame (DESIGN.md); ``T_studio_world`` places it in the
floor-level studio frame.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import yaml
from std_msgs.msg import String
from tqdm import tqdm

from volcap_calib.board import BoardConfig
from volcap_core import topics
from volcap_core.bag_writer import BagWriter
from volcap_core.conversions import camera_model_to_info, numpy_to_image
from volcap_core.errors import BadInput
from volcap_core.poses import invert, matrix_from_list, matrix_to_list
from volcap_core.rig import Rig
from volcap_core.topics import CAPTURE
from volcap_studio.render import ColorResponse
from volcap_studio.studio import FramePlan, StudioRenderer, SynthConfig, make_rig, session_plan

GT_VERSION = 1
GT_DIR = 'ground_truth'


@dataclass
class SynthSummary:
    path: Path
    frame_sets: int
    messages: int
    bag_bytes: int


def synthesize(out: str | Path, cfg: SynthConfig, progress: bool = True, overwrite: bool = False) -> SynthSummary:
    """Render the session and write the bag and ground truth to ``out`` (built aside, then moved)."""
    out = Path(out)
    if out.exists():
        if not overwrite:
            raise FileExistsError(f'{out} exists; choose another --out or pass --overwrite')
    rng = np.random.default_rng(cfg.seed)
    board = BoardConfig.from_yaml()
    rig, T_studio_color = make_rig(cfg, rng)
    plans = session_plan(cfg, board, rng)
    renderer = StudioRenderer(cfg, rig, T_studio_color, board, rng)

    staging = out.parent / f'.{out.name}.partial'
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    bag_dir = staging / out.name
    try:
        with BagWriter(bag_dir) as bag:
            _add_topics(bag, rig)
            frames_gt = _write_frames(bag, rig, renderer, plans, bag_dir / GT_DIR / 'frames', progress)
            count = bag.count
        _write_ground_truth(bag_dir / GT_DIR, cfg, rig, renderer, board, plans, frames_gt)
        if out.exists():
            shutil.rmtree(out)
        os.replace(bag_dir, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    size = sum(f.stat().st_size for f in out.glob('*.mcap'))
    return SynthSummary(out, len(plans), count, size)


def _add_topics(bag: BagWriter, rig: Rig) -> None:
    bag.add_topic(topics.RIG, 'std_msgs/msg/String', latched=True)
    bag.add_topic(topics.PHASE, 'std_msgs/msg/String', latched=True)
    for cam in rig.cameras:
        for name in (topics.COLOR_IMAGE, topics.DEPTH_IMAGE):
            bag.add_topic(topics.camera_topic(cam.name, name), 'sensor_msgs/msg/Image')
        for name in (topics.COLOR_INFO, topics.DEPTH_INFO):
            bag.add_topic(topics.camera_topic(cam.name, name), 'sensor_msgs/msg/CameraInfo')


def _write_frames(bag: BagWriter, rig: Rig, renderer: StudioRenderer, plans: list[FramePlan], gt_frames: Path,
                  progress: bool) -> list[dict]:
    gt_frames.mkdir(parents=True)
    bag.write(topics.RIG, String(data=rig.to_yaml()), plans[0].stamp_ns - 2_000_000 if plans else 0)
    phase, frames_gt, previous_ns = None, [], None
    for plan in tqdm(plans, desc='rendering studio', unit='frame set', disable=not progress):
        if plan.phase != phase:
            phase = plan.phase
            count = sum(p.phase == phase for p in plans)
            # the phase starts halfway from the previous frame set: clear of the cameras' stamp jitter
            since = plan.stamp_ns - 1_000_000 if previous_ns is None else (previous_ns + plan.stamp_ns) // 2
            bag.write(topics.PHASE, String(data=yaml.safe_dump({'phase': phase, 'frames': count, 'since_ns': since})),
                      plan.stamp_ns - 1_000_000)
        previous_ns = plan.stamp_ns
        frames = renderer.render(plan)
        preview = gt_frames.parent / 'preview.png'
        if not preview.exists() and (plan.phase == CAPTURE or plan is plans[-1]):
            write_preview(preview, rig, frames)
        out = []
        arrays = {}
        for cam in rig.cameras:
            f = frames[cam.name]
            c, d = f.color_stamp_ns, f.depth_stamp_ns
            out += [(c, topics.camera_topic(cam.name, topics.COLOR_IMAGE),
                     numpy_to_image(f.color, 'rgb8', c, cam.color_frame)),
                    (c, topics.camera_topic(cam.name, topics.COLOR_INFO),
                     camera_model_to_info(cam.color, c, cam.color_frame)),
                    (d, topics.camera_topic(cam.name, topics.DEPTH_IMAGE),
                     numpy_to_image(f.depth.depth_mm, '16UC1', d, cam.depth_frame)),
                    (d, topics.camera_topic(cam.name, topics.DEPTH_INFO),
                     camera_model_to_info(cam.depth, d, cam.depth_frame))]
            arrays.update({f'{cam.name}/depth_clean': f.depth.clean, f'{cam.name}/flying': f.depth.flying,
                           f'{cam.name}/speckle': f.depth.speckle, f'{cam.name}/dropped': f.depth.dropped,
                           f'{cam.name}/depth_subject': f.depth_subject, f'{cam.name}/color_subject': f.color_subject})
        for stamp, topic, msg in sorted(out, key=lambda m: m[0]):
            bag.write(topic, msg, stamp)
        np.savez_compressed(gt_frames / f'{plan.index:06d}.npz', **arrays)
        frames_gt.append({'index': plan.index, 'phase': plan.phase, 'stamp_ns': plan.stamp_ns,
                          'stamps': {n: {'color': f.color_stamp_ns, 'depth': f.depth_stamp_ns}
                                     for n, f in frames.items()}})
    return frames_gt


def write_preview(path: Path, rig: Rig, frames: dict) -> None:
    """Contact sheet of one frame set: each camera's colour over its depth (0-4 m, turbo)."""
    tiles = []
    for cam in rig.cameras:
        f = frames[cam.name]
        color = cv2.resize(f.color, (320, 180), interpolation=cv2.INTER_AREA)[:, :, ::-1]
        depth = np.clip(f.depth.depth_mm / 4000.0 * 255, 0, 255).astype(np.uint8)
        depth = cv2.applyColorMap(depth, cv2.COLORMAP_TURBO)
        depth[f.depth.depth_mm == 0] = 0
        depth = cv2.resize(depth, (320, 288), interpolation=cv2.INTER_NEAREST)
        tile = np.vstack([color, depth])
        for ink, width in (((0, 0, 0), 4), ((255, 255, 255), 1)):   # outlined, legible on any background
            cv2.putText(tile, cam.name, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, ink, width, cv2.LINE_AA)
        tiles.append(tile)
    while len(tiles) % 4:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + 4]) for i in range(0, len(tiles), 4)]
    cv2.imwrite(str(path), np.vstack(rows))


def _write_ground_truth(gt_dir: Path, cfg: SynthConfig, rig: Rig, renderer: StudioRenderer, board: BoardConfig,
                        plans: list[FramePlan], frames_gt: list[dict]) -> None:
    T_studio_world = renderer.T_studio_color[rig.cameras[0].name]
    T_world_studio = invert(T_studio_world)
    cameras = {}
    for cam in rig.cameras:
        T_world_color = T_world_studio @ renderer.T_studio_color[cam.name]
        cameras[cam.name] = {'T_world_color': matrix_to_list(T_world_color),
                             'T_world_depth': matrix_to_list(T_world_studio @ renderer.T_studio_depth[cam.name]),
                             'color_response': renderer.responses[cam.name].to_dict()}
    for plan, entry in zip(plans, frames_gt):
        if plan.board_pose is not None:
            entry['T_world_board'] = matrix_to_list(T_world_studio @ plan.board_pose)
        if plan.subject_pose is not None:
            entry['T_world_subject'] = matrix_to_list(T_world_studio @ plan.subject_pose)
    config = asdict(cfg)
    config['heights'] = list(cfg.heights)
    doc = {'version': GT_VERSION, 'world_frame': rig.cameras[0].color_frame, 'config': config,
           'T_studio_world': matrix_to_list(T_studio_world), 'rig': yaml.safe_load(rig.to_yaml()),
           'cameras': cameras, 'board': board.to_dict(),
           'lights': [asdict(light) for light in renderer.lights], 'ambient': renderer.ambient,
           'frames': frames_gt}
    (gt_dir / 'ground_truth.yaml').write_text(yaml.safe_dump(doc, sort_keys=False))
    o3d.io.write_triangle_mesh(str(gt_dir / 'subject.ply'), renderer.subject.mesh)


class GroundTruth:
    """The ground-truth sidecar of a synthetic bag."""

    def __init__(self, bag_dir: str | Path):
        self.dir = Path(bag_dir) / GT_DIR
        path = self.dir / 'ground_truth.yaml'
        if not path.exists():
            raise FileNotFoundError(f'{bag_dir} has no ground truth ({path} missing): not a synthetic bag?')
        self.doc = yaml.safe_load(path.read_text())
        self.rig = Rig.from_yaml(yaml.safe_dump(self.doc['rig']))
        self.frames = self.doc['frames']

    def T_world_color(self, camera: str) -> np.ndarray:
        return matrix_from_list(self.doc['cameras'][camera]['T_world_color'])

    def T_world_depth(self, camera: str) -> np.ndarray:
        return matrix_from_list(self.doc['cameras'][camera]['T_world_depth'])

    def color_response(self, camera: str) -> ColorResponse:
        return ColorResponse.from_dict(self.doc['cameras'][camera]['color_response'])

    def frames_in(self, phase: str) -> list[dict]:
        return [f for f in self.frames if f['phase'] == phase]

    def arrays(self, index: int, suffix: str = '') -> dict[str, np.ndarray]:
        """The frame's ground-truth arrays (``camN/name``), only those ending in ``suffix`` if given
        (an npz member is read only when asked for)."""
        with np.load(self.dir / 'frames' / f'{index:06d}.npz') as npz:
            return {k: npz[k] for k in npz.files if k.endswith(suffix)}

    def subject_mesh(self, index: int) -> o3d.geometry.TriangleMesh:
        """The subject mesh in the world frame at capture frame ``index``."""
        frame = self.frames[index]
        if 'T_world_subject' not in frame:
            raise BadInput(f'frame {index} ({frame["phase"]}) has no subject')
        mesh = o3d.io.read_triangle_mesh(str(self.dir / 'subject.ply'))
        return mesh.transform(matrix_from_list(frame['T_world_subject']))
