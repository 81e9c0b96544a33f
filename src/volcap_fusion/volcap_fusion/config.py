"""The fusion's settings, apart from the Open3D code so the command line and the docs read them
without loading Open3D."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volcap_core.errors import BadInput
from volcap_core.settings import setting, validate

from . import VOXEL_SIZE


def open3d_device(requested: str = 'auto') -> str:
    """The Open3D device string of a ``device`` setting: 'auto' is the first CUDA device when
    Open3D sees one, the CPU otherwise."""
    if requested == 'auto':
        import open3d as o3d
        return 'CUDA:0' if o3d.core.cuda.is_available() else 'CPU:0'
    return requested


@dataclass
class FusionConfig:
    voxel_size: float = setting(VOXEL_SIZE, 'TSDF voxel edge (m)', 0.0005, 0.1, read_only=True)
    trunc_voxels: float = setting(4.0, 'SDF truncation in voxels', 1.0, 32.0, read_only=True)
    weight_threshold: float = setting(0.5, 'a voxel is meshed when more cameras than this saw it (0.5: one is enough; capped below the '
                                      'number of cameras fused, so one camera still gives a mesh)', 0.0, 100.0,
                                      read_only=True)
    block_resolution: int = setting(8, 'voxels per block edge', choices=(4, 8, 16), read_only=True)
    block_count: int = setting(40_000, 'initial voxel block capacity (it grows when needed)', 1, 10_000_000,
                               read_only=True)
    depth_max: float = setting(3.0, 'depth beyond this is not fused (m)', 0.1, 6.5, read_only=True)
    # Capture box, axis-aligned in the output frame (the studio frame): edge lengths and centre
    # (None: on the floor around the studio origin, which lies below where the rig is aimed).
    box_size: tuple[float, float, float] = setting((2.6, 2.6, 2.6), 'capture box edge lengths (m)', 0.01, 100.0,
                                                   read_only=True)
    box_center: tuple[float, float, float] | None = setting(
        None, 'capture box centre x, y, z in the output frame (m); [0.0]: standing on the studio floor around '
        'its origin, or where the cameras point when the calibration has no floor', none_as=[0.0],
        read_only=True)
    capture_volume: str = setting('auto', 'auto: the box above where the cameras converge (or on the studio floor), '
                                  'else, when they do not converge, the bounds of all their depth; data: always the '
                                  'bounds of all depth (a room, a moving camera)', choices=('auto', 'data'),
                                  read_only=True)
    depth_upsample: int = setting(1, 'depth resampled this many times finer before integration', 1, 4,
                                  read_only=True)
    edge_tolerance: float = setting(0.02, 'depth step (m, +1 %) that separates surfaces', 0.0, 1.0, read_only=True)
    carry_decay: float = setting(0.8, 'share of the last frame set\'s weight a still voxel carries into the next (an '
                                 'exponential average over frame sets where the scene holds still; 0: each set '
                                 'fused alone)', 0.0, 0.95, read_only=True)
    carry_reset_mm: float = setting(1.5, 'scale (mm) of a block of voxels\' surface motion since the last frame set: '
                                    'moved this far beyond twice its recent wobble, it keeps e^-0.5 of its history; '
                                    'three times as far, none',
                                    0.01, 100.0, read_only=True)
    carry_max_gap_s: float = setting(2.0, 'a frame set this long (s) after the last one fused, or stamped before it, '
                                     'carries nothing over (a pause, a new take, a replay started again)', 0.0, 3600.0,
                                     read_only=True)
    device: str = setting('auto', 'CPU:0, CUDA:0 or auto (CUDA when Open3D has it)', read_only=True)

    def validate(self) -> None:
        validate(self)
        size = np.asarray(self.box_size, float)
        if size.shape != (3,) or not np.all(size > 0):
            raise BadInput(f'box_size must be 3 positive edge lengths, got {self.box_size}')
        if self.box_center is not None and (np.shape(self.box_center) != (3,)
                                            or not np.all(np.isfinite(self.box_center))):
            raise BadInput(f'box_center must be 3 finite values or None, got {self.box_center}')
        import open3d as o3d
        device = o3d.core.Device(open3d_device(self.device))
        if device.get_type() == o3d.core.Device.CUDA and not o3d.core.cuda.is_available():
            raise BadInput(f'device {self.device}: this Open3D has no CUDA device')


