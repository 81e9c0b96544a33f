"""The trained networks of a harmonisation (E, every camera's D, the reference) and their files:
``field.pt``, ``<camera>.mapper.pt``, ``manifest.json``; loaded back for the evaluation and for
baking the live form."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .config import HarmoniseConfig
from .neural_nets import CaptureMapper, ColorField, HashGridField
from .neural_train import predict, torch_device, use_bf16

CHECKPOINT = 'checkpoint.pt'


FIELD_FILE = 'field.pt'


MANIFEST = 'manifest.json'


@dataclass
class Harmonisation:
    """What ``harmonise`` trained: E, one D per camera and the reference they map to."""
    cameras: list[str]
    centres: dict[str, np.ndarray]
    field: nn.Module                # ColorField (paper) or HashGridField
    mappers: dict[str, CaptureMapper]
    reference: str
    config: HarmoniseConfig
    device: torch.device
    bf16: bool
    report: dict

    def reference_centres(self) -> np.ndarray:
        names = self.cameras if self.reference == 'mean' else [self.reference]
        return np.stack([self.centres[c] for c in names])

    def map_colors(self, camera: str, rgb: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """D of ``camera`` on sRGB (N, 3) in [0, 1] at normalised pixel positions (N, 2)."""
        t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=self.device)
        return predict(self.mappers[camera], (t(rgb), t(xy)), self.bf16).cpu().numpy().astype(np.float64)


def field_from_state(state: dict, cfg: HarmoniseConfig) -> nn.Module:
    """An untrained E of the layout ``state`` was saved from (``cfg.field``), ready to load it."""
    if cfg.field == 'paper':
        return ColorField(state['point_mean'], state['point_std'], state['camera_mean'], state['camera_std'],
                          cfg.field_width, cfg.point_frequencies, cfg.camera_frequencies)
    resolution = state['grid.resolution']
    return HashGridField(state['point_min'], float(state['point_extent']), state['centres'], cfg.grid_levels,
                         cfg.grid_log2_table, int(resolution[0]), int(resolution[-1]), cfg.head_width)


def load_harmonisation(models_dir: str | Path, device: str = 'cpu') -> Harmonisation:
    """The networks ``harmonise`` wrote into ``models_dir`` (with its manifest)."""
    models_dir = Path(models_dir)
    manifest_path = models_dir / MANIFEST
    if not manifest_path.exists():
        raise FileNotFoundError(f'{models_dir} has no {MANIFEST}: not a volcap harmonise output')
    manifest = json.loads(manifest_path.read_text())
    # folders written before identifiers were spelt "color" say lut_colours
    cfg_dict = {k.replace('colour', 'color'): v for k, v in manifest['config'].items()}
    cfg_dict['lut_grid'] = tuple(cfg_dict['lut_grid'])
    # folders written before the hash grid field have the paper's E and D without the skip,
    # those written before D's gain form its logit form
    cfg_dict.setdefault('mapper_form', 'logit' if 'field' in cfg_dict else 'none')
    cfg_dict.setdefault('field', 'paper')
    cfg = HarmoniseConfig(**cfg_dict)
    dev = torch_device(device)
    state = torch.load(models_dir / FIELD_FILE, map_location=dev, weights_only=False)['state']
    field_model = field_from_state(state, cfg).to(dev)
    if isinstance(field_model, HashGridField):      # fields written before the views' registration / crosstalk
        state.setdefault('registration', torch.zeros_like(field_model.registration))
        state.setdefault('response.crosstalk', field_model.response.crosstalk.clone())
    field_model.load_state_dict(state)
    field_model.eval()
    mappers = {}
    for cam in manifest['cameras']:
        m = CaptureMapper(cfg.mapper_width, cfg.mapper_layers, cfg.mapper_form).to(dev)
        mapper_state = torch.load(models_dir / f'{cam}.mapper.pt', map_location=dev, weights_only=False)['state']
        mapper_state.setdefault('unmix', m.unmix.clone())     # mappers written before the crosstalk
        m.load_state_dict(mapper_state)
        m.eval()
        mappers[cam] = m
    centres = {c: np.asarray(v, np.float32) for c, v in manifest['centres'].items()}
    return Harmonisation(manifest['cameras'], centres, field_model, mappers, manifest['reference'], cfg, dev,
                         use_bf16(cfg.precision, dev), manifest)
