"""Where the rig comes from: one rule, in one ROS-free place, for the nodes and the bag reader.

1. A rig file (``rig_file`` of a node, ``rig.yaml`` beside a bag's files): the operator's word,
   written by ``volcap rig`` from the camera makers' factory data. It wins over everything.
2. ``/volcap/rig``: the rig description a bag or another node publishes (latched).
3. Assembled: each camera's colour and depth camera_info, and the depth-to-colour extrinsic
   between their frame ids from the drivers' ``/tf_static`` (identity for depth the driver
   already registered to colour, whose frame id is the colour's).

The ``RigResolver`` is fed whatever arrives, in any order (``set_file``, ``offer_description``,
``add_camera_info``, ``add_transform``); ``rig`` is the rig by that rule and ``source`` says where
it came from. The depth_filter and calibration_service nodes feed it from their subscriptions
(sharing their ``/tf_static`` listener's ``transforms``);
``volcap_core.frames.read_rig`` feeds it a bag's messages.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .camera import CameraModel
from .errors import BadInput
from .rig import Rig, RigCamera
from .tf import StaticTransforms

FILE, TOPIC, ASSEMBLED = 'rig file', '/volcap/rig', 'camera_info + /tf_static'


class RigResolver:
    """The rig by the one rule (module docstring). ``cameras``: the camera names to assemble (in
    this order); ``tf_prefix``: prepended to camera_info frame ids when looking them up on
    ``/tf_static``."""

    def __init__(self, cameras: list[str] | None = None, tf_prefix: str = ''):
        self.cameras = list(cameras or [])
        self.tf_prefix = tf_prefix
        self.transforms = StaticTransforms()
        self.infos: dict[tuple[str, str], tuple[CameraModel, str]] = {}   # (camera, stream) -> (model, frame id)
        self.rig: Rig | None = None
        self.source = ''            # FILE (with its path), TOPIC or ASSEMBLED; '' while there is no rig
        self.waiting: list[str] = []    # assembled cameras still without an extrinsic, and why

    @property
    def decided_by_file(self) -> bool:
        return self.source.startswith(FILE)

    def set_file(self, path: str | Path) -> Rig:
        """The operator's rig file: it decides from now on. BadInput (or OSError) when unusable."""
        rig = Rig.from_yaml(Path(path).read_text())
        self.rig, self.source = rig, f'{FILE} {path}'
        return rig

    def offer_description(self, text: str) -> Rig | None:
        """A ``/volcap/rig`` description: the rig, unless a rig file decides (None: ignored).
        BadInput when unusable (the rig in force is kept)."""
        if self.decided_by_file:
            return None
        rig = Rig.from_yaml(text)
        self.rig, self.source = rig, TOPIC
        return rig

    def add_camera_info(self, camera: str, stream: str, model: CameraModel, frame_id: str) -> Rig | None:
        """A camera's ``color`` or ``depth`` camera_info; the newly assembled rig when that changed
        it (and neither a file nor ``/volcap/rig`` decides), else None."""
        if stream not in ('color', 'depth'):
            raise BadInput(f"stream must be 'color' or 'depth', got {stream!r}")
        if self.infos.get((camera, stream)) == (model, frame_id):
            return None          # every frame repeats its camera_info: nothing to assemble again
        if camera not in self.cameras:
            self.cameras.append(camera)
        self.infos[(camera, stream)] = (model, frame_id)
        return self._assemble()

    def add_transform(self, parent: str, child: str, T_parent_child: np.ndarray) -> Rig | None:
        """One ``/tf_static`` transform; the newly assembled rig when that changed it, else None."""
        self.transforms.add(parent, child, T_parent_child)
        return self._assemble()

    def refresh(self) -> Rig | None:
        """After ``transforms`` changed outside (a node's /tf_static listener shares it): the newly
        assembled rig when that changed it, else None."""
        return self._assemble()

    def extrinsic(self, camera: str) -> np.ndarray | None:
        """T_color_depth of ``camera`` from its camera_info frame ids and ``/tf_static`` (identity
        for registered depth), or None while the chain is unknown."""
        color, depth = self.infos.get((camera, 'color')), self.infos.get((camera, 'depth'))
        if color is None or depth is None:
            return None
        return self.transforms.depth_to_color(color[1], depth[1], self.tf_prefix)

    def _assemble(self) -> Rig | None:
        """Every camera whose camera_info and extrinsic are known. The assembled rig only grows
        (a camera that has spoken is not dropped), and never replaces a file's or /volcap/rig's."""
        if self.source and self.source != ASSEMBLED:
            return None
        cameras, waiting = [], []
        for cam in self.cameras:
            color, depth = self.infos.get((cam, 'color')), self.infos.get((cam, 'depth'))
            if color is None or depth is None:
                continue
            T = self.extrinsic(cam)
            if T is None:
                waiting.append(f'{cam} ({depth[1]} -> {color[1]})')
                continue
            cameras.append(RigCamera(cam, color[0], depth[0], T))
        self.waiting = waiting
        current = self.rig.cameras if self.rig is not None else []
        if not cameras or len(cameras) < len(current) or _same(cameras, current):
            return None
        self.rig, self.source = Rig(cameras, 'tf_static'), ASSEMBLED
        return self.rig


def _same(a: list[RigCamera], b: list[RigCamera]) -> bool:
    return [c.name for c in a] == [c.name for c in b] and all(
        x.color == y.color and x.depth == y.depth and np.allclose(x.T_color_depth, y.T_color_depth)
        for x, y in zip(a, b))
