"""One camera's pipeline, without ROS: raw colour + depth + camera models in, cleaned depth
registered to colour, corrected colour and the views the later stages take out.

It composes the stages' own session classes, so every entry point decides alike: the depth
filter's ``CleanPlateSession`` (clean plate, registration, mask, flying pixels; what to learn,
clean, hold or skip) and, when a colour correction is given, the colour corrector's
``CameraCorrection``. The offline replay (``volcap_pipeline.replay``: ``volcap calibrate``,
``color-fit``, ``harmonise``, the evaluations) drives it frame by frame with decoded arrays; on a
rig the ``camera_pipeline`` node (``camera_pipeline_node``, one process per camera) drives it with
messages, decoded only for the frames it cleans. The separate ``depth_filter`` and
``color_corrector`` nodes drive the same two session classes one each.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from volcap_color.corrector import CameraCorrection
from volcap_color.correspondence import View, smooth_depth
from volcap_core.camera import CameraModel, depth_to_millimetres
from volcap_core.frames import CameraFrame
from volcap_core.rig import Rig
from volcap_filter.mask import BackgroundModel
from volcap_filter.pipeline import CleanResult, DepthCleaner, DepthFilterConfig
from volcap_filter.session import CleanPlateSession, FramePair, Outcome


@dataclass
class CleanedCamera:
    """One camera's output for one frame set: its input frame, the cleaning result (depth
    registered to colour, float32 metres, 0 = removed), the cleaner that made it (its
    ``output_model`` is the cleaned depth's camera model) and the corrected colour (the raw
    colour when no correction applies)."""
    name: str
    frame: CameraFrame
    result: CleanResult
    cleaner: DepthCleaner
    color: np.ndarray

    @property
    def model(self) -> CameraModel:
        return self.cleaner.output_model

    def color_view(self, T_world_color: np.ndarray, rays: np.ndarray | None = None) -> View:
        """The view the colour stage takes (correspondences, harmonisation): the raw colour at the
        cleaned depth's grid, depth smoothed (registered ToF noise seen sideways is a match error)."""
        return View(self.name, self.frame.color, smooth_depth(self.result.depth), self.model,
                    T_world_color, _rays=rays)

    def fusion_view(self, T_world_color: np.ndarray):
        """The view fusion takes (``volcap_fusion.tsdf.CameraView``): cleaned depth (mm) and
        corrected colour, both on the colour grid."""
        from volcap_fusion.tsdf import CameraView  # Open3D: only where a model is fused, not in a camera's node
        return CameraView(self.name, depth_to_millimetres(self.result.depth), self.model, self.color,
                          self.frame.color_model, T_world_color)


def _arrays(payload):
    return payload


class CameraPipeline:
    """The per-camera job of one camera: feed it frames (``add``: decoded arrays, offline) or
    pairs (``add_pair``: whatever ``decode`` turns into rgb uint8 + depth float32 metres, e.g.
    messages in the node) with the phase of the session; it answers with the ``Outcome``s of the
    depth session and, for cleaned frames, a ``CleanedCamera`` (``add``) or the corrected colour
    (``correct``). ``correction`` (optional) colour-corrects the cleaned frames' colour.
    ``max_held``: pairs kept while camera models or the extrinsic are still to come (offline
    everything is known before the first frame: 0)."""

    def __init__(self, camera: str, cfg: DepthFilterConfig | None = None, rig: Rig | None = None,
                 output_size: tuple[int, int] = (0, 0), output_scale: float = 1.0,
                 correction: CameraCorrection | None = None, decode: Callable[[Any], tuple] = _arrays,
                 max_held: int = 0, background: BackgroundModel | None = None):
        self.camera = camera
        self.session = CleanPlateSession(camera, cfg or DepthFilterConfig(), decode, output_size,
                                         max_held=max_held, background=background, output_scale=output_scale)
        if rig is not None:
            self.session.set_rig(rig)
        self.correction = correction

    def add(self, frame: CameraFrame, stamp_ns: int, phase: str | None) -> tuple[list[Outcome], CleanedCamera | None]:
        """One decoded frame of this camera in ``phase``: (every outcome, the cleaned camera or None)."""
        s = self.session
        s.set_model('color', frame.color_model)
        s.set_model('depth', frame.depth_model)
        outcomes = s.set_phase(phase)
        pair = FramePair(stamp_ns, frame.color_frame_id, frame.depth_frame_id == frame.color_frame_id,
                         (frame.color, frame.depth))
        outcomes += s.add(pair)
        cleaned = None
        for o in outcomes:
            if o.kind == 'cleaned':
                color = self.correct(frame.color)
                cleaned = CleanedCamera(self.camera, frame, o.result, o.cleaner, frame.color if color is None else color)
        return outcomes, cleaned

    def correct(self, color: np.ndarray, keep: bool = True) -> np.ndarray | None:
        """``color`` corrected, ``color`` itself when no correction applies, None when the
        correction drops the frame. The corrector reuses its output buffer for the next frame:
        ``keep`` copies it (not needed when the result is serialised at once)."""
        if self.correction is None:
            return color
        corrected = self.correction.apply(color)
        return corrected.copy() if keep and corrected is not None and corrected is not color else corrected
