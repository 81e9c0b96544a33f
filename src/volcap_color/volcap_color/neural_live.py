"""The neural harmonisation's live form: each camera's networks baked into the region LUT the
``color_corrector`` applies, and how far the LUT is from the networks."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from .apply import ImageCorrector, RegionLut, pixel_centres
from .correspondence import View
from .neural_models import Harmonisation
from .neural_nets import CaptureMapper
from .neural_samples import SurfaceSamples
from .neural_train import predict


def bake_region_lut(harm: Harmonisation, camera: str, colors: int | None = None,
                    grid: tuple[int, int] | None = None) -> RegionLut:
    """D of ``camera`` sampled on ``colours``^3 colour nodes at each of ``grid`` (nx, ny) image
    nodes: what ``color_corrector`` applies at frame rate."""
    n = colors or harm.config.lut_colors
    nx, ny = grid or harm.config.lut_grid
    axis = np.linspace(0.0, 1.0, n, dtype=np.float32)
    rgb = np.stack(np.meshgrid(axis, axis, axis, indexing='ij'), axis=-1).reshape(-1, 1, 3)
    yx = np.stack(np.meshgrid(np.linspace(0, 1, ny, dtype=np.float32), np.linspace(0, 1, nx, dtype=np.float32),
                              indexing='ij'), axis=-1).reshape(1, -1, 2)
    rgb_all = np.broadcast_to(rgb, (n ** 3, nx * ny, 3)).reshape(-1, 3)
    xy_all = np.broadcast_to(yx[..., ::-1], (n ** 3, nx * ny, 2)).reshape(-1, 2)
    mapped = harm.map_colors(camera, rgb_all, xy_all)
    return RegionLut((mapped * 255.0).astype(np.float32).reshape(n, n, n, ny, nx, 3))


def export_error(harm: Harmonisation, camera: str, lut: RegionLut, images: list[np.ndarray]) -> dict:
    """The live form against D itself on every pixel of ``images`` (uint8 RGB), both as 8-bit
    images: mean, 99th percentile and maximum absolute difference in levels."""
    diffs = []
    corrector = ImageCorrector(lut)
    for img in images:
        h, w = img.shape[:2]
        ys, xs = np.mgrid[0:h, 0:w]
        xy = pixel_centres(xs.reshape(-1), ys.reshape(-1), w, h)
        net = np.round(np.clip(harm.map_colors(camera, img.reshape(-1, 3) / 255.0, xy), 0, 1) * 255.0)
        diffs.append(np.abs(corrector(img).reshape(-1, 3).astype(np.float64) - net).reshape(-1))
    d = np.concatenate(diffs)
    return {'mean_levels': float(d.mean()), 'p99_levels': float(np.percentile(d, 99)), 'max_levels': float(d.max()),
            'pixels': int(d.size // 3)}


def _mapper_error(field_model: nn.Module, mapper: CaptureMapper, samples: SurfaceSamples, target: torch.Tensor,
                  kind: str, bf16: bool) -> dict:
    """D against the colours it is to give ``samples`` (pixels D was not trained on;
    ``target``: ``neural.mapper_targets``), given what it was trained to map (``kind``,
    ``neural.mapper_inputs``): RMS and 99th percentile of the difference, in levels."""
    from .neural import mapper_inputs
    device = next(mapper.parameters()).device
    t = lambda a: torch.as_tensor(a, device=device)
    centre = samples.centres[0] if len(samples) else np.zeros(3, np.float32)
    inputs = mapper_inputs(field_model, samples, centre, kind, bf16)
    d = (predict(mapper, (t(inputs), t(samples.xy)), bf16) - target).cpu().numpy() * 255.0
    return {'rms_levels': float(np.sqrt(np.mean(d ** 2))), 'p99_levels': float(np.percentile(np.abs(d), 99)),
            'pixels': len(samples)}


def export_live(harm: Harmonisation, out_dir: str | Path, check_views: list[View], progress: bool = True) -> dict:
    """Bake every camera's D into ``<camera>.lut.npz`` and measure the LUT against D on every
    pixel of ``check_views`` (frame sets not trained on, where there are any)."""
    out_dir = Path(out_dir)
    errors = {}
    for cam in tqdm(harm.cameras, desc='live form (region LUTs)', unit='camera', disable=not progress):
        lut = bake_region_lut(harm, cam)
        lut.save(out_dir / f'{cam}.lut.npz', camera=cam, reference=harm.reference)
        mine = [v.color for v in check_views if v.name == cam]
        if mine:
            errors[cam] = export_error(harm, cam, lut, mine)
    return {'export_error': errors}
