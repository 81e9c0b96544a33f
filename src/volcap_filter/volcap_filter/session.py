"""One camera's depth-cleaning session: what to do with each colour/depth pair as frames, camera
models, the rig and the session phase arrive in any order.

A pair is learnt into the clean plate (during the ``clean_plate`` phase, or while a requested
capture still needs frames), cleaned, held (its camera models or the rig's depth-to-colour
extrinsic are still to come: topics have no order across them, so a late clean-plate frame
must still be learnt, not lost) or skipped (held too long, or unusable). The cleaner is rebuilt
whenever the camera models, the registration mode or the extrinsic change. Native depth needs
the depth-to-colour extrinsic: from the rig (``/volcap/rig`` or a rig file) or, on a rig of
vendor drivers, from their ``/tf_static``. The ``depth_filter`` node
and the per-camera pipeline (``volcap_pipeline.camera``, which the offline replay drives) both drive this class, so they decide alike.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from volcap_core import topics
from volcap_core.camera import CameraModel
from volcap_core.rig import Rig
from volcap_core.settings import color_transport_setting, setting, tf_prefix_setting

from .mask import BackgroundModel
from .pipeline import CleanResult, DepthCleaner, DepthFilterConfig
from .registration import DepthRegistration


@dataclass
class DepthFilterNodeConfig:
    """The depth_filter node's own settings (the cleaning itself: ``DepthFilterConfig``)."""
    camera: str = setting('', 'camera name in the rig description (empty: the last part of the namespace)',
                          read_only=True)
    rig_file: str = setting('', 'rig description YAML (`volcap rig`) giving the depth-to-colour extrinsic '
                            '(empty: /volcap/rig or /tf_static)', read_only=True)
    tf_prefix: str = tf_prefix_setting()
    color_transport: str = color_transport_setting()
    output_width: int = setting(0, 'cleaned depth width (0 = the colour width)', 0, 8192, read_only=True)
    output_height: int = setting(0, 'cleaned depth height (0 = the colour height)', 0, 8192, read_only=True)
    output_scale: float = setting(1.0, 'cleaned depth size as a fraction of the colour size, where output_width / '
                                  'output_height are 0 (volcap live: 0.5)', 0.05, 4.0, read_only=True)
    clean_plate_frames: int = setting(10, 'frames gathered by ~/capture_clean_plate', 1, 1000)
    background_file: str = setting('', 'clean plate to load at start and save after learning (npz)',
                                   read_only=True)
    publish_points: bool = setting(True, 'publish the coloured point cloud')
    sync_tolerance_ms: float = setting(0.0, 'stamp tolerance between colour and depth, ms (0: just under half the frame '
                                       'period the stamps show)', 0.0, 100.0,
                                       read_only=True)
    # Live, a colour image waits at most this long for its depth (and four newer frames push it
    # out sooner); offline the run waits longer, as a loaded host may serve the two streams
    # seconds apart and every frame counts.
    pair_timeout_ms: float = setting(500.0, 'how long an image waits for its colour or depth partner, ms (wall '
                                     'time; offline replay: longer)', 1.0, 600_000.0, read_only=True)
    max_held_frames: int = setting(4, 'image pairs kept while their camera_info or the rig is still to come',
                                   0, 100, read_only=True)
    reliable: bool = setting(False, 'subscribe reliably (offline replay: lose no frame)', read_only=True)
    figure_dir: str = setting('/tmp/volcap_figures', 'where ~/save_figures writes PNGs')


@dataclass
class FramePair:
    """A colour and a depth image of one stamp; ``payload`` is whatever ``decode`` turns into
    (rgb uint8, depth float32 metres): messages in the node, arrays offline."""
    stamp_ns: int              # the colour image's: cleaned output carries it
    frame_id: str              # the colour optical frame
    registered: bool           # depth already registered to colour (same frame_id)
    payload: Any


