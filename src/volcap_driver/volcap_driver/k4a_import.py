"""Convert an Azure Kinect recording (MKV from k4arecorder) into a one-camera volcap bag.

PyAV demuxes the MKV without the Kinect SDK: the colour track (MJPEG or raw), the depth track
(``b16g``: big-endian 16-bit millimetres) and the factory calibration attachment, which becomes
the rig description on ``volcap/rig``. Stamps are the recording's start time plus each frame's
device timestamp, so colour and depth of one capture share a stamp.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import av
import numpy as np
from std_msgs.msg import String
from tqdm import tqdm

from volcap_core import topics
from volcap_core.bag_writer import BagWriter
from volcap_core.conversions import camera_model_to_info, numpy_to_image
from volcap_core.errors import BadInput
from volcap_core.rig import Rig, rig_camera_from_k4a


class K4AImportError(BadInput):
    """The MKV is not a readable Azure Kinect recording."""


@dataclass
class ImportSummary:
    path: Path
    color_frames: int
    depth_frames: int
    rig: Rig


def _track(container, key: str):
    for s in container.streams:
        if key in s.metadata:
            return s
    return None


def import_k4a(mkv: str | Path, out: str | Path, camera: str = 'cam0', max_frames: int | None = None,
               progress: bool = True, overwrite: bool = False) -> ImportSummary:
    mkv, out = Path(mkv), Path(out)
    if out.exists():
        if not overwrite:
            raise FileExistsError(f'{out} exists; choose another --out or pass --overwrite')
        shutil.rmtree(out)
    try:
        container = av.open(str(mkv))
    except (av.error.FFmpegError, OSError) as e:
        raise K4AImportError(f'cannot open {mkv}: {e}') from e
    with container:
        color_s, depth_s = _track(container, 'K4A_COLOR_TRACK'), _track(container, 'K4A_DEPTH_TRACK')
        calib_s = next((s for s in container.streams if s.type == 'attachment' and s.name == 'calibration.json'),
                       None)
        if color_s is None or depth_s is None or calib_s is None:
            raise K4AImportError(f'{mkv} lacks a K4A colour track, depth track or calibration attachment '
                                 '(record with colour and depth enabled)')
        color_mode = color_s.metadata.get('K4A_COLOR_MODE', '').split('_')[-1]
        depth_mode = depth_s.metadata.get('K4A_DEPTH_MODE', '')
        cam = rig_camera_from_k4a(json.loads(bytes(calib_s.data)), camera, color_mode, depth_mode,
                                  serial=container.metadata.get('K4A_DEVICE_SERIAL_NUMBER', ''))
        rig = Rig([cam], name=f'k4a_{cam.serial or mkv.stem}')
        created = container.metadata.get('creation_time')
        base_ns = int(datetime.fromisoformat(created.replace('Z', '+00:00')).timestamp() * 1e9) if created else 0
        if depth_s.codec_context.width != cam.depth.width or depth_s.codec_context.height != cam.depth.height:
            raise K4AImportError(f'depth track is {depth_s.codec_context.width}x{depth_s.codec_context.height}, '
                                 f'calibration mode {depth_mode} says {cam.depth.width}x{cam.depth.height}')
        try:
            n_color, n_depth = _write_bag(container, out, rig, cam, camera, color_s, depth_s, base_ns, max_frames,
                                          progress, mkv.name)
        except BaseException:
            shutil.rmtree(out, ignore_errors=True)   # no half-written bag left behind
            raise
    return ImportSummary(out, n_color, n_depth, rig)


def _write_bag(container, out: Path, rig: Rig, cam, camera: str, color_s, depth_s, base_ns: int,
               max_frames: int | None, progress: bool, name: str) -> tuple[int, int]:
    n_color = n_depth = 0
    expected = cam.depth.width * cam.depth.height * 2
    with BagWriter(out) as bag, tqdm(desc=f'importing {name}', unit='frame', disable=not progress) as bar:
        bag.add_topic(topics.RIG, 'std_msgs/msg/String', latched=True)
        bag.write(topics.RIG, String(data=rig.to_yaml()), base_ns)
        for packet in container.demux(color_s, depth_s):
            if packet.pts is None or packet.size == 0:
                continue
            stamp = base_ns + int(round(float(packet.pts * packet.time_base) * 1e9))
            if packet.stream is color_s:
                frames = packet.decode()
                if not frames:
                    continue
                rgb = frames[0].to_ndarray(format='rgb24')
                bag.write(topics.camera_topic(camera, topics.COLOR_IMAGE),
                          numpy_to_image(rgb, 'rgb8', stamp, cam.color_frame), stamp)
                bag.write(topics.camera_topic(camera, topics.COLOR_INFO),
                          camera_model_to_info(cam.color, stamp, cam.color_frame), stamp)
                n_color += 1
            else:
                raw = bytes(packet)
                if len(raw) != expected:
                    raise K4AImportError(f'depth packet at {stamp} has {len(raw)} bytes, expected {expected}')
                depth = np.frombuffer(raw, '>u2').reshape(cam.depth.height, cam.depth.width).astype(np.uint16)
                bag.write(topics.camera_topic(camera, topics.DEPTH_IMAGE),
                          numpy_to_image(depth, '16UC1', stamp, cam.depth_frame), stamp)
                bag.write(topics.camera_topic(camera, topics.DEPTH_INFO),
                          camera_model_to_info(cam.depth, stamp, cam.depth_frame), stamp)
                n_depth += 1
                bar.update(1)
            if max_frames is not None and min(n_color, n_depth) >= max_frames:
                break
    return n_color, n_depth
