"""The volcap node graph as data: which node runs in which namespace with which parameters.
`volcap run` starts it as processes or in one process; ``launch/volcap.launch.py`` starts the
same list on a full ROS install. No rclpy here, so a launch file can import it."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from volcap_core import topics
from volcap_core.errors import BadInput
from volcap_core.settings import setting
from volcap_fusion import VOXEL_SIZE

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


# The per-camera process: one camera_pipeline per camera (colour and depth received once), or
# the depth filter and the colour corrector apart (two processes, colour received by both).
PER_CAMERA = {False: [('volcap_pipeline', 'camera_pipeline')],
              True: [('volcap_filter', 'depth_filter'), ('volcap_color', 'color_corrector')]}


def camera_nodes(split_stages: bool = False) -> list[str]:
    """The node names of one camera's work (``split_stages``: the two separate stages)."""
    return [executable for _, executable in PER_CAMERA[split_stages]]


def rig_graph(cameras: list[str], source: tuple[str, str, dict] | None, filters: dict[str, dict],
              corrector: dict, fusion: dict, calibration_service: dict | None = None, driver: str = 'volcap',
              registered: bool = False, remaps: dict[str, dict[str, str]] | None = None,
              split_stages: bool = False) -> list[NodeSpec]:
    """Every node of one rig's graph in start order: the frame source (a camera driver or the
    bag player, None when the cameras run elsewhere), the calibration service when given, one
    camera_pipeline per camera namespace (the depth filter's parameters ``filters[camera]`` and
    the colour correction's ``corrector``; with ``split_stages`` a depth_filter and a
    color_corrector instead) and the fusion. ``driver`` and ``registered`` say whose topics the
    nodes are remapped onto; ``remaps`` (per camera) replaces that when given."""
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
    if split_stages:
        nodes += [('volcap_filter', 'depth_filter', c, dict(filters.get(c, {})), dict(camera_maps.get(c, {})))
                  for c in cameras]
        nodes += [('volcap_color', 'color_corrector', c, dict(corrector), dict(camera_maps.get(c, {})))
                  for c in cameras]
    else:
        nodes += [('volcap_pipeline', 'camera_pipeline', c, {**filters.get(c, {}), **corrector},
                   dict(camera_maps.get(c, {}))) for c in cameras]
    # the camera pipelines send the compact wire; the separate stages only the full-size images
    nodes.append(('volcap_fusion', 'tsdf_fusion', '', {**fusion, 'input': 'full' if split_stages else 'wire'}, {}))
    return nodes


def live_controller(cameras: list[str], params: dict, driver: str = 'volcap', registered: bool = False,
                    remaps: dict[str, dict[str, str]] | None = None) -> NodeSpec:
    """The live controller of a rig graph (``volcap live``, the launch file's ``live:=true``), in
    the root namespace on the cameras' camera_info topics (the camera prefix on both sides)."""
    per_camera = camera_remaps(driver, registered)
    camera_maps = remaps or {c: per_camera for c in cameras}
    controller_remaps = {f'{c}/{k}': f'{c}/{v}' for c in cameras for k, v in camera_maps.get(c, {}).items()}
    return ('volcap_bringup', 'live_controller', '', {'cameras': list(cameras), **params}, controller_remaps)


@dataclass
class RunConfig:
    """`volcap run`: a bag through the whole graph, every frame set fused."""
    bag: str | Path
    calibration: str | Path
    out: str | Path                   # frames/, metrics.json, renders/
    voxel_size: float = setting(VOXEL_SIZE, 'TSDF voxel edge (m)', 0.0005, 0.1, option='--voxel')
    rate: float = setting(0.04, 'bag playback speed; the graph must keep up to fuse every frame set (2 cores: 0.04, '
                          'about 1.2 frame sets/s)', 0.001, 10.0)
    composed: bool = setting(False, 'run every node in this process (else each in its own, as on a rig)')
    depth_upsample: int = setting(1, 'depth resampled this many times finer before integration', 1, 4)
    half_depth: bool = setting(False, 'clean depth at half the colour size (less to clean and send, coarser: '
                               '2.7 mm against 1.3 mm at 4 mm voxels on the demo bag)')
    split_stages: bool = setting(False, 'each camera\'s depth filter and colour corrector as two nodes (else one '
                                 'camera_pipeline per camera)')
    # after playback, wait this long with no new mesh before stopping: longer than run_graph's
    # OFFLINE_TIMEOUT_MS (10 s), which an incomplete last frame set waits out first. A run
    # whose every capture set arrives stops at once, so only a lossy run pays for it.
    settle_s: float = 30.0
    progress: bool = True


@dataclass
class LiveConfig:
    """`volcap live`: the graph on live topics, kept real time by admission control."""
    calibration: str | Path
    bag: str | Path | None = setting(None, 'loop this bag at real time with fresh stamps instead of camera drivers')
    driver: str = setting('volcap', 'whose topics the cameras publish (without --bag)', choices=DRIVERS)
    registered: bool = setting(False, 'the driver registers depth to colour')
    color_format: str = setting('raw', 'the drivers\' colour: raw Image or JPEG CompressedImage (without --bag)',
                                choices=('raw', 'jpeg'))
    cameras: list[str] | None = None     # default: the calibration's
    voxel_size: float = setting(LIVE_VOXEL, 'TSDF voxel edge (m)', 0.0005, 0.1, option='--voxel')
    depth_scale: float = setting(LIVE_DEPTH_SCALE, 'cleaned depth size as a fraction of the colour size', 0.05, 4.0)
    every: int = setting(0, 'admit one frame set in N (0: chosen from the measured load)', 0, 1000)
    latency_budget_ms: float = setting(1000.0, 'the latency the admission keeps under (ms)', 10.0, 60_000.0)
    composed: bool = setting(False, 'run every node in this process')
    split_stages: bool = setting(False, 'each camera\'s depth filter and colour corrector as two nodes (else one '
                                 'camera_pipeline per camera)')
    output_dir: str = setting('', 'also write the sequence here (empty: no sequence)')
    rig_file: str = setting('', 'rig description YAML for the depth-to-colour extrinsic')
    rate: float = setting(1.0, 'with --bag, its playback speed (1: real time)', 0.01, 10.0)
    seconds: float | None = setting(None, 'stop after this long (default: at Ctrl-C)', 0.0, 1e9)
    warmup_s: float = setting(10.0, 'seconds left out of the final figures', 0.0, 3600.0, option='--warmup')
    probe: bool = False                  # also host a renderer stand-in that times every mesh
    source_nice: int = setting(0, 'with --bag, the player\'s niceness (e.g. 10: it yields the CPU to the graph, as '
                               'drivers on cores of their own would)', -20, 19)
