"""One camera's live colour correction without ROS: the mapping in use as calibrations and
neural models come and go, pass-through or drop without a model, and the reported status."""
import numpy as np
import pytest

from volcap_color.apply import RegionLut
from volcap_color.corrector import CameraCorrection
from volcap_core.calibration import Calibration, CameraCalibration

IMAGE = np.full((6, 8, 3), 100, np.uint8)


def calibration_yaml(cameras=('cam0', 'cam1'), gain=1.5, with_model=True):
    color = {'method': 'matrix_3x3', 'matrix': (np.eye(3) * gain).tolist()} if with_model else None
    return Calibration(cameras[0], f'{cameras[0]}_color_optical_frame',      # the reference is a calibrated camera
                       {c: CameraCalibration(np.eye(4), f'{c}_color_optical_frame', color=color)
                        for c in cameras}).to_yaml()


def test_without_a_model_images_pass_through_or_are_dropped():
    c = CameraCorrection('cam1')
    assert c.status()[0] == 'ok' and 'waiting' in c.status()[1]     # no image yet: nothing to act on
    assert c.apply(IMAGE) is IMAGE and c.passed == 1
    assert c.status()[0] == 'warn' and 'passed through' in c.status()[1]
    c.passthrough = False
    assert c.apply(IMAGE) is None and 'dropped' in c.status()[1]
    dropping = CameraCorrection('cam2', passthrough=False)
    assert dropping.apply(IMAGE) is None and dropping.status()[0] == 'warn'


def test_a_calibration_model_is_used_and_a_bad_one_keeps_the_current_model():
    c = CameraCorrection('cam1')
    used, _ = c.set_calibration(calibration_yaml(gain=1.5))
    assert used and c.apply(IMAGE).mean() > 120       # brighter, as the gain says
    level, message, values = c.status()
    assert level == 'ok' and 'matrix_3x3' in message and values['corrected'] == 1
    for bad, why in ((calibration_yaml(cameras=('cam0',)), 'no camera'),
                     (calibration_yaml(with_model=False), 'no colour model'),
                     ('not: [yaml', 'calibration not used'),
                     ('version: 1\nreference: cam0\nworld_frame: w\ncameras: [cam1]\n', 'calibration not used')):
        used, message = c.set_calibration(bad)
        assert not used and why in message and 'keeping matrix_3x3' in message
        assert c.apply(IMAGE).mean() > 120          # the last good model stays


@pytest.mark.parametrize('table_ok', [True, False])
def test_a_neural_lut_wins_over_calibrations_and_a_bad_one_falls_back(tmp_path, table_ok):
    if table_ok:
        grid = np.linspace(0, 255, 3, dtype=np.float32)
        table = np.stack(np.meshgrid(grid, grid, grid, indexing='ij'), axis=-1)[:, :, :, None, None, :]
        RegionLut(np.broadcast_to(255 - table, (3, 3, 3, 2, 2, 3)).copy()).save(tmp_path / 'cam1.lut.npz')
    else:
        (tmp_path / 'cam1.lut.npz').write_bytes(b'not a LUT')
    c = CameraCorrection('cam1')
    c.load_neural(tmp_path)
    used, message = c.set_calibration(calibration_yaml(gain=1.5))
    if table_ok:
        assert c.neural and not used and 'keeping the neural mapping' in message
        assert abs(float(c.apply(IMAGE).mean()) - 155) <= 2      # the LUT inverts
        assert c.status()[0] == 'ok'
    else:
        assert not c.neural and used and 'not a region LUT' in c.neural_problem
        assert c.apply(IMAGE).mean() > 120
        assert c.status()[0] == 'warn' and 'falling back' in c.status()[1]
