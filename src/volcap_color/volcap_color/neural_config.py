"""Settings of ``volcap harmonise`` (``neural``), importable without torch."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class HarmoniseConfig:
    points: int = 180_000            # surface samples for E, shared evenly by the training views
    field_epochs: int = 100
    field_batch: int = 5000
    field_lr: float = 1e-4
    field_lr_final: float | None = None   # exponential decay to this by the last epoch (None: constant)
    field_width: int = 256
    point_frequencies: int = 10
    camera_frequencies: int = 4
    mapper_points: int = 80_000      # pixels per camera for its D
    mapper_epochs: int = 20
    mapper_batch: int = 1000
    mapper_lr: float = 1e-4
    mapper_lr_final: float | None = None
    mapper_width: int = 128
    mapper_layers: int = 8
    background: float = 0.25         # D's extra samples without a surface point, per sample with one (ours)
    reference: str = 'mean'          # a camera name, or 'mean' (E averaged over every camera)
    lut_colours: int = 17            # live form: colour nodes per axis ...
    lut_grid: tuple[int, int] = (9, 5)   # ... and image nodes (x, y)
    seed: int = 0
    device: str = 'auto'             # auto (cuda when present), cpu or cuda
    precision: str = 'auto'          # auto (bf16 where the device computes it natively), bf16 or fp32
