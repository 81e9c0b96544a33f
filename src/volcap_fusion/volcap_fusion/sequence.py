"""The volumetric sequence on disk: one PLY and one glTF binary per time step, and
``sequence.jsonl`` listing them with their capture stamps, one JSON line per time step,
appended once the frame's files are in place (so a long take costs the same per frame; a
reader skips a last line still being written).

The GLB holds positions, 8-bit vertex colours (``COLOR_0``) and triangle indices, with an unlit
material (``KHR_materials_unlit``) so web players (three.js, Babylon.js, model-viewer) show the
captured colour instead of relighting it. Every file is written atomically: a player polling
the folder never reads half a frame.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d
import pygltflib

from volcap_core.files import atomic_write

from .tsdf import FusedModel, colors_to_uint8

MANIFEST = 'sequence.jsonl'


def glb_bytes(model: FusedModel) -> bytes:
    """The model as a glTF 2.0 binary."""
    vertices = np.ascontiguousarray(model.vertices, np.float32)
    colors = np.ascontiguousarray(np.concatenate([model.colors, np.full((len(model.colors), 1), 255, np.uint8)],
                                                 axis=1))   # VEC4: glTF needs 4-byte aligned attributes
    indices = np.ascontiguousarray(model.triangles, np.uint32)
    blobs = [vertices.tobytes(), colors.tobytes(), indices.tobytes()]
    offsets = np.cumsum([0] + [len(b) for b in blobs[:-1]]).tolist()
    lo = vertices.min(axis=0).tolist() if len(vertices) else [0.0] * 3
    hi = vertices.max(axis=0).tolist() if len(vertices) else [0.0] * 3
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(generator='volcap', version='2.0'),
        extensionsUsed=['KHR_materials_unlit'],
        scene=0, scenes=[pygltflib.Scene(nodes=[0])], nodes=[pygltflib.Node(mesh=0)],
        materials=[pygltflib.Material(pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorFactor=[1, 1, 1, 1], metallicFactor=0.0, roughnessFactor=1.0),
            extensions={'KHR_materials_unlit': {}}, doubleSided=True)],
        meshes=[pygltflib.Mesh(primitives=[pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=0, COLOR_0=1), indices=2, material=0,
            mode=pygltflib.TRIANGLES)])],
        accessors=[
            pygltflib.Accessor(bufferView=0, componentType=pygltflib.FLOAT, count=len(vertices), type=pygltflib.VEC3,
                               min=lo, max=hi),
            pygltflib.Accessor(bufferView=1, componentType=pygltflib.UNSIGNED_BYTE, normalized=True,
                               count=len(colors), type=pygltflib.VEC4),
            pygltflib.Accessor(bufferView=2, componentType=pygltflib.UNSIGNED_INT, count=indices.size,
                               type=pygltflib.SCALAR)],
        bufferViews=[
            pygltflib.BufferView(buffer=0, byteOffset=offsets[0], byteLength=len(blobs[0]),
                                 target=pygltflib.ARRAY_BUFFER, byteStride=12),
            pygltflib.BufferView(buffer=0, byteOffset=offsets[1], byteLength=len(blobs[1]),
                                 target=pygltflib.ARRAY_BUFFER, byteStride=4),
            pygltflib.BufferView(buffer=0, byteOffset=offsets[2], byteLength=len(blobs[2]),
                                 target=pygltflib.ELEMENT_ARRAY_BUFFER)],
        buffers=[pygltflib.Buffer(byteLength=sum(len(b) for b in blobs))])
    gltf.set_binary_blob(b''.join(blobs))
    return b''.join(gltf.save_to_bytes())


def read_glb(path: str | Path) -> FusedModel:
    """Vertices, colours and triangles of a GLB this module wrote."""
    gltf = pygltflib.GLTF2.load_binary(str(path))
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]

    def array(index, dtype, width):
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
        data = np.frombuffer(blob, dtype, acc.count * width, view.byteOffset + (acc.byteOffset or 0))
        return data.reshape(acc.count, width) if width > 1 else data
    vertices = array(prim.attributes.POSITION, np.float32, 3)
    colors = array(prim.attributes.COLOR_0, np.uint8, 4)[:, :3]
    triangles = array(prim.indices, np.uint32, 1).reshape(-1, 3).astype(np.int32)
    return FusedModel(vertices.copy(), colors.copy(), triangles)


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
    """Writes ``NNNNNN.ply`` and ``NNNNNN.glb`` per time step into a folder, and a line per
    time step (stamp, cameras, files) to ``sequence.jsonl``."""

    def __init__(self, folder: str | Path, formats: tuple[str, ...] = ('ply', 'glb')):
        unknown = set(formats) - {'ply', 'glb'}
        if unknown or not formats:
            raise ValueError(f'sequence formats must be ply and/or glb, got {formats}')
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.formats = formats
        if (self.folder / MANIFEST).exists():
            raise FileExistsError(f'{self.folder} already holds a sequence')
        self.written = 0

    def write(self, model: FusedModel, stamp_ns: int, missing: list[str] | None = None) -> dict:
        index = self.written
        entry = {'index': index, 'stamp_ns': int(stamp_ns), 'cameras': list(model.cameras),
                 'missing': list(missing or []), 'vertices': int(len(model.vertices)),
                 'triangles': int(len(model.triangles))}
        if 'ply' in self.formats:
            entry['ply'] = write_ply(self.folder / f'{index:06d}.ply', model).name
        if 'glb' in self.formats:
            data = glb_bytes(model)
            entry['glb'] = atomic_write(self.folder / f'{index:06d}.glb', lambda f: f.write(data)).name
        with open(self.folder / MANIFEST, 'a') as f:
            f.write(json.dumps(entry) + '\n')
        self.written += 1
        return entry


def read_manifest(folder: str | Path) -> list[dict]:
    path = Path(folder) / MANIFEST
    if not path.exists():
        raise FileNotFoundError(f'{folder} holds no volumetric sequence ({MANIFEST} missing)')
    frames = []
    for line in path.read_text().splitlines():
        try:
            frames.append(json.loads(line))
        except json.JSONDecodeError:
            break          # the line a writer is still appending
    return frames
