"""ROS message <-> numpy conversions: images, camera_info, point clouds, transforms and poses
(with ``cdr``, ``diagnostics`` and ``gltf_marker``, the core modules that import message types).

Images honour ``step`` (row padding) and ``is_bigendian``; unknown encodings, short buffers and
inconsistent sizes raise ``MessageConversionError`` with the reason. Conversions from
messages return views on the message buffer where the layout allows (no copy).
"""
from __future__ import annotations

import sys

import cv2
import numpy as np
import pointcloud2
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, TransformStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from .camera import DISTORTION_MODELS, CameraModel
from .errors import BadInput
from .poses import from_xyz_quat, to_xyz_quat


class MessageConversionError(BadInput):
    """A message cannot be converted: wrong encoding, sizes or buffer."""


# encoding -> (numpy scalar type, channels)
IMAGE_ENCODINGS = {
    'rgb8': (np.uint8, 3), 'bgr8': (np.uint8, 3), 'rgba8': (np.uint8, 4), 'bgra8': (np.uint8, 4),
    'mono8': (np.uint8, 1), 'mono16': (np.uint16, 1), '16UC1': (np.uint16, 1), '32FC1': (np.float32, 1),
}
COLOR_ENCODINGS = ('rgb8', 'bgr8', 'rgba8', 'bgra8')
DEPTH_ENCODINGS = ('16UC1', '32FC1')


