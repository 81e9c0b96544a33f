"""Fused meshes as glTF 2.0 binaries for renderers, within a triangle budget and compressed.

Per frame: meshoptimizer simplifies the mesh to ``max_triangles`` (quadric error; the vertex
colours of the kept vertices stay as they were), reorders it for the GPU's vertex cache, then
one of three encodings:

- ``meshopt`` (``EXT_meshopt_compression`` + ``KHR_mesh_quantization``): positions quantised to
  integer steps of ``position_step`` metres (by default half the fusion voxel, so a vertex moves
  at most sqrt(3)/4 of a voxel; the node's scale and translation put them back),
  colours to ``color_bits`` of linear light, both run through meshoptimizer's vertex and index
  codecs. Decodes in a browser in a few ms (three.js ``MeshoptDecoder``): the live default.
- ``draco`` (``KHR_draco_mesh_compression``): Google's Draco (DracoPy), positions quantised to
  the bits that keep the step under ``position_step``. Smallest; slower to decode.
- ``raw``: float positions, 16-bit colours, 32-bit indices, nothing compressed.

Conventions every player relies on (glTF 2.0 spec, section 3.4 and 3.7.2): metres, +Y up, and
the asset's front towards +Z. The studio frame is REP 103 (+Z up, +X towards the reference
camera), so a studio point (x, y, z) is written as (y, z, x): a rotation, handedness kept.
``COLOR_0`` is *linear* light (the cameras' colour is sRGB): 12 bits keep the round trip under
0.42 CIEDE2000 where 8 bits lose up to 7 in the shadows. The material is unlit
(``KHR_materials_unlit``): the captured colour already holds the studio's lighting. The capture
stamp and the frame index are in the scene's ``extras`` (three.js: ``scene.userData``), the stamp
as a decimal string because JSON numbers lose nanoseconds past 2^53.
"""
from __future__ import annotations

import functools
import json
import struct
import time
from dataclasses import dataclass, replace

import DracoPy
import meshoptimizer
import numpy as np

from volcap_core.color import linear_to_srgb, srgb_to_linear
from volcap_core.errors import BadInput
from volcap_core.settings import setting, validate

from .tsdf import FusedModel

ENCODINGS = ('meshopt', 'draco', 'raw')
GLB_MAGIC, GLB_VERSION, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 2, 0x4E4F534A, 0x004E4942
FLOAT, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
# studio (REP 103, +Z up, +X front) -> glTF (+Y up, +Z front): (x, y, z) -> (y, z, x)
STUDIO_TO_GLTF = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], np.float64)
DRACO_COLOR_ID = 1
DEFAULT_VOXEL = 0.004      # what a position_step of 0 assumes when nobody says the voxel size


@dataclass
class EncodeConfig:
    encoding: str = setting('meshopt', 'mesh encoding of the GLBs: meshopt (fast to decode), draco (smallest), '
                            'raw', choices=ENCODINGS)
    max_triangles: int = setting(30_000, 'triangle budget per frame (0: keep every triangle)', 0, 10_000_000)
    simplifier: str = setting('sloppy', 'how the budget is met: sloppy (meshoptimizer\'s clustering, ~15 ms for '
                              '325k triangles on one core) or quadric (edge collapse, better shapes, ~200 ms)',
                              choices=('sloppy', 'quadric'))
    position_step: float = setting(0.0, 'position quantisation step (m); 0: half the fusion voxel, which keeps '
                                   'every vertex within 0.43 voxel of where fusion put it', 0.0, 0.1)
    color_bits: int = setting(12, 'bits of linear colour kept per channel', 8, 16)

    def validate(self) -> None:
        validate(self)

    def for_voxel(self, voxel_size: float | None) -> 'EncodeConfig':
        """This config with ``position_step`` 0 resolved: half of ``voxel_size``, or half a 4 mm voxel
        when the voxel is not known."""
        if self.position_step:
            return self
        return replace(self, position_step=(voxel_size or DEFAULT_VOXEL) / 2)


@dataclass
class EncodedFrame:
    data: bytes
    triangles: int
    vertices: int
    timings_ms: dict


# colour and axes ------------------------------------------------------------------------------
@functools.cache
def _linear16_table(bits: int) -> np.ndarray:
    """Each 8-bit sRGB level as normalised 16-bit linear light, quantised to ``bits``."""
    levels = (1 << bits) - 1
    q = np.round(srgb_to_linear(np.arange(256) / 255.0) * levels)
    return np.round(q * (65535.0 / levels)).astype(np.uint16)


