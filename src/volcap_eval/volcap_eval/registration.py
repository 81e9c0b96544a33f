"""Registration check on real recordings: do depth edges land on colour edges?

Depth discontinuities of the registered depth are compared with Canny edges of the colour
image: the distance from each depth edge pixel to the nearest colour edge (median, px), and the
global shift of the depth edges that brings them closest (0, 0 when registration is right).
An overlay PNG shows the depth edges in red on the colour image.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from volcap_core.errors import BadInput
from volcap_core.figures import write_png
from volcap_core.frames import frame_sets
from volcap_filter.registration import DepthRegistration

MAX_SHIFT_PX = 6


def depth_edges(depth: np.ndarray, relative_step: float = 0.03) -> np.ndarray:
    """Pixels on the near side of a depth step larger than ``relative_step`` of their depth."""
    valid = depth > 0
    far = cv2.dilate(depth, np.ones((3, 3), np.uint8))
    return valid & (far - depth > relative_step * depth)


def color_edges(rgb: np.ndarray) -> np.ndarray:
    gray = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (5, 5), 1.2)
    return cv2.Canny(gray, 40, 100) > 0


def edge_offsets(rgb: np.ndarray, registered: np.ndarray) -> dict:
    """Median distance of depth edges to colour edges, at no shift and at the best shift."""
    de = depth_edges(registered)
    if de.sum() < 50:
        raise BadInput('too few depth edges to compare (flat or empty depth image)')
    dist = cv2.distanceTransform((~color_edges(rgb)).astype(np.uint8), cv2.DIST_L2, 5)
    v, u = np.nonzero(de)
    h, w = de.shape
    best = None
    for dy in range(-MAX_SHIFT_PX, MAX_SHIFT_PX + 1):
        for dx in range(-MAX_SHIFT_PX, MAX_SHIFT_PX + 1):
            y, x = v + dy, u + dx
            ok = (y >= 0) & (y < h) & (x >= 0) & (x < w)
            med = float(np.median(dist[y[ok], x[ok]]))
            if best is None or med < best[0]:
                best = (med, dx, dy)
    return {'edge_pixels': int(de.sum()), 'median_offset_px': float(np.median(dist[v, u])),
            'mean_offset_px': float(np.mean(np.minimum(dist[v, u], 20))),
            'best_shift_px': [best[1], best[2]], 'median_offset_at_best_shift_px': best[0]}, de


def check_registration(bag: str | Path, overlay: Path, camera: str | None = None) -> dict:
    """Register the first frame of ``camera`` at full colour resolution and measure edge offsets."""
    from volcap_core.bag_reader import BagReader
    from volcap_core.frames import read_rig
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    name = camera or rig.names[0]
    frame = next((fs.cameras[name] for fs in frame_sets(bag, cameras=[name]) if name in fs.cameras), None)
    if frame is None:
        raise BadInput(f'{bag} has no complete colour + depth frame of {name}')
    c = frame.color_model
    reg = DepthRegistration(frame.depth_model, c, rig.camera(name).T_color_depth, (c.width, c.height))
    registered = reg.register(frame.depth).depth
    report, edges = edge_offsets(frame.color, registered)
    img = frame.color.copy()
    img[edges] = (255, 0, 0)
    write_png(overlay, img)
    return {'camera': name, **report, 'overlay': str(overlay)}
