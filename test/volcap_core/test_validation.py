"""Every input a node trusts is checked before use: a malformed calibration, rig description or
camera_info is a ValueError that names what is wrong, never another exception (which would take
a node down) and never accepted."""
import copy

import numpy as np
import pytest
import yaml
from sensor_msgs.msg import CameraInfo

from volcap_core.calibration import Calibration, CameraCalibration, StudioFrame
from volcap_core.camera import CameraModel
from volcap_core.color import ColorModel
from volcap_core.conversions import MessageConversionError, camera_info_to_model
from volcap_core.rig import Rig, RigCamera

BAD_VALUES = [None, 'text', [], {}, [1, 2], float('nan'), float('inf'), -1, True, [[1, 2], [3, 4]],
              [[float('nan')] * 4] * 4]


def good_calibration() -> dict:
    T = np.eye(4)
    T[:3, 3] = (0.5, 0.0, 1.0)
    color = ColorModel('matrix_3x3', np.eye(3)).to_dict()
    cal = Calibration('cam0', 'cam0_color_optical_frame',
                      {'cam0': CameraCalibration(np.eye(4), 'cam0_color_optical_frame', 0.3, 2.0, 5, color),
                       'cam1': CameraCalibration(T, 'cam1_color_optical_frame', 0.4, None, 4, None)})
    cal.studio = StudioFrame(np.eye(4), details={'source': 'floor'})
    return yaml.safe_load(cal.to_yaml())


def paths(doc, prefix=()):
    """Every key path of a nested mapping."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield prefix + (k,)
            yield from paths(v, prefix + (k,))


def replaced(doc, path, value):
    out = copy.deepcopy(doc)
    node = out
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return out


# The values a field may legitimately take beyond the good document's, by field name. Text is
# free (a note, a frame name); the fit figures and the colour model are optional (None); a
# principal point may lie anywhere (a crop can put it off the image), a serial can be a number.
# Every other malformed value must be refused.
FREE = {'created': {'text', None}, 'method': {'text', None}, 'world_frame': {'text'}, 'color_frame': {'text', None},
        'frame': {'text'}, 'source': {'text'}, 'reproj_rms_px': {None}, 'depth_rms_mm': {None}, 'views': {None},
        'colour': {None}, 'distortion_model': {None}, 'name': {'text'}, 'serial': {'text', -1, None}, 'cx': {-1}, 'cy': {-1}}


def _allowed(path, value) -> bool:
    return any(value is v or (value == v and type(value) is type(v)) for v in FREE.get(path[-1], ()))


def test_every_malformed_field_of_a_calibration_is_a_clear_error():
    doc = good_calibration()
    Calibration.from_yaml(yaml.safe_dump(doc))
    accepted = []
    for path in paths(doc):
        for value in BAD_VALUES:
            text = yaml.safe_dump(replaced(doc, path, value))
            try:
                Calibration.from_yaml(text)
            except ValueError as e:
                assert str(e)          # a message, not a bare exception
            else:
                if not _allowed(path, value):
                    accepted.append((path, value))
    assert not accepted, accepted


@pytest.mark.parametrize('path, value, message', [
    (('cameras',), ['cam0', 'cam1'], 'cameras: expected a mapping'),
    (('cameras', 'cam0', 'colour'), 'linear', 'colour: expected a colour model'),
    (('cameras', 'cam0', 'colour', 'matrix'), [[1, 0], [0, 1]], 'needs a finite 3x3 matrix'),
    (('cameras', 'cam1', 'T_world_color'), [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], 'not a rigid'),
    (('cameras', 'cam1', 'T_world_color'), 'identity', 'T_world_color'),
    (('reference',), ['cam0'], 'reference'),
    (('studio', 'T_world_studio'), [[float('nan')] * 4] * 4, 'T_world_studio'),
])
def test_calibration_errors_name_the_field(path, value, message):
    with pytest.raises(ValueError, match=message):
        Calibration.from_yaml(yaml.safe_dump(replaced(good_calibration(), path, value)))


@pytest.mark.parametrize('text', ['{not yaml: [', '', 'just a string', '- a\n- list', 'version: 1\ncameras: {}'])
def test_not_a_calibration(text, tmp_path):
    with pytest.raises(ValueError):
        Calibration.from_yaml(text)
    (tmp_path / 'c.yaml').write_text(text)
    with pytest.raises(ValueError, match='c.yaml'):
        Calibration.load(tmp_path / 'c.yaml')
    with pytest.raises(ValueError, match='does not exist'):
        Calibration.load(tmp_path / 'missing.yaml')


def test_a_calibration_the_nodes_would_refuse_is_never_written(tmp_path):
    cal = Calibration.from_yaml(yaml.safe_dump(good_calibration()))
    cal.save(tmp_path / 'calibration.yaml')
    cal.cameras['cam1'].T_world_color = np.full((4, 4), np.nan)      # a degenerate solve
    with pytest.raises(ValueError, match='cam1'):
        cal.save(tmp_path / 'calibration.yaml')
    assert Calibration.load(tmp_path / 'calibration.yaml').cameras['cam1'].T_world_color[0, 3] == 0.5


def test_every_malformed_field_of_a_rig_is_a_clear_error():
    cam = RigCamera('cam0', CameraModel(1280, 720, 600, 600, 640, 360), CameraModel(640, 576, 500, 500, 320, 288))
    doc = yaml.safe_load(Rig([cam]).to_yaml())
    accepted = []
    cases = [(p, replaced(doc, p, v), v) for p in [*paths(doc), ('cameras',)] for v in BAD_VALUES]
    for path in paths(doc['cameras'][0]):
        for value in BAD_VALUES:
            bad = copy.deepcopy(doc)
            bad['cameras'][0] = replaced(doc['cameras'][0], path, value)
            cases.append((path, bad, value))
    for path, bad, value in cases:
        try:
            Rig.from_yaml(yaml.safe_dump(bad))
        except ValueError as e:
            assert str(e)
        else:
            if not _allowed(path, value):
                accepted.append((path, value))
    assert not accepted, accepted
    with pytest.raises(ValueError, match='not YAML'):
        Rig.from_yaml('{cameras: [')


@pytest.mark.parametrize('field, value, message', [
    ('width', 1_000_000, 'pixels a side'), ('height', 1_000_000, 'pixels a side'),
    ('d', [float('nan')] * 5, 'distortion coefficients must be finite'),
    ('k', [float('nan')] * 9, 'focal lengths'), ('k', [0.0] * 9, 'focal lengths'),
    ('d', [0.1] * 3, '3 distortion coefficients'), ('distortion_model', 'fisheye9', 'unsupported distortion'),
])
def test_camera_info_is_checked_before_use(field, value, message):
    info = CameraInfo(width=640, height=576, k=[500.0, 0, 320, 0, 500, 288, 0, 0, 1], d=[0.0] * 5,
                      distortion_model='plumb_bob')
    camera_info_to_model(info)
    setattr(info, field, value)
    with pytest.raises(MessageConversionError, match=message):
        camera_info_to_model(info)
