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

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from volcap_color.corrector import CameraCorrection
from volcap_color.correspondence import View, smooth_depth
from volcap_core import wire
from volcap_core.camera import CameraModel, depth_to_millimetres
from volcap_core.frames import CameraFrame
from volcap_core.rig import Rig
from volcap_core.settings import setting
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


@dataclass
class WireConfig:
    """What the camera pipeline sends the fusion host (``volcap_core.wire``)."""
    wire: bool = setting(True, 'publish the compact wire (wire/depth/image/compressedDepth, wire/color/image/'
                         'compressed and their camera_info) for the fusion host', read_only=True)
    wire_binning: int = setting(1, 'decimation of the cleaned depth on the wire (image_proc crop_decimate, '
                                'camera_info binning)', 1, 8, read_only=True)
    wire_color_binning: int = setting(1, 'decimation of the colour on the wire', 1, 8, read_only=True)
    wire_margin_px: int = setting(4, 'pixels of the depth grid kept around the mask region', 0, 64, read_only=True)
    jpeg_quality: int = setting(95, 'JPEG quality of the colour on the wire (4:4:4, no chroma subsampling)', 50, 100)
    png_level: int = setting(1, 'zlib level of the depth PNG on the wire (1: fastest; lossless at any level)',
                             0, 9)


@dataclass
class WireFrame:
    """One camera's frame on the wire: messages ready to publish or record, and what it cost."""
    depth: Any                 # CompressedImage (compressedDepth)
    depth_info: Any            # CameraInfo with roi / binning
    color: Any                 # CompressedImage (JPEG)
    color_info: Any
    timings_ms: dict = field(default_factory=dict)

    @property
    def bytes(self) -> int:
        return len(self.depth.data) + len(self.color.data)


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
                color = self.correct(o.color)
                cleaned = CleanedCamera(self.camera, frame, o.result, o.cleaner, o.color if color is None else color)
        return outcomes, cleaned

    def correct(self, color: np.ndarray, keep: bool = True) -> np.ndarray | None:
        """``color`` corrected, ``color`` itself when no correction applies, None when the
        correction drops the frame. The corrector reuses its output buffer for the next frame:
        ``keep`` copies it (not needed when the result is serialised at once)."""
        if self.correction is None:
            return color
        corrected = self.correction.apply(color)
        return corrected.copy() if keep and corrected is not None and corrected is not color else corrected

    def wire(self, depth_m: np.ndarray, depth_model: CameraModel, color: np.ndarray, color_model: CameraModel,
             stamp_ns: int, frame_id: str, cfg: WireConfig) -> WireFrame | None:
        """One cleaned frame on the wire: the depth (float32 metres on ``depth_model``'s grid, 0 =
        removed) cropped to its foreground and PNG'd, the raw ``color`` of that region corrected,
        masked and JPEG'd (None when the correction drops the frame). Only the region is touched
        after the crop. A frame with no depth left sends one empty block, so the fusion host
        still knows the camera delivered."""
        t0 = time.perf_counter()
        valid = depth_m > 0
        region = wire.foreground_region(valid, cfg.wire_binning, cfg.wire_margin_px)
        if region is None:
            region = wire.Region(0, 0, cfg.wire_binning, cfg.wire_binning, cfg.wire_binning)
        depth_mm = depth_to_millimetres(np.ascontiguousarray(region.take(depth_m)))
        size = (depth_model.width, depth_model.height)
        color_region = region.scaled_to(size, (color_model.width, color_model.height), cfg.wire_color_binning,
                                        margin=cfg.wire_color_binning)
        crop = color_region.take(color)
        t1 = time.perf_counter()
        if self.correction is not None:
            crop = self.correction.apply(crop, (color_region.x, color_region.y, color_model.width,
                                                color_model.height, color_region.binning))
            if crop is None:
                return None
        t2 = time.perf_counter()
        # the mask on the colour region: each colour pixel takes the depth pixel it lies in
        rows, cols = wire.pixels_under(color_region, (color_model.width, color_model.height), size)
        dilate = max(1, 8 // color_region.binning)         # a JPEG block around the silhouette
        crop = wire.mask_outside(np.ascontiguousarray(crop), valid[np.ix_(rows, cols)], dilate)
        depth_msg = wire.encode_depth(depth_mm, stamp_ns, frame_id, cfg.png_level)
        t3 = time.perf_counter()
        color_msg = wire.encode_color(crop, stamp_ns, frame_id, cfg.jpeg_quality)
        t4 = time.perf_counter()
        return WireFrame(depth_msg, wire.region_info(depth_model, region, stamp_ns, frame_id), color_msg,
                         wire.region_info(color_model, color_region, stamp_ns, frame_id),
                         {'crop_ms': (t1 - t0) * 1e3, 'correct_ms': (t2 - t1) * 1e3, 'png_ms': (t3 - t2) * 1e3,
                          'jpeg_ms': (t4 - t3) * 1e3})
