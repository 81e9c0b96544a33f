"""The neural harmonisation composed with the fusion (``volcap_pipeline.harmonise``): views that
disagree about where the subject is are put on the surface they fuse to, pixels far from it are
left out, and the training runs on what it gives."""
from dataclasses import replace

import numpy as np
import pytest

from volcap_color.config import HarmoniseConfig
from volcap_color.correspondence import View
from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput
from volcap_core.poses import look_at
from volcap_pipeline.harmonise import FusedSurface, SurfaceConfig, run, surface_of

RADIUS = 0.3
LENS = CameraModel(320, 240, 280.0, 280.0, 159.5, 119.5, (0.1, -0.05, 0.0, 0.0, 0.0))
# a view's depth is this far behind (+) or before the true surface (mm): calibrated real
# cameras disagree by a few millimetres
BIAS_MM = {f'cam{k}': b for k, b in enumerate((3.0, -3.0, 2.0, -2.0, 3.0, -2.0, 2.0, -3.0))}


def _view(name: str, azimuth: float, rng: np.random.Generator, noise_mm: float = 1.0) -> tuple[View, np.ndarray]:
    """A textured sphere at the origin seen through ``LENS`` from 1.2 m: the view (its depth off
    by ``BIAS_MM`` and noise) and the true depth."""
    eye = 1.2 * np.array([np.cos(azimuth), np.sin(azimuth), 0.1])
    T = look_at(eye, np.zeros(3))
    rays = LENS.pixel_rays() @ T[:3, :3].T
    b = np.einsum('hwc,c->hw', rays, eye)
    a = np.einsum('hwc,hwc->hw', rays, rays)
    disc = b * b - a * (eye @ eye - RADIUS ** 2)
    hit = disc > 0
    true = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / a, 0.0)
    p = eye + rays * true[..., None]
    texture = np.stack([0.5 + 0.3 * np.sin(20 * p[..., 0]), 0.5 + 0.3 * np.cos(17 * p[..., 1]),
                        0.5 + 0.3 * np.sin(13 * p[..., 2])], axis=-1)
    color = np.where(hit[..., None], np.round(255 * texture), 20).astype(np.uint8)
    depth = true + (BIAS_MM[name] + noise_mm * rng.standard_normal(true.shape)) / 1000
    return View(name, color, np.where(hit, depth, 0).astype(np.float32), LENS, T), true.astype(np.float32)


def _views(seed: int = 0):
    rng = np.random.default_rng(seed)
    pairs = [_view(name, k * 2 * np.pi / len(BIAS_MM), rng) for k, name in enumerate(BIAS_MM)]
    return [v for v, _ in pairs], [t for _, t in pairs]


def _disagreement(a: View, b: View) -> float:
    """Median distance (m) along b's rays between a's points and b's depth where b sees them."""
    ys, xs = np.nonzero(a.depth > 0)
    world = (a.camera.pixel_rays()[ys, xs] * a.depth[ys, xs, None]) @ a.T_world_camera[:3, :3].T \
        + a.T_world_camera[:3, 3]
    T = np.linalg.inv(b.T_world_camera)
    local = world @ T[:3, :3].T + T[:3, 3]
    px = np.round(b.camera.project(local)).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < b.camera.width) & (px[:, 1] >= 0) & (px[:, 1] < b.camera.height)
    there = b.depth[px[inside, 1], px[inside, 0]]
    near = (there > 0) & (np.abs(there - local[inside, 2]) < 0.02)      # seen by b, not occluded
    return float(np.median(np.abs(there - local[inside, 2])[near]))


def test_views_that_disagree_are_put_on_the_surface_they_fuse_to():
    views, _ = _views()
    moved, report = FusedSurface(SurfaceConfig(surface_voxel_mm=4.0))(views)
    assert [v.name for v in moved] == [v.name for v in views] and report['source'] == 'fused'
    for v, m in zip(views, moved):
        assert (m.depth > 0).sum() > 0.95 * (v.depth > 0).sum(), v.name              # measured 99 %
        assert np.array_equal(m.color, v.color) and np.array_equal(m.T_world_camera, v.T_world_camera)
    for a, b in zip(range(8), (1, 2, 3, 4, 5, 6, 7, 0)):
        own, fused = _disagreement(views[a], views[b]), _disagreement(moved[a], moved[b])
        # measured: 4.4-6.7 mm between neighbouring views' own depth, 0.82-0.85 mm on the fused
        # surface (what the nearest-pixel lookup itself costs on a surface seen at 45 degrees)
        assert fused < 0.25 * own and fused < 0.0012, (views[a].name, views[b].name, own, fused)
    kept = {r['view']: r['kept'] for r in report['views']}
    assert min(kept.values()) > 0.95 and report['triangles'] > 0


