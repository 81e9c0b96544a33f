"""The fused model as a glTF binary on a ROS topic: a visualization_msgs/Marker MESH_RESOURCE whose
pose turns glTF's +Y-up axes into the +Z-up studio frame."""
from __future__ import annotations

import numpy as np
from visualization_msgs.msg import Marker, MeshFile

from .conversions import make_header, matrix_to_pose

# glTF meshes are +Y up with the front towards +Z; the studio frame is REP 103 (+Z up, +X front).
# This rotation takes glTF coordinates (gx, gy, gz) to the studio's (gz, gx, gy).
GLTF_IN_STUDIO = np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)


def glb_marker(glb: bytes, stamp_ns: int, frame_id: str, name: str, ns: str = 'volcap', marker_id: int = 0
               ) -> Marker:
    """A visualization_msgs/Marker MESH_RESOURCE carrying a GLB in ``mesh_file`` (Jazzy's embedded
    mesh: ``mesh_resource`` is ``embedded://<name>``). The pose turns the GLB's +Y-up axes into
    the (+Z-up) ``frame_id``, so a renderer that applies it, as RViz does, shows the mesh upright."""
    marker = Marker(header=make_header(stamp_ns, frame_id), ns=ns, id=marker_id, type=Marker.MESH_RESOURCE,
                    action=Marker.ADD, pose=matrix_to_pose(GLTF_IN_STUDIO), mesh_resource=f'embedded://{name}',
                    mesh_use_embedded_materials=True)
    marker.scale.x = marker.scale.y = marker.scale.z = 1.0
    marker.color.a = 1.0
    marker.mesh_file = MeshFile(filename=name, data=glb)
    return marker
