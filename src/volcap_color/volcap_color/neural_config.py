"""Settings of ``volcap harmonise`` (``neural``), importable without torch."""
from __future__ import annotations

from dataclasses import dataclass

from volcap_core.settings import setting, validate


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
    lut_colors: int = setting(17, 'live form: colour nodes per axis', 2, 65)
    lut_grid: tuple[int, int] = setting((9, 5), 'live form: image nodes (x, y)', 2, 64)
    seed: int = setting(0, 'random seed', 0, 2**31 - 1)
    device: str = setting('auto', 'auto (cuda when present), cpu or cuda', choices=('auto', 'cpu', 'cuda'))
    precision: str = setting('auto', 'auto (bf16 where the device computes it natively), bf16 or fp32',
                             choices=('auto', 'bf16', 'fp32'))

    def validate(self) -> None:
        validate(self)
