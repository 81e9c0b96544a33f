"""The offline replay of a bag through the per-camera pipelines: learn the clean plate from its
clean-plate frames, and yield every capture frame set with each camera cleaned.

Each camera runs a ``CameraPipeline`` (the depth_filter node's own decisions: learn, clean,
hold, skip), so a replay decides as the graph does. Several cleaning configurations can run
side by side on the same frames (the depth evaluation scores four methods). ``volcap
color-fit``, ``volcap harmonise``, the colour and depth evaluations and the demo take their
inputs from here.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from volcap_color.correspondence import View
from volcap_core.bag_reader import BagReader
from volcap_core.calibration import Calibration
from volcap_core.errors import BadInput
from volcap_core.frames import BagFrameSet, frame_sets, read_rig
from volcap_core.topics import CAPTURE, CLEAN_PLATE
from volcap_filter.pipeline import DepthFilterConfig

from .camera import CameraPipeline, CleanedCamera

__all__ = ['CleanedCamera', 'capture_views', 'cleaned_frame_sets']


def cleaned_frame_sets(bag: str | Path, configs: dict[str, DepthFilterConfig], cameras: list[str] | None = None,
                       output_size: str = 'full', limit: int | None = None
                       ) -> Iterator[tuple[BagFrameSet, dict[str, dict[str, CleanedCamera]]]]:
    """Per capture frame set of ``bag`` (the first ``limit`` of them; None: all):
    ``{config name: {camera: CleanedCamera}}``.

    ``cameras`` limits the cameras (default: the rig's); ``output_size`` is ``full`` (the colour
    resolution, the depth_filter node's default) or ``half``."""
    if output_size not in ('full', 'half'):
        raise BadInput(f"output_size must be 'full' or 'half', got {output_size!r}")
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    names = [n for n in rig.names if cameras is None or n in cameras]
    scale = 1.0 if output_size == 'full' else 0.5
    pipelines = {(config, name): CameraPipeline(name, cfg, rig, output_scale=scale)
                 for config, cfg in configs.items() for name in names}
    if limit is not None and limit < 1:
        return
    captures = 0
    kept = dict.fromkeys(configs, 0)    # cleaned depth pixels per config, to refuse an empty result
    for fs in frame_sets(bag, phases=(CLEAN_PLATE, CAPTURE), cameras=names):
        out: dict[str, dict[str, CleanedCamera]] = {c: {} for c in configs}
        for name, frame in fs.cameras.items():
            for config in configs:
                outcomes, cleaned = pipelines[(config, name)].add(frame, fs.stamp_ns, fs.phase)
                failed = [o.message for o in outcomes if o.kind == 'failed']
                if failed:
                    raise BadInput(failed[0])
                if cleaned is not None:
                    out[config][name] = cleaned
                    if captures < 3:   # only the first sets are checked (_refuse_empty)
                        kept[config] += int(np.count_nonzero(cleaned.result.depth))
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
            raise BadInput(f'depth cleaning ({", ".join(empty)}) left no depth pixel in {captures} capture frame '
                           'sets of any camera: check the range gate, the clean plate and, for depth a driver '
                           'registered to colour, that its frame id equals the colour\'s (docs/rig.md)')


def capture_views(bag: str | Path, calibration: Calibration, frames: int, progress: bool = True
                  ) -> list[list[View]]:
    """Per capture frame set (up to ``frames``), one View per calibrated camera: cleaned depth
    registered to colour at full resolution and smoothed, posed by the calibration."""
    rays: dict[str, np.ndarray] = {}          # per camera, shared by its views of every frame set
    sets = []
    bar = tqdm(total=frames, desc='capture frame sets', unit='set', disable=not progress)
    for _, cleaned in cleaned_frame_sets(bag, {'volcap': DepthFilterConfig()}, cameras=list(calibration.cameras),
                                         limit=frames):
        views = []
        for n, c in cleaned['volcap'].items():
            view = c.color_view(calibration.T_world_color(n), rays.get(n))
            rays[n] = view.rays()
            views.append(view)
        sets.append(views)
        bar.update()
    bar.close()
    if not sets:
        raise BadInput(f'{bag} has no capture frame sets: the colour evaluation needs a subject in view')
    return sets
