"""The launch file starts the graph `volcap run` starts. The `launch` packages are not
installable here (see DESIGN.md), so the file runs against stand-ins that record what it asks
for; on a full ROS install `ros2 launch volcap_bringup volcap.launch.py` runs the same code."""
import importlib.util
import sys
import types
from pathlib import Path

import pytest

from volcap_bringup.processes import NODES

LAUNCH_FILE = Path(__file__).resolve().parents[2] / 'src' / 'volcap_bringup' / 'launch' / 'volcap.launch.py'


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


@pytest.fixture
def launch_file(monkeypatch):
    """The launch module loaded over recording stand-ins of launch and launch_ros."""
    fake = {name: types.ModuleType(name) for name in
            ('launch', 'launch.actions', 'launch.substitutions', 'launch_ros', 'launch_ros.actions')}
    fake['launch'].LaunchDescription = lambda entities: list(entities)
    fake['launch.actions'].DeclareLaunchArgument = type('DeclareLaunchArgument', (_Recorded,), {})
    fake['launch.actions'].OpaqueFunction = type('OpaqueFunction', (_Recorded,), {})
    fake['launch_ros.actions'].Node = type('Node', (_Recorded,), {})

    class LaunchConfiguration:
        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return context[self.name]

    fake['launch.substitutions'].LaunchConfiguration = LaunchConfiguration
    for name, module in fake.items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location('volcap_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _launched(module, **overrides):
    entities = module.generate_launch_description()
    context = {e.args[0]: e.kwargs['default_value'] for e in entities if type(e).__name__ == 'DeclareLaunchArgument'}
    context.update(overrides)
    opaque = [e for e in entities if type(e).__name__ == 'OpaqueFunction']
    assert len(opaque) == 1
    return opaque[0].kwargs['function'](context)


def test_launch_starts_the_rig_graph(launch_file):
    nodes = _launched(launch_file, cameras='3', calibration='/rig/calibration.yaml', output_dir='/takes/1')
    started = [(n.kwargs['package'], n.kwargs['executable'], n.kwargs['namespace']) for n in nodes]
    # one process per camera: colour and depth received once, beside the driver
    assert started == [('volcap_calib', 'calibration_service', None)] \
        + [('volcap_pipeline', 'camera_pipeline', f'cam{i}') for i in range(3)] \
        + [('volcap_fusion', 'tsdf_fusion', None)] + [('volcap_bringup', 'live_controller', None)]
    assert all((n.kwargs['package'], n.kwargs['executable']) in NODES for n in nodes)   # every one is a real node
    params = [n.kwargs['parameters'][0] for n in nodes]
    assert params[0] == {'output': '/rig/calibration.yaml'}
    assert params[1] == {'output_scale': 0.5}      # live: cleaned depth at half the colour size
    assert params[-2] == {'voxel_size': 0.01, 'output_dir': '/takes/1', 'device': 'auto', 'frame_timeout_ms': 600.0,
                          'input': 'wire'}       # the camera pipelines' compact wire
    assert params[-1] == {'cameras': ['cam0', 'cam1', 'cam2']}
    offline = [n.kwargs['parameters'][0] for n in _launched(launch_file, cameras='3', live='false')]
    assert offline[1] == {'output_scale': 1.0}     # every frame set, at the colour size, 4 mm voxels
    assert offline[-1] == {'voxel_size': 0.004, 'output_dir': '', 'device': 'auto', 'input': 'wire'}
    split = _launched(launch_file, cameras='3', split_stages='true')
    assert [(n.kwargs['executable'], n.kwargs['namespace']) for n in split[1:7]] == \
        [('depth_filter', f'cam{i}') for i in range(3)] + [('color_corrector', f'cam{i}') for i in range(3)]
    assert split[1].kwargs['parameters'] == [{'output_scale': 0.5}] and split[4].kwargs['parameters'] == [{}]
    assert split[-2].kwargs['parameters'][0]['input'] == 'full'     # the separate stages send full-size images


def test_launch_replays_a_bag_as_the_frame_source(launch_file):
    nodes = _launched(launch_file, cameras='2', bag='/captures/studio', rate='0.5', voxel_size='0.01')
    first = nodes[0].kwargs
    assert (first['package'], first['executable']) == ('volcap_driver', 'bag_player')
    assert first['parameters'] == [{'bag': '/captures/studio', 'rate': 0.5}]
    assert nodes[-2].kwargs['parameters'][0]['voxel_size'] == 0.01
    half = _launched(launch_file, depth_width='640', depth_height='360')
    assert half[1].kwargs['parameters'] == [{'output_width': 640, 'output_height': 360, 'output_scale': 0.5}]
    assert len(nodes) == 1 + 1 + 2 + 1 + 1


def test_launch_on_vendor_drivers_remaps_every_camera(launch_file):
    nodes = _launched(launch_file, cameras='2', driver='azure_kinect', registered='true', color_format='jpeg',
                      rig_file='/rig/rig.yaml')
    by_name = {(n.kwargs['executable'], n.kwargs['namespace']): n.kwargs for n in nodes}
    camera = by_name[('camera_pipeline', 'cam1')]
    assert dict(camera['remappings']) == {
        'color/image_raw': 'rgb/image_raw', 'color/image_raw/compressed': 'rgb/image_raw/compressed',
        'color/camera_info': 'rgb/camera_info', 'depth/image_raw': 'depth_to_rgb/image_raw',
        'depth/camera_info': 'depth_to_rgb/camera_info'}
    assert camera['parameters'] == [{'output_scale': 0.5, 'color_transport': 'compressed', 'rig_file': '/rig/rig.yaml'}]
    service = dict(by_name[('calibration_service', None)]['remappings'])
    assert service['cam1/color/image_raw/compressed'] == 'cam1/rgb/image_raw/compressed'
    assert by_name[('tsdf_fusion', None)]['remappings'] == []
    assert dict(by_name[('live_controller', None)]['remappings'])['cam1/color/camera_info'] == 'cam1/rgb/camera_info'
    orbbec = _launched(launch_file, cameras='1', driver='orbbec')
    assert all(n.kwargs['remappings'] == [] for n in orbbec)      # Orbbec uses volcap's names
