"""Frames in the exact layouts of the camera makers' ROS 2 drivers, to test volcap against them.

From any volcap frame (the real Azure Kinect recording imported by ``volcap import-k4a``, or the
synthetic studio) this builds the messages a vendor driver publishes for one camera, as read in
the drivers' sources:

- ``azure_kinect`` (Azure_Kinect_ROS_Driver, humble): ``rgb/image_raw`` bgra8 or, with
  ``color_format:=jpeg``, ``rgb/image_raw/compressed`` (format ``bgra8; jpeg compressed bgr8``);
  ``rgb/camera_info``; ``depth/image_raw`` 16UC1 with ``depth/camera_info``, or registered
  ``depth_to_rgb/image_raw`` with ``depth_to_rgb/camera_info``; ``rational_polynomial`` with 8
  coefficients; frames ``<tf_prefix>rgb_camera_link`` and ``<tf_prefix>depth_camera_link``;
  ``/tf_static`` ``camera_base -> depth_camera_link -> rgb_camera_link``; colour and depth stamped
  each at its own device timestamp.
- ``orbbec`` (OrbbecSDK_ROS2, Femto Bolt/Mega): ``color/image_raw`` rgb8 (or image_transport's
  ``color/image_raw/compressed``), ``color/camera_info``, ``depth/image_raw`` 16UC1 (in the colour
  frame with ``depth_registration:=true``), ``depth/camera_info``; ``plumb_bob`` with 8
  coefficients; ``/tf_static`` ``<name>_link -> <name>_depth_frame -> <name>_color_frame``, each
  with its ``_optical_frame`` child.

A driver registers depth to colour by projecting each depth pixel to the nearest colour pixel
with a z-buffer: 640x576 over 1280x720 leaves empty rows and columns every 4-6 px, reproduced here.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from volcap_core.bag_reader import BagReader
from volcap_core.bag_writer import BagWriter
from volcap_core.camera import CameraModel
from volcap_core.conversions import camera_model_to_info, numpy_to_image, rgb_to_compressed, transforms_to_tf_message
from volcap_core.errors import BadInput
from volcap_core.frames import frame_sets, read_rig
from volcap_core.poses import invert, make_transform
from volcap_core.rig import RigCamera

LAYOUTS = ('azure_kinect', 'orbbec')
# The optical frame in a body frame (x forward, z up): REP 103's rotation, as both drivers use it.
T_BODY_OPTICAL = make_transform(Rotation.from_euler('xyz', [-np.pi / 2, 0.0, -np.pi / 2]).as_matrix(), [0, 0, 0])


def frame_ids(layout: str, name: str) -> tuple[str, str]:
    """(colour, depth) optical frame ids of camera ``name`` (namespace and tf prefix)."""
    if layout == 'azure_kinect':
        return f'{name}_rgb_camera_link', f'{name}_depth_camera_link'
    if layout == 'orbbec':
        return f'{name}_color_optical_frame', f'{name}_depth_optical_frame'
    raise BadInput(f'unknown driver layout {layout!r}; known: {", ".join(LAYOUTS)}')


def topic_names(layout: str, name: str, registered: bool, color_format: str) -> dict[str, str]:
    """Fully qualified topics of one camera: color, color_info, depth, depth_info."""
    color = 'rgb' if layout == 'azure_kinect' else 'color'
    depth = 'depth_to_rgb' if layout == 'azure_kinect' and registered else 'depth'
    image = f'/{name}/{color}/image_raw' + ('/compressed' if color_format == 'jpeg' else '')
    return {'color': image, 'color_info': f'/{name}/{color}/camera_info',
            'depth': f'/{name}/{depth}/image_raw', 'depth_info': f'/{name}/{depth}/camera_info'}


def static_transforms(layout: str, name: str, cam: RigCamera) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, T_parent_child) the driver sends on ``/tf_static``."""
    color_frame, depth_frame = frame_ids(layout, name)
    T_depth_color = invert(cam.T_color_depth)
    if layout == 'azure_kinect':
        # camera_base and imu_link only complete the driver's tree (volcap never looks them up):
        # illustrative values of the device's order (depth camera tilted 6 degrees), not factory data
        T_base_depth = make_transform(T_BODY_OPTICAL[:3, :3] @ Rotation.from_euler('x', -6, degrees=True).as_matrix(),
                                      [0.0, 0.0, 0.0018])
        return [(f'{name}_camera_base', depth_frame, T_base_depth),
                (depth_frame, color_frame, T_depth_color),
                (depth_frame, f'{name}_imu_link', make_transform(np.eye(3), [-0.0511, 0.0035, 0.0012]))]
    body_depth, body_color = f'{name}_depth_frame', f'{name}_color_frame'
    # Orbbec: the colour body frame relative to the depth body frame, then each optical frame
    T_bd_bc = T_BODY_OPTICAL @ T_depth_color @ invert(T_BODY_OPTICAL)
    return [(f'{name}_link', body_depth, np.eye(4)), (body_depth, body_color, T_bd_bc),
            (body_depth, depth_frame, T_BODY_OPTICAL), (body_color, color_frame, T_BODY_OPTICAL)]


