"""``volcap wire``: a raw bag through every camera's pipeline, recorded as the camera hosts would
send it to the fusion host (``volcap_core.wire``), so the fusion host can be run and measured
alone from a cheap source (``volcap live --bag WIREBAG``), as on a rig.

Each camera runs a ``CameraPipeline`` with the decisions of the ``camera_pipeline`` node (clean
plate from the clean-plate frames, then every capture frame cleaned, corrected with the
calibration's colour model and cut to its foreground region). The wire bag holds, per camera,
``wire/depth/image/compressedDepth``, ``wire/color/image/compressed`` and their camera_info,
stamped with the capture stamps, plus ``/volcap/rig`` and ``/volcap/calibration`` (latched).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from std_msgs.msg import String
from tqdm import tqdm

from volcap_color.corrector import CameraCorrection
from volcap_core import topics, wire
from volcap_core.bag_reader import BagReader
from volcap_core.bag_writer import BagWriter
from volcap_core.calibration import Calibration
from volcap_core.errors import BadInput
from volcap_core.frames import frame_sets, read_rig
from volcap_core.settings import setting
from volcap_filter.pipeline import DepthFilterConfig

from .camera import CameraPipeline, WireConfig

WIRE_STREAMS = (wire.WIRE_DEPTH_INFO, wire.WIRE_COLOR_INFO, wire.WIRE_DEPTH, wire.WIRE_COLOR)
_TYPES = {wire.WIRE_DEPTH_INFO: 'sensor_msgs/msg/CameraInfo', wire.WIRE_COLOR_INFO: 'sensor_msgs/msg/CameraInfo',
          wire.WIRE_DEPTH: 'sensor_msgs/msg/CompressedImage', wire.WIRE_COLOR: 'sensor_msgs/msg/CompressedImage'}


@dataclass
class WireBagConfig:
    """`volcap wire`: the wire of a raw bag, recorded."""
    bag: str | Path
    calibration: str | Path
    out: str | Path
    depth_scale: float = setting(0.5, 'cleaned depth size as a fraction of the colour size (volcap live: 0.5)',
                                 0.05, 4.0)
    wire: WireConfig = field(default_factory=WireConfig)
    progress: bool = True


@dataclass
class WireBagReport:
    path: Path
    cameras: list[str]
    frame_sets: int
    bytes_per_camera_frame: float           # mean wire bytes of one camera's frame
    raw_bytes_per_camera_frame: float       # the same frames' raw colour + depth
    ms_per_camera_frame: dict               # the pipeline's stages, mean per camera and frame
    seconds: float

    def mbit_per_s(self, fps: float = 30.0) -> float:
        """One camera's wire at ``fps``."""
        return self.bytes_per_camera_frame * 8 * fps / 1e6


def is_wire_bag(reader: BagReader) -> bool:
    """Whether a bag holds a recorded wire (not raw camera streams)."""
    return any(t.endswith(wire.WIRE_DEPTH) for t in reader.topics)


def wire_cameras(reader: BagReader) -> list[str]:
    """The cameras of a wire bag, by its topics (``<cam>/wire/...``)."""
    suffix = '/' + wire.WIRE_DEPTH
    return sorted({t[:-len(suffix)] for t in reader.topics if t.endswith(suffix)})


def record_wire(cfg: WireBagConfig) -> WireBagReport:
    calibration = Calibration.load(cfg.calibration)
    with BagReader(cfg.bag) as reader:
        if is_wire_bag(reader):
            raise BadInput(f'{cfg.bag} is already a wire bag')
        rig = read_rig(reader)
        rig_text = next((m.decode().data for m in reader.messages([topics.RIG])), None)
    cameras = [c for c in rig.names if c in calibration.cameras]
    if not cameras:
        raise BadInput(f'no camera of {cfg.bag} is in the calibration {cfg.calibration}')
    calibration_text = Path(cfg.calibration).read_text()
    pipelines = {}
    for name in cameras:
        correction = CameraCorrection(name, passthrough=True)
        correction.set_calibration(calibration_text)
        # the full-size colour is not corrected (add() returns it raw): the wire corrects its region
        pipeline = CameraPipeline(name, DepthFilterConfig(), rig, output_scale=cfg.depth_scale)
        pipelines[name] = (pipeline, correction)
    count, sent, raw, ms = 0, 0, 0, {}
    t0 = time.monotonic()
    out = Path(cfg.out)
    bar = tqdm(desc='wire frame sets', unit='set', disable=not cfg.progress)
    with BagWriter(out) as writer:
        writer.add_topic(topics.RIG, 'std_msgs/msg/String', latched=True)
        writer.add_topic(topics.CALIBRATION, 'std_msgs/msg/String', latched=True)
        for c in cameras:
            for stream in WIRE_STREAMS:
                writer.add_topic(topics.camera_topic(c, stream), _TYPES[stream])
        for fs in frame_sets(cfg.bag, phases=(topics.CLEAN_PLATE, topics.CAPTURE), cameras=cameras):
            wrote = False
            for name, frame in fs.cameras.items():
                pipeline, correction = pipelines[name]
                outcomes, cleaned = pipeline.add(frame, fs.stamp_ns, fs.phase)
                failed = [o.message for o in outcomes if o.kind == 'failed']
                if failed:
                    raise BadInput(f'{name}: {failed[0]}')
                if cleaned is None:
                    continue
                if count == 0 and not wrote:
                    # stamped with the first set sent: the bag starts where the wire does (a
                    # looping player would otherwise wait out the clean-plate seconds each pass)
                    if rig_text is not None:
                        writer.write(topics.RIG, String(data=rig_text), fs.stamp_ns)
                    writer.write(topics.CALIBRATION, String(data=calibration_text), fs.stamp_ns)
                pipeline.correction = correction
                try:
                    frame_out = pipeline.wire(cleaned.result.depth, cleaned.model, cleaned.result.source_color,
                                              frame.color_model, fs.stamp_ns, frame.color_frame_id, cfg.wire)
                finally:
                    pipeline.correction = None
                for stream, msg in zip(WIRE_STREAMS, (frame_out.depth_info, frame_out.color_info, frame_out.depth,
                                                      frame_out.color)):
                    writer.write(topics.camera_topic(name, stream), msg, fs.stamp_ns)
                sent += frame_out.bytes
                raw += frame.color.nbytes + frame.depth.size * 2        # as the drivers send them: uint16 depth
                for k, v in {**frame_out.timings_ms, **cleaned.result.timings_ms}.items():
                    ms[k] = ms.get(k, 0.0) + v
                wrote = True
            if wrote:
                count += 1
                bar.update()
    bar.close()
    if count == 0:
        raise BadInput(f'{cfg.bag} has no capture frame set with a cleaned camera: nothing to send')
    frames = count * len(cameras)
    return WireBagReport(out, cameras, count, sent / frames, raw / frames,
                         {k: round(v / frames, 2) for k, v in sorted(ms.items())}, time.monotonic() - t0)


def wire_summary(report: WireBagReport) -> str:
    return (f'wrote {report.path}: {report.frame_sets} frame sets of {len(report.cameras)} cameras in '
            f'{report.seconds:.0f} s; {report.bytes_per_camera_frame / 1000:.1f} KB a camera and frame '
            f'({report.mbit_per_s():.1f} Mbit/s per camera at 30 fps, '
            f'{np.round(report.raw_bytes_per_camera_frame / max(report.bytes_per_camera_frame, 1)):.0f}x '
            'less than the raw frames)')
