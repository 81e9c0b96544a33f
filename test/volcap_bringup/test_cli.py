"""The `volcap` command line: clear errors for bad input, and the info listing."""
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest


def volcap(*args):
    return subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', *map(str, args)], capture_output=True,
                          text=True, timeout=300)


def test_import_of_a_file_that_is_not_a_k4a_recording(tmp_path, shared_data):
    run = volcap('import-k4a', shared_data / 'charuco' / 'choriginal.jpg', '--out', tmp_path / 'x')
    assert run.returncode == 2
    assert 'volcap import-k4a: error:' in run.stderr and 'K4A' in run.stderr
    assert not (tmp_path / 'x').exists()


@pytest.mark.slow
def test_synth_rejects_bad_options(tmp_path):
    run = volcap('synth', '--out', tmp_path / 'x', '--cameras', '0')
    assert run.returncode == 2 and 'at least one camera' in run.stderr
    run = volcap('info', tmp_path / 'nothing')
    assert run.returncode == 2 and 'does not exist' in run.stderr


@pytest.mark.slow
def test_synth_info_and_preview(tmp_path, shared_data):
    run = volcap('synth', '--out', tmp_path / 's', '--cameras', '2', '--frames', '1', '--board-poses', '0',
                 '--background-frames', '1', '--quiet')
    assert run.returncode == 0, run.stderr
    assert 'MB per second of capture' in run.stdout
    preview = cv2.imread(str(tmp_path / 's' / 'ground_truth' / 'preview.png'))
    assert preview.shape == (180 + 288, 4 * 320, 3) and preview[:180, :640].mean() > 20
    run = volcap('info', tmp_path / 's')
    assert run.returncode == 0
    assert 'cam1/depth/image_raw' in run.stdout and '(latched)' in run.stdout
    # A copy cut off as a crash leaves it: the loss named (this small bag is one chunk, so nothing
    # before the cut is readable), exit 2, one line, no traceback.
    cut = tmp_path / 'cut'
    shutil.copytree(tmp_path / 's', cut)
    mcap = next(cut.glob('*.mcap'))
    mcap.write_bytes(mcap.read_bytes()[:mcap.stat().st_size * 2 // 3])
    run = volcap('info', cut)
    assert run.returncode == 2, run.stdout + run.stderr
    assert 'lost' in run.stdout + run.stderr and 'Traceback' not in run.stderr


def test_a_users_mistake_is_one_line_and_a_bug_is_a_traceback(tmp_path, monkeypatch, capsys):
    from volcap_bringup import cli
    assert cli.main(['info', str(tmp_path / 'nothing')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('volcap info: error:') and 'Traceback' not in err

    def broken(args):
        return {}['a key volcap forgot']      # a bug, not the user's doing
    monkeypatch.setattr(cli, 'cmd_info', broken)
    with pytest.raises(KeyError):          # propagates: Python prints the traceback and exits 1
        cli.main(['info', str(tmp_path)])


def test_live_refuses_what_it_cannot_run(tmp_path):
    """A missing calibration or a camera it lacks: a clear error before anything starts."""
    from volcap_core.calibration import Calibration, CameraCalibration
    run = volcap('live', '--calibration', tmp_path / 'none.yaml', '--seconds', '1')
    assert run.returncode == 2 and 'volcap live: error:' in run.stderr
    calibration = tmp_path / 'calibration.yaml'
    Calibration('cam0', 'world', {'cam0': CameraCalibration(np.eye(4), 'cam0_color_optical_frame')}).save(calibration)
    run = volcap('live', '--calibration', calibration, '--cameras', 'cam0,cam5', '--seconds', '1')
    assert run.returncode == 2 and "['cam5'] are not in the calibration" in run.stderr
