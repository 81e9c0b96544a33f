"""The rig pipeline without ROS: one frame set's camera parts -> the views placed in the output
frame -> the fused model -> its GLB -> the sequence on disk.

The tsdf_fusion node drives it (its parts are the received messages, and it publishes what
``fuse`` returns); so can anything else that has a frame set's cleaned depth and corrected colour
(``volcap_pipeline``'s offline code uses the same ``TsdfFusion``, ``encode`` and
``SequenceWriter`` it composes). The decisions about missing and unusable cameras are
``frame_sets.frame_set_views``'.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from volcap_core import wire
from volcap_core.calibration import Calibration
from volcap_core.conversions import compressed_to_rgb
from volcap_core.poses import invert

from .frame_sets import FrameSetViews, frame_set_views
from .glb import EncodeConfig, EncodedFrame, encode
from .sequence import SequenceWriter
from .tsdf import CameraView, FusedModel, TsdfFusion


@dataclass
class FusedSet:
    """What became of one frame set: its views and the cameras left out (``plan``; ``plan.skipped``
    says why nothing was fused), the model (None when skipped), its GLB (when one was asked for
    or the sequence keeps GLBs) and the frame both are given in."""
    stamp_ns: int
    plan: FrameSetViews
    frame: str
    T_frame_world: np.ndarray
    model: FusedModel | None = None
    encoded: EncodedFrame | None = None

    @property
    def empty(self) -> bool:
        return self.model is not None and len(self.model.vertices) == 0


class RigFusion:
    """Frame sets into models, GLBs and (with ``writer``) a sequence. ``min_cameras``: fewer
    usable views and the set is skipped."""

    def __init__(self, fusion: TsdfFusion, encoding: EncodeConfig, min_cameras: int = 1,
                 writer: SequenceWriter | None = None, decode_threads: int = 2):
        self.fusion = fusion
        self.encoding = encoding
        self.min_cameras = min_cameras
        self.writer = writer
        # the cameras' parts become views in these threads (the wire's PNG / JPEG decoding
        # releases the GIL): 12.0 -> 12.6 sets/s at 10 mm from the demo's wire on 2 cores
        self.pool = ThreadPoolExecutor(decode_threads, 'rig_views') if decode_threads > 1 else None

    def fuse(self, stamp_ns: int, calibration: Calibration, cameras: list[str], parts: dict[str, Any],
             to_view: Callable[[str, Any, np.ndarray], CameraView], glb: bool = False) -> FusedSet:
        """``parts[camera]`` (absent or None: the camera missed the set) becomes a view through
        ``to_view(camera, part, T_frame_color)``; the views are fused in the calibration's output
        frame (the studio frame when it has one, on the floor when the floor defined it). A GLB is
        encoded when ``glb`` or the sequence keeps GLBs, and the model is not empty."""
        frame, T_frame_world = calibration.output_frame()
        studio = calibration.studio
        on_floor = studio is not None and studio.details.get('source') == 'floor'
        plan = frame_set_views(stamp_ns, cameras, parts,
                               lambda c, p: to_view(c, p, T_frame_world @ calibration.T_world_color(c)),
                               self.min_cameras, self.pool)
        out = FusedSet(stamp_ns, plan, frame, T_frame_world)
        if plan.skipped:
            return out
        out.model = self.fusion.fuse(plan.views, on_floor=on_floor, stamp_ns=stamp_ns)
        if not out.empty and (glb or (self.writer is not None and 'glb' in self.writer.formats)):
            out.encoded = encode(out.model, self.encoding, stamp_ns, self.writer.written if self.writer else None,
                                 frame)
        return out

    def write(self, fused: FusedSet) -> None:
        """The fused set into the sequence (a ``writer`` is needed). ``OSError`` (a full disk)
        leaves the sequence whole up to the frame before."""
        self.writer.write(fused.model, fused.stamp_ns, fused.plan.missing, fused.frame, invert(fused.T_frame_world),
                          fused.encoded)


def wire_view(cam: str, depth_msg, depth_info, color_msg, color_info, T_frame_color: np.ndarray) -> CameraView:
    """One camera's wire (``volcap_core.wire``) as the view fusion integrates: each region
    decoded and put back on its full (binned) grid."""
    model, region = wire.info_region(depth_info)
    depth_mm, depth_model = wire.place_region(wire.decode_depth(depth_msg), region, model)
    model, region = wire.info_region(color_info)
    color, color_model = wire.place_region(compressed_to_rgb(color_msg), region, model)
    return CameraView(cam, depth_mm, depth_model, color, color_model, T_frame_color)
