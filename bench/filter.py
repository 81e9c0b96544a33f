"""Depth cleaning cost per frame (8 cameras, colour 1280x720, depth 640x576) on one core.

    .venv/bin/python bench/filter.py [--bag DIR]

Times each flying-pixel filter (ours with and without the sparse-return rescue), the fill of the
holes amid sparse returns (with and without the quadric on curved patches), registration, the
clean-plate mask, the whole cleaning (with and without the completion of holes inside the mask,
and with planes only) and the
node's whole callback (message decode, cleaning, point cloud, message encode), with the bare
cv2/numpy operations they compete with measured in the same run: a 3x3 min/max filter (the
cheapest way to see a depth step) and cv2.projectPoints of every depth pixel. Without --bag, a
small synthetic studio bag is rendered first.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from volcap_core.conversions import color_to_rgb, depth_to_metres, numpy_to_image, points_to_pointcloud2  # noqa: E402
from volcap_core.frames import frame_sets  # noqa: E402
from volcap_filter.flying import FlyingPixelConfig, fill_sparse_returns, flying_pixels, paper_flying_pixels  # noqa: E402
from volcap_filter.pipeline import DepthCleaner, DepthFilterConfig  # noqa: E402
from volcap_filter.registration import DepthRegistration  # noqa: E402
from volcap_studio.session import GroundTruth, synthesize  # noqa: E402
from volcap_studio.studio import SynthConfig  # noqa: E402


def timed(fn, frames, repeat=3) -> float:
    """Median ms of fn(frame) over every frame, each run ``repeat`` times (after one warm-up)."""
    fn(frames[0])
    out = []
    for f in frames:
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn(f)
            out.append((time.perf_counter() - t0) * 1000)
    return statistics.median(out)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument('--bag', default='')
    args = ap.parse_args()
    cv2.setNumThreads(1)
    tmp = None
    bag = Path(args.bag) if args.bag else None
    if bag is None:
        tmp = tempfile.TemporaryDirectory()
        bag = Path(tmp.name) / 'bag'
        synthesize(bag, SynthConfig(cameras=8, frames=2, board_poses=0, background_frames=2, seed=11), progress=False)
    rig = GroundTruth(bag).rig
    cleaners, uncompleted, planes, frames = {}, {}, {}, []
    for fs in frame_sets(bag, phases=('clean_plate', 'capture')):
        for name, f in fs.cameras.items():
            if name not in cleaners:
                reg = DepthRegistration(f.depth_model, f.color_model, rig.camera(name).T_color_depth)
                cleaners[name] = DepthCleaner(reg)
                uncompleted[name] = DepthCleaner(reg, DepthFilterConfig(complete_radius=0))
                planes[name] = DepthCleaner(reg, DepthFilterConfig(flying=FlyingPixelConfig(curved_support=0)))
            if fs.phase == 'clean_plate':
                for c in (cleaners, uncompleted, planes):
                    c[name].learn_background(f.color, f.depth)
            else:
                frames.append((name, f))
    msgs = [(name, numpy_to_image(f.color, 'rgb8', 0, 'c'), numpy_to_image(np.round(f.depth * 1000).astype(np.uint16),
                                                                           '16UC1', 0, 'd')) for name, f in frames]

    def node_callback(m):
        name, color_msg, depth_msg = m
        c = cleaners[name]
        result = c.process(color_to_rgb(color_msg), depth_to_metres(depth_msg))
        numpy_to_image(np.round(result.depth * 1000).astype(np.uint16), '16UC1', 0, 'c')
        points_to_pointcloud2(*c.points(result), 0, 'c')

    removed = {}     # the fill's input per frame: the depth after the flying-pixel filter, its removals
    for f in frames:
        fly = flying_pixels(f[1].depth, f[1].depth_model.fx)
        removed[id(f)] = (np.where(fly, np.float32(0.0), f[1].depth.astype(np.float32)), fly, f[1].depth_model.fx)
    k3 = np.ones((3, 3), np.uint8)
    rows = [
        ('bare cv2 3x3 max-min of depth (reference)', timed(lambda f: cv2.dilate(f[1].depth, k3) - cv2.erode(f[1].depth, k3), frames)),
        ('paper Eq. 5, horizontal', timed(lambda f: paper_flying_pixels(f[1].depth, 'horizontal'), frames)),
        ('paper Eq. 5, all directions', timed(lambda f: paper_flying_pixels(f[1].depth, 'all'), frames)),
        ('volcap flying-pixel filter, axis tests only (sparse_radius 0)',
         timed(lambda f: flying_pixels(f[1].depth, f[1].depth_model.fx, FlyingPixelConfig(sparse_radius=0)), frames)),
        ('volcap flying-pixel filter (with the sparse-return rescue)',
         timed(lambda f: flying_pixels(f[1].depth, f[1].depth_model.fx), frames)),
        ('fill of the holes amid sparse returns', timed(lambda f: fill_sparse_returns(*removed[id(f)]), frames)),
        ('the same fill, planes only (curved_support 0)',
         timed(lambda f: fill_sparse_returns(*removed[id(f)], FlyingPixelConfig(curved_support=0)), frames)),
        ('bare cv2.projectPoints of all depth pixels (reference)',
         timed(lambda f: f[1].color_model.project(cleaners[f[0]].registration.rays.reshape(-1, 3)
                                                  * np.maximum(f[1].depth.reshape(-1, 1), 0.1)), frames)),
        ('registration (project + z-buffered raster)', timed(lambda f: cleaners[f[0]].registration.register(f[1].depth), frames)),
        ('whole cleaning (DepthCleaner.process)', timed(lambda f: cleaners[f[0]].process(f[1].color, f[1].depth), frames)),
        ('whole cleaning without the completion inside the mask (complete_radius 0)',
         timed(lambda f: uncompleted[f[0]].process(f[1].color, f[1].depth), frames)),
        ('whole cleaning, holes filled and completed by planes only (curved_support 0)',
         timed(lambda f: planes[f[0]].process(f[1].color, f[1].depth), frames)),
        ('node callback (decode, clean, cloud, encode)', timed(node_callback, msgs)),
    ]
    stages = {}
    for name, f in frames:
        for k, v in cleaners[name].process(f.color, f.depth).timings_ms.items():
            stages.setdefault(k, []).append(v)
    ref = rows[0][1]
    print(f'{len(frames)} frames of 8 cameras, depth 640x576, colour 1280x720, one core')
    print('| step | ms per frame | x bare 3x3 cv2 |')
    print('|---|---|---|')
    for name, ms in rows:
        print(f'| {name} | {ms:.2f} | {ms / ref:.1f} |')
    print('stages of the whole cleaning (median ms): ' +
          ', '.join(f'{k} {statistics.median(v):.1f}' for k, v in stages.items()))
    if tmp:
        tmp.cleanup()
    return 0


if __name__ == '__main__':
    sys.exit(main())