def linear_color16(colors_srgb8: np.ndarray, bits: int) -> np.ndarray:
    """(N, 4) uint16 normalised linear RGBA of 8-bit sRGB colours, quantised to ``bits``."""
    out = np.full((len(colors_srgb8), 4), 65535, np.uint16)
    out[:, :3] = _linear16_table(bits)[colors_srgb8]
    return out


def srgb8_from_linear16(colors: np.ndarray) -> np.ndarray:
    return np.clip(np.round(linear_to_srgb(colors[:, :3] / 65535.0) * 255.0), 0, 255).astype(np.uint8)


def to_gltf_axes(vertices_studio: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(vertices_studio[:, [1, 2, 0]], np.float32)


def from_gltf_axes(vertices_gltf: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(vertices_gltf[:, [2, 0, 1]], np.float32)


# budget ---------------------------------------------------------------------------------------
def simplify(model: FusedModel, max_triangles: int, simplifier: str = 'sloppy') -> FusedModel:
    """At most ``max_triangles`` (meshoptimizer), with the vertices reordered for the vertex cache
    and fetch (which also shrinks the codecs' output); the mesh as it is when it fits."""
    vertices = np.ascontiguousarray(model.vertices, np.float32)
    indices = np.ascontiguousarray(model.triangles, np.uint32).reshape(-1)
    if max_triangles and len(model.triangles) > max_triangles:
        out = np.zeros_like(indices)
        count = len(indices)
        if simplifier == 'quadric':
            count = meshoptimizer.simplify(out, indices, vertices, target_index_count=3 * max_triangles,
                                           target_error=0.05)
        if count > 3 * max_triangles:     # sloppy, or the error limit stopped quadric short: any budget
            count = meshoptimizer.simplify_sloppy(out, indices, vertices, target_index_count=3 * max_triangles,
                                                  target_error=1.0)
        indices = out[:count]
    optimized = np.zeros_like(indices)
    # the FIFO cache model: 2.7 ms where the full optimiser takes 8 ms for 30 000 triangles, and
    # the codecs' output 2 % larger
    meshoptimizer.optimize_vertex_cache_fifo(optimized, indices, len(indices), len(vertices), 16)
    remap = np.zeros(len(vertices), np.uint32)
    unique = meshoptimizer.optimize_vertex_fetch_remap(remap, optimized, len(optimized), len(vertices))
    used = remap != 0xFFFFFFFF
    new_vertices = np.zeros((unique, 3), np.float32)
    new_colors = np.zeros((unique, 3), np.uint8)
    new_vertices[remap[used]] = vertices[used]
    new_colors[remap[used]] = model.colors[used]
    return FusedModel(new_vertices, new_colors, remap[optimized].reshape(-1, 3).astype(np.int32), model.cameras,
                      model.timings_ms)


# writing --------------------------------------------------------------------------------------
class _Builder:
    """glTF JSON and its binary chunk, assembled view by view."""

    def __init__(self):
        self.bin = bytearray()
        self.doc = {'asset': {'version': '2.0', 'generator': 'volcap'}, 'bufferViews': [], 'accessors': [],
                    'buffers': []}
        self.used, self.required = {'KHR_materials_unlit'}, set()

    def put(self, data: bytes) -> tuple[int, int]:
        while len(self.bin) % 4:
            self.bin.append(0)
        offset = len(self.bin)
        self.bin += data
        return offset, len(data)

    def view(self, data: bytes, **fields) -> int:
        offset, length = self.put(data)
        self.doc['bufferViews'].append({'buffer': 0, 'byteOffset': offset, 'byteLength': length, **fields})
        return len(self.doc['bufferViews']) - 1

    def accessor(self, **fields) -> int:
        self.doc['accessors'].append(fields)
        return len(self.doc['accessors']) - 1

    def glb(self, primitive: dict, node: dict, extras: dict, fallback_bytes: int = 0) -> bytes:
        while len(self.bin) % 4:
            self.bin.append(0)
        self.doc['buffers'] = [{'byteLength': len(self.bin)}]
        if fallback_bytes:   # EXT_meshopt_compression: where a decoder puts the decoded views
            self.doc['buffers'].append({'byteLength': fallback_bytes,
                                        'extensions': {'EXT_meshopt_compression': {'fallback': True}}})
        self.doc['materials'] = [{'pbrMetallicRoughness': {'baseColorFactor': [1, 1, 1, 1], 'metallicFactor': 0.0,
                                                           'roughnessFactor': 1.0},
                                  'extensions': {'KHR_materials_unlit': {}}, 'doubleSided': True}]
        self.doc['meshes'] = [{'primitives': [{**primitive, 'material': 0, 'mode': 4}]}]
        self.doc['nodes'] = [{'mesh': 0, **node}]
        self.doc['scenes'] = [{'nodes': [0], 'extras': extras}]
        self.doc['scene'] = 0
        self.doc['extensionsUsed'] = sorted(self.used)
        if self.required:
            self.doc['extensionsRequired'] = sorted(self.required)
        if not self.doc['bufferViews']:
            del self.doc['bufferViews']
        return pack_glb(self.doc, bytes(self.bin))


def pack_glb(doc: dict, binary: bytes) -> bytes:
    text = json.dumps(doc, separators=(',', ':')).encode()
    text += b' ' * (-len(text) % 4)
    binary += b'\0' * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack('<III', GLB_MAGIC, GLB_VERSION, total) + struct.pack('<II', len(text), JSON_CHUNK) + text
            + struct.pack('<II', len(binary), BIN_CHUNK) + binary)


def frame_extras(stamp_ns: int | None, index: int | None, frame: str) -> dict:
    extras = {'volcap': {'frame': frame, 'up': '+Y (glTF); studio +Z', 'color': 'linear'}}
    if stamp_ns is not None:
        extras['volcap'].update(stamp_ns=str(int(stamp_ns)), stamp_s=int(stamp_ns) / 1e9)
    if index is not None:
        extras['volcap']['index'] = int(index)
    return extras


def encode(model: FusedModel, cfg: EncodeConfig | None = None, stamp_ns: int | None = None,
           index: int | None = None, frame: str = 'volcap_studio') -> EncodedFrame:
    """The model (studio frame) as a GLB: simplified to the budget, then encoded."""
    cfg = (cfg or EncodeConfig()).for_voxel(None)
    t0 = time.perf_counter()
    mesh = simplify(model, cfg.max_triangles, cfg.simplifier)
    t1 = time.perf_counter()
    extras = frame_extras(stamp_ns, index, frame)
    if not len(mesh.triangles):
        raise BadInput('an empty mesh has no glTF form (an accessor counts at least one element)')
    writer = {'meshopt': _meshopt_glb, 'draco': _draco_glb, 'raw': _raw_glb}[cfg.encoding]
    data = writer(mesh, cfg, extras)
    t2 = time.perf_counter()
    return EncodedFrame(data, len(mesh.triangles), len(mesh.vertices),
                        {'simplify': (t1 - t0) * 1e3, 'encode': (t2 - t1) * 1e3})


def _bounds(v: np.ndarray) -> tuple[list, list]:
    return v.min(axis=0).tolist(), v.max(axis=0).tolist()


def _raw_glb(mesh: FusedModel, cfg: EncodeConfig, extras: dict) -> bytes:
    b = _Builder()
    v = to_gltf_axes(mesh.vertices)
    lo, hi = _bounds(v)
    colors = linear_color16(mesh.colors, cfg.color_bits)
    pos = b.accessor(bufferView=b.view(v.tobytes(), byteStride=12, target=ARRAY_BUFFER), componentType=FLOAT,
                     count=len(v), type='VEC3', min=lo, max=hi)
    col = b.accessor(bufferView=b.view(colors.tobytes(), byteStride=8, target=ARRAY_BUFFER),
                     componentType=UNSIGNED_SHORT, normalized=True, count=len(v), type='VEC4')
    idx = b.accessor(bufferView=b.view(np.ascontiguousarray(mesh.triangles, np.uint32).tobytes(),
                                       target=ELEMENT_ARRAY_BUFFER), componentType=UNSIGNED_INT,
                     count=int(mesh.triangles.size), type='SCALAR')
    return b.glb({'attributes': {'POSITION': pos, 'COLOR_0': col}, 'indices': idx}, {}, extras)


def _meshopt_glb(mesh: FusedModel, cfg: EncodeConfig, extras: dict) -> bytes:
    b = _Builder()
    b.used |= {'EXT_meshopt_compression', 'KHR_mesh_quantization'}
    b.required |= {'EXT_meshopt_compression', 'KHR_mesh_quantization'}
    v = to_gltf_axes(mesh.vertices).astype(np.float64)
    origin = v.min(axis=0)
    steps = np.round((v - origin) / cfg.position_step)
    if steps.max() > 65535:
        raise BadInput(f'the mesh spans {np.ptp(v, axis=0).max():.2f} m: more than 65535 steps of '
                         f'{cfg.position_step * 1000:g} mm; raise position_step')
    n = len(v)
    positions = np.zeros((n, 4), np.uint16)        # 8-byte stride: vertex attributes are 4-byte aligned
    positions[:, :3] = steps
    colors = linear_color16(mesh.colors, cfg.color_bits)
    index_size = 2 if n <= 65536 else 4
    indices = np.ascontiguousarray(mesh.triangles, np.uint32).reshape(-1)
    fallback = 0

    def compressed_view(raw_len: int, stride: int, count: int, mode: str, data: bytes, target: int) -> int:
        nonlocal fallback
        offset, length = b.put(data)
        b.doc['bufferViews'].append({
            'buffer': 1, 'byteOffset': fallback, 'byteLength': raw_len, **({'byteStride': stride} if mode ==
                                                                              'ATTRIBUTES' else {}),
            'target': target,
            'extensions': {'EXT_meshopt_compression': {'buffer': 0, 'byteOffset': offset, 'byteLength': length,
                                                       'byteStride': stride, 'count': count, 'mode': mode}}})
        fallback += raw_len + (-raw_len % 4)
        return len(b.doc['bufferViews']) - 1

    meshoptimizer.encode_vertex_version(0)     # the version EXT_meshopt_compression specifies
    pos = b.accessor(bufferView=compressed_view(n * 8, 8, n, 'ATTRIBUTES', meshoptimizer.encode_vertex_buffer(
        positions, n, 8), ARRAY_BUFFER), componentType=UNSIGNED_SHORT, count=n, type='VEC3',
        min=steps.min(axis=0).tolist(), max=steps.max(axis=0).tolist())
    col = b.accessor(bufferView=compressed_view(n * 8, 8, n, 'ATTRIBUTES', meshoptimizer.encode_vertex_buffer(
        colors, n, 8), ARRAY_BUFFER), componentType=UNSIGNED_SHORT, normalized=True, count=n, type='VEC4')
    idx = b.accessor(bufferView=compressed_view(len(indices) * index_size, index_size, len(indices), 'TRIANGLES',
                                                meshoptimizer.encode_index_buffer(indices, len(indices), n),
                                                ELEMENT_ARRAY_BUFFER),
                     componentType=UNSIGNED_SHORT if index_size == 2 else UNSIGNED_INT, count=len(indices),
                     type='SCALAR')
    node = {'translation': origin.tolist(), 'scale': [cfg.position_step] * 3}
    return b.glb({'attributes': {'POSITION': pos, 'COLOR_0': col}, 'indices': idx}, node, extras, fallback)


@functools.cache
def _draco_position_id() -> int:
    """The Draco attribute id DracoPy gives the positions when the colour is generic attribute
    ``DRACO_COLOR_ID`` (asked of DracoPy once, on a triangle)."""
    data = DracoPy.encode(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], np.uint32),
                          generic_attributes={DRACO_COLOR_ID: np.zeros((3, 4), np.uint16)})
    return next(a['unique_id'] for a in DracoPy.decode(data).attributes if a['attribute_type'] == 0)