def ns_to_stamp(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def make_header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def image_to_numpy(msg: Image) -> np.ndarray:
    """(H, W) or (H, W, C) array of an Image, in native byte order."""
    if msg.encoding not in IMAGE_ENCODINGS:
        raise MessageConversionError(
            f'unsupported image encoding {msg.encoding!r}; supported: {", ".join(IMAGE_ENCODINGS)}')
    scalar, channels = IMAGE_ENCODINGS[msg.encoding]
    dtype = np.dtype(scalar).newbyteorder('>' if msg.is_bigendian else '<')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * channels * dtype.itemsize
    if h == 0 or w == 0:
        raise MessageConversionError(f'empty {msg.encoding} image ({w}x{h})')
    if step < row_bytes:
        raise MessageConversionError(f'{msg.encoding} image step {step} < width*channels*size {row_bytes}')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size < step * (h - 1) + row_bytes:
        raise MessageConversionError(
            f'{msg.encoding} {w}x{h} image with step {step} needs {step * (h - 1) + row_bytes} bytes, '
            f'got {buf.size}')
    if step % dtype.itemsize:
        raise MessageConversionError(f'{msg.encoding} image step {step} is not a multiple of {dtype.itemsize}')
    shape = (h, w, channels) if channels > 1 else (h, w)
    strides = (step, channels * dtype.itemsize, dtype.itemsize)[:len(shape)]
    arr = np.ndarray(shape, dtype=dtype, buffer=buf, strides=strides)
    if dtype.byteorder == '>' or (dtype.byteorder == '<' and sys.byteorder == 'big'):
        arr = arr.astype(dtype.newbyteorder('='))
    return arr


def numpy_to_image(arr: np.ndarray, encoding: str, stamp_ns: int = 0, frame_id: str = '') -> Image:
    if encoding not in IMAGE_ENCODINGS:
        raise MessageConversionError(
            f'unsupported image encoding {encoding!r}; supported: {", ".join(IMAGE_ENCODINGS)}')
    scalar, channels = IMAGE_ENCODINGS[encoding]
    if arr.dtype != scalar:
        raise MessageConversionError(f'{encoding} needs dtype {np.dtype(scalar).name}, got {arr.dtype}')
    if arr.ndim == 3 and channels == 1 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    expected = 3 if channels > 1 else 2
    if arr.ndim != expected or (channels > 1 and arr.shape[2] != channels):
        raise MessageConversionError(f'{encoding} needs shape (H, W{", %d" % channels if channels > 1 else ""}),'
                                     f' got {arr.shape}')
    h, w = arr.shape[:2]
    msg = Image(header=make_header(stamp_ns, frame_id), height=h, width=w, encoding=encoding,
                is_bigendian=int(sys.byteorder == 'big'), step=w * channels * arr.dtype.itemsize)
    msg.data = np.ascontiguousarray(arr).tobytes()  # bytes assignment is a fast memcpy in rclpy
    return msg


def color_to_rgb(msg: Image) -> np.ndarray:
    """rgb8 (H, W, 3) array of any supported colour encoding."""
    arr = image_to_numpy(msg)
    if msg.encoding == 'rgb8':
        return arr
    if msg.encoding == 'bgr8':
        return arr[:, :, ::-1]
    if msg.encoding == 'rgba8':
        return arr[:, :, :3]
    if msg.encoding == 'bgra8':
        return arr[:, :, 2::-1]
    raise MessageConversionError(f'colour image expected ({", ".join(COLOR_ENCODINGS)}), got {msg.encoding!r}')


def compressed_to_rgb(msg: CompressedImage) -> np.ndarray:
    """rgb8 (H, W, 3) array of a JPEG or PNG ``CompressedImage`` (the Azure Kinect driver's
    ``rgb/image_raw/compressed``, image_transport's ``compressed``), decoded by OpenCV."""
    fmt = msg.format.lower()
    if 'jpeg' not in fmt and 'jpg' not in fmt and 'png' not in fmt and fmt:
        raise MessageConversionError(f'compressed colour must be JPEG or PNG, got format {msg.format!r}')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size == 0:
        raise MessageConversionError('empty compressed image')
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if bgr is None:
        raise MessageConversionError(f'cannot decode {buf.size}-byte compressed image (format {msg.format!r})')
    return bgr[:, :, ::-1]   # a view, as color_to_rgb gives for bgr8: no 2.7 MB copy per frame


def rgb_to_compressed(rgb: np.ndarray, stamp_ns: int = 0, frame_id: str = '', quality: int = 90) -> CompressedImage:
    """A JPEG ``CompressedImage`` as image_transport's compressed publisher writes it."""
    ok, data = cv2.imencode('.jpg', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise MessageConversionError(f'cannot JPEG-encode an image of shape {rgb.shape}')
    msg = CompressedImage(header=make_header(stamp_ns, frame_id), format='rgb8; jpeg compressed bgr8')
    msg.data = data.tobytes()
    return msg


def color_message_to_rgb(msg: Image | CompressedImage) -> np.ndarray:
    """rgb8 array of a raw or compressed colour message."""
    return compressed_to_rgb(msg) if isinstance(msg, CompressedImage) else color_to_rgb(msg)


def tf_message_to_transforms(msg: TFMessage) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, T_parent_child) of each transform of a ``/tf_static`` message."""
    out = []
    for t in msg.transforms:
        p, q = t.transform.translation, t.transform.rotation
        out.append((t.header.frame_id, t.child_frame_id, from_xyz_quat([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])))
    return out


def transforms_to_tf_message(transforms: list[tuple[str, str, np.ndarray]], stamp_ns: int = 0) -> TFMessage:
    """A ``/tf_static`` message of (parent, child, T_parent_child) triples."""
    msg = TFMessage()
    for parent, child, T in transforms:
        xyz, q = to_xyz_quat(T)
        t = TransformStamped(header=make_header(stamp_ns, parent), child_frame_id=child)
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (float(v) for v in xyz)
        (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
         t.transform.rotation.w) = (float(v) for v in q)
        msg.transforms.append(t)
    return msg


def depth_to_metres(msg: Image) -> np.ndarray:
    """float32 (H, W) depth in metres, 0 where invalid (16UC1 millimetres or 32FC1 metres)."""
    arr = image_to_numpy(msg)
    if msg.encoding == '16UC1':
        return arr.astype(np.float32) * np.float32(0.001)
    if msg.encoding == '32FC1':
        return np.where(np.isfinite(arr) & (arr > 0), arr, np.float32(0.0)).astype(np.float32)
    raise MessageConversionError(f'depth image expected ({", ".join(DEPTH_ENCODINGS)}), got {msg.encoding!r}')


def camera_model_to_info(model: CameraModel, stamp_ns: int = 0, frame_id: str = '') -> CameraInfo:
    K = model.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    return CameraInfo(header=make_header(stamp_ns, frame_id), width=model.width, height=model.height,
                      distortion_model=model.distortion_model, d=list(model.dist),
                      k=K.ravel().tolist(), r=np.eye(3).ravel().tolist(), p=P.ravel().tolist())


def camera_info_to_model(msg: CameraInfo) -> CameraModel:
    if msg.width == 0 or msg.height == 0:
        raise MessageConversionError('camera_info has no image size (uncalibrated camera?)')
    if msg.distortion_model not in ('', *DISTORTION_MODELS.values()):
        raise MessageConversionError(f'unsupported distortion model {msg.distortion_model!r}')
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    d = list(msg.d) or [0.0] * 5
    if len(d) not in DISTORTION_MODELS:
        raise MessageConversionError(f'camera_info has {len(d)} distortion coefficients, expected 5 or 8')
    try:
        return CameraModel(int(msg.width), int(msg.height), K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(d))
    except ValueError as e:
        raise MessageConversionError(f'unusable camera_info: {e}') from e


_XYZRGB_DTYPE = np.dtype({'names': ['x', 'y', 'z', 'rgb'], 'formats': ['<f4'] * 3 + ['<u4'],
                          'offsets': [0, 4, 8, 12], 'itemsize': 16})


def points_to_pointcloud2(xyz: np.ndarray, rgb: np.ndarray | None = None, stamp_ns: int = 0,
                          frame_id: str = '') -> PointCloud2:
    """Unorganised cloud with float32 x, y, z and, if given, ROS packed ``rgb`` (uint8 colours)."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise MessageConversionError(f'points must be (N, 3), got {xyz.shape}')
    if rgb is not None and (rgb.shape != xyz.shape or rgb.dtype != np.uint8):
        raise MessageConversionError(f'colours must be uint8 {xyz.shape}, got {rgb.dtype} {rgb.shape}')
    names = ['x', 'y', 'z'] + (['rgb'] if rgb is not None else [])
    cloud = np.zeros(len(xyz), dtype=_XYZRGB_DTYPE if rgb is not None else
                     np.dtype({'names': names, 'formats': ['<f4'] * 3, 'offsets': [0, 4, 8]}))
    cloud['x'], cloud['y'], cloud['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if rgb is not None:
        c = rgb.astype(np.uint32)
        cloud['rgb'] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
              for f in pointcloud2.fields_from_dtype(cloud.dtype)]
    for f in fields:
        if f.name == 'rgb':
            f.datatype = PointField.FLOAT32  # ROS convention: packed colour declared as float32
    msg = PointCloud2(header=make_header(stamp_ns, frame_id), height=1, width=len(cloud), fields=fields,
                      is_bigendian=False, point_step=cloud.dtype.itemsize,
                      row_step=cloud.dtype.itemsize * len(cloud), is_dense=True)
    msg.data = cloud.tobytes()
    return msg


def pointcloud2_to_points(msg: PointCloud2) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float32 xyz and (N, 3) uint8 rgb (or None) of a cloud; NaN points dropped."""
    names = {f.name for f in msg.fields}
    if not {'x', 'y', 'z'} <= names:
        raise MessageConversionError(f'PointCloud2 lacks x, y, z fields (has {sorted(names)})')
    fields = [{'name': f.name, 'offset': f.offset,
               'datatype': PointField.UINT32 if f.name in ('rgb', 'rgba') else f.datatype, 'count': f.count}
              for f in msg.fields]
    dtype = pointcloud2.dtype_from_fields(fields, point_step=msg.point_step)
    if msg.is_bigendian:
        dtype = dtype.newbyteorder('>')
    n = int(msg.width) * int(msg.height)
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if msg.row_step * msg.height > buf.size or msg.point_step * msg.width > msg.row_step:
        raise MessageConversionError(f'PointCloud2 buffer of {buf.size} bytes is too short for {n} points')
    rows = buf[:msg.row_step * msg.height].reshape(msg.height, msg.row_step)[:, :msg.point_step * msg.width]
    cloud = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    xyz = np.stack([cloud['x'], cloud['y'], cloud['z']], axis=1).astype(np.float32)
    keep = np.isfinite(xyz).all(axis=1)
    rgb = None
    color_field = 'rgb' if 'rgb' in names else 'rgba' if 'rgba' in names else None
    if color_field:
        packed = cloud[color_field].astype(np.uint32)
        rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.uint8)[keep]
    return xyz[keep], rgb


def pose_to_matrix(pose: Pose) -> np.ndarray:
    p, q = pose.position, pose.orientation
    return from_xyz_quat([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])


def matrix_to_pose(T: np.ndarray) -> Pose:
    xyz, q = to_xyz_quat(T)
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in xyz)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


