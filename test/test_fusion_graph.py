"""`volcap run`: a synthetic bag through bag_player, depth_filter and color_corrector per
camera and tsdf_fusion, each in its own process; the fused output reaches the runner's renderer
probe (another process), one mesh per capture frame set, and `volcap eval fusion` scores it."""
import json

import numpy as np
import pytest

from volcap_bringup.cli import main
from volcap_core.calibration import Calibration, CameraCalibration
from volcap_driver.synth.session import GroundTruth

pytestmark = pytest.mark.ros


@pytest.mark.timeout(400)
def test_volcap_run_fuses_every_capture_frame_set(studio_bag, tmp_path):
    gt = GroundTruth(studio_bag)
    calibration = Calibration(gt.rig.names[0], gt.doc['world_frame'],
                              {c: CameraCalibration(gt.T_world_color(c), f'{c}_color_optical_frame')
                               for c in gt.rig.names})
    calibration.save(tmp_path / 'calibration.yaml')
    out = tmp_path / 'run'
    assert main(['run', str(studio_bag), '--calibration', str(tmp_path / 'calibration.yaml'), '--out', str(out),
                 '--voxel', '0.01', '--rate', '0.1', '--quiet']) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    captures = len(gt.frames_in('capture'))
    assert metrics['capture_frame_sets_in_bag'] == captures == 2
    assert metrics['frames_written'] == captures
    assert metrics['probe']['meshes_received'] == captures and metrics['probe']['clouds_received'] == captures
    assert all(c == 0 for c in metrics['node_exit_codes'].values()), metrics['node_exit_codes']
    for frame in metrics['frames']:
        assert (out / 'frames' / frame['ply']).exists() and (out / 'frames' / frame['glb']).exists()
        assert frame['missing'] == [] and frame['triangles'] > 5000
    assert metrics['renders'] and all((out / 'renders').glob('*.png'))
    report = tmp_path / 'fusion.json'
    assert main(['eval', 'fusion', str(out), str(studio_bag), '--json', str(report), '--quiet']) == 0
    scores = json.loads(report.read_text())
    assert scores['frames'] == captures
    # This bag has a one-frame clean plate, which the filters may miss while starting: the room
    # is then fused too and accuracy is meaningless here (372 mm measured). Completeness of
    # the subject is still scored: 70 % measured at 10 mm voxels.
    assert np.isfinite(scores['accuracy_mm']) and scores['completeness'] > 0.6
