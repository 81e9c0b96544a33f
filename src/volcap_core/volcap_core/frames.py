"""Frame sets of a recorded bag as numpy arrays, for the offline tools (eval, calibrate, run).

Messages are grouped by the same synchroniser the nodes use; the session phase announced on
``volcap/phase`` is attached to every set (a bag without phase messages, such as any plain
recording, is all capture), and the rig comes from ``volcap/rig``.

Bags recorded straight from the vendor drivers are read too: each camera namespace holding a
colour and a depth stream is a camera, whichever layout it uses (volcap's ``color/image_raw``
and ``depth/image_raw``, OrbbecSDK_ROS2's same names, the Azure Kinect driver's
``rgb/image_raw`` and ``depth/image_raw`` or ``depth_to_rgb/image_raw``, JPEG
``.../compressed`` colour). Without ``volcap/rig`` the rig is a ``rig.yaml`` in the bag folder
(``volcap rig``), or is assembled from the camera_info messages and the drivers' ``/tf_static``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from volcap_core import topics
from volcap_core.camera import CameraModel
from volcap_core.conversions import camera_info_to_model, color_message_to_rgb, depth_to_metres, stamp_to_ns, tf_message_to_transforms
from volcap_core.rig import Rig
from volcap_core.rig_source import RigResolver
from volcap_core.sync import FrameSetSynchronizer

from .bag_io import BagError
from .bag_reader import BagReader

STREAMS = ('color', 'color_info', 'depth', 'depth_info')

RIG_SIDECAR = 'rig.yaml'

# Per camera namespace, the topics of each stream in order of preference. Colour: volcap and
# Orbbec, Azure Kinect, then JPEG. Depth with its own camera_info: native depth (registered
# by volcap with the extrinsic) before a driver's registered depth.
COLOR_CANDIDATES = (('color/image_raw', 'color/camera_info'), ('rgb/image_raw', 'rgb/camera_info'),
                    ('color/image_raw/compressed', 'color/camera_info'),
                    ('rgb/image_raw/compressed', 'rgb/camera_info'))
DEPTH_CANDIDATES = (('depth/image_raw', 'depth/camera_info'), ('depth_to_rgb/image_raw', 'depth_to_rgb/camera_info'))
REGISTERED_DEPTH = ('depth_to_rgb/image_raw', 'depth_to_rgb/camera_info')


def camera_topics(reader: BagReader, cameras: list[str] | None = None) -> dict[str, dict[str, str]]:
    """camera -> {stream: topic} for each camera namespace with colour and depth topics (the
    namespace is the camera's name). A native depth stream is chosen only where the bag can
    give its extrinsic (``volcap/rig``, ``rig.yaml``, ``/tf_static``); else registered depth."""
    present = reader.topics
    extrinsic_known = topics.RIG in present or topics.TF_STATIC in present or (reader.path / RIG_SIDECAR).exists()
    depth_candidates = DEPTH_CANDIDATES if extrinsic_known else (REGISTERED_DEPTH, *DEPTH_CANDIDATES)
    namespaces = sorted({t.rsplit('/', 2)[0] for t in present if t.count('/') >= 2})
    found = {}
    for ns in namespaces:
        color = next(((f'{ns}/{i}', f'{ns}/{c}') for i, c in COLOR_CANDIDATES
                      if f'{ns}/{i}' in present and f'{ns}/{c}' in present), None)
        depth = next(((f'{ns}/{i}', f'{ns}/{c}') for i, c in depth_candidates
                      if f'{ns}/{i}' in present and f'{ns}/{c}' in present), None)
        if color and depth and (cameras is None or ns in cameras):
            found[ns] = dict(zip(STREAMS, (*color, *depth)))
    return found


@dataclass
class CameraFrame:
    color: np.ndarray          # (H, W, 3) uint8 RGB
    depth: np.ndarray          # (h, w) float32 metres, 0 = invalid
    color_model: CameraModel
    depth_model: CameraModel
    depth_frame_id: str
    color_frame_id: str


@dataclass
class BagFrameSet:
    index: int
    phase: str | None
    stamp_ns: int
    cameras: dict[str, CameraFrame]
    missing: list[str]


def read_rig(reader: BagReader) -> Rig:
    """The bag's rig by the one rule (``volcap_core.rig_source``): ``rig.yaml`` beside the bag's
    files (a rig file), else ``volcap/rig``, else assembled from the first camera_info of each
    camera and the depth-to-colour transforms on ``/tf_static``."""
    sidecar = reader.path / RIG_SIDECAR
    if sidecar.exists():
        try:
            return RigResolver().set_file(sidecar)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise BagError(f'{sidecar} is not a usable rig description: {e}') from e
    for msg in reader.messages([topics.RIG]):
        return RigResolver().offer_description(msg.decode().data)
    cams = camera_topics(reader)
    if not cams:
        raise BagError(f'{reader.path} has no rig description on {topics.RIG}, no {RIG_SIDECAR}, and no camera '
                       'namespace with colour and depth topics')
    resolver = RigResolver(list(cams))
    wanted = {cams[c][s]: (c, s) for c in cams for s in ('color_info', 'depth_info')}
    seen: set[tuple[str, str]] = set()
    complete_at = None
    for m in reader.messages([topics.TF_STATIC, *wanted]):
        if m.topic == topics.TF_STATIC:
            for parent, child, T in tf_message_to_transforms(m.decode()):
                resolver.add_transform(parent, child, T)
        elif wanted[m.topic] not in seen:
            seen.add(wanted[m.topic])
            cam, stream = wanted[m.topic]
            info = m.decode()
            resolver.add_camera_info(cam, stream.removesuffix('_info'), camera_info_to_model(info),
                                     info.header.frame_id)
        if len(seen) == len(wanted):
            complete_at = m.stamp_ns if complete_at is None else complete_at
            # the drivers' latched /tf_static lands at the start of a recording: a second more will do
            if topics.TF_STATIC not in reader.topics or m.stamp_ns - complete_at > 1_000_000_000:
                break
    for cam in cams:
        color, depth = resolver.infos.get((cam, 'color')), resolver.infos.get((cam, 'depth'))
        if color is None or depth is None:
            raise BagError(f'{reader.path}: camera {cam} has no camera_info messages')
        if resolver.extrinsic(cam) is None:
            raise BagError(f'{reader.path}: no depth-to-colour extrinsic for {cam}: no /tf_static chain from '
                           f'{depth[1]!r} to {color[1]!r} and no {topics.RIG}; write one '
                           f'with `volcap rig ... --out {sidecar}`')
    return Rig(resolver.rig.cameras, name=reader.path.name)


def frame_sets(path: str | Path, phases: tuple[str, ...] | None = None, tolerance_ns: int | None = None,
               cameras: list[str] | None = None) -> Iterator[BagFrameSet]:
    """Every frame set of the bag in stamp order (optionally only those in ``phases``)."""
    with BagReader(path) as reader:
        rig = read_rig(reader)
        names = cameras or rig.names
        layout = camera_topics(reader, names)
        missing = [n for n in names if n not in layout]
        if missing:
            raise BagError(f'{reader.path} has no colour and depth topics for cameras {missing}')
        stream_of = {topic: (cam, stream) for cam, streams in layout.items() for stream, topic in streams.items()}
        sync = FrameSetSynchronizer(names, STREAMS, tolerance_ns=tolerance_ns, timeout_ns=10**18, max_pending=8)
        # A bag without phase messages (any plain recording) is all capture.
        phase_changes: dict[int, str] = {} if topics.PHASE in reader.topics else {0: topics.CAPTURE}
        index = 0

        def emit(sets):
            nonlocal index
            for fs in sets:
                cams, missing = {}, []
                for name in names:
                    parts = {s: fs.get(name, s) for s in STREAMS}
                    if any(p is None for p in parts.values()):
                        missing.append(name)
                        continue
                    cams[name] = CameraFrame(color_message_to_rgb(parts['color']), depth_to_metres(parts['depth']),
                                             camera_info_to_model(parts['color_info']),
                                             camera_info_to_model(parts['depth_info']),
                                             parts['depth'].header.frame_id, parts['color'].header.frame_id)
                set_phase = _phase_at(phase_changes, fs.stamp_ns)
                if phases is None or set_phase in phases:
                    yield BagFrameSet(index, set_phase, fs.stamp_ns, cams, missing)
                index += 1

        for m in reader.messages([topics.PHASE, *stream_of]):
            if m.topic == topics.PHASE:
                phase_changes[m.stamp_ns] = topics.parse_phase(m.decode().data)
                continue
            camera, stream = stream_of[m.topic]
            msg = m.decode()
            yield from emit(sync.add(camera, stamp_to_ns(msg.header.stamp), msg, stream=stream))
        yield from emit(sync.flush())


def _phase_at(changes: dict[int, str], stamp_ns: int) -> str | None:
    """The phase announced last at or before ``stamp_ns``."""
    before = [t for t in changes if t <= stamp_ns]
    return changes[max(before)] if before else None
