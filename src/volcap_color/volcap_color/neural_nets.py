"""Paper 001's networks in torch: the colour field E (``ColorField``) and the per-camera mapping D
(``CaptureMapper``), with their positional encoding; the layouts are described in ``neural``."""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn


def positional_encoding(v: torch.Tensor, frequencies: int) -> torch.Tensor:
    """gamma(v) = (v, sin(2^0 pi v), cos(2^0 pi v), ..., sin(2^(L-1) pi v), cos(2^(L-1) pi v))."""
    scales = (2.0 ** torch.arange(frequencies, device=v.device, dtype=v.dtype)) * math.pi
    x = (v[..., None] * scales).flatten(-2)
    return torch.cat([v, torch.sin(x), torch.cos(x)], dim=-1)


class ColorField(nn.Module):
    """E: (world point, world camera centre) -> sRGB in [0, 1]."""

    def __init__(self, point_mean, point_std, camera_mean, camera_std, width: int = 256,
                 point_frequencies: int = 10, camera_frequencies: int = 4):
        super().__init__()
        for name, v in (('point_mean', point_mean), ('point_std', point_std), ('camera_mean', camera_mean),
                        ('camera_std', camera_std)):
            self.register_buffer(name, torch.as_tensor(np.asarray(v, np.float32)))
        self.point_frequencies, self.camera_frequencies = point_frequencies, camera_frequencies
        p_dim, c_dim = 3 + 6 * point_frequencies, 3 + 6 * camera_frequencies
        self.trunk = nn.ModuleList([nn.Linear(p_dim, width)] + [nn.Linear(width, width) for _ in range(3)])
        self.skip = nn.ModuleList([nn.Linear(width + p_dim, width)] + [nn.Linear(width, width) for _ in range(3)])
        self.feature = nn.Linear(width, width)
        self.view = nn.Linear(width + c_dim, width // 2)
        self.rgb = nn.Linear(width // 2, 3)

    def forward(self, points: torch.Tensor, cameras: torch.Tensor) -> torch.Tensor:
        p = positional_encoding((points - self.point_mean) / self.point_std, self.point_frequencies)
        c = positional_encoding((cameras - self.camera_mean) / self.camera_std, self.camera_frequencies)
        h = p
        for layer in self.trunk:
            h = torch.relu(layer(h))
        h = torch.cat([h, p], dim=-1)
        for layer in self.skip:
            h = torch.relu(layer(h))
        h = torch.cat([self.feature(h), c], dim=-1)
        return torch.sigmoid(self.rgb(torch.relu(self.view(h))))


class CaptureMapper(nn.Module):
    """D: (sRGB in [0, 1], pixel x y in [0, 1]) -> harmonised sRGB in [0, 1]."""

    def __init__(self, width: int = 128, layers: int = 8):
        super().__init__()
        sizes = [5] + [width] * layers
        self.hidden = nn.ModuleList([nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:])])
        self.rgb = nn.Linear(width, 3)

    def forward(self, rgb: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
        h = torch.cat([rgb, xy], dim=-1)
        for layer in self.hidden:
            h = torch.relu(layer(h))
        return torch.sigmoid(self.rgb(h))
