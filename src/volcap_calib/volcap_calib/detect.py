"""Calibration-target detection: ChArUco corners (the volcap board) and plain chessboards.

A detection is the target's corner ids, their pixels (sub-pixel refined) and the matching
target coordinates, which is all the extrinsic solver needs from an image.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput

from .board import BoardConfig


@dataclass
class Detection:
    ids: np.ndarray            # (N,) corner ids of the target
    pixels: np.ndarray         # (N, 2) float64 image coordinates
    object_points: np.ndarray  # (N, 3) target coordinates (metres), z = 0 on the target plane
    marker_ids: np.ndarray | None = None      # ArUco ids (ChArUco only)
    marker_corners: np.ndarray | None = None  # (M, 4, 2)

    def __len__(self) -> int:
        return len(self.ids)


class DetectionError(BadInput):
    """The target was not found, or too little of it to use."""


def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise BadInput(f'expected a grey or RGB image, got shape {image.shape}')


class BoardDetector:
    """ChArUco corners of ``board``; uses the intrinsics (when given) to interpolate corners."""

    def __init__(self, board: BoardConfig, min_corners: int = 6):
        if min_corners < 4:
            raise BadInput('min_corners must be >= 4 (a pose needs four non-collinear corners)')
        self.board, self.min_corners = board, min_corners
        self._charuco = board.charuco_board()
        self._corners3d = board.charuco_corners()
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._params = params
        self._detectors: dict = {}

    def _detector(self, camera: CameraModel | None) -> 'cv2.aruco.CharucoDetector':
        key = None if camera is None else (camera.fx, camera.fy, camera.cx, camera.cy, camera.dist)
        if key not in self._detectors:
            cp = cv2.aruco.CharucoParameters()
            if camera is not None:
                cp.cameraMatrix, cp.distCoeffs = camera.K, camera.D
            self._detectors[key] = cv2.aruco.CharucoDetector(self._charuco, cp, self._params)
        return self._detectors[key]

    def detect(self, image: np.ndarray, camera: CameraModel | None = None) -> Detection:
        """Raises DetectionError when fewer than ``min_corners`` corners are found."""
        corners, ids, marker_corners, marker_ids = self._detector(camera).detectBoard(_gray(image))
        n = 0 if ids is None else len(ids)
        if n < self.min_corners:
            markers = 0 if marker_ids is None else len(marker_ids)
            raise DetectionError(f'{n} ChArUco corners found ({markers} markers), need {self.min_corners}')
        ids = ids.ravel().astype(np.int64)
        return Detection(ids, corners.reshape(-1, 2).astype(np.float64), self._corners3d[ids],
                         marker_ids.ravel().astype(np.int64),
                         np.asarray(marker_corners, np.float64).reshape(-1, 4, 2))


def chessboard_points(pattern: tuple[int, int], square: float) -> np.ndarray:
    """(cols * rows, 3) target coordinates of a chessboard's inner corners, OpenCV's order."""
    cols, rows = pattern
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
    return np.hstack([grid, np.zeros((len(grid), 1))])


def detect_chessboard(image: np.ndarray, pattern: tuple[int, int], square: float) -> Detection:
    """All inner corners of a ``pattern`` = (cols, rows) chessboard, sub-pixel refined."""
    gray = _gray(image)
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                               | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        raise DetectionError(f'no {pattern[0]}x{pattern[1]} chessboard found')
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-3)
    corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
    ids = np.arange(pattern[0] * pattern[1])
    return Detection(ids, corners.reshape(-1, 2).astype(np.float64), chessboard_points(pattern, square))
