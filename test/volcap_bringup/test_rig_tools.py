"""`volcap rig` from each maker's factory data gives the same rig description; `volcap monitor`
names the camera whose stamps drift on a replayed bag."""
import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from volcap_bringup.cli import main
from volcap_bringup.processes import start_node
from volcap_core.bag_reader import BagReader
from volcap_core.bag_writer import BagWriter
from volcap_core.conversions import numpy_to_image
from volcap_core.frames import read_rig
from volcap_core.rig import Rig, rig_camera_from_k4a
from volcap_studio.vendor import vendor_model, write_vendor_bag


def _echo(doc: dict) -> str:
    """A message as `ros2 topic echo --once` prints it."""
    return yaml.safe_dump(doc, sort_keys=False) + '---\n'


def _info_echo(model, frame_id):
    K = model.K
    return _echo({'header': {'stamp': {'sec': 0, 'nanosec': 0}, 'frame_id': frame_id}, 'height': model.height,
                  'width': model.width, 'distortion_model': 'plumb_bob', 'd': list(model.dist),
                  'k': K.ravel().tolist(), 'r': np.eye(3).ravel().tolist(),
                  'p': np.hstack([K, np.zeros((3, 1))]).ravel().tolist(), 'binning_x': 0, 'binning_y': 0})


def assert_same_camera(a, b):
    for m, n in ((a.color, b.color), (a.depth, b.depth)):
        assert (m.width, m.height) == (n.width, n.height)
        assert np.allclose([m.fx, m.fy, m.cx, m.cy, *m.dist], [n.fx, n.fy, n.cx, n.cy, *n.dist])
    assert np.allclose(a.T_color_depth, b.T_color_depth, atol=1e-7)


def test_rig_from_k4a_orbbec_and_a_drivers_recording_agree(shared_data, k4a_bag, tmp_path):
    calibration = shared_data / 'azure_kinect' / 'calibration.json'
    assert main(['rig', '--k4a', f'cam0={calibration}', '--out', str(tmp_path / 'k4a.yaml')]) == 0
    k4a = Rig.from_yaml((tmp_path / 'k4a.yaml').read_text()).camera('cam0')
    assert_same_camera(k4a, rig_camera_from_k4a(calibration, 'cam0'))

    # the same camera as OrbbecSDK_ROS2 reports it: depth_to_color and the two camera_info topics
    T = k4a.T_color_depth
    (tmp_path / 'd2c.yaml').write_text(_echo({'header': {'stamp': {'sec': 0, 'nanosec': 0},
                                                         'frame_id': 'depth_to_color_extrinsics'},
                                              'rotation': T[:3, :3].ravel().tolist(),
                                              'translation': T[:3, 3].tolist()}))
    (tmp_path / 'color.yaml').write_text(_info_echo(vendor_model('orbbec', k4a.color), 'cam0_color_optical_frame'))
    (tmp_path / 'depth.yaml').write_text(_info_echo(vendor_model('orbbec', k4a.depth), 'cam0_depth_optical_frame'))
    files = ','.join(str(tmp_path / f) for f in ('d2c.yaml', 'color.yaml', 'depth.yaml'))
    assert main(['rig', '--orbbec', f'cam0={files}', '--out', str(tmp_path / 'orbbec.yaml')]) == 0
    assert_same_camera(Rig.from_yaml((tmp_path / 'orbbec.yaml').read_text()).camera('cam0'), k4a)

    # a recording of either driver (of the real recording's camera): camera_info and /tf_static
    with BagReader(k4a_bag) as reader:
        recorded = read_rig(reader).camera('cam0')
    for layout in ('azure_kinect', 'orbbec'):
        bag = tmp_path / f'{layout}_bag'
        write_vendor_bag(k4a_bag, bag, layout, max_sets=1)
        assert main(['rig', '--bag', str(bag), '--out', str(tmp_path / f'{layout}.yaml')]) == 0
        from_bag = Rig.from_yaml((tmp_path / f'{layout}.yaml').read_text()).camera('cam0')
        assert_same_camera(from_bag, recorded)


def test_rig_refuses_bad_inputs_with_the_reason(tmp_path, capsys):
    (tmp_path / 'bad.json').write_text('{"CalibrationInformation": {}}')
    assert main(['rig', '--k4a', f'cam0={tmp_path / "bad.json"}', '--out', str(tmp_path / 'r.yaml')]) == 2
    assert 'not an Azure Kinect calibration' in capsys.readouterr().err
    (tmp_path / 'd2c.yaml').write_text(_echo({'rotation': [1, 2, 3, 4, 5, 6, 7, 8, 9], 'translation': [0, 0, 0]}))
    (tmp_path / 'info.yaml').write_text(_echo({'width': 4, 'height': 3, 'k': [1, 0, 2, 0, 1, 1, 0, 0, 1]}))
    files = ','.join(str(tmp_path / f) for f in ('d2c.yaml', 'info.yaml', 'info.yaml'))
    assert main(['rig', '--orbbec', f'cam0={files}', '--out', str(tmp_path / 'r.yaml')]) == 2
    assert 'rotation matrix' in capsys.readouterr().err
    assert main(['rig', '--k4a', 'no-name.json', '--out', str(tmp_path / 'r.yaml')]) == 2
    assert not (tmp_path / 'r.yaml').exists()


@pytest.mark.ros
def test_monitor_names_the_camera_whose_stamps_drift(tmp_path, procs):
    """Four cameras at 30 fps for 8 s; cam2's stamps drift 1 ms/s from the others."""
    bag = tmp_path / 'drift'
    start, period = 1_700_000_000_000_000_000, 33_333_333
    tiny = np.zeros((8, 8, 3), np.uint8)
    depth = np.full((8, 8), 1000, np.uint16)
    with BagWriter(bag) as w:
        for k in range(240):
            t = start + k * period
            for cam in ('cam0', 'cam1', 'cam2', 'cam3'):
                stamp = t + (k * period // 1000 if cam == 'cam2' else 0)     # +1 ms per second
                w.write(f'{cam}/depth/image_raw', numpy_to_image(depth, '16UC1', stamp), t)
                w.write(f'{cam}/color/image_raw', numpy_to_image(tiny, 'rgb8', stamp + 8_000_000), t)
    out = tmp_path / 'health.json'
    cmd = [sys.executable, '-m', 'volcap_bringup.cli', 'monitor', '--cameras', 'cam0', 'cam1', 'cam2', 'cam3',
           '--seconds', '14', '--json', str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    procs.append(proc)
    procs.append(start_node('volcap_driver', 'bag_player', {'bag': str(bag), 'wait_for_subscribers': 20.0}))
    text, _ = proc.communicate(timeout=90)
    assert proc.returncode == 0, text
    report = json.loads(out.read_text())
    assert report['cameras']['cam2']['drift_ms_per_s'] == pytest.approx(1.0, abs=0.1)
    assert any('drifting' in w for w in report['cameras']['cam2']['warnings'])
    for cam in ('cam0', 'cam1', 'cam3'):
        # The bag (8 s) ends before the monitor (14 s): by then every camera is silent, and says so.
        assert abs(report['cameras'][cam]['drift_ms_per_s']) < 0.1
        warnings = report['cameras'][cam]['warnings']
        assert any(w.startswith('silent for') for w in warnings), warnings     # (and, under load, a dropped frame)
    assert 'cam2: drifting' in text
