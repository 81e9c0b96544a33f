"""synthetic_rig: the synthetic studio as live cameras.

    ros2 run volcap_studio synthetic_rig --ros-args -p cameras:=8 -p fps:=30.0

Renders a short loop of studio frames at start-up (ray casting is far slower than real time),
then publishes them round and round at ``fps`` with current hardware-synced stamps, on the same
topics a real rig's drivers use, plus the rig description (latched) on ``volcap/rig``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from volcap_calib.board import BoardConfig
from volcap_core import qos, topics
from volcap_core.conversions import camera_model_to_info, ns_to_stamp, numpy_to_image
from volcap_core.errors import BadInput
from volcap_core.ros import Diagnostics, declare_config, node_main
from volcap_core.settings import setting
from volcap_studio.studio import (
    SCENES,
    StudioRenderer,
    SynthConfig,
    default_bunny_mesh,
    default_k4a_calibration,
    make_rig,
    session_plan,
)


@dataclass
class SyntheticRigConfig:
    """What the live studio renders (a short loop: ray casting is far slower than real time) and
    how fast it plays it; the rest of the studio is ``SynthConfig``'s."""
    cameras: int = setting(8, 'number of cameras (two per stand)', 1, 16, read_only=True)
    frames: int = setting(4, 'capture frames rendered for the loop', 0, 300, read_only=True)
    board_poses: int = setting(0, 'calibration board poses in the loop', 0, 64, read_only=True)
    background_frames: int = setting(0, 'clean-plate frames in the loop', 0, 64, read_only=True)
    scene: str = setting('person', 'subject', choices=SCENES, read_only=True)
    seed: int = setting(0, 'random seed', 0, 2**31 - 1, read_only=True)
    fps: float = setting(30.0, 'frame sets per second', 0.1, 120.0, read_only=True)
    k4a_calibration: str = setting('', 'Azure Kinect factory calibration JSON the rig is modelled on (empty: the '
                                       'shared recording\'s)', read_only=True)
    bunny_mesh: str = setting('', 'mesh of the bunny scene (empty: the shared one)', read_only=True)

    def studio(self) -> SynthConfig:
        return SynthConfig(cameras=self.cameras, frames=self.frames, board_poses=self.board_poses,
                           background_frames=self.background_frames, scene=self.scene, seed=self.seed, fps=self.fps,
                           k4a_calibration=self.k4a_calibration or default_k4a_calibration(),
                           bunny_mesh=self.bunny_mesh or default_bunny_mesh())


class SyntheticRig(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('synthetic_rig', **node_options)
        rig_cfg = declare_config(self, SyntheticRigConfig)
        cfg = rig_cfg.studio()
        fps = rig_cfg.fps
        self.diagnostics = Diagnostics(self, 'synthetic rig')
        rng = np.random.default_rng(cfg.seed)
        board = BoardConfig.from_yaml()
        rig, poses = make_rig(cfg, rng)
        plans = session_plan(cfg, board, rng)
        if not plans:
            raise BadInput('nothing to render: frames, board_poses and background_frames are all 0')
        renderer = StudioRenderer(cfg, rig, poses, board, rng)
        self.get_logger().info(f'rendering {len(plans)} frame sets for {cfg.cameras} cameras...')
        self.frames = []
        for plan in plans:
            rendered = renderer.render(plan)
            self.frames.append({cam.name: (numpy_to_image(rendered[cam.name].color, 'rgb8', 0, cam.color_frame),
                                           numpy_to_image(rendered[cam.name].depth.depth_mm, '16UC1', 0,
                                                          cam.depth_frame))
                                for cam in rig.cameras})
        self.infos = {cam.name: (camera_model_to_info(cam.color, 0, cam.color_frame),
                                 camera_model_to_info(cam.depth, 0, cam.depth_frame)) for cam in rig.cameras}
        self.pubs = {cam.name: [self.create_publisher(kind, topics.camera_topic(cam.name, name), qos.DRIVER)
                                for kind, name in ((Image, topics.COLOR_IMAGE), (CameraInfo, topics.COLOR_INFO),
                                                   (Image, topics.DEPTH_IMAGE), (CameraInfo, topics.DEPTH_INFO))]
                     for cam in rig.cameras}
        self.create_publisher(String, topics.RIG, qos.LATCHED).publish(String(data=rig.to_yaml()))
        self.jitter_ns = cfg.stamp_jitter_ms * 1e6
        self.rng = rng
        self.index = 0
        self.published = 0
        self.create_timer(1.0 / fps, self._publish)
        self.create_timer(1.0, lambda: self.diagnostics.report('ok', 'publishing', frame_sets=self.published))
        self.get_logger().info(f'synthetic_rig started: {len(self.frames)} frame sets looping at {fps:g} fps')

    def _publish(self) -> None:
        now = time.time_ns()
        for name, (color, depth) in self.frames[self.index].items():
            stamp = ns_to_stamp(now + int(np.clip(self.rng.normal(0, self.jitter_ns), -1e6, 1e6)))
            color_info, depth_info = self.infos[name]
            for msg, pub in zip((color, color_info, depth, depth_info), self.pubs[name]):
                msg.header.stamp = stamp
                pub.publish(msg)
        self.index = (self.index + 1) % len(self.frames)
        self.published += 1


def main(args=None):
    node_main(SyntheticRig, args)


if __name__ == '__main__':
    main()
