"""Static transforms as the vendor drivers publish them on ``/tf_static``, without tf2.

A driver sends its fixed frames once, transient-local: the Azure Kinect driver
``depth_camera_link -> rgb_camera_link`` (and ``camera_base``, ``imu_link``), OrbbecSDK_ROS2
``camera_link -> camera_depth_frame -> camera_depth_optical_frame`` and the same for colour.
Each edge ``(parent, child, T_parent_child)`` is kept; ``lookup`` chains edges in either
direction to give ``T_target_source`` between any two connected frames, e.g. the depth-to-colour
extrinsic between the frame ids of a camera's two camera_info headers.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from .errors import BadInput
from .poses import invert


class TransformError(LookupError):
    """Two frames are not connected by the static transforms received so far."""


class StaticTransforms:
    def __init__(self):
        self._edges: dict[str, dict[str, np.ndarray]] = {}   # frame -> neighbour -> T_frame_neighbour

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        """One static transform; a later one for the same pair replaces it (a driver restarted)."""
        parent, child = parent.lstrip('/'), child.lstrip('/')
        if not parent or not child or parent == child:
            raise BadInput(f'a static transform needs two different frame ids, got {parent!r} -> {child!r}')
        T = np.asarray(T_parent_child, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise BadInput(f'transform {parent} -> {child} is not a finite 4x4 matrix')
        self._edges.setdefault(parent, {})[child] = T
        self._edges.setdefault(child, {})[parent] = invert(T)

    def __len__(self) -> int:
        return sum(len(n) for n in self._edges.values()) // 2

    @property
    def frames(self) -> list[str]:
        return sorted(self._edges)

    def lookup(self, target: str, source: str) -> np.ndarray:
        """T_target_source: maps points in ``source`` into ``target``."""
        target, source = target.lstrip('/'), source.lstrip('/')
        if target == source:
            return np.eye(4)
        # Breadth-first from the target; T accumulates T_target_frame along the path.
        seen = {target: np.eye(4)}
        queue = deque([target])
        while queue:
            frame = queue.popleft()
            for neighbour, T in self._edges.get(frame, {}).items():
                if neighbour in seen:
                    continue
                seen[neighbour] = seen[frame] @ T
                if neighbour == source:
                    return seen[neighbour]
                queue.append(neighbour)
        known = ', '.join(self.frames) or 'none yet'
        raise TransformError(f'no static transform chain from {source!r} to {target!r} (frames: {known})')

    def depth_to_color(self, color_frame: str, depth_frame: str, prefix: str = '') -> np.ndarray | None:
        """T_color_depth between a camera's two camera_info frame ids: identity for registered
        depth (the same frame), else the chain between them (``prefix`` prepended to both ids,
        for drivers whose headers lack their tf prefix), else None (not published yet)."""
        if color_frame == depth_frame:
            return np.eye(4)
        try:
            return self.lookup(prefix + color_frame, prefix + depth_frame)
        except TransformError:
            return None
