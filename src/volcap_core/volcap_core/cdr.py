"""Serialised (CDR) messages without rclpy message objects: the capture stamp read straight from a
serialised message's header, and images and mesh markers written as CDR bytes (an rclpy message
with a multi-MB array field costs a copy element by element)."""
from __future__ import annotations

import struct
import sys

import numpy as np

from .conversions import MessageConversionError, numpy_to_image
from .errors import BadInput


def cdr_stamp_format(data: bytes) -> str:
    # 4-byte CDR encapsulation header (byte 1: little-endian flag), then stamp.sec (int32) and
    # stamp.nanosec (uint32) of the leading std_msgs/Header.
    if len(data) < 12 or data[0] != 0:
        raise BadInput('not a CDR-encapsulated message')
    return '<iI' if data[1] & 1 else '>iI'


def cdr_stamp_ns(data: bytes) -> int:
    """header.stamp of a CDR message whose first field is a std_msgs/Header, without decoding."""
    sec, nsec = struct.unpack_from(cdr_stamp_format(data), data, 4)
    return sec * 1_000_000_000 + nsec


class _CdrWriter:
    """Little-endian CDR (XCDR1, the ROS 2 default) with alignment counted from the payload start."""

    def __init__(self):
        self.parts, self.size = [b'\x00\x01\x00\x00'], 0

    def _align(self, n: int) -> None:
        pad = -self.size % n
        if pad:
            self._raw(b'\x00' * pad)

    def _raw(self, data: bytes) -> None:
        self.parts.append(data)
        self.size += len(data)

    def scalars(self, fmt: str, *values) -> None:
        data = np.array(values, dtype=fmt)
        self._align(data.itemsize)
        self._raw(data.tobytes())

    def string(self, text: str) -> None:
        data = text.encode() + b'\x00'
        self.scalars('<u4', len(data))
        self._raw(data)

    def sequence(self, array: np.ndarray, align: int) -> None:
        """A sequence of fixed-size elements, one per row of ``array`` (already little-endian)."""
        self.scalars('<u4', len(array))
        if len(array):
            self._align(align)
            self._raw(np.ascontiguousarray(array).tobytes())

    def header(self, stamp_ns: int, frame_id: str) -> None:
        self.scalars('<i4', stamp_ns // 1_000_000_000)
        self.scalars('<u4', stamp_ns % 1_000_000_000)
        self.string(frame_id)

    def bytes(self) -> bytes:
        return b''.join(self.parts)


def image_to_cdr(arr: np.ndarray, encoding: str, stamp_ns: int = 0, frame_id: str = '') -> bytes:
    """A serialised sensor_msgs/Image, for ``Publisher.publish(bytes)``: the same checks as
    ``numpy_to_image``, without rclpy's serialisation of the message (2.3 ms for 1280x720 rgb8,
    bench/live.py)."""
    msg = numpy_to_image(arr[:1], encoding)       # validates encoding, dtype and shape cheaply
    h, w = arr.shape[:2]
    step = msg.step
    writer = _CdrWriter()
    writer.header(stamp_ns, frame_id)
    writer.scalars('<u4', h, w)
    writer.string(encoding)
    writer.scalars('u1', int(sys.byteorder == 'big'))
    writer.scalars('<u4', step)
    writer.scalars('<u4', h * step)
    writer._raw(np.ascontiguousarray(arr).data)
    return writer.bytes()


def mesh_to_marker_cdr(vertices: np.ndarray, colors: np.ndarray, triangles: np.ndarray, stamp_ns: int,
                       frame_id: str, ns: str = 'volcap', marker_id: int = 0) -> bytes:
    """A serialised visualization_msgs/Marker TRIANGLE_LIST (three points per triangle, one
    colour per point), for ``Publisher.publish(bytes)``. Built from arrays directly: a Marker of
    a million geometry_msgs/Point objects takes seconds to fill from Python."""
    if vertices.ndim != 2 or vertices.shape[1] != 3 or colors.shape != vertices.shape or triangles.ndim != 2 \
            or triangles.shape[1] != 3:
        raise MessageConversionError(f'mesh needs (N, 3) vertices and colours and (M, 3) triangles, got '
                                     f'{vertices.shape}, {colors.shape}, {triangles.shape}')
    corners = triangles.reshape(-1)
    points = vertices[corners].astype('<f8')
    rgba = np.empty((len(corners), 4), '<f4')
    rgba[:, :3] = colors[corners] / np.float32(255.0)
    rgba[:, 3] = 1.0
    w = _CdrWriter()
    w.header(stamp_ns, frame_id)
    w.string(ns)
    w.scalars('<i4', marker_id, 11, 0)                      # id, TRIANGLE_LIST, ADD
    w.scalars('<f8', 0, 0, 0, 0, 0, 0, 1)                   # pose: identity
    w.scalars('<f8', 1, 1, 1)                               # scale
    w.scalars('<f4', 1, 1, 1, 1)                            # colour (the per-point colours apply)
    w.scalars('<i4', 0)                                     # lifetime: forever
    w.scalars('<u4', 0)
    w.scalars('u1', 0)                                      # frame_locked
    w.sequence(points, 8)
    w.sequence(rgba, 4)
    w.string('')                                            # texture_resource
    w.header(0, '')                                         # texture: empty CompressedImage
    w.string('')
    w.sequence(np.zeros(0, np.uint8), 1)
    w.sequence(np.zeros((0, 2), '<f4'), 4)                  # uv_coordinates
    w.string('')                                            # text
    w.string('')                                            # mesh_resource
    w.string('')                                            # mesh_file: filename, data
    w.sequence(np.zeros(0, np.uint8), 1)
    w.scalars('u1', 0)                                      # mesh_use_embedded_materials
    return w.bytes()


