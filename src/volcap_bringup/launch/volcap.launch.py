"""The volcap graph on a rig: calibration service (publishes calibration.yaml on start), one
camera_pipeline per camera namespace (``split_stages:=true``: a depth_filter and a
color_corrector instead), and tsdf_fusion; optionally the bag player as the frame source
instead of camera drivers.

    ros2 launch volcap_bringup volcap.launch.py calibration:=/rig/calibration.yaml \\
        cameras:=8 output_dir:=/captures/take1 [bag:=/captures/studio] [voxel_size:=0.006]
    ros2 launch volcap_bringup volcap.launch.py driver:=azure_kinect registered:=true \\
        color_format:=jpeg calibration:=/rig/calibration.yaml

Live by default, as `volcap live`: the live controller admits only the frame sets the graph can
process (the same ones in every stage), the cleaned depth is half the colour size and the voxels
are 10 mm; ``live:=false`` processes every frame set at full depth size and 4 mm voxels.

``driver`` remaps every camera's topics onto a vendor driver's running in ``cam0``..``camN-1``
(docs/driver.md, "On a rig"); the drivers' ``/tf_static`` gives the depth-to-colour extrinsic.

The node list comes from ``volcap_bringup.graph.rig_graph``, the one `volcap run` starts.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from volcap_bringup.graph import LIVE_DEPTH_SCALE, LIVE_FRAME_TIMEOUT_MS, LIVE_VOXEL, live_controller, rig_graph
from volcap_fusion import VOXEL_SIZE

ARGUMENTS = {
    'cameras': ('8', 'number of camera namespaces cam0..camN-1'),
    'calibration': ('calibration.yaml', 'rig calibration; the calibration service publishes it on start'),
    'bag': ('', 'a recorded session to replay as the frame source (empty: camera drivers run elsewhere)'),
    'rate': ('1.0', 'bag playback speed'),
    'live': ('true', 'admission control (live_controller), half-size cleaned depth, 10 mm voxels by default'),
    'voxel_size': ('', f'TSDF voxel size (m; empty: {LIVE_VOXEL} live, {VOXEL_SIZE} otherwise)'),
    'depth_scale': ('', 'cleaned depth size as a fraction of the colour size (empty: 0.5 live, 1 otherwise)'),
    'output_dir': ('', 'write the PLY/GLB sequence here (empty: publish only)'),
    'depth_width': ('0', 'cleaned depth width (0: the colour width, the depth_filter default)'),
    'depth_height': ('0', 'cleaned depth height (0: the colour height)'),
    'device': ('auto', 'fusion device: auto, CPU:0 or CUDA:0'),
    'driver': ('volcap', 'whose topics the cameras publish: volcap, azure_kinect or orbbec'),
    'registered': ('false', 'the driver registers depth to colour (Azure Kinect depth_to_rgb, Orbbec '
                   'depth_registration)'),
    'color_format': ('raw', 'colour as raw images or jpeg (CompressedImage on .../image_raw/compressed)'),
    'rig_file': ('', 'rig description YAML (`volcap rig`) instead of /tf_static for the depth-to-colour extrinsic'),
    'split_stages': ('false', 'each camera\'s depth_filter and color_corrector as two nodes instead of one '
                     'camera_pipeline'),
}


def _nodes(context):
    arg = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    cameras = [f'cam{i}' for i in range(int(arg['cameras']))]
    source = None
    if arg['bag']:
        source = ('volcap_driver', 'bag_player', {'bag': arg['bag'], 'rate': float(arg['rate'])})
    # 0 leaves the node's own default (the colour size)
    live = arg['live'].lower() in ('true', '1', 'yes')
    depth_size = {k: int(arg[a]) for k, a in (('output_width', 'depth_width'), ('output_height', 'depth_height'))
                  if int(arg[a])}
    depth_size['output_scale'] = float(arg['depth_scale'] or (LIVE_DEPTH_SCALE if live else 1.0))
    voxel = float(arg['voxel_size'] or (LIVE_VOXEL if live else VOXEL_SIZE))
    fusion = {'voxel_size': voxel, 'output_dir': arg['output_dir'], 'device': arg['device'],
              **({'frame_timeout_ms': LIVE_FRAME_TIMEOUT_MS} if live else {})}
    # Only what differs from the nodes' defaults, so their own defaults stay in one place.
    inputs = {**({'color_transport': 'compressed'} if arg['color_format'] == 'jpeg' else {}),
              **({'rig_file': arg['rig_file']} if arg['rig_file'] else {})}
    graph = rig_graph(cameras, source, {c: {**depth_size, **inputs} for c in cameras},
                      {'color_transport': 'compressed'} if arg['color_format'] == 'jpeg' else {}, fusion,
                      calibration_service={'output': arg['calibration'], **inputs}, driver=arg['driver'],
                      registered=arg['registered'].lower() in ('true', '1', 'yes'),
                      split_stages=arg['split_stages'].lower() in ('true', '1', 'yes'))
    if live:
        graph.append(live_controller(cameras, {}, arg['driver'], arg['registered'].lower() in ('true', '1', 'yes')))
    return [Node(package=package, executable=executable, namespace=namespace or None, parameters=[params],
                 remappings=list(remaps.items()), output='screen')
            for package, executable, namespace, params, remaps in graph]


def generate_launch_description():
    return LaunchDescription([DeclareLaunchArgument(name, default_value=default, description=text)
                              for name, (default, text) in ARGUMENTS.items()] + [OpaqueFunction(function=_nodes)])
