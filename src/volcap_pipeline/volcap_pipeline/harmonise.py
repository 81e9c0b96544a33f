"""The neural colour harmonisation composed with the fusion: where E's and D's training pixels
lie on the subject.

Paper 001 places every pixel at its own view's depth. Real cameras disagree about where the
subject is: on real texture (rgbd_box) the views' depths lie 2.6-3.0 mm from each other at the
median, four pixel footprints, so one point of the surface is a different place in E's hash
grid for every camera and E learns the disagreement as texture. ``FusedSurface`` fuses a
training frame set's views (the fusion's own TSDF, ``volcap_fusion.TsdfFusion``, lens
distortion included), ray-casts the surface back into each view along its own pixel rays and
gives E and D that depth instead; a pixel whose own depth lies more than ``surface_agree_mm``
from the surface (occlusion edges, flying pixels) or where the surface is missing is left out
of training. Measured on rgbd_box seeds 0 / 1 / 2 (``bench/neural_fused_surface.py`` on
8e9cda2): 77 % of the pixels kept, the views' own depth 1.6 mm from the surface at the median;
the neural method's distance from the truth 1.575 / 1.504 / 1.526 against 1.661 / 1.570 /
1.583 with each view's depth; the run's figures are in docs/benchmarks.md.

``run`` is `volcap harmonise`, the demo's short run and `volcap eval color-frames --harmonise`:
``volcap_color.neural.run`` with the surface chosen here. The colour stage may not import the
fusion, so this composition lives in the pipeline.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from volcap_core.settings import setting, validate

if TYPE_CHECKING:   # the command line reads SurfaceConfig without loading OpenCV, Open3D or torch
    from volcap_color.config import HarmoniseConfig
    from volcap_color.correspondence import View

MAX_DEPTH_M = 6.5        # the fusion's own limit (0.1 mm units in uint16)


@dataclass(frozen=True)
class SurfaceConfig:
    """Where the neural harmonisation's training pixels lie (``volcap harmonise``)."""
    surface: str = setting('fused', 'where each training pixel of E and D lies: fused (ours: the training frame '
                           'set\'s views fused into a TSDF and ray-cast back into each view, so every camera puts a '
                           'point of the subject in one place) or views (each view\'s own depth, paper 001)',
                           choices=('fused', 'views'))
    surface_voxel_mm: float = setting(2.0, 'voxel edge of the fused surface (mm)', 0.5, 50.0)
    surface_agree_mm: float = setting(20.0, 'a pixel whose own depth lies further than this from the fused surface, '
                                      'or where the surface is missing, is left out of training (mm)', 0.1, 1000.0)

    def validate(self) -> None:
        validate(self)


class FusedSurface:
    """``volcap_color.neural.Surface`` from the fusion: a frame set's views fused, the surface
    ray-cast back into each. Measured on 2 cores: 1.6 s the first frame set of eight 640x480
    views (rgbd_box), 1.2 s each one after (the volume and the lens maps are kept); about 2.5 s
    of eight 1280x720 (the synthetic studio)."""

    def __init__(self, cfg: SurfaceConfig = SurfaceConfig()):
        cfg.validate()
        self.cfg = cfg
        self.settings = asdict(cfg)
        self._fusion = None     # one TsdfFusion for every frame set: its volume and lens maps are kept

    def __call__(self, views: list[View]) -> tuple[list[View], dict]:
        from volcap_color.correspondence import View
        from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion, surface_depth
        t0 = time.perf_counter()
        if self._fusion is None:
            # every depth the fusion can hold (the box comes from the data); each frame set
            # starts from an empty volume (no carry)
            self._fusion = TsdfFusion(FusionConfig(voxel_size=self.cfg.surface_voxel_mm / 1000, carry_decay=0.0,
                                                   capture_volume='data', depth_max=MAX_DEPTH_M))
        model = self._fusion.fuse([CameraView(v.name, _millimetres(v.depth), v.camera, v.color, v.camera,
                                              v.T_world_camera) for v in views])
        moved, per_view = [], []
        scene = model.raycasting_scene() if len(model.triangles) else None
        for v in views:
            fused = surface_depth(scene, v.camera, v.T_world_camera) if scene is not None \
                else np.zeros_like(v.depth)
            own = v.depth > 0
            keep = own & (fused > 0) & (np.abs(fused - v.depth) <= self.cfg.surface_agree_mm / 1000)
            moved.append(View(v.name, v.color, np.where(keep, fused, 0).astype(np.float32), v.camera,
                              v.T_world_camera))
            per_view.append({'view': v.name, 'kept': float(keep.sum() / max(1, own.sum())),
                             'median_difference_mm': float(1000 * np.median(np.abs(fused - v.depth)[keep]))
                             if keep.any() else None})
        return moved, {'source': 'fused', 'voxel_mm': self.cfg.surface_voxel_mm,
                       'agree_mm': self.cfg.surface_agree_mm, 'triangles': int(len(model.triangles)),
                       'seconds': time.perf_counter() - t0, 'views': per_view}


def _millimetres(depth_m: np.ndarray) -> np.ndarray:
    """Depth in metres as the fusion takes it: uint16 millimetres, 0 = none, with one-pixel
    cracks filled by their 3x3 median. Depth registered to a finer colour grid (and the
    re-projected real views) is cracked every few pixels; a voxel whose nearest pixel is a
    crack gets no weight, and marching cubes drops every cube beside it: on rgbd_box 30-41 % of
    a view's pixels with depth had no surface without the fill, 17-27 % with it (the rest lie
    where the views' noisy depth of oblique surfaces leaves the TSDF with holes)."""
    import cv2

    from volcap_core.camera import depth_to_millimetres
    mm = depth_to_millimetres(depth_m)
    return np.where(mm == 0, cv2.medianBlur(mm, 3), mm)


def surface_of(cfg: SurfaceConfig) -> FusedSurface | None:
    """The ``surface`` argument of ``volcap_color.neural.run`` for ``cfg`` (None: each view's depth)."""
    cfg.validate()
    return FusedSurface(cfg) if cfg.surface == 'fused' else None


def run(sets: list[list[View]], cameras: list[str], cfg: HarmoniseConfig, out_dir: str | Path,
        surface: SurfaceConfig = SurfaceConfig(), **kwargs):
    """``volcap_color.neural.run`` (its other arguments in ``kwargs``) with the training pixels
    on the surface ``surface`` chooses; returns its ``HarmoniseReport``."""
    from volcap_color import neural
    return neural.run(sets, cameras, cfg, out_dir, surface=surface_of(surface), **kwargs)