def test_pixels_far_from_the_fused_surface_are_left_out():
    views, _ = _views(1)
    h, w = views[0].depth.shape
    patch = (slice(h // 2 - 10, h // 2 + 10), slice(w // 2 - 10, w // 2 + 10))
    views[0].depth[patch] += 0.05                      # a flying patch 5 cm behind the subject
    moved, report = FusedSurface(SurfaceConfig(surface_voxel_mm=4.0, surface_agree_mm=20.0))(views)
    assert (moved[0].depth[patch] == 0).all()
    assert (moved[0].depth > 0).sum() > 0.9 * (views[0].depth > 0).sum()
    kept = report['views'][0]['kept']
    assert kept < 1 - 400 / (views[0].depth > 0).sum() + 1e-9


def test_nothing_to_fuse_leaves_every_pixel_out_and_the_choice_is_checked():
    views, _ = _views()
    empty = [View(v.name, v.color, np.zeros_like(v.depth), v.camera, v.T_world_camera) for v in views]
    moved, report = FusedSurface(SurfaceConfig(surface_voxel_mm=4.0))(empty)
    assert all((m.depth == 0).all() for m in moved) and report['triangles'] == 0
    assert surface_of(SurfaceConfig(surface='views')) is None
    with pytest.raises(BadInput):
        surface_of(SurfaceConfig(surface='mesh'))


TINY = HarmoniseConfig(points=20_000, field_epochs=3, field_batch=1024, grid_levels=6, grid_log2_table=12,
                       grid_cell_mm=8.0, head_width=16, mapper_points=2000, mapper_epochs=3, mapper_batch=256,
                       mapper_width=16, mapper_layers=2, reference='mean', lut_colors=9, lut_grid=(5, 3),
                       precision='fp32', device='cpu')


def test_the_harmonisation_trains_on_the_fused_surface(tmp_path):
    """`volcap harmonise`'s composition: the manifest says where the pixels lay and the report
    says so; E's training pixels are the surface's (a surface keeping half a view's pixels
    leaves E fewer samples)."""
    sets = [_views(0)[0], _views(1)[0]]
    cameras = list(BIAS_MM)
    report = run(sets, cameras, replace(TINY, points=None), tmp_path / 'fused', SurfaceConfig(surface_voxel_mm=4.0),
                 progress=False)
    surface = report.manifest['surface']
    assert surface['source'] == 'fused' and len(surface['frame_sets']) == 1       # 'even': the 1st set trains
    assert min(v['kept'] for v in surface['frame_sets'][0]['views']) > 0.95
    assert any(line.startswith('training pixels on the fused surface') for line in report.lines())
    assert not any('WARNING' in line for line in report.lines())
    # a camera few of whose pixels lie on the surface (a wrong pose) is named
    import copy

    from volcap_color.neural import HarmoniseReport
    manifest = copy.deepcopy(report.manifest)
    manifest['surface']['frame_sets'][0]['views'][2]['kept'] = 0.3
    warned = [line for line in HarmoniseReport(manifest, cameras, report.out_dir).lines() if 'WARNING' in line]
    assert len(warned) == 1 and warned[0].startswith('WARNING: cam2: only 30%')
    own = run(sets, cameras, replace(TINY, points=None), tmp_path / 'views', SurfaceConfig(surface='views'),
              progress=False)
    assert own.manifest['surface']['source'] == 'views'
    # the fused surface leaves out the few pixels off it (the sphere's rim), so E gets fewer samples
    assert 0.95 * own.manifest['field_samples'] < report.manifest['field_samples'] < own.manifest['field_samples']

    from volcap_color import neural

    def left_half(views):
        out = []
        for v in views:
            d = v.depth.copy()
            d[:, d.shape[1] // 2:] = 0
            out.append(View(v.name, v.color, d, v.camera, v.T_world_camera))
        return out, {'source': 'left half', 'views': []}
    left_half.settings = {'half': 'left'}
    half = neural.run(sets, cameras, replace(TINY, points=None), tmp_path / 'half', progress=False, surface=left_half)
    assert half.manifest['surface']['source'] == 'left half'
    assert half.manifest['field_samples'] < 0.7 * own.manifest['field_samples']
    # networks trained on one surface are not resumed on another
    with pytest.raises(BadInput, match='other settings'):
        run(sets, cameras, replace(TINY, points=None), tmp_path / 'fused', SurfaceConfig(surface='views'),
            progress=False, resume=True)