def draco_position_bits(extent: float, step: float) -> int:
    return int(min(30, max(8, np.ceil(np.log2(extent / step + 1)))))


def _draco_glb(mesh: FusedModel, cfg: EncodeConfig, extras: dict) -> bytes:
    b = _Builder()
    b.used |= {'KHR_draco_mesh_compression'}
    b.required |= {'KHR_draco_mesh_compression'}
    v = to_gltf_axes(mesh.vertices)
    lo, hi = _bounds(v)
    extent = float(max(np.max(np.subtract(hi, lo)), cfg.position_step))
    bits = draco_position_bits(extent, cfg.position_step)
    colors = linear_color16(mesh.colors, cfg.color_bits)
    data = DracoPy.encode(v, np.ascontiguousarray(mesh.triangles, np.uint32), quantization_bits=bits,
                          compression_level=7, generic_attributes={DRACO_COLOR_ID: colors})
    view = b.view(data)
    n = len(v)
    pos = b.accessor(componentType=FLOAT, count=n, type='VEC3', min=lo, max=hi)
    col = b.accessor(componentType=UNSIGNED_SHORT, normalized=True, count=n, type='VEC4')
    idx = b.accessor(componentType=UNSIGNED_INT, count=int(mesh.triangles.size), type='SCALAR')
    draco = {'bufferView': view, 'attributes': {'POSITION': _draco_position_id(), 'COLOR_0': DRACO_COLOR_ID}}
    return b.glb({'attributes': {'POSITION': pos, 'COLOR_0': col}, 'indices': idx,
                  'extensions': {'KHR_draco_mesh_compression': draco}}, {}, extras)


