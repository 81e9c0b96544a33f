"""The rig calibration file (``calibration.yaml``): per camera T_world_color, fit quality and
colour model. Written atomically; a failed calibration never replaces a good file."""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .errors import BadInput, UnknownName
from .files import atomic_write
from .poses import invert, matrix_to_list, rigid_transform

VERSION = 1
STUDIO_FRAME = 'volcap_studio'


class CalibrationFileError(BadInput):
    """A calibration file or message that is not a usable volcap calibration (says which field)."""


def _number(value, what: str, minimum: float = 0.0):
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < minimum:
        raise CalibrationFileError(f'{what}: expected a finite number >= {minimum}, got {value!r}')
    return value


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
            raise CalibrationFileError('studio: expected a mapping with T_world_studio')
        try:
            T = rigid_transform(d['T_world_studio'], 'studio: T_world_studio')
        except ValueError as e:
            raise CalibrationFileError(str(e)) from e
        for key in ('frame', 'source'):
            if key in d and (not isinstance(d[key], str) or not d[key]):
                raise CalibrationFileError(f'studio: {key}: expected a name, got {d[key]!r:.40}')
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
    # the solve's predicted RMS pose error relative to the reference: {'rot_deg', 'trans_mm'}
    predicted_error: dict | None = None

    def to_dict(self) -> dict:
        out = {'T_world_color': matrix_to_list(self.T_world_color), 'color_frame': self.color_frame,
               'reproj_rms_px': self.reproj_rms_px, 'depth_rms_mm': self.depth_rms_mm, 'views': self.views,
               'colour': self.color}
        if self.predicted_error is not None:
            out['predicted_error'] = dict(self.predicted_error)
        return out

    @classmethod
    def from_dict(cls, d: dict, name: str = 'camera') -> 'CameraCalibration':
        """Checked field by field: a CalibrationFileError names the first one that is wrong."""
        from .color import ColorModel
        if not isinstance(d, dict):
            raise CalibrationFileError(f'cameras: {name}: expected a mapping, got {type(d).__name__}')
        if 'T_world_color' not in d:
            raise CalibrationFileError(f'cameras: {name}: no T_world_color')
        try:
            T = rigid_transform(d['T_world_color'], f'cameras: {name}: T_world_color')
        except ValueError as e:
            raise CalibrationFileError(str(e)) from e
        views = _number(d.get('views', 0), f'cameras: {name}: views')
        if 'color_frame' in d and d['color_frame'] is not None and not isinstance(d['color_frame'], str):
            raise CalibrationFileError(f'cameras: {name}: color_frame: expected a frame name, got {d["color_frame"]!r:.40}')
        color = d.get('colour')
        if color is not None:
            if not isinstance(color, dict):
                raise CalibrationFileError(f'cameras: {name}: colour: expected a colour model mapping, '
                                       f'got {type(color).__name__}')
            try:
                ColorModel.from_dict(color)
            except (KeyError, TypeError, ValueError) as e:
                raise CalibrationFileError(f'cameras: {name}: colour: {e}') from e
        predicted = d.get('predicted_error')
        if predicted is not None:
            if not isinstance(predicted, dict):
                raise CalibrationFileError(f'cameras: {name}: predicted_error: expected a mapping, '
                                           f'got {type(predicted).__name__}')
            predicted = {k: _number(predicted.get(k), f'cameras: {name}: predicted_error: {k}')
                         for k in ('rot_deg', 'trans_mm')}
        return cls(T, str(d.get('color_frame') or ''), _number(d.get('reproj_rms_px'), f'cameras: {name}: reproj_rms_px'),
                   _number(d.get('depth_rms_mm'), f'cameras: {name}: depth_rms_mm'), int(views or 0), color,
                   predicted)


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
            raise UnknownName(f'camera {camera!r} is not in the calibration ({", ".join(self.cameras)})')
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
        """A calibration from its YAML, every field checked; CalibrationFileError (a ValueError) says
        what is wrong, so a subscriber can refuse it and keep the one it has."""
        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise CalibrationFileError(f'not YAML: {e}') from e
        if not isinstance(d, dict) or 'cameras' not in d:
            raise CalibrationFileError('not a volcap calibration (no cameras)')
        if isinstance(d.get('version'), bool) or d.get('version') != VERSION:
            raise CalibrationFileError(f'calibration version {d.get("version")!r} is not supported (expected {VERSION})')
        cameras = d['cameras']
        if not isinstance(cameras, dict) or not cameras:
            raise CalibrationFileError(f'cameras: expected a mapping of camera name to calibration, got '
                                   f'{type(cameras).__name__ if cameras else "nothing"}')
        for key in ('reference', 'world_frame'):
            if not isinstance(d.get(key), str) or not d[key]:
                raise CalibrationFileError(f'{key}: expected a name, got {d.get(key)!r}')
        if d['reference'] not in cameras:
            raise CalibrationFileError(f'reference: {d["reference"]!r} is not one of the calibrated cameras '
                                       f'({", ".join(map(str, cameras))})')
        for key in ('method', 'created'):
            if d.get(key) is not None and not isinstance(d[key], str):
                raise CalibrationFileError(f'{key}: expected text, got {d[key]!r:.40}')
        known = {'version', 'created', 'reference', 'world_frame', 'method', 'cameras'}
        calibration = cls(d['reference'], d['world_frame'],
                          {str(n): CameraCalibration.from_dict(c, str(n)) for n, c in cameras.items()},
                          str(d.get('method') or ''), str(d.get('created') or ''),
                          {k: v for k, v in d.items() if k not in known})
        _ = calibration.studio          # checks the studio frame, when there is one
        return calibration

    def checked_yaml(self) -> str:
        """The YAML, after reading it back with every check a subscriber makes: a calibration
        that the nodes would refuse is never written or published."""
        text = self.to_yaml()
        Calibration.from_yaml(text)
        return text

    def save(self, path: str | Path) -> Path:
        text = self.checked_yaml()
        return atomic_write(path, lambda f: f.write(text), binary=False)

    @classmethod
    def load(cls, path: str | Path) -> 'Calibration':
        """Read and check ``path``; CalibrationFileError names the file and what is wrong with it."""
        try:
            text = Path(path).read_text()
        except FileNotFoundError as e:
            raise CalibrationFileError(f'calibration {path} does not exist') from e
        except (OSError, UnicodeDecodeError) as e:
            raise CalibrationFileError(f'calibration {path} is unreadable: {e}') from e
        try:
            return cls.from_yaml(text)
        except CalibrationFileError as e:
            raise CalibrationFileError(f'calibration {path}: {e}') from e
