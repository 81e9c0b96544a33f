"""From a gathered frame set to the views the fusion integrates, and what to do about cameras that
are missing or unusable (the tsdf_fusion node's decisions, without ROS)."""
from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, Callable

from volcap_core import topics
from volcap_core.errors import BadInput
from volcap_core.settings import setting

from .tsdf import CameraView

ALL = 'all'
WIRE, FULL = 'wire', 'full'      # the tsdf_fusion node's inputs


@dataclass
class FusionNodeConfig:
    """The tsdf_fusion node's own settings (the fusion itself: ``FusionConfig``)."""
    cameras: tuple[str, ...] = setting((ALL,), 'cameras to fuse ("all": every calibrated camera)', read_only=True)
    input: str = setting(WIRE, 'what each camera sends: "wire" (the camera pipelines\' compact wire: foreground '
                         'regions, compressedDepth + JPEG with roi / binning) or "full" (depth/image_clean and '
                         'color/image_corrected, as depth_filter + color_corrector publish them)',
                         choices=(WIRE, FULL), read_only=True)
    sync_tolerance_ms: float = setting(0.0, 'stamp tolerance within a frame set, ms (0: just under half the frame '
                                       'period the stamps show)', 0.0, 100.0,
                                       read_only=True)
    frame_timeout_ms: float = setting(300.0, 'after this, fuse the cameras that arrived', 1.0, 10_000.0,
                                      read_only=True)
    min_cameras: int = setting(1, 'fewer usable cameras than this: the frame set is skipped', 1, 64)
    queue_size: int = setting(1, 'frame sets waiting for fusion (the oldest is dropped)', 1, 100, read_only=True)
    phases: tuple[str, ...] = setting((topics.CAPTURE,), 'session phases to fuse while one is announced on '
                                      '/volcap/phase')
    reliable: bool = setting(False, 'subscribe reliably (offline replay: lose no frame)', read_only=True)
    in_order: bool = setting(True, 'drop a frame set older than one already sent to fusion (one left incomplete '
                             'past a newer complete one), so a renderer never goes back in time; offline '
                             'replay keeps them')
    marker_max_triangles: int = setting(150_000, 'the mesh marker is decimated above this', 1000, 10_000_000)
    output_dir: str = setting('', 'write the sequence (PLY + GLB per time step) here', read_only=True)
    output_formats: tuple[str, ...] = setting(('ply', 'glb'), 'sequence file formats', read_only=True)
    silent_periods: float = setting(10.0, 'a camera is reported silent (ERROR) once the others have delivered this '
                                    'many frames since its last one, until it returns (all quiet together: idle)',
                                    2.0, 1000.0)
    calibration_grace_s: float = setting(15.0, 'waiting longer than this for the latched calibration is reported '
                                         '(WARN); before it the node is starting (discovery takes 2-5 s on 2 cores)',
                                         0.0, 3600.0)


@dataclass
class FrameSetViews:
    """The views of one frame set, and the cameras left out of it."""
    stamp_ns: int
    views: list[CameraView]
    missing: list[str]                                    # absent or unusable, sorted
    problems: dict[str, str] = field(default_factory=dict)   # unusable camera -> why
    skipped: str = ''                                     # why the set is not fused ('' = fuse it)


def frame_set_views(stamp_ns: int, cameras: list[str], parts: dict[str, Any],
                    to_view: Callable[[str, Any], CameraView], min_cameras: int,
                    pool: Executor | None = None) -> FrameSetViews:
    """``parts[camera]`` is what ``to_view`` turns into a CameraView (absent or None: the camera
    missed the set). A camera whose conversion fails is left out with the reason; a set with
    fewer than ``min_cameras`` views is skipped. ``pool``: convert the cameras in its threads
    (decoding the wire's PNG and JPEG releases the GIL)."""
    views, problems, absent = [], {}, []

    def convert(cam):
        try:
            return to_view(cam, parts[cam]), None
        except (ValueError, KeyError) as e:
            return None, str(e)
    present = []
    for cam in cameras:
        if parts.get(cam) is None:
            absent.append(cam)
        else:
            present.append(cam)
    for cam, (view, problem) in zip(present, (pool.map if pool is not None else map)(convert, present)):
        if problem is not None:
            problems[cam] = problem
        else:
            views.append(view)
    missing = sorted(set(absent) | set(problems))
    skipped = ''
    if len(views) < min_cameras:
        skipped = (f'frame set {stamp_ns} skipped: {len(views)} of {len(cameras)} cameras'
                   + (f' (missing {", ".join(missing)})' if missing else ''))
    return FrameSetViews(stamp_ns, views, missing, problems, skipped)


def fused_cameras(calibrated: list[str], wanted: list[str]) -> list[str]:
    """The cameras to fuse: every calibrated one for ``[all]``, else ``wanted``, each of which the
    calibration must have (ValueError naming the others)."""
    if wanted == [ALL]:
        return list(calibrated)
    absent = [c for c in wanted if c not in calibrated]
    if absent:
        raise BadInput(f'cameras {absent} are not in the calibration')
    return list(wanted)


def fused_phase(announced: str | None, phases: tuple[str, ...]) -> bool:
    """Whether a frame set captured while ``announced`` was the session phase is fused (no phase
    announced, or no phase filter: every set)."""
    return announced is None or not phases or announced in phases


class PhaseTimeline:
    """The session phase each frame set was captured in. A phase message that carries
    ``since_ns`` (``topics.parse_phase_change``; `volcap synth` writes it) places the change at
    that capture stamp. One without it is placed by arrival: it is sent in order with the frames
    (a player sends it at its place in the bag; a rig's session tool between frames), so frames
    stamped up to the newest one received before the change belong to the phase before it.
    Arrival is only as good as the frames' lag: the fusion receives the camera pipelines' output,
    which trails the player by the pipelines' work, and on a loaded host the board views still in
    the pipelines when ``capture`` was announced were fused as capture. Deciding at emission time
    would be worse still: a set that waited for its late cameras would take the phase that began
    meanwhile."""

    def __init__(self, keep: int = 16):
        self._changes: list[tuple[int, str]] = []     # (frames stamped after this belong to it, phase)
        self._keep = keep
        self.newest_ns = -1

    def frame(self, stamp_ns: int) -> None:
        self.newest_ns = max(self.newest_ns, stamp_ns)

    def change(self, phase: str | None, since_ns: int | None = None) -> None:
        boundary = self.newest_ns if since_ns is None else since_ns - 1
        self._changes = sorted(self._changes + [(boundary, phase)], key=lambda c: c[0])[-self._keep:]

    def at(self, stamp_ns: int) -> str | None:
        """The phase of a frame set with this stamp (None: none announced before it)."""
        phase = None
        for boundary, name in self._changes:
            if stamp_ns > boundary:
                phase = name
        return phase
