"""Rig description: the cameras, their names, intrinsics and factory depth-to-colour extrinsics.

Published as YAML on ``volcap/rig`` and stored in bags, so any node can rebuild it. Also read
by the nodes from a file (``rig_file``), written by ``volcap rig`` from each camera maker's
factory data: an Azure Kinect ``calibration.json`` (``k4arecorder``, ``k4a_device_get_raw_calibration``)
or OrbbecSDK_ROS2's topics as ``ros2 topic echo --once`` prints them (``depth_to_color``,
``color/camera_info``, ``depth/camera_info``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .camera import K4A_COLOR_MODES, K4A_DEPTH_MODES, CameraModel, camera_from_k4a
from .errors import BadInput, UnknownName
from .poses import make_transform, matrix_to_list, rigid_transform

RIG_VERSION = 1


@dataclass
class RigCamera:
    name: str
    color: CameraModel
    depth: CameraModel
    T_color_depth: np.ndarray = field(default_factory=lambda: np.eye(4))
    serial: str = ''

    @property
    def color_frame(self) -> str:
        return f'{self.name}_color_optical_frame'

    @property
    def depth_frame(self) -> str:
        return f'{self.name}_depth_optical_frame'

    def to_dict(self) -> dict:
        return {'name': self.name, 'serial': self.serial, 'color': self.color.to_dict(),
                'depth': self.depth.to_dict(), 'T_color_depth': matrix_to_list(self.T_color_depth)}

    @classmethod
    def from_dict(cls, d: dict) -> 'RigCamera':
        """Checked: a ValueError names the camera and the field that is wrong."""
        if not isinstance(d, dict) or not d.get('name'):
            raise BadInput(f'rig camera: expected a mapping with a name, got {d!r:.80}')
        if not isinstance(d['name'], str):
            raise BadInput(f'rig camera: name: expected text, got {d["name"]!r:.40}')
        name = d['name']
        serial = d.get('serial')
        if serial is not None and not isinstance(serial, (str, int)) or isinstance(serial, bool):
            raise BadInput(f'rig camera {name}: serial: expected text, got {serial!r:.40}')
        models = {}
        for stream in ('color', 'depth'):
            try:
                models[stream] = CameraModel.from_dict(d[stream])
            except KeyError as e:
                raise BadInput(f'rig camera {name}: no {stream} camera model') from e
            except ValueError as e:
                raise BadInput(f'rig camera {name}: {stream}: {e}') from e
        T = rigid_transform(d.get('T_color_depth', np.eye(4).tolist()), f'rig camera {name}: T_color_depth')
        return cls(name, models['color'], models['depth'], T, str(d.get('serial') or ''))


@dataclass
class Rig:
    cameras: list[RigCamera]
    name: str = 'volcap'

    def __post_init__(self):
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise BadInput(f'camera names must be unique, got {names}')

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def camera(self, name: str) -> RigCamera:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise UnknownName(f'no camera {name!r} in rig (cameras: {self.names})')

    def to_yaml(self) -> str:
        return yaml.safe_dump({'version': RIG_VERSION, 'name': self.name,
                               'cameras': [c.to_dict() for c in self.cameras]}, sort_keys=False)

    @classmethod
    def from_yaml(cls, text: str) -> 'Rig':
        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise BadInput(f'rig description is not YAML: {e}') from e
        if not isinstance(d, dict) or not isinstance(d.get('cameras'), list) or not d['cameras']:
            raise BadInput('rig YAML must be a mapping with a "cameras" list')
        version = d.get('version', RIG_VERSION)
        if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= RIG_VERSION:
            raise BadInput(f'rig YAML version {version!r} is not one this volcap reads (newer than {RIG_VERSION}?)')
        name = d.get('name', 'volcap')
        if not isinstance(name, str) or not name:
            raise BadInput(f'rig name: expected text, got {name!r:.40}')
        return cls([RigCamera.from_dict(c) for c in d['cameras']], name)


def rig_camera_from_k4a(calibration: dict | str | Path, name: str, color_mode: str = '720P',
                        depth_mode: str = 'NFOV_UNBINNED', serial: str = '') -> RigCamera:
    """RigCamera from an Azure Kinect factory calibration JSON (dict, text or file path)."""
    if isinstance(calibration, Path) or (isinstance(calibration, str) and not calibration.lstrip().startswith('{')):
        calibration = Path(calibration).read_text()
    if isinstance(calibration, str):
        calibration = json.loads(calibration)
    try:
        cams = {c['Purpose']: c for c in calibration['CalibrationInformation']['Cameras']}
        depth, color = cams['CALIBRATION_CameraPurposeDepth'], cams['CALIBRATION_CameraPurposePhotoVideo']
    except (KeyError, TypeError) as e:
        raise BadInput(f'not an Azure Kinect calibration JSON: missing {e}') from e
    if color_mode not in K4A_COLOR_MODES:
        raise BadInput(f'unknown colour mode {color_mode!r}; known: {sorted(K4A_COLOR_MODES)}')
    if depth_mode not in K4A_DEPTH_MODES:
        raise BadInput(f'unknown depth mode {depth_mode!r}; known: {sorted(K4A_DEPTH_MODES)}')
    # Each camera's Rt maps depth-camera points into that camera (metres).
    T_color_depth = make_transform(np.reshape(color['Rt']['Rotation'], (3, 3)), color['Rt']['Translation'])
    return RigCamera(name, camera_from_k4a(color['Intrinsics']['ModelParameters'], K4A_COLOR_MODES[color_mode]),
                     camera_from_k4a(depth['Intrinsics']['ModelParameters'], K4A_DEPTH_MODES[depth_mode]),
                     T_color_depth, serial)


def _echoed(source: str | Path) -> dict:
    """The first message of ``ros2 topic echo`` output (YAML documents separated by ``---``): a
    file (Path) or its text (str)."""
    text = source.read_text() if isinstance(source, Path) else source
    for doc in yaml.safe_load_all(text):
        if isinstance(doc, dict):
            return doc
    raise BadInput('no message in the echoed YAML')


def camera_model_from_echo(info: dict) -> CameraModel:
    """CameraModel of a sensor_msgs/CameraInfo as ``ros2 topic echo`` prints it (8 coefficients
    under plumb_bob, as Orbbec sends them, are OpenCV's rational model)."""
    try:
        k = [float(v) for v in info['k']]
        dist = tuple(float(v) for v in info.get('d') or [0.0] * 5)
        return CameraModel(int(info['width']), int(info['height']), k[0], k[4], k[2], k[5], dist)
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise BadInput(f'not a camera_info message: {e}') from e


def rig_camera_from_orbbec(name: str, extrinsics, color_info, depth_info, serial: str = '') -> RigCamera:
    """RigCamera from OrbbecSDK_ROS2's ``depth_to_color`` (orbbec_camera_msgs/Extrinsics: row-major
    rotation, translation in metres, depth to colour) and the two camera_info messages, each as
    ``ros2 topic echo --once`` writes it (a Path, its text, or the parsed dict)."""
    ex, ci, di = (m if isinstance(m, dict) else _echoed(m) for m in (extrinsics, color_info, depth_info))
    try:
        R = np.reshape([float(v) for v in ex['rotation']], (3, 3))
        t = [float(v) for v in ex['translation']]
    except (KeyError, TypeError, ValueError) as e:
        raise BadInput(f'not an Orbbec depth_to_color extrinsics message: {e}') from e
    if len(t) != 3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-4):
        raise BadInput('Orbbec extrinsics need a rotation matrix (9 values) and 3 translation values')
    return RigCamera(name, camera_model_from_echo(ci), camera_model_from_echo(di), make_transform(R, t), serial)
