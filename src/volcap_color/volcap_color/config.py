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




# how D may change a colour (``neural_nets.CaptureMapper``)
MAPPER_FORMS = ('gain', 'logit', 'none')

# What each colour field trains with where its setting is left unset (None): the paper's
# published settings for its MLP (with the sample count bounded for a CPU), and for the hash grid
# what converged on 2 cores (docs/color.md, bench/neural.py).
FIELD_DEFAULTS = {
    'hashgrid': {'points': 1_000_000, 'field_epochs': 12, 'field_batch': 16384, 'field_lr': 1e-2,
                 'field_lr_final': 1e-3},
    'paper': {'points': 180_000, 'field_epochs': 100, 'field_batch': 5000, 'field_lr': 1e-4, 'field_lr_final': None},
}


@dataclass
class HarmoniseConfig:
    field: str = setting('hashgrid', 'colour field E: hashgrid (ours: multi-resolution hash grid, a latent surface '
                         'colour and a camera-conditioned response head; converges in minutes on a CPU) or paper '
                         '(paper 001\'s MLP with positional encoding)', choices=('hashgrid', 'paper'))
    points: int | None = setting(None, 'surface samples for E, shared evenly by the training views (None: 1 000 000 '
                                 'for hashgrid, 180 000 for paper)', 1, 100_000_000)
    field_epochs: int | None = setting(None, 'epochs of E (None: 12 for hashgrid, 100 for paper)', 1, 100_000)
    field_batch: int | None = setting(None, 'batch of E (None: 16384 for hashgrid, 5000 for paper)', 1, 10_000_000)
    field_lr: float | None = setting(None, 'learning rate of E (None: 1e-2 for hashgrid, 1e-4 for paper)', 0.0, 1.0)
    field_lr_final: float | None = setting(None, 'decay the learning rate of E exponentially to this by the last '
                                           'epoch (None: 1e-3 for hashgrid, constant for paper)', 0.0, 1.0)
    field_width: int = setting(256, 'hidden width of E (paper)', 1, 4096)
    point_frequencies: int = setting(10, 'positional encoding frequencies of the point (paper)', 0, 32)
    camera_frequencies: int = setting(4, 'positional encoding frequencies of the camera position (paper)', 0, 32)
    grid_levels: int = setting(12, 'hash grid levels (hashgrid)', 1, 32)
    grid_log2_table: int = setting(18, 'hash grid entries per level, log2 (hashgrid)', 8, 24)
    grid_cell_mm: float | None = setting(None, 'hash grid: size of the finest level\'s cells in mm (None: the '
                                         'training views\' median pixel footprint on the surface, depth over focal '
                                         'length, at least 1 mm)', 0.1, 1000.0)
    edge_levels: float = setting(12.0, 'E weighs each pixel 1 / (1 + (g / edge_levels)^2) by its luminance gradient g '
                                 '(levels per pixel): texture edges, where registration error changes the colour, '
                                 'count less (0: all pixels alike)', 0.0, 1000.0)
    robust_levels: float = setting(4.0, 'E\'s loss: Cauchy with this scale in levels, so pixels far from the '
                                   'field (registration error, occlusion edges) pull less on the camera responses '
                                   '(0: least squares)', 0.0, 255.0)
    register_views: bool = setting(True, 'hashgrid: E also learns a small rigid correction of each view (rotation '
                                   'about its centre, translation), so misregistration between views is not '
                                   'taken for texture or colour', )
    crosstalk_from_chart: bool = setting(True, 'hashgrid, where the calibration has a chart colour model for '
                                         'every camera: each camera response in E mixes the channels as its chart '
                                         'model says the camera does (crosstalk), fixed rather than learnt, so D '
                                         'undoes it', )
    head_width: int = setting(64, 'hidden width of the hash grid field\'s MLP (hashgrid)', 4, 1024)
    mapper_input: str = setting('field', 'what each D is trained to map: field (ours: E\'s colour of the point as '
                                'this camera records it, so input and target are the same surface colour and D '
                                'cannot trade texture for agreement) or pixels (the paper: the camera\'s pixels)',
                                choices=('field', 'pixels'))
    gamut: float = setting(0.5, 'hashgrid with mapper_input field: D also trains on this many random surface '
                           'colours per pixel, spanning those the field holds, as E records them for the camera '
                           'at random image positions (the field is smoother than the images: without them D '
                           'is trained on a narrower gamut than it corrects)', 0.0, 10.0)
    mapper_form: str = setting('gain', 'how D changes a colour: gain (ours: per-channel gains in linear light, '
                               'smooth up to white, as exposure and white balance are), logit (an offset to the '
                               'colour\'s logit, the form before 2026-12-06) or none (the paper: the whole mapping)',
                               choices=MAPPER_FORMS)
    mapper_points: int = setting(80_000, 'pixels per camera for its D', 1, 100_000_000)
    mapper_epochs: int = setting(60, 'epochs of each D', 1, 100_000)
    mapper_batch: int = setting(4096, 'batch of each D', 1, 10_000_000)
    mapper_lr: float = setting(1e-3, 'learning rate of D', 0.0, 1.0)
    mapper_lr_final: float | None = setting(1e-4, 'decay the learning rate of D to this by the last epoch (None: '
                                            'constant)', 0.0, 1.0)
    mapper_width: int = setting(64, 'hidden width of D (the paper: 128)', 1, 4096)
    mapper_layers: int = setting(4, 'hidden layers of D (the paper: 8)', 1, 64)
    background: float = setting(0.25, 'pixels without a surface point added to each D, per pixel with one, aimed '
                                      'at the camera\'s affine map onto the reference (0: the paper, D sees the '
                                      'subject only)', 0.0, 4.0)
    reference: str = setting('mean', 'camera whose colours D reproduces, or mean (E averaged over every camera)')
    anchor: str = setting('auto', 'what makes the reference true: chart (the average camera through the gains, '
                          'or the 3x3 (--anchor-fit), that take it onto the average of the cameras\' views through '
                          'their chart colour models, at the cameras\' exposure: absolute colour), grey_world (one '
                          'white balance making the scene average neutral), none; auto: chart when the calibration '
                          'has a chart model for every camera, else none', choices=('auto', 'chart', 'grey_world', 'none'))
    anchor_fit: str = setting('gains', 'the chart anchor\'s form: gains (one per channel in linear light, the charts\' '
                              'white balance, on the cameras\' views without the crosstalk their charts measured) or '
                              'matrix_3x3 (a full 3x3 on the views as recorded, which also takes up the saturation '
                              'the chart models add: the earlier form)', choices=('gains', 'matrix_3x3'))
    lut_colors: int = setting(17, 'live form: colour nodes per axis', 2, 65, option='--lut-colours')
    lut_grid: tuple[int, int] = setting((9, 5), 'live form: image nodes (x, y)', 2, 64)
    seed: int = setting(0, 'random seed', 0, 2**31 - 1)
    device: str = setting('auto', 'auto (cuda when present), cpu or cuda', choices=('auto', 'cpu', 'cuda'))
    precision: str = setting('auto', 'auto (bf16 where the device computes it natively), bf16 or fp32',
                             choices=('auto', 'bf16', 'fp32'))

    def field_setting(self, name: str):
        """``points``, ``field_epochs``, ``field_batch``, ``field_lr`` or ``field_lr_final`` as
        set, or the chosen field's default (``FIELD_DEFAULTS``)."""
        value = getattr(self, name)
        return FIELD_DEFAULTS[self.field][name] if value is None else value

    def validate(self) -> None:
        validate(self)
