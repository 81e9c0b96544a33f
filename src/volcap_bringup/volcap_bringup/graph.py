"""The volcap node graph as data: which node runs in which namespace with which parameters.
`volcap run` starts it as processes or in one process; ``launch/volcap.launch.py`` starts the
same list on a full ROS install. No rclpy here, so a launch file can import it."""
from __future__ import annotations

NodeSpec = tuple[str, str, str, dict]     # (package, executable, namespace, parameters)


def rig_graph(cameras: list[str], source: tuple[str, str, dict] | None, filters: dict[str, dict],
              corrector: dict, fusion: dict, calibration_service: dict | None = None) -> list[NodeSpec]:
    """Every node of one rig's graph in start order: the frame source (a camera driver or the
    bag player, None when the cameras run elsewhere), the calibration service when given, one
    depth_filter (``filters[camera]``) and one color_corrector per camera namespace, and the
    fusion."""
    nodes: list[NodeSpec] = []
    if source is not None:
        package, executable, params = source
        nodes.append((package, executable, '', dict(params)))
    if calibration_service is not None:
        nodes.append(('volcap_calib', 'calibration_service', '', dict(calibration_service)))
    nodes += [('volcap_filter', 'depth_filter', c, dict(filters.get(c, {}))) for c in cameras]
    nodes += [('volcap_color', 'color_corrector', c, dict(corrector)) for c in cameras]
    nodes.append(('volcap_fusion', 'tsdf_fusion', '', dict(fusion)))
    return nodes
