"""The rig calibration file (``calibration.yaml``): per camera T_world_color, fit quality and
colour model. Written atomically; a failed calibration never replaces a good file."""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .files import atomic_write
from .poses import invert, matrix_from_list, matrix_to_list

VERSION = 1
STUDIO_FRAME = 'volcap_studio'


@dataclass
class StudioFrame:
    """The gravity-aligned studio frame (REP 103: +Z up, origin on the floor at the centre of the
    capture volume) in the calibration's world frame, and how it was found."""
    T_world_studio: np.ndarray
    name: str = STUDIO_FRAME
    details: dict = field(default_factory=dict)   # source ('floor' or 'cameras'), floor fit figures

    def to_dict(self) -> dict:
        return {'frame': self.name, 'T_world_studio': matrix_to_list(self.T_world_studio), **self.details}

    @classmethod
    def from_dict(cls, d: dict) -> 'StudioFrame':
        if not isinstance(d, dict) or 'T_world_studio' not in d:
            raise ValueError('studio: expected a mapping with T_world_studio')
        T = matrix_from_list(d['T_world_studio'])
        R = T[:3, :3]
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise ValueError('studio: T_world_studio is not a rigid transform')
        return cls(T, str(d.get('frame', STUDIO_FRAME)), {k: v for k, v in d.items()
                                                          if k not in ('frame', 'T_world_studio')})


@dataclass
class CameraCalibration:
    T_world_color: np.ndarray
    color_frame: str = ''
    reproj_rms_px: float | None = None
    depth_rms_mm: float | None = None
    views: int = 0
    color: dict | None = None      # {'method', 'matrix', fit errors...}: a volcap_core.color.ColorModel

    def to_dict(self) -> dict:
        return {'T_world_color': matrix_to_list(self.T_world_color), 'color_frame': self.color_frame,
                'reproj_rms_px': self.reproj_rms_px, 'depth_rms_mm': self.depth_rms_mm, 'views': self.views,
                'colour': self.color}

    @classmethod
    def from_dict(cls, d: dict) -> 'CameraCalibration':
        return cls(matrix_from_list(d['T_world_color']), d.get('color_frame', ''), d.get('reproj_rms_px'),
                   d.get('depth_rms_mm'), int(d.get('views', 0)), d.get('colour'))


@dataclass
class Calibration:
    reference: str
    world_frame: str
    cameras: dict[str, CameraCalibration]
    method: str = 'joint_least_squares'
    created: str = field(default_factory=lambda: dt.datetime.now(dt.timezone.utc).isoformat(timespec='seconds'))
    extra: dict = field(default_factory=dict)   # board, solver settings, summary figures

    def T_world_color(self, camera: str) -> np.ndarray:
        if camera not in self.cameras:
            raise KeyError(f'camera {camera!r} is not in the calibration ({", ".join(self.cameras)})')
        return self.cameras[camera].T_world_color

    @property
    def studio(self) -> StudioFrame | None:
        """The studio frame, when the calibration found one (files before it have none)."""
        return StudioFrame.from_dict(self.extra['studio']) if 'studio' in self.extra else None

    @studio.setter
    def studio(self, frame: StudioFrame) -> None:
        self.extra['studio'] = frame.to_dict()

    def output_frame(self) -> tuple[str, np.ndarray]:
        """(frame id, T_frame_world) fused output is given in: the studio frame, or the world
        frame itself for a calibration without one."""
        studio = self.studio
        if studio is None:
            return self.world_frame, np.eye(4)
        return studio.name, invert(studio.T_world_studio)

    def to_yaml(self) -> str:
        doc = {'version': VERSION, 'created': self.created, 'reference': self.reference,
               'world_frame': self.world_frame, 'method': self.method,
               'cameras': {n: c.to_dict() for n, c in self.cameras.items()}, **self.extra}
        return yaml.safe_dump(doc, sort_keys=False)

    @classmethod
    def from_yaml(cls, text: str) -> 'Calibration':
        d = yaml.safe_load(text)
        if not isinstance(d, dict) or 'cameras' not in d:
            raise ValueError('not a volcap calibration (no cameras)')
        if d.get('version') != VERSION:
            raise ValueError(f'calibration version {d.get("version")!r} is not supported (expected {VERSION})')
        known = {'version', 'created', 'reference', 'world_frame', 'method', 'cameras'}
        return cls(d['reference'], d['world_frame'],
                   {n: CameraCalibration.from_dict(c) for n, c in d['cameras'].items()},
                   d.get('method', ''), d.get('created', ''), {k: v for k, v in d.items() if k not in known})

    def save(self, path: str | Path) -> Path:
        text = self.to_yaml()
        return atomic_write(path, lambda f: f.write(text), binary=False)

    @classmethod
    def load(cls, path: str | Path) -> 'Calibration':
        return cls.from_yaml(Path(path).read_text())
