"""The volcap node graph as data: which node runs in which namespace with which parameters.
`volcap run` starts it as processes or in one process; ``launch/volcap.launch.py`` starts the
same list on a full ROS install. No rclpy here, so a launch file can import it."""
from __future__ import annotations

from volcap_core import topics
from volcap_core.errors import BadInput

NodeSpec = tuple[str, str, str, dict, dict]   # (package, executable, namespace, parameters, remaps)

# Live defaults (`volcap live`, the launch file's live:=true). Cleaned depth at half the colour
# size still puts ~3.5 px on every 10 mm voxel at 2 m and costs a quarter of the cleaning and
# integration.
LIVE_VOXEL = 0.01
LIVE_DEPTH_SCALE = 0.5
# A camera slower than the rest still makes its frame set while the set is within 60 % of the
# live controller's default 1 s latency budget.
LIVE_FRAME_TIMEOUT_MS = 600.0

# The frame sources volcap sits on. Per camera namespace, the remaps of volcap's relative topic
# names onto the driver's (for the driver's node started in that namespace, e.g. the Azure
# Kinect driver with ``tf_prefix:=cam0_`` under ``/cam0``, OrbbecSDK_ROS2 with
# ``camera_name:=cam0``). Orbbec uses volcap's names; registered depth keeps its topic.
DRIVERS = ('volcap', 'azure_kinect', 'orbbec')
_AZURE_COLOR = {'color/image_raw': 'rgb/image_raw', 'color/image_raw/compressed': 'rgb/image_raw/compressed',
                'color/camera_info': 'rgb/camera_info'}
_AZURE_REGISTERED = {'depth/image_raw': 'depth_to_rgb/image_raw', 'depth/camera_info': 'depth_to_rgb/camera_info'}


def camera_remaps(driver: str, registered: bool = False) -> dict[str, str]:
    """volcap topic -> driver topic, both relative to the camera namespace."""
    if driver not in DRIVERS:
        raise BadInput(f'unknown camera driver {driver!r}; known: {", ".join(DRIVERS)}')
    if driver != 'azure_kinect':
        return {}
    return {**_AZURE_COLOR, **(_AZURE_REGISTERED if registered else {})}


_VOLCAP_STREAMS = {'color': topics.COLOR_IMAGE, 'color_info': topics.COLOR_INFO, 'depth': topics.DEPTH_IMAGE,
                   'depth_info': topics.DEPTH_INFO}


def stream_remaps(camera: str, streams: dict[str, str]) -> tuple[dict[str, str], dict]:
    """Remaps and input parameters that put one camera's nodes on the topics a bag holds
    (``volcap_core.frames.camera_topics``: stream -> topic, e.g. a vendor driver's)."""
    remaps, params = {}, {}
    for stream, topic in streams.items():
        theirs, ours = topic.removeprefix(camera + '/'), _VOLCAP_STREAMS[stream]
        if stream == 'color' and theirs.endswith('/compressed'):
            ours, params['color_transport'] = topics.COLOR_COMPRESSED, 'compressed'
        if theirs != ours:
            remaps[ours] = theirs
    return remaps, params


def rig_graph(cameras: list[str], source: tuple[str, str, dict] | None, filters: dict[str, dict],
              corrector: dict, fusion: dict, calibration_service: dict | None = None, driver: str = 'volcap',
              registered: bool = False, remaps: dict[str, dict[str, str]] | None = None) -> list[NodeSpec]:
    """Every node of one rig's graph in start order: the frame source (a camera driver or the
    bag player, None when the cameras run elsewhere), the calibration service when given, one
    depth_filter (``filters[camera]``) and one color_corrector per camera namespace, and the
    fusion. ``driver`` and ``registered`` say whose topics the nodes are remapped onto;
    ``remaps`` (per camera) replaces that when given."""
    per_camera = camera_remaps(driver, registered)
    camera_maps = remaps or {c: per_camera for c in cameras}
    nodes: list[NodeSpec] = []
    if source is not None:
        package, executable, params = source
        nodes.append((package, executable, '', dict(params), {}))
    if calibration_service is not None:
        # in the root namespace: the camera prefix goes on both sides
        service_remaps = {f'{c}/{k}': f'{c}/{v}' for c in cameras for k, v in camera_maps.get(c, {}).items()}
        nodes.append(('volcap_calib', 'calibration_service', '', dict(calibration_service), service_remaps))
    nodes += [('volcap_filter', 'depth_filter', c, dict(filters.get(c, {})), dict(camera_maps.get(c, {})))
              for c in cameras]
    nodes += [('volcap_color', 'color_corrector', c, dict(corrector), dict(camera_maps.get(c, {}))) for c in cameras]
    nodes.append(('volcap_fusion', 'tsdf_fusion', '', dict(fusion), {}))
    return nodes


def live_controller(cameras: list[str], params: dict, driver: str = 'volcap', registered: bool = False,
                    remaps: dict[str, dict[str, str]] | None = None) -> NodeSpec:
    """The live controller of a rig graph (``volcap live``, the launch file's ``live:=true``), in
    the root namespace on the cameras' camera_info topics (the camera prefix on both sides)."""
    per_camera = camera_remaps(driver, registered)
    camera_maps = remaps or {c: per_camera for c in cameras}
    controller_remaps = {f'{c}/{k}': f'{c}/{v}' for c in cameras for k, v in camera_maps.get(c, {}).items()}
    return ('volcap_bringup', 'live_controller', '', {'cameras': list(cameras), **params}, controller_remaps)
