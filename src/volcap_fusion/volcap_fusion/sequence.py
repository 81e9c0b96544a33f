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

import json
import os
import tempfile
from collections import deque
from pathlib import Path

import numpy as np
import open3d as o3d

from volcap_core.files import atomic_write, write_json
from volcap_core.poses import matrix_from_list, matrix_to_list

from .glb import EncodeConfig, EncodedFrame, encode
from .tsdf import FusedModel, colors_to_uint8

MANIFEST = 'sequence.jsonl'
SUMMARY = 'manifest.json'
SEQUENCE_VERSION = 2
RATE_WINDOW = 900           # stamps the manifest's frame rate is measured over (30 s at 30 fps)


def write_ply(path: str | Path, model: FusedModel) -> Path:
    """Binary PLY with vertex colours, written atomically (Open3D picks the format by suffix)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f'.{target.stem}.', suffix='.ply')
    os.close(fd)
    try:
        if not o3d.io.write_triangle_mesh(tmp, model.legacy_mesh(), write_ascii=False, compressed=False,
                                          write_vertex_normals=False):
            raise OSError(f'could not write {target}')
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def read_ply(path: str | Path) -> FusedModel:
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.vertices) == 0:
        raise ValueError(f'{path}: no mesh')
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
            raise ValueError(f'sequence formats must be ply and/or glb, got {formats}')
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

    def _append(self, doc: dict) -> None:
        with open(self.folder / MANIFEST, 'a') as f:
            f.write(json.dumps(doc) + '\n')

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
        if 'ply' in self.formats:
            entry['ply'] = write_ply(self.folder / f'{index:06d}.ply', model).name
        if 'glb' in self.formats:
            encoded = encoded or encode(model, self.encoding, stamp_ns, index, frame)
            entry['glb'] = atomic_write(self.folder / f'{index:06d}.glb', lambda f: f.write(encoded.data)).name
            entry.update(glb_bytes=len(encoded.data), glb_triangles=encoded.triangles,
                         encode_ms=round(sum(encoded.timings_ms.values()), 2))
            self.bytes += len(encoded.data)
        self._append(entry)
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
