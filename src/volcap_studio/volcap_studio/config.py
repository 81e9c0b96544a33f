"""What a synthetic studio session is made of (``volcap synth``): its settings and the sensor
model, kept apart from the renderer so the command line can read them without loading it."""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from volcap_core.errors import BadInput
from volcap_core.settings import setting

SCENES = ('person', 'bunny')
BOARD_LAYOUTS = ('sweep', 'pairs')
MOTIONS = ('turn', 'none')


def shared_data_dir() -> Path:
    """Real data the studio is modelled on: ``$VOLCAP_DATA``, else ``../shared/data`` beside the
    checkout (factory calibration in ``azure_kinect/``, the bunny in ``meshes/``)."""
    return Path(os.environ.get('VOLCAP_DATA') or Path(__file__).resolve().parents[4] / 'shared' / 'data')


def default_k4a_calibration() -> str:
    return str(shared_data_dir() / 'azure_kinect' / 'calibration.json')


def default_bunny_mesh() -> str:
    return str(shared_data_dir() / 'meshes' / 'bunny.ply')


@dataclass
class ToFModel:
    """Azure Kinect NFOV-like time-of-flight behaviour."""
    min_range: float = 0.25
    max_range: float = 3.86
    noise_base: float = 0.0008       # sigma(z) = base + quad * z^2 (metres)
    noise_quad: float = 0.0010
    grazing_cos: float = 0.12        # no return beyond ~83 deg incidence
    dark_albedo: float = 0.03        # below this IR reflectance returns drop out
    flying_keep: float = 0.85        # fraction of mixed pixels the sensor still reports
    subsamples: int = 3              # S x S sub-pixel rays per pixel at discontinuities
    edge_threshold: float = 0.02     # 3x3 depth range per (1 m + z) that marks a discontinuity
    speckle_prob: float = 0.3        # chance per image of an interference burst
    speckle_blobs: int = 12

    def sigma(self, z: np.ndarray) -> np.ndarray:
        return self.noise_base + self.noise_quad * z ** 2

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class SynthConfig:
    cameras: int = setting(8, 'cameras, two per stand', 1, 64)
    frames: int = setting(10, 'capture frames of the subject', 0, 100_000)
    board_poses: int = setting(12, 'calibration board poses', 0, 10_000)
    board_layout: str = setting('sweep', 'sweep: the board turned through every direction; pairs: held between '
                                'neighbouring stands (as the calibration\'s advice guides)', choices=BOARD_LAYOUTS)
    background_frames: int = setting(3, 'clean-plate frames (no subject)', 0, 10_000)
    scene: str = setting('person', 'the subject', choices=SCENES)
    motion: str = setting('turn', 'turn: the subject turns slowly (20 deg/s) with a little sway; none: it holds still '
                          '(temporal stability)', choices=MOTIONS)
    seed: int = setting(0, 'random seed of the rig\'s devices, the motion and the sensor noise', 0, 2**31 - 1)
    fps: float = setting(30.0, 'capture frame rate', 1.0, 240.0)
    stamp_jitter_ms: float = 0.3
    stand_radius: float = 1.8
    heights: tuple[float, float] = (1.7, 0.7)
    k4a_calibration: str = setting(default_factory=lambda: default_k4a_calibration(),
                                   description='Azure Kinect factory calibration JSON the rig is modelled on '
                                               '(the shared data\'s by default)')
    bunny_mesh: str = field(default_factory=lambda: default_bunny_mesh())
    tof: ToFModel = field(default_factory=ToFModel)

    def __post_init__(self):
        if self.cameras < 1:
            raise BadInput('need at least one camera')
        if min(self.frames, self.board_poses, self.background_frames) < 0:
            raise BadInput('frame counts must be >= 0')
        if self.board_layout not in BOARD_LAYOUTS:
            raise BadInput(f'unknown board layout {self.board_layout!r}; choose from {BOARD_LAYOUTS}')
        if self.scene not in SCENES:
            raise BadInput(f'unknown scene {self.scene!r}; choose from {SCENES}')
        needed = [('Azure Kinect calibration', self.k4a_calibration)]
        if self.scene == 'bunny':
            needed.append(('bunny mesh', self.bunny_mesh))
        for what, path in needed:
            if not Path(path).is_file():
                raise FileNotFoundError(f'{what} {path} not found: set VOLCAP_DATA to the shared data folder')


