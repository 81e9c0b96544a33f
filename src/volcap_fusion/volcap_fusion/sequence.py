"""The volumetric sequence on disk, a stream a player can follow while it grows:

- ``NNNNNN.glb`` per time step (``glb.encode``: +Y up, linear colour, the capture stamp in the
  scene extras; meshopt-compressed within a triangle budget by default, ``raw`` on request) and
  ``NNNNNN.ply`` (the full mesh, studio frame +Z up, 8-bit sRGB vertex colour as PLY viewers
  expect);
- ``sequence.jsonl``: a header line (the frame the meshes are in and where it lies in the
  calibration's world, the encoding), then one line per time step (index, capture stamp,
  cameras, files, bytes, triangles), appended once the frame's files are in place, so a long
  take costs the same per frame and a reader skips a last line still being written;
- ``manifest.json``: the summary a player starts from (frame rate measured from the last 900 stamps,
  frame count, duration, encoding), rewritten atomically every second of capture and at the end.

Every file is written atomically: a player polling the folder never reads half a frame.
"""
from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from collections import deque
from pathlib import Path

import numpy as np
import open3d as o3d

from volcap_core.errors import BadInput
from volcap_core.files import FILE_MODE, append_line, atomic_write, publish, write_failure, write_json
from volcap_core.poses import matrix_from_list, matrix_to_list

from .glb import EncodeConfig, EncodedFrame, encode
from .tsdf import FusedModel, colors_to_uint8

MANIFEST = 'sequence.jsonl'
SUMMARY = 'manifest.json'
SEQUENCE_VERSION = 2
RATE_WINDOW = 900           # stamps the manifest's frame rate is measured over (30 s at 30 fps)


PLY_HEADER_MAX = 4096
_PLY_TYPE_BYTES = {'char': 1, 'uchar': 1, 'int8': 1, 'uint8': 1, 'short': 2, 'ushort': 2, 'int16': 2,
                   'uint16': 2, 'int': 4, 'uint': 4, 'int32': 4, 'uint32': 4, 'float': 4, 'float32': 4,
                   'double': 8, 'float64': 8}


def binary_ply_size(path: str | Path, list_length: int = 3) -> int:
    """The size a binary PLY's header says the file has (lists taken as ``list_length`` long)."""
    with open(path, 'rb') as f:
        header = b''
        while not header.endswith(b'end_header\n'):
            line = f.readline()
            if not line:
                raise BadInput(f'{path}: no PLY header')
            header += line
    size, count = len(header), 0
    for line in header.decode('ascii', 'replace').splitlines():
        words = line.split()
        if words[:1] == ['element']:
            count = int(words[2])
        elif words[:2] == ['property', 'list']:
            size += count * (_PLY_TYPE_BYTES[words[2]] + list_length * _PLY_TYPE_BYTES[words[3]])
        elif words[:1] == ['property']:
            size += count * _PLY_TYPE_BYTES[words[1]]
    return size


