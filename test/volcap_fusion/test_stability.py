"""Frame-to-frame change of fused models (``volcap_fusion.stability``) against cases whose answer
is known: the same surface, a surface moved by a known distance, a known colour change, a part
that vanishes."""
import numpy as np
import open3d as o3d
import pytest

from volcap_core.color import delta_e2000
from volcap_fusion.stability import frame_change, sequence_stability
from volcap_fusion.tsdf import FusedModel


def sphere(radius=0.3, color=(120, 80, 60), shift=(0.0, 0.0, 0.0)) -> FusedModel:
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=60)
    v = np.asarray(mesh.vertices, np.float32) + np.float32(shift)
    return FusedModel(v, np.tile(np.uint8(color), (len(v), 1)), np.asarray(mesh.triangles, np.int32))


def test_the_same_surface_does_not_change():
    c = frame_change(sphere(), sphere(), samples=20_000)
    assert c.jitter_rms_mm < 0.05 and c.flicker_de < 0.01 and c.appeared == 0 and c.vanished == 0


def test_a_grown_surface_jitters_by_the_distance_and_its_motion_is_taken_out():
    # every point 1 mm out along its normal: the RMS distance is 1 mm (less the facets' sag)
    c = frame_change(sphere(0.3), sphere(0.301), samples=20_000)
    assert 0.9 < c.jitter_rms_mm < 1.1 and c.appeared == 0 and c.vanished == 0
    # a rigid move the caller knows (the ground truth's) is not shimmer
    moved = sphere(shift=(0.02, 0.0, 0.0))
    T = np.eye(4)
    T[0, 3] = 0.02
    assert frame_change(sphere(), moved, samples=20_000, motion=T).jitter_rms_mm < 0.05
    unknown = frame_change(sphere(), moved, samples=20_000)
    assert unknown.appeared > 0.1 and unknown.vanished > 0.1    # 20 mm apart on the sides it moves to


def test_a_colour_change_is_flicker_of_its_ciede2000():
    c = frame_change(sphere(color=(120, 80, 60)), sphere(color=(126, 80, 60)), samples=5_000)
    expected = float(delta_e2000(np.array([120, 80, 60]) / 255.0, np.array([126, 80, 60]) / 255.0))
    assert c.flicker_de == pytest.approx(expected, rel=1e-3)


def test_a_vanished_part_is_its_share_of_the_surface():
    whole = sphere()
    upper = whole.vertices[:, 2] > 0.0
    keep = upper[whole.triangles].all(axis=1)
    half = FusedModel(whole.vertices, whole.colors, whole.triangles[keep])
    c = frame_change(whole, half, samples=40_000)
    assert c.appeared < 0.01 and 0.4 < c.vanished < 0.55
    report = sequence_stability([whole, half, whole], samples=10_000)
    assert report['frame_pairs'] == 2 and 0.2 < report['appear_vanish'] < 0.3
    empty = FusedModel(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.int32))
    gone = frame_change(whole, empty)
    assert gone.vanished == 1.0 and gone.appeared == 0.0 and gone.jitter_rms_mm is None
