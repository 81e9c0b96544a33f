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
  ``exp(-0.5 (m' / reset_mm)^2)`` (a bilateral weight in time) and dropped beyond
  ``BLOCK_RESET`` times ``reset_mm`` (of ``|m|`` itself). A soft weight lags a moving surface
  less than a hard threshold of the same reach: on the turning studio (``bench/stability.py``,
  seed 3, decay 0.7) a hard 3 mm reset gave 1.46 mm accuracy and the soft 1.5 mm 1.35 (1.36
  with no carry), at a still studio's jitter 0.33 and 0.37 mm (0.61 with no carry);
- ``m'`` is ``|m|`` less ``WOBBLE_K`` times the block's wobble: how far it has lately gone back
  and forth without getting anywhere (an average of ``|m|`` over the last sets less the
  magnitude of the average of ``m``, both with memory ``WOBBLE_MEMORY``). Motion keeps its
  direction from set to set and so has no wobble; the completed shoes of a still subject swing
  by 1-4 mm a set at block level (the body 0.1-0.3 mm) and are averaged in spite of it. On seed
  3's still studio this took the jitter from 0.34 to 0.30 mm (the shoes' 0-6 cm from 1.30 to
  1.08 mm), the turning studio's accuracy unchanged at 1.34 mm. A surface that stood still and
  starts to move is first held back by its wobble (at most ``WOBBLE_K`` times it: a body's
  fraction of a millimetre), then followed as the average of ``m`` catches up;
- a voxel whose own TSDF moved by more than ``VOXEL_RESET`` of the truncation (another surface)
  or whose colour changed by more than ``COLOR_RESET`` levels in a channel. At half the
  truncation and 24 levels these reset much of the still shoes' completions, whose depth and
  colour swing widely from set to set (seed 3: 0.36 against 0.34 mm with 0.75 and 48, the
  turning studio's accuracy 1.35 and 1.34 mm); with no resets at all the still studio measured
  0.31 mm at ``reset_mm`` 100 (0.25 with the voxel resets off too), which a moving subject
  cannot afford;
- a voxel this set did not see (nothing it carries can appear without a camera seeing it now:
  no ghosts, and the meshed extent is this set's own).

``carry_decay`` 0.8 (the default) against 0.7, ``bench/stability.py --seeds 3 8``: still studios
0.28 / 0.28 mm jitter against 0.31 / 0.30 (0.61 / 0.60 with no carry), the turning ones 1.36 /
1.35 mm accuracy against 1.34 / 1.34 (1.36 / 1.35 with no carry).

The arithmetic runs in torch on the volume's own memory (DLPack, no copy), so the CPU and the
CUDA volumes share this code.
"""
from __future__ import annotations

from dataclasses import dataclass

import open3d as o3d
import open3d.core as o3c
import torch
from torch.utils.dlpack import from_dlpack

VOXEL_RESET = 0.75    # of the truncation: a voxel whose TSDF moved this far shows another surface
COLOR_RESET = 48.0    # levels (0-255) in any channel: the colour there changed, not its noise
BLOCK_RESET = 3.0     # of ``reset_mm``: a block that moved this far carries nothing
WOBBLE_MEMORY = 0.5   # share of a block's wobble averages kept from one set to the next
WOBBLE_K = 2.0        # a block's motion counts beyond this many times its wobble


@dataclass
class BlockWobble:
    """Per block of a volume (indexed by its buffer index): the running averages of the signed
    surface motion ``m`` (mm) and of its magnitude, from which the block's wobble is told."""
    signed: torch.Tensor
    magnitude: torch.Tensor

    def wobble(self, buf: torch.Tensor) -> torch.Tensor:
        return (self.magnitude[buf] - self.signed[buf].abs()).clamp(min=0)


def _torch(tensor: o3c.Tensor) -> torch.Tensor:
    return from_dlpack(tensor.to_dlpack())


def carry_over(current: o3d.t.geometry.VoxelBlockGrid, previous: o3d.t.geometry.VoxelBlockGrid, decay: float,
               reset_mm: float, trunc_mm: float, wobble: BlockWobble | None = None
               ) -> tuple[dict, BlockWobble | None]:
    """Blends ``previous`` (the last frame set's volume, same voxel grid) into ``current`` in
    place, as the module says; ``wobble`` is what the last call returned for ``previous``
    (None: no history). Returns counts (voxels both sets saw, and of them those carried and
    those in blocks that moved) and the blocks' wobble for ``current``."""
    counts = {'seen_twice': 0, 'carried': 0, 'moved': 0}
    if decay <= 0:
        return counts, None
    cur, prev = current.hashmap(), previous.hashmap()
    active = cur.active_buf_indices()
    if active.shape[0] == 0 or prev.size() == 0:
        return counts, None
    prev_buf, found = prev.find(cur.key_tensor()[active.to(o3c.int64)])
    found = _torch(found)
    cb = _torch(active).long()[found]
    pb = _torch(prev_buf).long()[found]
    if cb.numel() == 0:
        return counts, None
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
    signed_mm = mean_change * trunc_mm
    moved_mm = signed_mm.abs()
    moved = (moved_mm > BLOCK_RESET * reset_mm)[:, None, None, None]
    # what goes back and forth without getting anywhere is not motion
    beyond_mm = moved_mm if wobble is None else (moved_mm - WOBBLE_K * wobble.wobble(pb)).clamp(min=0)
    # soft: the history counts less the more the block moved (a bilateral weight in time)
    still = torch.exp(-0.5 * (beyond_mm / max(reset_mm, 1e-6)) ** 2)[:, None, None, None]
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
    # the blocks' wobble for the next set: blocks new in this one start from their first motion
    size = cur.capacity()
    carried_wobble = BlockWobble(torch.zeros(size, device=signed_mm.device), torch.zeros(size, device=signed_mm.device))
    if wobble is None:
        carried_wobble.signed[cb], carried_wobble.magnitude[cb] = signed_mm, moved_mm
    else:
        carried_wobble.signed[cb] = WOBBLE_MEMORY * wobble.signed[pb] + (1 - WOBBLE_MEMORY) * signed_mm
        carried_wobble.magnitude[cb] = WOBBLE_MEMORY * wobble.magnitude[pb] + (1 - WOBBLE_MEMORY) * moved_mm
    return counts, carried_wobble
