"""The one rule for where the rig comes from: a rig file, then /volcap/rig, then camera_info and
/tf_static, whatever order they arrive in."""
import numpy as np
import pytest

from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput
from volcap_core.poses import make_transform
from volcap_core.rig import Rig, RigCamera
from volcap_core.rig_source import ASSEMBLED, FILE, TOPIC, RigResolver

COLOR = CameraModel(1280, 720, 600.0, 600.0, 640.0, 360.0)
DEPTH = CameraModel(640, 576, 500.0, 500.0, 320.0, 288.0)
T_FILE = make_transform(np.eye(3), [0.032, 0.0, 0.0])
T_TOPIC = make_transform(np.eye(3), [0.030, 0.0, 0.0])
T_TF = make_transform(np.eye(3), [0.025, 0.001, 0.0])


def _rig_yaml(T) -> str:
    return Rig([RigCamera('cam0', COLOR, DEPTH, T)], 'test').to_yaml()


def _infos(r: RigResolver, camera='cam0', depth_frame='cam0_depth'):
    r.add_camera_info(camera, 'color', COLOR, f'{camera}_rgb')
    return r.add_camera_info(camera, 'depth', DEPTH, depth_frame)


def test_a_rig_file_wins_whatever_arrives_before_or_after(tmp_path):
    path = tmp_path / 'rig.yaml'
    path.write_text(_rig_yaml(T_FILE))
    r = RigResolver(['cam0'])
    assert r.offer_description(_rig_yaml(T_TOPIC)).camera('cam0').T_color_depth[0, 3] == pytest.approx(0.030)
    assert r.source == TOPIC
    r.set_file(path)
    assert r.source.startswith(FILE) and r.rig.camera('cam0').T_color_depth[0, 3] == pytest.approx(0.032)
    assert r.offer_description(_rig_yaml(T_TOPIC)) is None          # a bag's rig does not replace the file
    _infos(r)
    assert r.add_transform('cam0_rgb', 'cam0_depth', T_TF) is None  # nor does an assembled one
    assert r.rig.camera('cam0').T_color_depth[0, 3] == pytest.approx(0.032)


def test_volcap_rig_wins_over_camera_info_and_tf_static():
    r = RigResolver(['cam0'])
    _infos(r)
    assert r.rig is None and r.waiting == ['cam0 (cam0_depth -> cam0_rgb)']
    assembled = r.add_transform('cam0_rgb', 'cam0_depth', T_TF)
    assert r.source == ASSEMBLED and assembled.camera('cam0').T_color_depth[0, 3] == pytest.approx(0.025)
    assert r.offer_description(_rig_yaml(T_TOPIC)) is not None and r.source == TOPIC
    assert r.add_transform('cam0_rgb', 'cam0_depth', T_TF) is None and r.source == TOPIC


def test_assembled_rig_grows_camera_by_camera_and_registered_depth_needs_no_transform():
    r = RigResolver(['cam0', 'cam1'], tf_prefix='')
    assert _infos(r, 'cam1', depth_frame='cam1_rgb').names == ['cam1']     # registered: same frame id
    assert np.allclose(r.rig.camera('cam1').T_color_depth, np.eye(4))
    _infos(r, 'cam0')
    assert r.rig.names == ['cam1'] and r.waiting
    grown = r.add_transform('cam0_depth', 'cam0_rgb', np.linalg.inv(T_TF))  # either direction of the edge
    assert grown.names == ['cam0', 'cam1']
    assert grown.camera('cam0').T_color_depth == pytest.approx(T_TF)
    assert _infos(r, 'cam0') is None                                 # nothing new: no new rig


def test_an_unusable_description_is_refused_and_the_rig_in_force_kept(tmp_path):
    r = RigResolver(['cam0'])
    r.offer_description(_rig_yaml(T_TOPIC))
    with pytest.raises(BadInput):
        r.offer_description('cameras: [')
    with pytest.raises(BadInput):
        r.offer_description('cameras: []')
    bad = tmp_path / 'rig.yaml'
    bad.write_text('not: a rig')
    with pytest.raises(BadInput):
        r.set_file(bad)
    assert r.source == TOPIC and r.rig.camera('cam0').T_color_depth[0, 3] == pytest.approx(0.030)
