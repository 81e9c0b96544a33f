"""Replay a bag as the depth filters would see it: learn the clean plate from its clean-plate
frames, and yield every capture frame set with each camera's depth cleaned.

The decisions (learn, clean, hold, skip) are the ``depth_filter`` node's own
(``volcap_filter.session.CleanPlateSession``); several configurations can be run side by side
on the same frames (the depth evaluation scores four methods).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from volcap_color.correspondence import View, smooth_depth
from volcap_core.bag_io import BagReader
from volcap_core.calibration import Calibration
from volcap_core.frames import BagFrameSet, CameraFrame, frame_sets, read_rig
from volcap_core.topics import CAPTURE, CLEAN_PLATE
from volcap_filter.pipeline import CleanResult, DepthCleaner, DepthFilterConfig
from volcap_filter.session import CleanPlateSession, FramePair


@dataclass
class CleanedCamera:
    frame: CameraFrame
    result: CleanResult
    cleaner: DepthCleaner


def cleaned_frame_sets(bag: str | Path, configs: dict[str, DepthFilterConfig], cameras: list[str] | None = None,
                       output_size: str = 'full', limit: int | None = None
                       ) -> Iterator[tuple[BagFrameSet, dict[str, dict[str, CleanedCamera]]]]:
    """Per capture frame set of ``bag`` (the first ``limit`` of them; None: all):
    ``{config name: {camera: CleanedCamera}}``.

    ``cameras`` limits the cameras (default: the rig's); ``output_size`` is ``full`` (the colour
    resolution, the depth_filter node's default) or ``half``."""
    if output_size not in ('full', 'half'):
        raise ValueError(f"output_size must be 'full' or 'half', got {output_size!r}")
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    names = [n for n in rig.names if cameras is None or n in cameras]
    sessions: dict[tuple[str, str], CleanPlateSession] = {}

    def session(config: str, name: str, frame: CameraFrame) -> CleanPlateSession:
        key = (config, name)
        if key not in sessions:
            c = frame.color_model
            size = (c.width, c.height) if output_size == 'full' else (c.width // 2, c.height // 2)
            s = CleanPlateSession(name, configs[config], lambda arrays: arrays, size, max_held=0)
            s.set_rig(rig)
            sessions[key] = s
        s = sessions[key]
        s.set_model('color', frame.color_model)
        s.set_model('depth', frame.depth_model)
        return s

    if limit is not None and limit < 1:
        return
    captures = 0
    kept = dict.fromkeys(configs, 0)    # cleaned depth pixels per config, to refuse an empty result
    for fs in frame_sets(bag, phases=(CLEAN_PLATE, CAPTURE), cameras=names):
        out: dict[str, dict[str, CleanedCamera]] = {c: {} for c in configs}
        for name, frame in fs.cameras.items():
            pair = FramePair(fs.stamp_ns, frame.color_frame_id, frame.depth_frame_id == frame.color_frame_id,
                             (frame.color, frame.depth))
            for config in configs:
                s = session(config, name, frame)
                s.set_phase(fs.phase)
                for o in s.add(pair):
                    if o.kind == 'cleaned':
                        out[config][name] = CleanedCamera(frame, o.result, o.cleaner)
                        if captures < 3:   # only the first sets are checked (_refuse_empty)
                            kept[config] += int(np.count_nonzero(o.result.depth))
                    elif o.kind == 'failed':
                        raise ValueError(o.message)
        if fs.phase == CAPTURE:
            captures += 1
            _refuse_empty(kept, captures, limit)
            yield fs, out
            if captures == limit:
                return


def _refuse_empty(kept: dict[str, int], captures: int, limit: int | None) -> None:
    """A cleaning that leaves no depth at all is a failure, not an empty table: checked once the
    first capture frame sets are in (a few empty ones can be a momentarily empty stage)."""
    if captures == min(limit or 3, 3):
        empty = [c for c, n in kept.items() if n == 0]
        if empty:
            raise ValueError(f'depth cleaning ({", ".join(empty)}) left no depth pixel in {captures} capture frame '
                             'sets of any camera: check the range gate, the clean plate and, for depth a driver '
                             'registered to colour, that its frame id equals the colour\'s (docs/rig.md)')


def capture_views(bag: str | Path, calibration: Calibration, frames: int, progress: bool = True
                  ) -> list[list[View]]:
    """Per capture frame set (up to ``frames``), one View per calibrated camera: cleaned depth
    registered to colour at full resolution and smoothed, posed by the calibration."""
    rays: dict[str, np.ndarray] = {}          # per camera, shared by its views of every frame set
    sets = []
    bar = tqdm(total=frames, desc='capture frame sets', unit='set', disable=not progress)
    for fs, cleaned in cleaned_frame_sets(bag, {'volcap': DepthFilterConfig()}, cameras=list(calibration.cameras),
                                          limit=frames):
        views = []
        for n, c in cleaned['volcap'].items():
            view = View(n, c.frame.color, smooth_depth(c.result.depth), c.cleaner.output_model,
                        calibration.T_world_color(n), _rays=rays.get(n))
            rays[n] = view.rays()
            views.append(view)
        sets.append(views)
        bar.update()
    bar.close()
    if not sets:
        raise ValueError(f'{bag} has no capture frame sets: the colour evaluation needs a subject in view')
    return sets
