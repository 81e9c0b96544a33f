"""Pinhole camera with Brown-Conrady distortion, as Azure Kinect factory calibrations give it.

Pixel convention is ROS / OpenCV: the centre of the top-left pixel is (0, 0). Distortion is
kept in OpenCV order (k1, k2, p1, p2, k3, k4, k5, k6): eight coefficients is the rational
model ROS calls ``rational_polynomial``, five is ``plumb_bob``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import cv2
import numpy as np

from .errors import BadInput

DISTORTION_MODELS = {5: 'plumb_bob', 8: 'rational_polynomial'}


MAX_IMAGE_SIDE = 16384       # pixels: beyond any depth or colour camera, below a size that exhausts memory


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = field(default=(0.0,) * 5)

    def __post_init__(self):
        if not (0 < self.width <= MAX_IMAGE_SIDE and 0 < self.height <= MAX_IMAGE_SIDE):
            raise BadInput(f'camera size must be 1-{MAX_IMAGE_SIDE} pixels a side, got {self.width}x{self.height}')
        if not (np.isfinite(self.fx) and np.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise BadInput(f'focal lengths must be positive, got fx={self.fx} fy={self.fy}')
        if not (np.isfinite(self.cx) and np.isfinite(self.cy)):
            raise BadInput(f'principal point must be finite, got cx={self.cx} cy={self.cy}')
        if len(self.dist) not in DISTORTION_MODELS:
            raise BadInput(f'expected 5 or 8 distortion coefficients, got {len(self.dist)}')
        if not np.all(np.isfinite(self.dist)):
            raise BadInput(f'distortion coefficients must be finite, got {list(self.dist)}')
        # plain Python numbers (models built from numpy arrays must still serialise to YAML)
        for name in ('width', 'height'):
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in ('fx', 'fy', 'cx', 'cy'):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, 'dist', tuple(float(d) for d in self.dist))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def distortion_model(self) -> str:
        return DISTORTION_MODELS[len(self.dist)]

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame points (N, 3) with z > 0, distortion applied."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 3)
        if not len(pts):        # OpenCV answers None for no points
            return np.zeros((0, 2))
        zero = np.zeros(3)
        px, _ = cv2.projectPoints(pts, zero, zero, self.K, self.D)
        return px.reshape(-1, 2)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (N, 2) (x/z, y/z) of distorted pixels (N, 2)."""
        px = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        xy = cv2.undistortPoints(px, self.K, self.D, R=np.eye(3), P=np.eye(3), criteria=criteria)
        return xy.reshape(-1, 2)

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame directions with z = 1 through every pixel centre; read-only.

        Shared by every caller in the process: undistorting every pixel to 1e-12 costs 0.3-0.5 s
        a 1280x720 camera on 2 cores, and one colour evaluation used to repeat it about 40 times
        (12 of its 55 s), the studio renderer 16 times a bag. Copy (``astype``) to change it."""
        return _pixel_rays(self)

    def scaled(self, width: int, height: int) -> 'CameraModel':
        """The same lens seen at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    def to_dict(self) -> dict:
        return {'width': self.width, 'height': self.height, 'fx': self.fx, 'fy': self.fy,
                'cx': self.cx, 'cy': self.cy, 'distortion_model': self.distortion_model,
                'D': list(self.dist)}

    @classmethod
    def from_dict(cls, d: dict) -> 'CameraModel':
        """Checked: anything but a usable model is a ValueError saying what is wrong."""
        if not isinstance(d, dict):
            raise BadInput(f'not a camera model: expected a mapping, got {d!r:.40}')
        for key in ('width', 'height', 'fx', 'fy', 'cx', 'cy'):
            if isinstance(d.get(key), bool) or (key in ('width', 'height') and isinstance(d.get(key), float)
                                                and not float(d[key]).is_integer()):
                raise BadInput(f'{key}: expected a number of pixels, got {d.get(key)!r}')
        model = d.get('distortion_model')
        try:
            out = cls(int(d['width']), int(d['height']), float(d['fx']), float(d['fy']),
                      float(d['cx']), float(d['cy']), tuple(float(v) for v in d.get('D', (0.0,) * 5)))
        except (KeyError, TypeError, AttributeError, OverflowError) as e:
            raise BadInput(f'not a camera model ({type(e).__name__}: {e})') from e
        if model is not None and model != out.distortion_model:
            raise BadInput(f'distortion_model {model!r:.40} does not match the {len(out.dist)} coefficients of D '
                           f'(expected {out.distortion_model!r})')
        return out


# A rig's colour and depth cameras (8 + 8). 22 MB a 1280x720 camera: a process that meets more
# lenses than this computes the oldest again.
@lru_cache(maxsize=16)
def _pixel_rays(model: CameraModel) -> np.ndarray:
    u, v = np.meshgrid(np.arange(model.width, dtype=np.float64), np.arange(model.height, dtype=np.float64))
    xy = model.undistort_pixels(np.stack([u.ravel(), v.ravel()], axis=1))
    rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1).reshape(model.height, model.width, 3)
    rays.flags.writeable = False
    return rays


# Azure Kinect: how each sensor mode crops and scales the factory calibration image.
# (calibration image size after binning, crop offset, output size); see the Azure Kinect SDK's
# transformation_get_mode_specific_camera_calibration.
K4A_DEPTH_MODES = {
    'NFOV_2X2BINNED': ((512, 512), (96, 90), (320, 288)),
    'NFOV_UNBINNED': ((1024, 1024), (192, 180), (640, 576)),
    'WFOV_2X2BINNED': ((512, 512), (0, 0), (512, 512)),
    'WFOV_UNBINNED': ((1024, 1024), (0, 0), (1024, 1024)),
}
K4A_COLOR_MODES = {
    '720P': ((1280, 960), (0, 120), (1280, 720)),
    '1080P': ((1920, 1440), (0, 180), (1920, 1080)),
    '1440P': ((2560, 1920), (0, 240), (2560, 1440)),
    '1536P': ((2048, 1536), (0, 0), (2048, 1536)),
    '2160P': ((3840, 2880), (0, 360), (3840, 2160)),
    '3072P': ((4096, 3072), (0, 0), (4096, 3072)),
}


def camera_from_k4a(params: list[float], mode: tuple) -> CameraModel:
    """CameraModel of one Azure Kinect sensor mode from the 14 factory Brown-Conrady parameters.

    ``params`` is (cx, cy, fx, fy, k1..k6, codx, cody, p2, p1) normalised by the calibration
    image size, as stored in the device's calibration JSON.
    """
    if len(params) < 14:
        raise BadInput(f'Azure Kinect intrinsics need 14 parameters, got {len(params)}')
    (bw, bh), (ox, oy), (w, h) = mode
    cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, _codx, _cody, p2, p1 = params[:14]
    return CameraModel(w, h, fx * bw, fy * bh, cx * bw - ox - 0.5, cy * bh - oy - 0.5,
                       (k1, k2, p1, p2, k3, k4, k5, k6))


def depth_to_millimetres(depth_m: np.ndarray) -> np.ndarray:
    """A depth image in metres as uint16 millimetres (the 16UC1 convention, 0 = no depth):
    NaN, infinite and negative values become 0, depth beyond 65.535 m is clipped."""
    d = np.nan_to_num(np.asarray(depth_m, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16)
