"""The colour stage's settings, importable without torch, OpenCV or colour-science (the command
line and the docs read them): correspondences, the chart-free fit (``volcap color-fit``) and the
neural harmonisation (``volcap harmonise``)."""
from __future__ import annotations

from dataclasses import dataclass, field

from volcap_core.settings import setting, validate

# The chart-free model families, and those the automatic choice picks from (simplest first).
CHART_FREE_MODELS = ('gain', 'gain_offset', 'matrix_3x3', 'affine_3x4')
SELECTABLE_MODELS = ('gain', 'matrix_3x3', 'affine_3x4')     # simplest first


@dataclass
class CaptureSetsConfig:
    """How many of a bag's capture frame sets the colour commands read (`color-fit`, `harmonise`,
    `eval color`)."""
    frames: int = setting(4, 'capture frame sets to use (eval color: alternately fit and scored)', 1, 10_000)


@dataclass
class ColorCorrectionConfig:
    """How a camera's live colour correction behaves (the color_corrector and camera_pipeline
    nodes' parameters)."""
    passthrough: bool = setting(True, 'publish uncorrected images while there is no colour model (false: drop '
                                'them)')
    neural_models: str = setting('', 'volcap harmonise output folder: apply its neural mapping for this camera '
                                 'instead of the calibration\'s colour model ("" = off)', read_only=True)


@dataclass
class CorrespondenceConfig:
    depth_tolerance_m: float = 0.01      # absolute part of the z-buffer agreement test
    depth_tolerance_rel: float = 0.005   # plus this share of the depth (ToF noise grows with it)
    min_fraction: float = 0.01           # pairs with fewer matches (share of a's pixels) are left out
    max_angle_deg: float = 75.0          # surface seen more obliquely than this by either camera: skipped
    max_round_trip_px: float = 0.5       # b's surface point at the match must project back this close to a's pixel
    max_gradient: float = 12.0           # luminance gradient (levels/px) above which a pixel is a texture edge
                                         # and left out, in either camera (0: keep all)
    stride: int = 1                      # use every stride-th pixel of a in x and y


@dataclass
class ColorFitConfig:
    model: str = setting('auto', 'per-camera model (auto: the simplest that fits without hurting dark pixels, '
                                 'or none when the rig is already consistent)', choices=('auto',) + CHART_FREE_MODELS)
    reference: str = setting('mean', 'mean (no camera favoured), chart (on top of the calibration\'s chart '
                                     'models, anchored to the board views) or a camera name')
    fit_min_fraction: float = setting(0.001, 'camera pairs with fewer pixels in correspondence are left out',
                                      0.0, 1.0)
    correspondence: CorrespondenceConfig = field(default_factory=lambda: CorrespondenceConfig(min_fraction=0.0))

    def validate(self) -> None:
        validate(self)




@dataclass
class HarmoniseConfig:
    points: int = setting(180_000, 'surface samples for E, shared evenly by the training views', 1, 100_000_000)
    field_epochs: int = setting(100, 'epochs of E', 1, 100_000)
    field_batch: int = setting(5000, 'batch of E', 1, 10_000_000)
    field_lr: float = setting(1e-4, 'learning rate of E', 0.0, 1.0)
    field_lr_final: float | None = setting(None, 'decay the learning rate of E exponentially to this by the last '
                                           'epoch (None: constant)', 0.0, 1.0)
    field_width: int = setting(256, 'hidden width of E', 1, 4096)
    point_frequencies: int = setting(10, 'positional encoding frequencies of the point', 0, 32)
    camera_frequencies: int = setting(4, 'positional encoding frequencies of the camera position', 0, 32)
    mapper_points: int = setting(80_000, 'pixels per camera for its D', 1, 100_000_000)
    mapper_epochs: int = setting(20, 'epochs of each D', 1, 100_000)
    mapper_batch: int = setting(1000, 'batch of each D', 1, 10_000_000)
    mapper_lr: float = setting(1e-4, 'learning rate of D', 0.0, 1.0)
    mapper_lr_final: float | None = setting(None, 'decay the learning rate of D to this by the last epoch', 0.0, 1.0)
    mapper_width: int = setting(128, 'hidden width of D', 1, 4096)
    mapper_layers: int = setting(8, 'hidden layers of D', 1, 64)
    background: float = setting(0.25, 'pixels without a surface point added to each D, per pixel with one, aimed '
                                      'at the camera\'s affine map onto the reference (0: the paper, D sees the '
                                      'subject only)', 0.0, 4.0)
    reference: str = setting('mean', 'camera whose colours D reproduces, or mean (E averaged over every camera)')
    lut_colors: int = setting(17, 'live form: colour nodes per axis', 2, 65, option='--lut-colours')
    lut_grid: tuple[int, int] = setting((9, 5), 'live form: image nodes (x, y)', 2, 64)
    seed: int = setting(0, 'random seed', 0, 2**31 - 1)
    device: str = setting('auto', 'auto (cuda when present), cpu or cuda', choices=('auto', 'cpu', 'cuda'))
    precision: str = setting('auto', 'auto (bf16 where the device computes it natively), bf16 or fp32',
                             choices=('auto', 'bf16', 'fp32'))

    def validate(self) -> None:
        validate(self)
