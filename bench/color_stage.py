"""Colour stage timings at rig sizes (8 cameras, colour 1280x720), each against the raw library
call measured in the same run (named color_stage: a bench/colour.py would shadow colour-science):

- live correction per 1280x720 frame (``ImageCorrector``) for every kind of model, against one
  bare ``cv2.transform`` of the uint8 image with a 3x3 matrix (what a model on the encoded values
  costs);
- the correspondence finder per 8-camera frame set (28 pairs), against one bare
  ``cv2.projectPoints`` of every valid pixel of every camera into every other camera;
- the chart-free fit and the baselines on those correspondences.

    python bench/color_stage.py BAG CALIBRATION   (a bag with clean plate and capture frames, and
                                             its calibration.yaml)
"""
import sys
import time

import cv2
import numpy as np

from volcap_color.apply import ImageCorrector
from volcap_color.correspondence import find_correspondences, merge_matches
from volcap_core import transport
from volcap_core.calibration import Calibration
from volcap_core.color import ColorModel
from volcap_eval.color import ColorEvalConfig, method_mappings
from volcap_pipeline.replay import capture_views

M = np.array([[1.1, 0.05, -0.02], [0.03, 0.92, 0.01], [-0.04, 0.02, 1.2]])
MODELS = {
    'matrix_3x3': ColorModel('matrix_3x3', M),
    'affine_3x4': ColorModel('affine_3x4', np.hstack([M, [[0.01], [-0.01], [0.0]]])),
    'gamma_3x3 + harmonising post': ColorModel('gamma_3x3', M, (1.1, 0.95, 1.02),
                                               post=np.hstack([np.eye(3) * 0.95, np.zeros((3, 1))])),
    'root_polynomial_2 (3D LUT)': ColorModel('root_polynomial_2', np.hstack([np.eye(3) * 1.05, np.full((3, 3), 0.02)])),
    'paper_diagonal': ColorModel('paper_diagonal', np.diag([1.1, 0.9, 1.05])),
}


def median_ms(fn, repeat=50) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e3


def main(bag: str, calibration_path: str) -> None:
    transport.configure()      # the malloc settings every node runs with
    image = np.random.default_rng(0).integers(0, 256, (720, 1280, 3), dtype=np.uint8)
    bare = median_ms(lambda: cv2.transform(image, M.astype(np.float32)))
    print(f'bare cv2.transform 3x3 on uint8 1280x720:            {bare:6.2f} ms')
    for name, model in MODELS.items():
        corrector = ImageCorrector(model)
        out = corrector(image)
        ms = median_ms(lambda: corrector(image, out))
        print(f'ImageCorrector {name:<32} {ms:6.2f} ms  ({ms / bare:5.1f}x bare; {corrector.kind})')

    calibration = Calibration.load(calibration_path)
    cfg = ColorEvalConfig()
    t0 = time.perf_counter()
    sets = capture_views(bag, calibration, 2, progress=False)
    t_views = (time.perf_counter() - t0) / len(sets)
    find_correspondences(sets[0], cfg.correspondence)      # first use builds each camera's ray table
    views = sets[1]
    t0 = time.perf_counter()
    matches = find_correspondences(views, cfg.correspondence)
    t_match = time.perf_counter() - t0

    def bare_projection():
        for a in views:
            v, u = np.nonzero(a.depth > 0)
            pts = a.rays()[v, u] * a.depth[v, u, None]
            for b in views:
                if b is a:
                    continue
                T = np.linalg.inv(b.T_world_camera) @ a.T_world_camera
                cv2.projectPoints(np.ascontiguousarray(pts @ T[:3, :3].T + T[:3, 3], np.float64).reshape(-1, 1, 3),
                                  np.zeros(3), np.zeros(3), b.camera.K, b.camera.D)
    t0 = time.perf_counter()
    bare_projection()
    t_bare = time.perf_counter() - t0
    n = sum(len(m) for m in matches.values())
    print(f'capture views per frame set (clean, register at 1280x720, smooth; 8 cameras): {t_views:6.2f} s')
    print(f'correspondences per frame set: {t_match:6.2f} s for {len(matches)} pairs, {n} matches '
          f'({t_match / t_bare:.2f}x bare cv2.projectPoints of every pixel into every camera, {t_bare:.2f} s)')
    fit = merge_matches([matches], cfg.fit_min_fraction)
    t0 = time.perf_counter()
    method_mappings(fit, [v.name for v in views], calibration, None, cfg)
    print(f'fitting every correspondence method (baselines + chart-free): {time.perf_counter() - t0:6.2f} s')


if __name__ == '__main__':
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
