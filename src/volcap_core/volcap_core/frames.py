"""Frame sets of a recorded bag as numpy arrays, for the offline tools (eval, calibrate, run).

Messages are grouped by the same synchroniser the nodes use; the session phase announced on
``volcap/phase`` is attached to every set, and the rig comes from ``volcap/rig``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from volcap_core import topics
from volcap_core.camera import CameraModel
from volcap_core.conversions import camera_info_to_model, color_to_rgb, depth_to_metres, stamp_to_ns
from volcap_core.rig import Rig
from volcap_core.sync import SYNC_TOLERANCE_NS, FrameSetSynchronizer

from .bag_io import BagError, BagReader

STREAMS = {topics.COLOR_IMAGE: 'color', topics.COLOR_INFO: 'color_info',
           topics.DEPTH_IMAGE: 'depth', topics.DEPTH_INFO: 'depth_info'}


@dataclass
class CameraFrame:
    color: np.ndarray          # (H, W, 3) uint8 RGB
    depth: np.ndarray          # (h, w) float32 metres, 0 = invalid
    color_model: CameraModel
    depth_model: CameraModel
    depth_frame_id: str
    color_frame_id: str


@dataclass
class BagFrameSet:
    index: int
    phase: str | None
    stamp_ns: int
    cameras: dict[str, CameraFrame]
    missing: list[str]


def read_rig(reader: BagReader) -> Rig:
    for msg in reader.messages([topics.RIG]):
        return Rig.from_yaml(msg.decode().data)
    raise BagError(f'{reader.path} has no rig description on {topics.RIG}')


def frame_sets(path: str | Path, phases: tuple[str, ...] | None = None, tolerance_ns: int = SYNC_TOLERANCE_NS,
               cameras: list[str] | None = None) -> Iterator[BagFrameSet]:
    """Every frame set of the bag in stamp order (optionally only those in ``phases``)."""
    with BagReader(path) as reader:
        rig = read_rig(reader)
        names = cameras or rig.names
        wanted = [topics.PHASE] + [topics.camera_topic(c, t) for c in names for t in STREAMS]
        sync = FrameSetSynchronizer(names, tuple(STREAMS.values()), tolerance_ns=tolerance_ns,
                                    timeout_ns=10**18, max_pending=8)
        phase_changes: dict[int, str] = {}   # stamp -> phase announced there
        index = 0

        def emit(sets):
            nonlocal index
            for fs in sets:
                cams, missing = {}, []
                for name in names:
                    parts = {s: fs.get(name, s) for s in STREAMS.values()}
                    if any(p is None for p in parts.values()):
                        missing.append(name)
                        continue
                    cams[name] = CameraFrame(color_to_rgb(parts['color']), depth_to_metres(parts['depth']),
                                             camera_info_to_model(parts['color_info']),
                                             camera_info_to_model(parts['depth_info']),
                                             parts['depth'].header.frame_id, parts['color'].header.frame_id)
                set_phase = _phase_at(phase_changes, fs.stamp_ns)
                if phases is None or set_phase in phases:
                    yield BagFrameSet(index, set_phase, fs.stamp_ns, cams, missing)
                index += 1

        for m in reader.messages(wanted):
            if m.topic == topics.PHASE:
                phase_changes[m.stamp_ns] = topics.parse_phase(m.decode().data)
                continue
            camera, _, rel = m.topic.partition('/')
            msg = m.decode()
            yield from emit(sync.add(camera, stamp_to_ns(msg.header.stamp), msg, stream=STREAMS[rel]))
        yield from emit(sync.flush())


def _phase_at(changes: dict[int, str], stamp_ns: int) -> str | None:
    """The phase announced last at or before ``stamp_ns``."""
    before = [t for t in changes if t <= stamp_ns]
    return changes[max(before)] if before else None