def write_ply(path: str | Path, model: FusedModel) -> Path:
    """Binary PLY with vertex colours, whole or absent. Open3D (which picks the format by suffix)
    reports success on a short write to a full disk and keeps the file open, its space held, until
    the process ends: so a PLY that cannot fit is refused before Open3D starts, and the size
    written is checked against the header after."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    needed = len(model.vertices) * 15 + len(model.triangles) * 13 + PLY_HEADER_MAX
    if shutil.disk_usage(target.parent).free < needed:
        raise write_failure(target, OSError(errno.ENOSPC, 'no space'))
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f'.{target.stem}.', suffix='.ply')
    os.close(fd)
    try:
        ok = o3d.io.write_triangle_mesh(tmp, model.legacy_mesh(), write_ascii=False, compressed=False,
                                        write_vertex_normals=False)
        written = os.path.getsize(tmp)
        if not ok or written != binary_ply_size(tmp):
            raise OSError(errno.ENOSPC if written else errno.EIO, f'short PLY write ({written} bytes)')
        with open(tmp, 'rb') as f:
            os.fsync(f.fileno())
        os.chmod(tmp, FILE_MODE)
        publish(tmp, target)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise write_failure(target, e) from e
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def read_ply(path: str | Path) -> FusedModel:
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.vertices) == 0:
        raise BadInput(f'{path}: no mesh')
    colors = colors_to_uint8(np.asarray(mesh.vertex_colors)) if mesh.has_vertex_colors() else \
        np.zeros((len(mesh.vertices), 3), np.uint8)
    return FusedModel(np.asarray(mesh.vertices, np.float32), colors, np.asarray(mesh.triangles, np.int32))


class SequenceWriter:
    """Writes ``NNNNNN.glb`` and ``NNNNNN.ply`` per time step into a folder, with ``sequence.jsonl``
    and ``manifest.json``. ``frame`` / ``T_world_frame``: the frame the models are in (the studio
    frame) and its pose in the calibration's world frame."""

    def __init__(self, folder: str | Path, formats: tuple[str, ...] = ('ply', 'glb'),
                 encoding: EncodeConfig | None = None, voxel_size: float | None = None):
        unknown = set(formats) - {'ply', 'glb'}
        if unknown or not formats:
            raise BadInput(f'sequence formats must be ply and/or glb, got {formats}')
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.formats = formats
        self.encoding = (encoding or EncodeConfig()).for_voxel(voxel_size)
        self.encoding.validate()
        if (self.folder / MANIFEST).exists():
            raise FileExistsError(f'{self.folder} already holds a sequence')
        self.written = 0
        self.frame: tuple[str, np.ndarray] | None = None
        self.first_stamp: int | None = None
        self.last_stamp: int | None = None
        self.recent_stamps: deque[int] = deque(maxlen=RATE_WINDOW)     # bounded: the cost per frame stays flat
        self.bytes = 0
        self.missing: dict[str, int] = {}       # camera -> frames written without it
        self.frames_short = 0

    def _append(self, doc: dict) -> None:
        append_line(self.folder / MANIFEST, json.dumps(doc))

    def _header(self, frame: str, T_world_frame: np.ndarray) -> None:
        self._append({'volcap_sequence': SEQUENCE_VERSION, 'frame': frame,
                      'T_world_frame': matrix_to_list(T_world_frame), 'from_index': self.written,
                      'glb': {'encoding': self.encoding.encoding, 'up': '+Y', 'front': '+Z', 'units': 'm',
                              'color': 'linear', 'max_triangles': self.encoding.max_triangles,
                              'position_step_m': self.encoding.position_step},
                      'ply': {'up': '+Z', 'color': 'sRGB'}})
        self.frame = (frame, np.asarray(T_world_frame, float))

    def write(self, model: FusedModel, stamp_ns: int, missing: list[str] | None = None,
              frame: str = 'volcap_studio', T_world_frame: np.ndarray | None = None,
              encoded: EncodedFrame | None = None) -> dict:
        """Writes one time step; ``encoded``: its GLB when the caller already made it."""
        T = np.eye(4) if T_world_frame is None else np.asarray(T_world_frame, float)
        if self.frame is None or self.frame[0] != frame or not np.allclose(self.frame[1], T):
            self._header(frame, T)       # a new calibration mid-take starts a new header line
        index = self.written
        entry = {'index': index, 'stamp_ns': int(stamp_ns), 'cameras': list(model.cameras),
                 'missing': list(missing or []), 'vertices': int(len(model.vertices)),
                 'triangles': int(len(model.triangles))}
        written = []
        try:      # the frame's files, then its line: the index lists only frames whose files are whole
            if 'ply' in self.formats:
                written.append(write_ply(self.folder / f'{index:06d}.ply', model))
                entry['ply'] = written[-1].name
            if 'glb' in self.formats:
                encoded = encoded or encode(model, self.encoding, stamp_ns, index, frame)
                written.append(atomic_write(self.folder / f'{index:06d}.glb', lambda f: f.write(encoded.data)))
                entry.update(glb=written[-1].name, glb_bytes=len(encoded.data), glb_triangles=encoded.triangles,
                             encode_ms=round(sum(encoded.timings_ms.values()), 2))
            self._append(entry)
        except BaseException:
            for path in written:          # no orphan files for a frame the index does not list
                path.unlink(missing_ok=True)
            raise
        if 'glb' in self.formats:
            self.bytes += len(encoded.data)
        self.frames_short += bool(missing)
        for cam in missing or []:
            self.missing[cam] = self.missing.get(cam, 0) + 1
        self.written += 1
        self.first_stamp = int(stamp_ns) if self.first_stamp is None else self.first_stamp
        self.last_stamp = int(stamp_ns)
        self.recent_stamps.append(int(stamp_ns))
        rate = frame_rate(self.recent_stamps)
        if self.written == 1 or self.written % max(1, round(rate or 1)) == 0:
            self.write_summary()
        return entry

    def write_summary(self) -> Path:
        """``manifest.json`` as the sequence stands."""
        rate = frame_rate(self.recent_stamps)
        duration = (self.last_stamp - self.first_stamp) / 1e9 if self.written else 0.0
        return write_json(self.folder / SUMMARY, {
            'volcap_sequence': SEQUENCE_VERSION, 'frames': self.written, 'frame_rate': rate,
            'first_stamp_ns': str(self.first_stamp) if self.written else None,
            'duration_s': round(duration, 3), 'frame': self.frame[0] if self.frame else None,
            'frames_short_of_cameras': self.frames_short, 'frames_missing_per_camera': dict(self.missing),
            'index': MANIFEST, 'glb_encoding': self.encoding.encoding if 'glb' in self.formats else None,
            'mean_glb_bytes': round(self.bytes / self.written) if self.written and 'glb' in self.formats else None,
            'mbit_per_s': round(self.bytes * 8 / self.written * rate / 1e6, 2) if self.written and rate and
            'glb' in self.formats else None})

    def close(self) -> None:
        if self.written:
            self.write_summary()


def frame_rate(stamps) -> float | None:
    """Frames per second from capture stamps (the median step: dropped sets do not lower it)."""
    if len(stamps) < 2:
        return None
    steps = np.diff(np.asarray(stamps, np.int64))
    steps = steps[steps > 0]
    return round(1e9 / float(np.median(steps)), 3) if len(steps) else None


def read_sequence(folder: str | Path) -> tuple[list[dict], list[dict]]:
    """(header lines, frame lines) of ``sequence.jsonl``."""
    path = Path(folder) / MANIFEST
    if not path.exists():
        raise FileNotFoundError(f'{folder} holds no volumetric sequence ({MANIFEST} missing)')
    headers, frames = [], []
    for line in path.read_text().splitlines():
        try:
            doc = json.loads(line)
        except json.JSONDecodeError:
            break          # the line a writer is still appending
        (frames if 'index' in doc else headers).append(doc)
    return headers, frames


def read_manifest(folder: str | Path) -> list[dict]:
    """The frame lines of ``sequence.jsonl``."""
    return read_sequence(folder)[1]


def T_world_frame(headers: list[dict], index: int) -> np.ndarray:
    """The pose in the world frame of the frame that frame ``index`` is in (identity for a
    sequence written before the studio frame)."""
    current = np.eye(4)
    for h in headers:
        if h.get('from_index', 0) <= index and 'T_world_frame' in h:
            current = matrix_from_list(h['T_world_frame'])
    return current