def vendor_model(layout: str, model: CameraModel) -> CameraModel:
    """The intrinsics as the driver reports them: 8 coefficients (Orbbec pads plumb_bob to 8)."""
    dist = tuple(model.dist) + (0.0,) * (8 - len(model.dist))
    return CameraModel(model.width, model.height, model.fx, model.fy, model.cx, model.cy, dist)


def camera_info(layout: str, model: CameraModel, stamp_ns: int, frame_id: str):
    info = camera_model_to_info(vendor_model(layout, model), stamp_ns, frame_id)
    # Orbbec labels its 8 coefficients plumb_bob; the Azure Kinect driver rational_polynomial
    info.distortion_model = 'plumb_bob' if layout == 'orbbec' else 'rational_polynomial'
    return info


def register_like_driver(depth_m: np.ndarray, cam: RigCamera) -> np.ndarray:
    """Depth in the colour camera as a driver registers it: each depth pixel to the nearest
    colour pixel, the nearest surface kept; no splatting, so upsampling leaves holes."""
    rays = cam.depth.pixel_rays().reshape(-1, 3)
    z = depth_m.reshape(-1).astype(np.float64)
    valid = z > 0
    points = rays[valid] * z[valid, None]
    points = points @ cam.T_color_depth[:3, :3].T + cam.T_color_depth[:3, 3]
    front = points[:, 2] > 0
    points = points[front]
    uv = np.round(cam.color.project(points)).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.color.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.color.height)
    uv, zc = uv[inside], points[inside, 2].astype(np.float32)
    out = np.full(cam.color.width * cam.color.height, np.inf, np.float32)
    np.minimum.at(out, uv[:, 1] * cam.color.width + uv[:, 0], zc)
    out[~np.isfinite(out)] = 0.0
    return out.reshape(cam.color.height, cam.color.width)


def frame_messages(layout: str, name: str, cam: RigCamera, color_rgb: np.ndarray, depth_m: np.ndarray,
                   stamp_ns: int, registered: bool = False, color_format: str = 'raw',
                   color_delay_ns: int = 0) -> list[tuple[str, object]]:
    """(topic, message) of one capture in the driver's order (depth, then colour). The colour is
    stamped ``color_delay_ns`` after the depth (real drivers stamp each at its own exposure)."""
    if color_format not in ('raw', 'jpeg'):
        raise BadInput(f"color_format must be 'raw' or 'jpeg', got {color_format!r}")
    color_frame, depth_frame = frame_ids(layout, name)
    names = topic_names(layout, name, registered, color_format)
    color_stamp = stamp_ns + color_delay_ns
    if registered:
        depth = register_like_driver(depth_m, cam)
        depth_model, depth_id = cam.color, color_frame
    else:
        depth, depth_model, depth_id = depth_m, cam.depth, depth_frame
    depth_mm = np.round(np.clip(depth, 0, 65.535) * 1000).astype(np.uint16)
    if color_format == 'jpeg':
        color_msg = rgb_to_compressed(color_rgb, color_stamp, color_frame)
        if layout == 'azure_kinect':
            color_msg.format = 'bgra8; jpeg compressed bgr8'
    elif layout == 'azure_kinect':
        bgra = np.concatenate([color_rgb[:, :, ::-1], np.full(color_rgb.shape[:2] + (1,), 255, np.uint8)], axis=2)
        color_msg = numpy_to_image(np.ascontiguousarray(bgra), 'bgra8', color_stamp, color_frame)
    else:
        color_msg = numpy_to_image(np.ascontiguousarray(color_rgb), 'rgb8', color_stamp, color_frame)
    return [(names['depth'], numpy_to_image(depth_mm, '16UC1', stamp_ns, depth_id)),
            (names['depth_info'], camera_info(layout, depth_model, stamp_ns, depth_id)),
            (names['color'], color_msg),
            (names['color_info'], camera_info(layout, cam.color, color_stamp, color_frame))]


def tf_static_message(layout: str, rig_cameras: list[RigCamera], stamp_ns: int = 0):
    """One ``/tf_static`` message with every camera's transforms."""
    transforms = [t for cam in rig_cameras for t in static_transforms(layout, cam.name, cam)]
    return transforms_to_tf_message(transforms, stamp_ns)


def write_vendor_bag(source_bag, out, layout: str, registered: bool = False, color_format: str = 'raw',
                     color_delay_ns: int = 0, max_sets: int | None = None) -> int:
    """What ``ros2 bag record`` of the vendor drivers writes for a volcap bag's frames: the
    drivers' fully qualified topics and ``/tf_static``, no volcap topics. Returns the frame sets."""
    with BagReader(source_bag) as reader:
        rig = read_rig(reader)
    n = 0
    with BagWriter(out) as bag:
        bag.add_topic('/tf_static', 'tf2_msgs/msg/TFMessage', latched=True)
        first = True
        for fs in frame_sets(source_bag):
            if first:
                bag.write('/tf_static', tf_static_message(layout, rig.cameras, fs.stamp_ns), fs.stamp_ns)
                first = False
            for cam_name, frame in fs.cameras.items():
                for topic, msg in frame_messages(layout, cam_name, rig.camera(cam_name), frame.color, frame.depth,
                                                 fs.stamp_ns, registered, color_format, color_delay_ns):
                    bag.write(topic, msg, fs.stamp_ns)
            n += 1
            if max_sets is not None and n >= max_sets:
                break
    return n
