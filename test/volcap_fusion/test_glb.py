"""GLB encodings without ROS: glTF axes (+Y up, front +Z) from the studio frame, linear vertex
colour, the quantisation bounds (geometry within half a voxel, colour within 1 CIEDE2000 of the
uncompressed mesh), the triangle budget and the stamp in the extras, decoded by meshoptimizer
and DracoPy as a player would."""
import numpy as np
import pytest

from volcap_core.color import delta_e2000, srgb_to_linear
from volcap_fusion.glb import ENCODINGS, EncodeConfig, decode_glb, encode, simplify, unpack_glb
from volcap_fusion.tsdf import FusedModel


def grid_model(n: int = 120, seed: int = 0) -> FusedModel:
    """A wavy 1.2 m x 1.8 m sheet standing upright (studio +Z up) with random dark-to-bright colours."""
    rng = np.random.default_rng(seed)
    y, z = np.meshgrid(np.linspace(-0.6, 0.6, n), np.linspace(0.0, 1.8, n))
    x = 0.05 * np.sin(6 * y) * np.cos(4 * z)
    vertices = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    colors = rng.integers(0, 256, (len(vertices), 3)).astype(np.uint8)
    colors[:100] = 3                                  # deep shadow: where 8-bit linear colour fails
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).reshape(-1)
    triangles = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    return FusedModel(vertices, colors, triangles.astype(np.int32), ['cam0'])


def nearest_same(decoded: FusedModel, source: FusedModel) -> np.ndarray:
    from scipy.spatial import cKDTree
    return cKDTree(source.vertices).query(decoded.vertices)[1]


@pytest.mark.parametrize('encoding', ENCODINGS)
def test_every_encoding_round_trips_within_the_bounds(encoding):
    model = grid_model()
    cfg = EncodeConfig(encoding=encoding, max_triangles=0, position_step=0.002)
    frame = encode(model, cfg, stamp_ns=1_733_000_000_123_456_789, index=7)
    doc, _ = unpack_glb(frame.data)
    compression = {'meshopt': {'EXT_meshopt_compression', 'KHR_mesh_quantization'},
                   'draco': {'KHR_draco_mesh_compression'}, 'raw': set()}[encoding]
    assert set(doc['extensionsUsed']) == {'KHR_materials_unlit'} | compression
    assert set(doc.get('extensionsRequired', [])) == compression
    decoded, extras = decode_glb(frame.data)
    assert extras['volcap']['stamp_ns'] == '1733000000123456789' and extras['volcap']['index'] == 7
    assert len(decoded.triangles) == len(model.triangles)
    match = nearest_same(decoded, model)
    # half a 4 mm voxel, the bound the issue sets; the step keeps it well inside
    assert np.abs(decoded.vertices - model.vertices[match]).max() <= 0.002
    assert delta_e2000(decoded.colors / 255.0, model.colors[match] / 255.0).max() <= 1.0


def test_gltf_is_y_up_with_linear_colour():
    model = grid_model()
    frame = encode(model, EncodeConfig(encoding='raw', max_triangles=0))
    doc, binary = unpack_glb(frame.data)
    prim = doc['meshes'][0]['primitives'][0]
    pos = doc['accessors'][prim['attributes']['POSITION']]
    # studio z (height, 0..1.8 m) is glTF y; studio x (towards the reference camera) is glTF z
    assert pos['min'][1] == pytest.approx(0.0, abs=1e-6) and pos['max'][1] == pytest.approx(1.8, abs=1e-6)
    assert pos['max'][0] == pytest.approx(0.6, abs=1e-6)
    col = doc['accessors'][prim['attributes']['COLOR_0']]
    view = doc['bufferViews'][col['bufferView']]
    stored = np.frombuffer(binary, np.uint16, 4 * col['count'], view['byteOffset']).reshape(-1, 4)
    decoded, _ = decode_glb(frame.data)
    k = nearest_same(decoded, model)
    expected = srgb_to_linear(model.colors[k] / 255.0)
    assert np.abs(stored[:, :3] / 65535.0 - expected).max() < 1 / 4095     # linear light, 12 bits
    assert col['normalized'] and col['componentType'] == 5123


def test_the_triangle_budget_holds():
    model = grid_model(200)
    for encoding in ENCODINGS:
        frame = encode(model, EncodeConfig(encoding=encoding, max_triangles=5000))
        assert 0 < frame.triangles <= 5000
        assert len(decode_glb(frame.data)[0].triangles) == frame.triangles
    assert len(simplify(model, 0).triangles) == len(model.triangles)


def test_the_step_follows_the_voxel():
    assert EncodeConfig().for_voxel(0.01).position_step == 0.005
    assert EncodeConfig().for_voxel(None).position_step == 0.002
    assert EncodeConfig(position_step=0.001).for_voxel(0.01).position_step == 0.001
    model = grid_model()
    coarse = decode_glb(encode(model, EncodeConfig(max_triangles=0).for_voxel(0.01)).data)[0]
    fine = decode_glb(encode(model, EncodeConfig(max_triangles=0).for_voxel(0.002)).data)[0]
    error = lambda d: np.abs(d.vertices - model.vertices[nearest_same(d, model)]).max()
    assert error(fine) <= np.sqrt(3) / 4 * 0.002 + 1e-6 < error(coarse) <= np.sqrt(3) / 4 * 0.01 + 1e-6


def test_compressed_is_smaller_and_a_huge_mesh_is_refused_clearly():
    model = grid_model(150)
    sizes = {e: len(encode(model, EncodeConfig(encoding=e, max_triangles=0)).data) for e in ENCODINGS}
    assert sizes['draco'] < sizes['meshopt'] < sizes['raw']
    wide = FusedModel(model.vertices * 100, model.colors, model.triangles)
    with pytest.raises(ValueError, match='position_step'):
        encode(wide, EncodeConfig(encoding='meshopt', max_triangles=0))
