"""The wire carries what the fusion needs: eight cameras' ideal views of the studio's person
(cleaned depth at half the colour size, colour at 1280x720, as `volcap live` runs them) sent as
each camera pipeline sends them and fused, against the same views fused from the full frames
(decimated as crop_decimate does, for a wire with binning).
Also: the region LUT corrects a region as it does the whole image (the camera pipeline corrects
only the region it sends)."""
import numpy as np
import pytest

from volcap_color.apply import ImageCorrector, RegionLut
from volcap_core.camera import CameraModel
from volcap_core.color import delta_e2000
from volcap_core.wire import binned_model
from volcap_fusion.rig import wire_view
from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion
from volcap_pipeline.camera import CameraPipeline, WireConfig
from volcap_studio.ideal import IdealView, ring_views

DEPTH = CameraModel(640, 360, 305.0, 305.0, 319.5, 179.5)
COLOR = CameraModel(1280, 720, 610.0, 610.0, 639.5, 359.5)


@pytest.fixture(scope='module')
def ring():
    out = []
    for name, _, T, view in ring_views(DEPTH):
        out.append((name, T, view.depth_mm, IdealView(COLOR, T).rgb))
    return out


def _fuse(views):
    return TsdfFusion(FusionConfig(voxel_size=0.01)).fuse(views)


@pytest.mark.parametrize('binning', [1, 2])
def test_fusion_from_the_wire_matches_the_full_frames(ring, binning):
    full, sent, wire_bytes = [], [], 0
    cfg = WireConfig(wire_binning=binning)
    for name, T, depth_mm, rgb in ring:
        # the reference: the full frames, decimated as crop_decimate does (binning 1: as they are)
        full.append(CameraView(name, np.ascontiguousarray(depth_mm[::binning, ::binning]),
                               binned_model(DEPTH, binning), rgb, COLOR, T))
        out = CameraPipeline(name).wire(depth_mm.astype(np.float32) / 1000, DEPTH, rgb, COLOR, 7, name, cfg)
        assert out.depth_info.roi.width < DEPTH.width and out.color_info.roi.height <= COLOR.height
        wire_bytes += out.bytes
        sent.append(wire_view(name, out.depth, out.depth_info, out.color, out.color_info, T))
    raw_bytes = sum(d.nbytes + c.nbytes for _, _, d, c in ring)
    assert wire_bytes < raw_bytes / 10
    a, b = _fuse(full), _fuse(sent)
    assert len(b.vertices) == pytest.approx(len(a.vertices), rel=0.01)     # lossless depth: the same surface
    scene = a.raycasting_scene()
    import open3d.core as o3c
    distance = scene.compute_distance(o3c.Tensor(b.vertices.astype(np.float32))).numpy()
    assert np.median(distance) < 1e-4
    # vertex colours: the nearest full-frame vertex's, through JPEG
    from scipy.spatial import cKDTree
    _, nearest = cKDTree(a.vertices).query(b.vertices)
    close = distance < 1e-3
    de = delta_e2000(b.colors[close] / 255.0, a.colors[nearest[close]] / 255.0)
    assert np.mean(de) < 1.0


def test_region_lut_corrects_a_region_as_the_whole_image():
    rng = np.random.default_rng(3)
    table = np.clip(np.linspace(0, 255, 5)[:, None, None, None, None, None] + rng.normal(0, 8, (5, 5, 5, 3, 4, 3)),
                    0, 255)                                # (r, g, b, ny, nx, out): varies over the image
    lut = RegionLut(table.astype(np.float32))
    image = rng.integers(0, 256, (120, 200, 3), dtype=np.uint8)
    whole = ImageCorrector(lut)(image)
    for x, y, w, h, step in ((37, 11, 50, 40, 1), (20, 30, 100, 60, 2)):
        crop = np.ascontiguousarray(image[y:y + h:step, x:x + w:step])
        out = ImageCorrector(lut)(crop, window=(x, y, 200, 120, step))
        np.testing.assert_array_equal(out, whole[y:y + h:step, x:x + w:step])
