"""Calibration stage timings on a synthetic studio bag (8 cameras, colour 1280x720):
board detection against a bare OpenCV CharucoDetector on the same images, the solve (joint
least squares, colour fits) against the paper's SED gradient-descent baseline, and the
ColorChecker finder on the real photos in ../shared/data/colorchecker against one bare OpenCV
threshold-and-contours pass over the same photo.

    python bench/calib.py BAG      (a bag from `volcap synth --board-poses 40 --frames 0`)
"""
import sys
import time
from pathlib import Path

import cv2

from volcap_calib.board import BoardConfig, reference_srgb8
from volcap_calib.calibrate import BoardView, CalibrationConfig, Calibrator
from volcap_calib.chart import find_color_checker
from volcap_calib.color import fit_camera_color
from volcap_calib.extrinsics import sed_baseline
from volcap_core.bag_reader import BagReader
from volcap_core.frames import frame_sets, read_rig
from volcap_core.topics import CALIBRATION_PHASE


def main(bag: str) -> None:
    board = BoardConfig.from_yaml()
    sets = list(frame_sets(bag, phases=(CALIBRATION_PHASE,)))
    with BagReader(bag) as reader:
        rig = read_rig(reader)
    bare = cv2.aruco.CharucoDetector(board.charuco_board())
    images = [f.color for fs in sets for f in fs.cameras.values()]
    t0 = time.perf_counter()
    for img in images:
        bare.detectBoard(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    t_bare = (time.perf_counter() - t0) / len(images)
    calibrator = Calibrator(rig, board, CalibrationConfig())
    t0 = time.perf_counter()
    for fs in sets:
        calibrator.add(fs.index, {n: BoardView(f.color, f.color_model, f.depth, f.depth_model)
                                  for n, f in fs.cameras.items()})
    t_add = (time.perf_counter() - t0) / len(images)
    t0 = time.perf_counter()
    outcome = calibrator.solve()
    t_solve = time.perf_counter() - t0
    t0 = time.perf_counter()
    sed_baseline(calibrator.observations, calibrator.models, outcome.calibration.reference)
    t_base = time.perf_counter() - t0
    print(f'{len(sets)} frame sets, {len(images)} images, {len(calibrator.observations)} board observations')
    print(f'bare cv2 CharucoDetector per image:              {t_bare * 1000:7.1f} ms')
    print(f'Calibrator.add per image (detect, PnP, depth, patches): {t_add * 1000:7.1f} ms  '
          f'({t_add / t_bare:.2f}x bare detection)')
    print(f'solve (joint least squares + colour leave-one-out): {t_solve:7.1f} s')
    print(f'paper SED gradient-descent baseline:               {t_base:7.1f} s')
    t0 = time.perf_counter()
    illumination = calibrator.illumination()
    for c in rig.names:
        fit_camera_color(*calibrator.color_samples(c, illumination))
    print(f'  of the solve, colour (illumination, 6 models x leave-one-patch-out, Lab refinement, 8 cameras): '
          f'{time.perf_counter() - t0:5.1f} s')
    charts = Path(__file__).resolve().parents[2] / 'shared' / 'data' / 'colorchecker'
    reference = reference_srgb8() / 255.0
    for photo in sorted(charts.glob('*.png')):
        image = cv2.cvtColor(cv2.imread(str(photo)), cv2.COLOR_BGR2RGB)
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        t0 = time.perf_counter()
        cv2.findContours(cv2.adaptiveThreshold(gray, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, 61, -5),
                         cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        t_pass = time.perf_counter() - t0
        t0 = time.perf_counter()
        find_color_checker(image, reference)
        t_find = time.perf_counter() - t0
        print(f'ColorChecker finder, {photo.name} ({image.shape[1]}x{image.shape[0]}): {t_find * 1000:6.1f} ms '
              f'({t_find / t_pass:.0f}x one bare threshold + contours pass, {t_pass * 1000:.1f} ms)')


if __name__ == '__main__':
    main(sys.argv[1] if len(sys.argv) > 1 else 'bench_calib_bag')
