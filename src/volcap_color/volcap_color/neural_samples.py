"""The neural harmonisation's training data: surface points, their pixels' colours and the cameras
that saw them, sampled from the views of the training frame sets."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volcap_core.errors import BadInput

from .apply import pixel_centres
from .correspondence import View

FIELDS = ('points', 'centres', 'colors', 'xy', 'camera', 'gradient')


@dataclass
class SurfaceSamples:
    """Pixels with a surface point, from one or more views."""
    points: np.ndarray      # (N, 3) float32 world
    centres: np.ndarray     # (N, 3) float32 world position of the camera that saw it
    colors: np.ndarray     # (N, 3) float32 sRGB [0, 1]
    xy: np.ndarray          # (N, 2) float32 pixel centre / image size (``apply.pixel_centres``)
    camera: np.ndarray      # (N,) int16 index of the camera in the ``cameras`` list sampled for
    gradient: np.ndarray    # (N,) float32 luminance gradient at the pixel, levels per pixel (``View.gradient``)

    def __len__(self) -> int:
        return len(self.points)

    def select(self, keep: np.ndarray) -> SurfaceSamples:
        return SurfaceSamples(*(getattr(self, k)[keep] for k in FIELDS))


def view_samples(view: View, count: int | None, rng: np.random.Generator, camera: int = 0) -> SurfaceSamples:
    """Up to ``count`` random pixels of ``view`` with depth (all of them for None); ``camera``
    is the view's camera index."""
    h, w = view.depth.shape
    valid = np.flatnonzero(view.depth.reshape(-1) > 0)
    if count is not None and len(valid) > count:
        valid = np.sort(rng.choice(valid, count, replace=False))
    y, x = np.divmod(valid, w)
    local = view.rays().reshape(-1, 3)[valid] * view.depth.reshape(-1)[valid, None]
    T = view.T_world_camera
    points = (local @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    return SurfaceSamples(points, np.broadcast_to(T[:3, 3].astype(np.float32), points.shape).copy(),
                          view.color.reshape(-1, 3)[valid].astype(np.float32) / 255.0, pixel_centres(x, y, w, h),
                          np.full(len(valid), camera, np.int16),
                          view.gradient().reshape(-1)[valid].astype(np.float32))


def concat_samples(parts: list[SurfaceSamples]) -> SurfaceSamples:
    return SurfaceSamples(*(np.concatenate([getattr(p, k) for p in parts]) for k in FIELDS))


def training_samples(sets: list[list[View]], cameras: list[str], total: int | None, seed: int) -> SurfaceSamples:
    """About ``total`` samples shared evenly by every view of every frame set (all for None)."""
    rng = np.random.default_rng(seed)
    views = [v for views in sets for v in views if v.name in cameras]
    if not views:
        raise BadInput('no view of the calibrated cameras to train on')
    share = None if total is None else max(1, total // len(views))
    samples = concat_samples([view_samples(v, share, rng, cameras.index(v.name)) for v in views])
    if not len(samples):
        raise BadInput('the training views have no pixel with depth: is the subject in view and the clean plate '
                         'learnt?')
    return samples