@dataclass
class Outcome:
    """What happened: ``cleaned`` (result and cleaner set), ``learnt``, ``plate_done`` (the clean
    plate is complete), ``held``, ``skipped`` or ``failed`` (the pair could not be used)."""
    kind: str
    message: str = ''
    pair: FramePair | None = None
    result: CleanResult | None = None
    cleaner: DepthCleaner | None = None
    color: np.ndarray | None = None
    depth: np.ndarray | None = None


class CleanPlateSession:
    def __init__(self, camera: str, cfg: DepthFilterConfig, decode: Callable[[Any], tuple[np.ndarray, np.ndarray]],
                 output_size: tuple[int, int] = (0, 0), max_held: int = 4,
                 background: BackgroundModel | None = None, output_scale: float = 1.0):
        """``output_size`` (0: the colour size times ``output_scale``) is the cleaned depth's."""
        self.camera = camera
        self.cfg = cfg
        self.decode = decode
        self.output_size = output_size
        self.output_scale = output_scale
        self.max_held = max_held
        self.background = background or BackgroundModel()
        self.rig: Rig | None = None
        self.extrinsic: np.ndarray | None = None   # T_color_depth from /tf_static
        self.models: dict[str, CameraModel] = {}
        self.phase: str | None = None
        self.learn_remaining = 0
        self.cleaned_for_capture = 0    # frames cleaned outside the calibration and clean-plate phases
        self.cleaner: DepthCleaner | None = None
        self.held: deque[tuple[FramePair, str | None]] = deque()

    # inputs ------------------------------------------------------------------------------
    def set_rig(self, rig: Rig) -> list[Outcome]:
        rig.camera(self.camera)   # KeyError when the rig lacks this camera
        self.rig = rig
        self.cleaner = None       # rebuilt with the new extrinsic on the next frame
        return self._process_held()

    def set_extrinsic(self, T_color_depth: np.ndarray) -> list[Outcome]:
        """The depth-to-colour extrinsic from the drivers' static transforms (a rig wins over it)."""
        if self.extrinsic is None or not np.allclose(self.extrinsic, T_color_depth):
            self.extrinsic = np.asarray(T_color_depth, dtype=np.float64)
            if self.rig is None:
                self.cleaner = None
        return self._process_held()

    def set_model(self, stream: str, model: CameraModel) -> list[Outcome]:
        self.models[stream] = model
        return self._process_held()

    def set_config(self, cfg: DepthFilterConfig) -> None:
        self.cfg = cfg
        if self.cleaner is not None:
            self.cleaner.cfg = cfg

    def set_phase(self, phase: str | None) -> list[Outcome]:
        out = []
        if phase == topics.CLEAN_PLATE and self.phase != phase:
            self._reset_background()
        elif self.phase == topics.CLEAN_PLATE and phase != topics.CLEAN_PLATE and not self._plate_frames_held():
            out.append(self._plate_done())   # else once the held clean-plate frames are learnt
        self.phase = phase
        return out

    def capture_clean_plate(self, frames: int) -> None:
        """Learn a new clean plate from the next ``frames`` pairs, whatever the phase."""
        self._reset_background()
        self.learn_remaining = frames

    def add(self, pair: FramePair) -> list[Outcome]:
        """A new pair, in the current phase."""
        self.held.append((pair, self.phase))
        return self._process_held()

    @property
    def has_clean_plate(self) -> bool:
        return self.background.frames > 0

    @property
    def missing_clean_plate(self) -> bool:
        """Frames are being cleaned for capture without the clean plate the mask needs (none
        learnt, none being learnt). Not before the first such frame: a graph that starts before
        its driver or bag, or a session still showing the board or learning the plate in its
        ``clean_plate`` phase, lacks nothing yet."""
        return (self.cfg.mask_mode == 'clean_plate' and not self.has_clean_plate and self.learn_remaining == 0
                and self.cleaned_for_capture > 0)

    # decisions ---------------------------------------------------------------------------
    def waiting_for(self, pair: FramePair) -> str | None:
        """What a pair still needs before it can be cleaned, or None."""
        if 'color' not in self.models or 'depth' not in self.models:
            return 'no camera_info yet'
        if not pair.registered and self.rig is None and self.extrinsic is None:
            return (f'waiting for the depth-to-colour extrinsic (/tf_static from the driver, rig_file, or '
                    f'/{topics.RIG})')
        return None

    def _process_held(self) -> list[Outcome]:
        out: list[Outcome] = []
        while self.held:
            pair, phase = self.held[0]
            waiting = self.waiting_for(pair)
            if waiting is None:
                self.held.popleft()
                out += self._process(pair, phase)
            elif len(self.held) > self.max_held:
                self.held.popleft()
                out.append(Outcome('skipped', f'{self.camera}: {waiting}; frame skipped', pair))
                out += self._late_plate_frame_done(phase)
            else:
                out.append(Outcome('held', f'{self.camera}: {waiting}; {len(self.held)} frame(s) held', pair))
                break
        return out

    def _process(self, pair: FramePair, phase: str | None) -> list[Outcome]:
        try:
            cleaner = self._cleaner(pair)
            color, depth = self.decode(pair.payload)
            if phase == topics.CLEAN_PLATE or self.learn_remaining > 0:
                cleaner.learn_background(color, depth)
                out = [Outcome('learnt', pair=pair)]
                if self.learn_remaining > 0:
                    self.learn_remaining -= 1
                    if self.learn_remaining == 0:
                        out.append(self._plate_done())
                else:
                    out += self._late_plate_frame_done(phase)
                return out
            result = cleaner.process(color, depth)
            if phase not in (topics.CALIBRATION_PHASE, topics.CLEAN_PLATE):
                self.cleaned_for_capture += 1
        except ValueError as e:   # conversion errors, sizes that disagree with camera_info, empty depth
            return [Outcome('failed', f'{self.camera}: frame skipped: {e}', pair)]
        # the colour the depth was cleaned with: averaged where the scene held still (temporal)
        return [Outcome('cleaned', pair=pair, result=result, cleaner=cleaner, color=result.source_color, depth=depth)]

    def _cleaner(self, pair: FramePair) -> DepthCleaner:
        color_model, depth_model = self.models['color'], self.models['depth']
        c = self.cleaner
        if c is None or c.registration.color_model != color_model or c.registration.depth_model != depth_model \
                or c.registration.registered != pair.registered:
            T = np.eye(4) if pair.registered else self.rig.camera(self.camera).T_color_depth \
                if self.rig is not None else self.extrinsic
            w, h = self.output_size
            size = (w or max(1, round(color_model.width * self.output_scale)),
                    h or max(1, round(color_model.height * self.output_scale)))
            c = DepthCleaner(DepthRegistration(depth_model, color_model, T, size, registered=pair.registered),
                             self.cfg)
            c.background = self.background
            self.cleaner = c
        return c

    def _reset_background(self) -> None:
        self.background = BackgroundModel()
        if self.cleaner is not None:
            self.cleaner.background = self.background

    def _plate_frames_held(self) -> bool:
        return any(phase == topics.CLEAN_PLATE for _, phase in self.held)

    def _late_plate_frame_done(self, phase: str | None) -> list[Outcome]:
        """A held clean-plate frame was learnt or dropped after its phase ended: the plate is
        complete once no other is held."""
        if phase == topics.CLEAN_PLATE and self.phase != topics.CLEAN_PLATE and not self._plate_frames_held():
            return [self._plate_done()]
        return []

    def _plate_done(self) -> Outcome:
        frames = self.background.frames
        if frames == 0:
            return Outcome('skipped', f'{self.camera}: the clean-plate phase ended with no frame learnt')
        return Outcome('plate_done', f'{self.camera}: clean plate learnt from {frames} frames')
