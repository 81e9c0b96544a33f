"""The calibration service's session without ROS: rigs, the collect phase, views gathered by the
worker, a solve that writes the file only on success."""
import numpy as np
import pytest

from volcap_calib.board import BoardConfig
from volcap_calib.calibrate import BoardView
from volcap_calib.extrinsics import CalibrationError
from volcap_calib.session import CalibrationServiceConfig, CalibrationSession
from volcap_core import topics
from volcap_core.camera import CameraModel
from volcap_core.rig import Rig, RigCamera

COLOR = CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5)


def _rig(*names):
    return Rig([RigCamera(n, COLOR, COLOR) for n in names])


def _session(tmp_path, **cfg):
    return CalibrationSession(CalibrationServiceConfig(output=str(tmp_path / 'calibration.yaml'), **cfg),
                              BoardConfig.from_yaml())


def test_a_rig_with_other_cameras_starts_over_and_unheard_cameras_are_refused(tmp_path):
    s = _session(tmp_path, cameras=('cam0', 'cam1', 'cam2'))
    assert not s.ready
    assert s.set_rig(_rig('cam0', 'cam1')) == '' and s.ready
    first = s.calibrator
    assert s.set_rig(_rig('cam0', 'cam1')) == '' and s.calibrator is first     # the same cameras: views kept
    assert 'dropped' in s.set_rig(_rig('cam0', 'cam2')) and s.calibrator is not first
    with pytest.raises(ValueError, match='cam7'):
        s.set_rig(_rig('cam0', 'cam7'))


def test_frame_sets_are_gathered_in_the_collect_phase_only(tmp_path):
    s = _session(tmp_path)
    assert s.collecting(None) and s.collecting(topics.CALIBRATION_PHASE) and not s.collecting(topics.CAPTURE)
    assert _session(tmp_path, collect_phase='').collecting(topics.CAPTURE)


def test_views_without_the_board_are_counted_and_a_failed_solve_keeps_the_file(tmp_path):
    s = _session(tmp_path, cameras=('cam0', 'cam1'))
    s.set_rig(_rig('cam0', 'cam1'))
    blank = np.full((48, 64, 3), 128, np.uint8)
    s.add({c: BoardView(blank, COLOR, None, None) for c in ('cam0', 'cam1')})
    s.add({})                                    # nothing usable: not a frame set
    assert s.counts() == (0, 1)
    out = tmp_path / 'calibration.yaml'
    out.write_text('previous calibration\n')
    with pytest.raises(CalibrationError) as e:
        s.solve()
    assert set(e.value.cameras) >= {'cam1'}
    assert out.read_text() == 'previous calibration\n'


def test_solving_without_a_rig_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match='no rig'):
        _session(tmp_path).solve()