# reading --------------------------------------------------------------------------------------
def unpack_glb(data: bytes) -> tuple[dict, bytes]:
    """(glTF JSON, binary chunk) of a GLB; ValueError for anything else."""
    if len(data) < 20:
        raise BadInput('not a GLB: too short')
    magic, version, length = struct.unpack_from('<III', data)
    if magic != GLB_MAGIC or version != 2 or length > len(data):
        raise BadInput('not a glTF 2.0 binary (bad header or truncated)')
    json_len, kind = struct.unpack_from('<II', data, 12)
    if kind != JSON_CHUNK:
        raise BadInput('GLB without a JSON chunk')
    doc = json.loads(data[20:20 + json_len])
    binary = b''
    at = 20 + json_len
    if at + 8 <= length:
        bin_len, kind = struct.unpack_from('<II', data, at)
        if kind == BIN_CHUNK:
            binary = data[at + 8:at + 8 + bin_len]
    return doc, binary


def decode_glb(data: bytes) -> tuple[FusedModel, dict]:
    """The studio-frame mesh (8-bit sRGB colours) and the scene extras of a GLB written by
    ``encode`` (any encoding), decoded with the same libraries a player would use."""
    doc, binary = unpack_glb(data)
    prim = doc['meshes'][0]['primitives'][0]
    accessors = doc['accessors']
    node = doc['nodes'][0]
    extras = doc['scenes'][0].get('extras', {})
    if 'KHR_draco_mesh_compression' in prim.get('extensions', {}):
        ext = prim['extensions']['KHR_draco_mesh_compression']
        view = doc['bufferViews'][ext['bufferView']]
        decoded = DracoPy.decode(binary[view['byteOffset']:view['byteOffset'] + view['byteLength']])
        by_id = {a['unique_id']: a['data'] for a in decoded.attributes}
        v = np.asarray(by_id[ext['attributes']['POSITION']], np.float32)
        colors = np.asarray(by_id[ext['attributes']['COLOR_0']], np.uint16)
        tris = np.asarray(decoded.faces, np.int32).reshape(-1, 3)
    else:
        def read(index: int, dtype, width: int) -> np.ndarray:
            acc = accessors[index]
            view = doc['bufferViews'][acc['bufferView']]
            count = acc['count']
            ext = view.get('extensions', {}).get('EXT_meshopt_compression')
            if ext is None:
                stride = view.get('byteStride', np.dtype(dtype).itemsize * width)
                raw = binary[view['byteOffset']:view['byteOffset'] + view['byteLength']]
            else:
                stride = ext['byteStride']
                src = binary[ext['byteOffset']:ext['byteOffset'] + ext['byteLength']]
                if ext['mode'] != 'ATTRIBUTES':
                    return meshoptimizer.decode_index_buffer(ext['count'], 4, src)
                raw = meshoptimizer.decode_vertex_buffer(ext['count'], stride, src).view(np.uint8).tobytes()
            per = stride // np.dtype(dtype).itemsize
            return np.frombuffer(raw, dtype, count * per).reshape(count, per)[:, :width]
        component = {FLOAT: np.float32, UNSIGNED_SHORT: np.uint16, UNSIGNED_INT: np.uint32}
        pa, ca, ia = accessors[prim['attributes']['POSITION']], accessors[prim['attributes']['COLOR_0']], \
            accessors[prim['indices']]
        v = read(prim['attributes']['POSITION'], component[pa['componentType']], 3).astype(np.float64)
        v = (v * np.asarray(node.get('scale', [1, 1, 1])) + np.asarray(node.get('translation', [0, 0, 0]))
             ).astype(np.float32)
        colors = read(prim['attributes']['COLOR_0'], component[ca['componentType']], 4)
        tris = read(prim['indices'], component[ia['componentType']], 1).reshape(-1, 3).astype(np.int32)
    return FusedModel(from_gltf_axes(v), srgb8_from_linear16(colors), tris), extras
