"""The TSDF of what holds still, carried from one frame set to the next (issue 30's shimmer).

Each frame set is integrated into an empty volume as before; then every voxel the cameras saw
in this set *and* in the last one is averaged with the last one's value, the history weighted
down by ``decay``: ``(w * tsdf + decay * W * TSDF) / (w + decay * W)``, the same for colour,
and the voxel's weight becomes ``w + decay * W``. A still surface is thus an exponential
average over frame sets (in steady state this set counts ``1 - decay``), in 3D, where the
depth filter's per-pixel average cannot reach: completions that differ from frame to frame,
pixels that start again each frame at silhouette rims, the marching-cubes edge.

The history counts less where the scene moved, and not at all where it changed:
- a block (8^3 voxels) whose surface moved: ``m``, the mean signed TSDF change over its voxels
  near the surface, in millimetres along the normal. Noise averages out over the ~100 voxels a
  surface crosses in a block, motion does not. The history is weighted by
  ``exp(-0.5 (m / reset_mm)^2)`` (a bilateral weight in time) and dropped beyond
  ``BLOCK_RESET`` times ``reset_mm``. A soft weight lags a moving surface less than a hard
  threshold of the same reach: on the turning studio (``bench/stability.py``, seed 3, decay
  0.7) a hard 3 mm reset gave 1.46 mm accuracy and the soft 1.5 mm 1.35 (1.36 with no carry),
  at a still studio's jitter 0.33 and 0.37 mm (0.61 with no carry);
- a voxel whose own TSDF moved by more than ``VOXEL_RESET`` of the truncation (another surface)
  or whose colour changed by more than ``COLOR_RESET`` levels in a channel;
- a voxel this set did not see (nothing it carries can appear without a camera seeing it now:
  no ghosts, and the meshed extent is this set's own).

The arithmetic runs in torch on the volume's own memory (DLPack, no copy), so the CPU and the
CUDA volumes share this code.
"""
from __future__ import annotations

import open3d as o3d
import open3d.core as o3c
import torch
from torch.utils.dlpack import from_dlpack

VOXEL_RESET = 0.5     # of the truncation: a voxel whose TSDF moved this far shows another surface
COLOR_RESET = 24.0    # levels (0-255) in any channel: the colour there changed, not its noise
BLOCK_RESET = 3.0     # of ``reset_mm``: a block that moved this far carries nothing


def _torch(tensor: o3c.Tensor) -> torch.Tensor:
    return from_dlpack(tensor.to_dlpack())


def carry_over(current: o3d.t.geometry.VoxelBlockGrid, previous: o3d.t.geometry.VoxelBlockGrid, decay: float,
               reset_mm: float, trunc_mm: float) -> dict:
    """Blends ``previous`` (the last frame set's volume, same voxel grid) into ``current`` in
    place, as the module says. Returns counts: voxels both sets saw, and of them those carried
    and those in blocks that moved."""
    counts = {'seen_twice': 0, 'carried': 0, 'moved': 0}
    if decay <= 0:
        return counts
    cur, prev = current.hashmap(), previous.hashmap()
    active = cur.active_buf_indices()
    if active.shape[0] == 0 or prev.size() == 0:
        return counts
    prev_buf, found = prev.find(cur.key_tensor()[active.to(o3c.int64)])
    found = _torch(found)
    cb = _torch(active).long()[found]
    pb = _torch(prev_buf).long()[found]
    if cb.numel() == 0:
        return counts
    tsdf_c, weight_c, color_c = (_torch(cur.value_tensor(i)) for i in range(3))
    tsdf_p, weight_p, color_p = (_torch(prev.value_tensor(i)) for i in range(3))
    t_c, w_c = tsdf_c[cb][..., 0], weight_c[cb][..., 0]
    t_p, w_p = tsdf_p[pb][..., 0], weight_p[pb][..., 0]
    both = (w_c > 0) & (w_p > 0)
    change = t_c - t_p
    # the block's surface motion: mean signed change where either set is within the truncation
    near = both & ((t_c.abs() < 1) | (t_p.abs() < 1))
    n_near = near.flatten(1).sum(1)
    mean_change = (change * near).flatten(1).sum(1) / n_near.clamp(min=1)
    moved_mm = mean_change.abs() * trunc_mm
    moved = (moved_mm > BLOCK_RESET * reset_mm)[:, None, None, None]
    # soft: the history counts less the more the block moved (a bilateral weight in time)
    still = torch.exp(-0.5 * (moved_mm / max(reset_mm, 1e-6)) ** 2)[:, None, None, None]
    c_c, c_p = color_c[cb], color_p[pb]
    keep = (both & ~moved & (change.abs() <= VOXEL_RESET)
            & ((c_c - c_p).abs().amax(-1) <= COLOR_RESET))
    history = decay * w_p * keep * still
    weight = w_c + history
    share = (history / weight.clamp(min=1e-6))
    tsdf_c[cb] = (t_c + share * (t_p - t_c))[..., None]
    color_c[cb] = c_c + share[..., None] * (c_p - c_c)
    weight_c[cb] = weight[..., None]
    counts.update(seen_twice=int(both.sum()), carried=int(keep.sum()), moved=int((both & moved).sum()))
    return counts
