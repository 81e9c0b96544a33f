"""Neural colour harmonisation (paper 001) on a tiny scene: E's loss falls, D reproduces E's
reference colour on pixels of a frame it was not trained on, the live region LUT matches D,
training is deterministic and resumes from its checkpoint; `volcap harmonise` and
`volcap eval colour --neural` end to end on the small studio bag."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from volcap_color.apply import ImageCorrector, RegionLut
from volcap_color.config import HarmoniseConfig
from volcap_color.correspondence import View, match_pair
from volcap_color.neural import harmonise
from volcap_color.neural_live import bake_region_lut, export_error
from volcap_color.neural_models import load_harmonisation
from volcap_color.neural_nets import CaptureMapper
from volcap_color.neural_train import train
from volcap_core.camera import CameraModel
from volcap_core.color import linear_to_srgb
from volcap_core.poses import look_at

RADIUS = 0.3
GAINS = {'cam0': (1.0, 1.0, 1.0), 'cam1': (0.75, 0.85, 1.1), 'cam2': (1.2, 1.0, 0.8)}


def _view(name: str, eye, turn: float, size=(128, 96), frequency: float = 1.0, crosstalk=None) -> View:
    """A textured sphere at the origin seen from ``eye``; each camera has its own channel gains
    and vignetting (and, given, a ``crosstalk`` matrix after them), and the texture
    (``frequency`` times finer than the default) turns by ``turn`` radians between frames."""
    w, h = size
    cam = CameraModel(w, h, 0.9 * w, 0.9 * w, w / 2, h / 2)
    T = look_at(eye, (0.0, 0.0, 0.0))
    rays = cam.pixel_rays().reshape(-1, 3)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    d_world = rays @ T[:3, :3].T
    o = T[:3, 3]
    b = d_world @ o
    disc = b ** 2 - (o @ o - RADIUS ** 2)
    t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), 0.0)
    p = o + t[:, None] * d_world
    c, s = np.cos(turn), np.sin(turn)
    q = p @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    f = frequency
    albedo = np.stack([0.45 + 0.25 * np.sin(14 * f * q[:, 0]), 0.4 + 0.2 * np.cos(11 * f * q[:, 1]),
                       0.35 + 0.2 * np.sin(9 * f * q[:, 2] + 1)], axis=1)
    u = cam.pixel_rays()[..., :2].reshape(-1, 2)
    vignette = 1.0 - 0.25 * np.sum((u / np.abs(u).max(0)) ** 2, axis=1) / 2
    linear = albedo * np.asarray(GAINS[name]) * vignette[:, None]
    linear = np.clip(linear if crosstalk is None else linear @ np.asarray(crosstalk).T, 0, 1)
    linear[disc <= 0] = 0.05
    color = np.round(linear_to_srgb(linear) * 255).astype(np.uint8).reshape(h, w, 3)
    z = (t * (rays[:, 2])).astype(np.float32)          # depth along the optical axis
    depth = np.where(disc > 0, z, 0.0).astype(np.float32).reshape(h, w)
    return View(name, color, depth, cam, T)


EYES = {'cam0': (1.2, 0.0, 0.2), 'cam1': (0.6, 1.04, 0.1), 'cam2': (0.6, -1.04, 0.3)}


def _sets(frames=2):
    return [[_view(n, e, 0.15 * f) for n, e in EYES.items()] for f in range(frames)]


# the hash grid field (the default) sized for a 0.6 m sphere; a fixed number of steps
TINY = HarmoniseConfig(points=30_000, field_epochs=40, field_batch=1024, grid_levels=8, grid_log2_table=14,
                       grid_cell_mm=8.0, head_width=32, mapper_points=3000, mapper_epochs=60, mapper_batch=256,
                       mapper_width=32, mapper_layers=3, reference="cam0", lut_colors=17, lut_grid=(9, 5),
                       precision='fp32', device='cpu')
# paper 001's MLP field, as small
PAPER_TINY = replace(TINY, field='paper', points=20_000, field_epochs=30, field_batch=500, field_lr=2e-3,
                     field_lr_final=None, field_width=64, point_frequencies=6, camera_frequencies=2)


@pytest.fixture(scope='module')
def trained(tmp_path_factory):
    sets = _sets()
    out = tmp_path_factory.mktemp('neural')
    harm = harmonise(sets[:1], list(GAINS), TINY, out, progress=False)
    return sets, harm, out


def test_the_field_fits_the_cameras_own_held_out_pixels_in_a_fixed_number_of_steps(trained):
    """E reproduces pixels it never saw, of every camera, to within a few levels (the images'
    own noise and rounding are about one level), after a fixed number of steps."""
    _, harm, _ = trained
    e = harm.report['field_error']
    assert e["pixels"] > 500 and set(e['per_camera']) == set(GAINS)
    assert e['rms_levels'] < 4.0 and max(e['per_camera'].values()) < 5.0, e
    assert harm.report['field']['steps'] == TINY.field_epochs * -(-harm.report['field_samples'] // TINY.field_batch)


def test_d_keeps_the_texture_and_maps_onto_the_true_colours(trained):
    """On a textured view D keeps the saturated chroma and the lightness spread of the truth
    within 10 % (the cameras differ only in gains and vignetting, the reference is cam0, so
    the truth is cam0's gains without vignetting)."""
    sets, harm, _ = trained
    from volcap_core.color import srgb_to_lab, srgb_to_linear
    for cam in GAINS:
        view = next(v for v in sets[1] if v.name == cam)
        ok = view.depth.reshape(-1) > 0
        h, w = view.depth.shape
        ys, xs = np.divmod(np.flatnonzero(ok), w)
        xy = np.stack([(xs + 0.5) / w, (ys + 0.5) / h], axis=1)
        rgb = view.color.reshape(-1, 3)[ok] / 255.0
        mapped = harm.map_colors(cam, rgb, xy)
        u = view.camera.pixel_rays()[..., :2].reshape(-1, 2)[ok]
        vignette = 1.0 - 0.25 * np.sum((u / np.abs(view.camera.pixel_rays()[..., :2].reshape(-1, 2)).max(0)) ** 2,
                                       axis=1) / 2
        true_lin = srgb_to_linear(rgb) / (np.asarray(GAINS[cam]) * vignette[:, None]) * np.asarray(GAINS['cam0'])
        lab_m, lab_t = srgb_to_lab(mapped), srgb_to_lab(linear_to_srgb(np.clip(true_lin, 0, 1)))
        chroma_m, chroma_t = np.hypot(*lab_m[:, 1:].T), np.hypot(*lab_t[:, 1:].T)
        sat = chroma_t >= 15
        assert sat.sum() > 200
        assert abs(chroma_m[sat].mean() / chroma_t[sat].mean() - 1) < 0.10, (cam, chroma_m[sat].mean(),
                                                                             chroma_t[sat].mean())
        assert abs(lab_m[:, 0].std() / lab_t[:, 0].std() - 1) < 0.10
        assert np.abs(lab_m - lab_t).mean() < 3.0
        kept = harm.report['texture'][cam]
        assert kept['lightness_kept'] > 0.9 and kept.get('chroma_kept', 1.0) > 0.9, kept


def test_training_lowers_the_loss_and_d_reproduces_e_on_held_out_pixels(trained):
    sets, harm, _ = trained
    field = harm.report['field']['losses']
    assert len(field) == TINY.field_epochs and field[-1] < 0.05 * field[0]
    for cam in GAINS:
        losses = harm.report['mappers'][cam]['losses']
        assert losses[-1] < 2e-3 and losses[-1] < 0.5 * losses[0]     # D starts as the identity
        err = harm.report['mapper_error'][cam]          # pixels of the training frame D did not train on
        assert err['pixels'] > 100 and err['rms_levels'] < 3.0, (cam, err)
    assert harm.report['anchor'] == 'none' and harm.report['reference'] == 'cam0'
    # D brings the cameras' different gains to the reference: on the second (unseen) frame the
    # mapped colours of corresponding pixels agree much better than the raw ones
    for a, b in ((0, 1), (0, 2)):
        va, vb = sets[1][a], sets[1][b]
        m = match_pair(va, vb)
        assert len(m) > 200
        xy_a = (m.pixels_a + 0.5) / (va.camera.width, va.camera.height)
        xy_b = (m.pixels_b + 0.5) / (vb.camera.width, vb.camera.height)
        raw = np.abs(m.colors_a - m.colors_b).mean()
        mapped = np.abs(harm.map_colors(va.name, m.colors_a, xy_a) - harm.map_colors(vb.name, m.colors_b, xy_b))
        assert mapped.mean() < 0.3 * raw, (va.name, vb.name, mapped.mean(), raw)


def test_live_region_lut_matches_d(trained):
    """The live form stays within 0.5 CIEDE2000 of the networks on a frame they never saw."""
    from volcap_core.color import delta_e2000
    sets, harm, _ = trained
    for cam in GAINS:
        lut = bake_region_lut(harm, cam)
        image = next(v.color for v in sets[1] if v.name == cam)
        err = export_error(harm, cam, lut, [image])
        assert err['mean_levels'] < 1.5 and err['p99_levels'] <= 4, (cam, err)
        h, w = image.shape[:2]
        ys, xs = np.mgrid[0:h, 0:w]
        xy = np.stack([(xs.reshape(-1) + 0.5) / w, (ys.reshape(-1) + 0.5) / h], axis=1)
        live = ImageCorrector(lut)(image).reshape(-1, 3) / 255.0
        net = np.clip(harm.map_colors(cam, image.reshape(-1, 3) / 255.0, xy), 0, 1)      # D itself, not rounded
        assert delta_e2000(live, net).mean() < 0.5, cam
    # the uint8 kernel and the float interpolation used for scoring are the same function
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (30, 50, 3), dtype=np.uint8)
    fast = ImageCorrector(lut)(image).reshape(-1, 3).astype(int)
    ys, xs = np.mgrid[0:30, 0:50]
    xy = np.stack([(xs.reshape(-1) + 0.5) / 50, (ys.reshape(-1) + 0.5) / 30], axis=1)
    exact = np.round(lut.apply_points(image.reshape(-1, 3) / 255.0, xy) * 255).astype(int)
    assert np.abs(fast - exact).max() <= 1


def test_region_lut_rejects_bad_tables_and_files(tmp_path):
    with pytest.raises(ValueError, match='ny, nx'):
        RegionLut(np.zeros((5, 5, 5, 3), np.float32))
    with pytest.raises(ValueError, match='non-finite'):
        RegionLut(np.full((2, 2, 2, 2, 2, 3), np.nan, np.float32))
    bad = tmp_path / 'cam0.lut.npz'
    bad.write_bytes(b'not a zip file')
    with pytest.raises(ValueError, match='not a region LUT'):
        RegionLut.load(bad)


def test_training_is_deterministic_and_resumes_from_its_checkpoint(tmp_path):
    rng = np.random.default_rng(0)
    x = torch.as_tensor(rng.random((600, 3), dtype=np.float32))
    xy = torch.as_tensor(rng.random((600, 2), dtype=np.float32))
    y = torch.sigmoid(x @ torch.tensor([[1.5, -0.5, 0.2], [0.3, 1.0, -0.4], [0.0, 0.2, 1.2]]))

    def run(epochs, checkpoint=None):
        torch.manual_seed(4)
        m = CaptureMapper(16, 3)
        r = train(m, (x, xy), y, epochs=epochs, batch=100, lr=3e-3, seed=9, bf16=False, label='D test',
                  checkpoint=checkpoint, progress=False)
        return m, r
    a, ra = run(4)
    b, _ = run(4)
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    ck = tmp_path / 'checkpoint.pt'
    _, first = run(2, ck)                  # "interrupted" after two epochs
    assert ck.exists() and len(first.losses) == 2
    with pytest.raises(ValueError, match='other settings'):
        train(CaptureMapper(16, 3), (x, xy), y, epochs=4, batch=100, lr=3e-3, seed=9, bf16=False, label='D test',
              checkpoint=ck, settings={'mapper_width': 32}, progress=False)
    c, rc = run(4, ck)                     # a fresh model resumes from the checkpoint
    assert rc.losses == pytest.approx(ra.losses, rel=1e-6)
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), c.state_dict().values()))


def test_harmonise_resumes_after_the_networks_it_finished(trained):
    sets, harm, out = trained
    again = harmonise(sets[:1], list(GAINS), TINY, out, resume=True, progress=False)
    assert again.report['field'] == harm.report['field'] and again.report['mappers'] == harm.report['mappers']
    for a, b in [(harm.field, again.field)] + [(harm.mappers[c], again.mappers[c]) for c in GAINS]:
        assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    from dataclasses import replace
    with pytest.raises(ValueError, match='other settings'):
        harmonise(sets[:1], list(GAINS), replace(TINY, field_epochs=61), out, resume=True, progress=False)


def test_the_papers_field_still_trains(tmp_path):
    """``field='paper'``: paper 001's MLP with positional encoding, for reproduction."""
    # only E is checked here: each camera's D gets one epoch
    harm = harmonise(_sets(1), list(GAINS), replace(PAPER_TINY, mapper_epochs=1, lut_colors=5, lut_grid=(2, 2)),
                     tmp_path, progress=False)
    losses = harm.report['field']['losses']
    assert len(losses) == PAPER_TINY.field_epochs and losses[-1] < 0.2 * losses[0]
    assert type(harm.field).__name__ == 'ColorField'


def test_the_reference_is_anchored_to_the_charts_or_grey_world(tmp_path):
    """With a chart model per camera the reference is anchored to each camera's view through its
    chart model, averaged: a cast every camera shares (here the charts say the truth is 20 % less
    red than every camera records) is taken out; without charts ``grey_world`` balances the
    scene average; asking for charts that the calibration lacks is a clear error."""
    from volcap_color.neural_train import Reference
    from volcap_core.color import ColorModel
    sets = _sets(1)
    cfg = replace(TINY, reference='mean', field_epochs=20, mapper_epochs=2)
    less_red = {c: ColorModel('matrix_3x3', np.diag([0.8, 1.0, 1.0])) for c in GAINS}
    harm = harmonise(sets, list(GAINS), replace(cfg, anchor='auto'), tmp_path / 'chart', progress=False,
                     chart_models=less_red)
    assert harm.report['anchor'] == 'chart'
    points = torch.as_tensor(np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32) * 0.1)
    plain = Reference(harm.field, harm.reference_centres(), False)(points).numpy()
    charted = Reference(harm.field, harm.reference_centres(), False, [less_red[c] for c in GAINS])(points).numpy()
    from volcap_core.color import srgb_to_linear
    ratio = srgb_to_linear(charted).mean(0) / srgb_to_linear(plain).mean(0)
    assert ratio == pytest.approx([0.8, 1.0, 1.0], abs=0.02)
    # harmonise's own reference: the average camera through the gains that take it onto the
    # charts' average (here the charts' shared cast), at the cameras' own exposure
    anchor = np.asarray(harm.report['anchor_matrix'])
    assert anchor / anchor[1, 1] == pytest.approx(np.diag([0.8, 1.0, 1.0]), abs=0.03)
    assert anchor[1, 1] == pytest.approx(1.0, abs=0.1)
    # charts that saturate every colour (grey kept grey), as a chart's patches read under mixed
    # lights and the board's sheen: the gains take none of it into the reference, the full 3x3
    # (``anchor_fit='matrix_3x3'``) does; a red cast comes through both
    from volcap_color.neural_train import chart_anchor_matrix
    saturating = np.full((3, 3), -0.05) + np.diag([1.15] * 3)
    cast = {c: ColorModel('matrix_3x3', np.diag([0.8, 1.0, 1.0]) @ saturating) for c in GAINS}
    reference = Reference(harm.field, harm.reference_centres(), False)
    gains = chart_anchor_matrix(reference, [cast[c] for c in GAINS], points, 'gains')
    assert gains == pytest.approx(np.diag(np.diag(gains)))
    assert np.diag(gains) / gains[1, 1] == pytest.approx([0.8, 1.0, 1.0], abs=0.02)
    full = chart_anchor_matrix(reference, [cast[c] for c in GAINS], points, 'matrix_3x3')
    assert full / full[1, 1] == pytest.approx(np.diag([0.8, 1.0, 1.0]) @ saturating / saturating[1, 1], abs=0.02)
    grey = harmonise(sets, list(GAINS), replace(cfg, anchor='grey_world'), tmp_path / 'grey', progress=False)
    assert grey.report['anchor'] == 'grey_world' and len(grey.report['anchor_gains']) == 3
    with pytest.raises(ValueError, match='no chart colour model for cam1'):
        harmonise(sets, list(GAINS), replace(cfg, anchor='chart'), tmp_path / 'x', progress=False,
                  chart_models={'cam0': less_red['cam0']})


CROSSTALK = {'cam0': np.eye(3), 'cam1': [[0.88, 0.12, 0.0], [0.0, 0.9, 0.1], [0.1, 0.0, 0.9]],
             'cam2': [[0.92, 0.0, 0.08], [0.1, 0.86, 0.04], [0.0, 0.12, 0.88]]}


def test_a_response_unmixed_is_the_same_camera_without_its_crosstalk():
    """``CameraResponse(..., mixed=False)``, the reference's view of a camera: everything the
    camera does (gains, fall-off, tone curve) but the crosstalk a chart measured."""
    from volcap_color.neural_nets import CameraResponse
    torch.manual_seed(0)
    mixed = CameraResponse(3)
    with torch.no_grad():
        mixed.gains.copy_(torch.rand(3, 3) + 0.5)
        mixed.falloff.copy_(torch.rand(3, 3) * -0.2)
    mixed.set_crosstalk(np.stack([np.asarray(CROSSTALK[c], np.float32) for c in ('cam0', 'cam1', 'cam2')]))
    plain = CameraResponse(3)
    plain.load_state_dict({**mixed.state_dict(), 'crosstalk': torch.eye(3).repeat(3, 1, 1)})
    linear, xy = torch.rand(200, 3) * 0.8, torch.rand(200, 2)
    camera = torch.arange(200) % 3
    assert torch.allclose(mixed(linear, camera, xy, mixed=False), plain(linear, camera, xy))
    differs = ~torch.isclose(mixed(linear, camera, xy), plain(linear, camera, xy), atol=1e-3).all(1)
    assert differs[camera > 0].float().mean() > 0.9 and not differs[camera == 0].any()     # cam0 has none


def test_a_chart_models_crosstalk_is_the_camera_matrix_without_its_gains():
    """The chart model of a camera that mixes its channels by M after gains d is (M diag d)^-1;
    ``chart_crosstalk`` gives M back (rows summing to 1) for every linear-light model form."""
    from volcap_color.neural import chart_crosstalk
    from volcap_core.color import ColorModel
    m, d = np.asarray(CROSSTALK['cam2']), np.array([0.7, 1.1, 1.3])
    inverse = np.linalg.inv(m @ np.diag(d))
    assert chart_crosstalk(ColorModel('matrix_3x3', inverse)) == pytest.approx(m, abs=1e-6)
    affine = ColorModel('affine_3x4', np.hstack([inverse, [[0.01], [0.0], [-0.02]]]))
    assert chart_crosstalk(affine) == pytest.approx(m, abs=1e-6)
    assert chart_crosstalk(ColorModel('paper_diagonal', np.diag([1.2, 1.0, 0.9]))) == pytest.approx(np.eye(3))
    assert chart_crosstalk(ColorModel('matrix_3x3', np.zeros((3, 3)))) == pytest.approx(np.eye(3))


def test_d_undoes_the_crosstalk_the_charts_measured(tmp_path):
    """Cameras whose channels mix differently (10 %): E's gains and tone curves cannot say how,
    and D's colour-dependent gains cannot undo a matrix, so without the charts' crosstalk every
    camera but cam0 (which has none) keeps its mixing (3-4 a* b* units off the truth). With it
    E's responses hold the mixing, the reference leaves it out, D undoes it first, and every
    camera maps onto the truth (the albedo, since the reference is the charts') several times
    closer."""
    from volcap_core.color import ColorModel, srgb_to_lab, srgb_to_linear
    sets = [[_view(n, e, 0.15 * f, crosstalk=CROSSTALK[n]) for n, e in EYES.items()] for f in range(2)]
    charts = {c: ColorModel('matrix_3x3', np.linalg.inv(np.asarray(CROSSTALK[c]) @ np.diag(GAINS[c])))
              for c in GAINS}
    cfg = replace(TINY, anchor='chart', reference='mean', points=15_000, field_epochs=30, mapper_epochs=30)
    errors = {}
    for fixed in (True, False):
        harm = harmonise(sets[:1], list(GAINS), replace(cfg, crosstalk_from_chart=fixed), tmp_path / str(fixed),
                         progress=False, chart_models=charts)
        assert (harm.report['crosstalk'] is not None) == fixed
        # the reference (gains on the charts) is the cameras without the mixing the charts measured
        assert harm.report['reference_unmixed'] == fixed
        if fixed:
            assert np.asarray(harm.report['crosstalk']['cam1']) == pytest.approx(np.asarray(CROSSTALK['cam1']), abs=1e-3)
        worst = 0.0
        for view in sets[1]:
            ok = view.depth.reshape(-1) > 0
            h, w = view.depth.shape
            ys, xs = np.divmod(np.flatnonzero(ok), w)
            xy = np.stack([(xs + 0.5) / w, (ys + 0.5) / h], axis=1)
            rgb = view.color.reshape(-1, 3)[ok] / 255.0
            u = view.camera.pixel_rays()[..., :2].reshape(-1, 2)
            vignette = (1.0 - 0.25 * np.sum((u / np.abs(u).max(0)) ** 2, axis=1) / 2)[ok]
            true_lin = charts[view.name].apply_linear(srgb_to_linear(rgb)) / vignette[:, None]
            mapped = harm.map_colors(view.name, rgb, xy)
            # the charts' reference is the albedo itself; a* b* carry what the mixing does
            worst = max(worst, float(np.abs(srgb_to_lab(mapped) - srgb_to_lab(
                linear_to_srgb(np.clip(true_lin, 0, 1))))[:, 1:].mean()))
        errors[fixed] = worst
    assert errors[True] < 1.0 and errors[True] * 4 < errors[False], errors


def test_harmonise_rejects_an_unknown_reference(tmp_path):
    with pytest.raises(ValueError, match='reference'):
        harmonise(_sets(1), list(GAINS), HarmoniseConfig(reference='cam9'), tmp_path, progress=False)
    with pytest.raises(FileNotFoundError, match='manifest'):
        load_harmonisation(tmp_path)




def test_models_written_before_the_color_spelling_still_load(trained, tmp_path):
    """A harmonise folder's manifest from before identifiers were spelt "color" says lut_colours."""
    import json
    import shutil
    sets, harm, out = trained
    old = tmp_path / 'models'
    shutil.copytree(out, old)
    report = json.loads(json.dumps(harm.report))
    report['config']['lut_colours'] = report['config'].pop('lut_colors')
    (old / 'manifest.json').write_text(json.dumps(report))
    loaded = load_harmonisation(old)
    assert loaded.config == harm.config
    rgb, xy = np.full((4, 3), 0.5, np.float32), np.full((4, 2), 0.5, np.float32)
    assert np.allclose(loaded.map_colors('cam1', rgb, xy), harm.map_colors('cam1', rgb, xy), atol=1e-5)
    # and one from before D's gain form has its D in the logit form it was trained in
    report['config'].pop('mapper_form')
    (old / 'manifest.json').write_text(json.dumps(report))
    assert {m.form for m in load_harmonisation(old).mappers.values()} == {'logit'}
    # and one from before the charts' crosstalk: E's response and D without their fixed matrices
    report['config']['mapper_form'] = harm.config.mapper_form
    (old / 'manifest.json').write_text(json.dumps(report))
    for name, key in (('field.pt', 'response.crosstalk'), *((f'{c}.mapper.pt', 'unmix') for c in GAINS)):
        saved = torch.load(old / name, weights_only=False)
        del saved['state'][key]
        torch.save(saved, old / name)
    loaded = load_harmonisation(old)
    assert np.allclose(loaded.map_colors('cam1', rgb, xy), harm.map_colors('cam1', rgb, xy), atol=1e-5)


def test_the_hash_grid_field_trains_deterministically_and_resumes(tmp_path):
    """The hash grid's scatter-add backward is deterministic on the CPU: two runs, and a run
    resumed from its checkpoint, give the same weights."""
    from volcap_color.neural_nets import HashGridField
    rng = np.random.default_rng(1)
    points = torch.as_tensor(rng.random((2000, 3), dtype=np.float32))
    centres = np.array([[2.0, 0, 0], [0, 2.0, 0]], np.float32)
    cams = torch.as_tensor(centres[rng.integers(0, 2, 2000)])
    xy = torch.as_tensor(rng.random((2000, 2), dtype=np.float32))
    target = torch.as_tensor(rng.random((2000, 3), dtype=np.float32))

    def run(epochs, checkpoint=None):
        torch.manual_seed(5)
        field = HashGridField(np.zeros(3), 1.0, centres, levels=4, log2_table=10, coarsest=4, finest=32, width=16)
        train(field, (points, cams, xy), target, epochs=epochs, batch=256, lr=1e-2, seed=3, bf16=False,
              label='E test', checkpoint=checkpoint, progress=False)
        return field
    a, b = run(3), run(3)
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    ck = tmp_path / 'checkpoint.pt'
    run(1, ck)
    c = run(3, ck)
    assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), c.state_dict().values()))


def test_hash_grid_interpolates_trilinearly_like_scipy():
    """A level whose grid fits its table is indexed densely: its encoding is the trilinear
    interpolation of the table laid out as the grid (checked against scipy); a finer level is
    hashed into its table (Instant-NGP's primes), every index within it."""
    from scipy.interpolate import RegularGridInterpolator

    from volcap_color.neural_nets import HashGrid
    grid = HashGrid(levels=2, log2_table=12, coarsest=8, finest=64, features=2)
    with torch.no_grad():
        grid.table.copy_(torch.as_tensor(np.random.default_rng(2).normal(size=grid.table.shape).astype(np.float32)))
    assert grid.dense.tolist() == [True, False]
    points = np.random.default_rng(3).random((500, 3)).astype(np.float32)
    with torch.no_grad():
        encoded = grid(torch.as_tensor(points)).numpy()
    dense = grid.table.detach().numpy()[:9 ** 3].reshape(9, 9, 9, 2)       # [z][y][x]: index x + 9 y + 81 z
    axis = np.arange(9)
    for f in range(2):
        expected = RegularGridInterpolator((axis, axis, axis), dense[..., f])(points[:, ::-1] * 8)
        assert np.allclose(encoded[:, f], expected, atol=1e-5)
    assert np.isfinite(encoded[:, 2:]).all() and np.abs(encoded[:, 2:]).max() > 0


def test_the_field_registers_a_misregistered_view(tmp_path):
    """One camera's pose is off by 0.2 deg about its centre, so the fine texture it sees lands
    about 4 mm from where the others put it: E learns that view's correction, pointing back at
    the true pose, and reproduces that camera's held-out pixels better than without it."""
    from scipy.spatial.transform import Rotation

    views = [_view(n, e, 0.0, size=(192, 144), frequency=6.0) for n, e in EYES.items()]
    tilt = np.radians(0.2) * np.array([0.0, 0.6, 0.8])
    T = views[1].T_world_camera.copy()
    T[:3, :3] = Rotation.from_rotvec(tilt).as_matrix() @ T[:3, :3]
    views[1] = View(views[1].name, views[1].color, views[1].depth, views[1].camera, T)
    # only E is checked here: each camera's D gets one epoch (its 60 took 6 s of the 20 s run)
    cfg = replace(TINY, reference='mean', grid_cell_mm=4.0, grid_log2_table=16, points=60_000, mapper_epochs=1,
                  lut_colors=5, lut_grid=(2, 2))
    with_reg = harmonise([views], list(GAINS), cfg, tmp_path / 'on', progress=False)
    without = harmonise([views], list(GAINS), replace(cfg, register_views=False), tmp_path / 'off', progress=False)
    on, off = with_reg.report['field_error']['per_camera'], without.report['field_error']['per_camera']
    assert on['cam1'] < 0.8 * off['cam1'], (on, off)
    # cam1's surface points as its wrong pose puts them, moved by its correction, against where
    # the other views' corrections put the true points (the rig as a whole may move a little)
    field, true_view = with_reg.field, _view('cam1', EYES['cam1'], 0.0, size=(192, 144), frequency=6.0)
    ok = true_view.depth.reshape(-1) > 0
    local = true_view.rays().reshape(-1, 3)[ok] * true_view.depth.reshape(-1)[ok, None]
    truth = torch.as_tensor(local @ true_view.T_world_camera[:3, :3].T + T[:3, 3], dtype=torch.float32)
    wrong = torch.as_tensor(local @ T[:3, :3].T + T[:3, 3], dtype=torch.float32)
    with torch.no_grad():
        moved = field.register(wrong, torch.as_tensor(T[:3, 3], dtype=torch.float32).expand(len(wrong), 3))
        gauge = torch.stack([field.register(truth, torch.as_tensor(v.T_world_camera[:3, 3], dtype=torch.float32)
                                            .expand(len(truth), 3)) - truth for v in (views[0], views[2])]).mean(0)
    before = (wrong - truth).norm(dim=1).mean()
    after = (moved - truth - gauge).norm(dim=1).mean()
    assert after < 0.5 * before, (float(before), float(after))
    reg = with_reg.report['registration']
    assert set(reg) == set(GAINS) and max(reg, key=lambda c: reg[c]['translation_mm']) == 'cam1', reg
    assert not np.any(without.field.registration.detach().numpy())


def test_the_finest_cells_follow_the_views_pixel_footprint():
    """By default the hash grid's finest cells are the median pixel footprint on the surface
    (depth over focal length), never finer than 1 mm; the manifest says which was used."""
    from volcap_color.neural import MIN_CELL_MM, pixel_footprint_mm
    cam = CameraModel(64, 48, 500.0, 500.0, 32, 24)
    color = np.zeros((48, 64, 3), np.uint8)
    view = lambda z: View('cam0', color, np.full((48, 64), z, np.float32), cam, np.eye(4))
    assert pixel_footprint_mm([view(1.0), view(1.5), view(2.0)]) == pytest.approx(3.0)
    assert pixel_footprint_mm([view(0.2)]) == MIN_CELL_MM


def test_a_saturated_colour_is_taken_at_the_cameras_clip_level():
    """``CameraResponse.unclipped``: where a camera records a colour saturated, the brightest
    colour it records below saturation; a colour it records unclipped is left alone."""
    from volcap_color.neural_nets import SATURATED, CameraResponse
    response = CameraResponse(1)
    with torch.no_grad():
        response.gains.copy_(torch.tensor([[1.6, 1.0, 0.7]]))
    linear = torch.tensor([[0.9, 0.9, 0.9], [0.3, 0.3, 0.3]])
    camera, xy = torch.zeros(2, dtype=torch.long), torch.full((2, 2), 0.5)
    with torch.no_grad():
        recorded = response(linear, camera, xy)
        kept = response.unclipped(linear, camera, xy)
        at_clip = response(kept, camera, xy)
    assert recorded[0, 0] >= SATURATED and recorded[0, 2] < SATURATED
    from volcap_core.color import srgb_to_linear
    # red: where 1.6 x reaches the level that rounds to white (the tone curve starts as sRGB's)
    assert kept[0, 0] == pytest.approx(srgb_to_linear(SATURATED) / 1.6, rel=2e-3)
    assert torch.equal(kept[0, 1:], linear[0, 1:]) and torch.equal(kept[1], linear[1])
    assert SATURATED - 0.01 < at_clip[0, 0] < SATURATED


def test_d_in_gains_maps_a_saturated_pixel_as_the_camera_recorded_it():
    """D's gain form starts as the identity, and learns a camera that saturates (a gain of 1.4
    in linear light, clipped at white) mapped onto its true colour up to white: a clipped pixel
    goes where the brightest unclipped one goes, within a few levels (the logit form's
    correction would have to change steeply at white)."""
    from volcap_core.color import srgb_to_linear
    rng = np.random.default_rng(3)
    true = rng.random((6000, 3)).astype(np.float32) * 0.9
    recorded = linear_to_srgb(np.clip(srgb_to_linear(true) * 1.4, 0, 1)).astype(np.float32)
    target = linear_to_srgb(np.minimum(srgb_to_linear(true), 1 / 1.4)).astype(np.float32)   # at the clip level
    xy = rng.random((6000, 2)).astype(np.float32)
    torch.manual_seed(0)
    mapper = CaptureMapper(32, 3)
    mapper.eval()
    probe = torch.tensor([[0.2, 0.5, 0.8], [1.0, 1.0, 1.0]])
    with torch.no_grad():
        assert torch.allclose(mapper(probe, torch.full((2, 2), 0.5)), probe, atol=1e-5)
    train(mapper, (torch.as_tensor(recorded), torch.as_tensor(xy)), torch.as_tensor(target), epochs=30, batch=256,
          lr=3e-3, seed=1, bf16=False, label='D gain', progress=False)
    with torch.no_grad():
        white = mapper(torch.ones(1, 3), torch.full((1, 2), 0.5))[0].numpy() * 255
    assert np.abs(white - linear_to_srgb(np.full(3, 1 / 1.4)) * 255).max() < 3.0


def test_the_torch_srgb_curves_match_colour_science():
    """D's gain form converts with hand-written torch sRGB curves (colour-science works on
    numpy); they must agree with ``volcap_core.color``'s, which call colour-science."""
    from volcap_color.neural_nets import linear_to_srgb as torch_encode
    from volcap_color.neural_nets import srgb_to_linear as torch_decode
    from volcap_core.color import srgb_to_linear
    v = np.linspace(0.0, 1.0, 2001)
    assert np.allclose(torch_decode(torch.as_tensor(v)).numpy(), srgb_to_linear(v), atol=1e-7)
    assert np.allclose(torch_encode(torch.as_tensor(v)).numpy(), linear_to_srgb(v), atol=1e-7)


def test_no_crosstalk_leaves_the_responses_and_d_exact_under_bf16_autocast():
    """Without charts the crosstalk and D's unmixing are the identity and change nothing, bit for
    bit, also under the bf16 autocast the CPU and CUDA train with (a matrix product there would
    round every colour to bf16: rgbd_box's E went from 17.8 to 20.0 levels RMS)."""
    from volcap_color.neural_nets import CameraResponse, linear_to_srgb, srgb_to_linear
    rng = np.random.default_rng(0)
    linear = torch.as_tensor(rng.uniform(0.0, 1.0, (4096, 3)).astype(np.float32))
    xy = torch.as_tensor(rng.uniform(0.0, 1.0, (4096, 2)).astype(np.float32))
    camera = torch.as_tensor(rng.integers(0, 3, 4096))
    response = CameraResponse(3)
    with torch.no_grad():
        response.gains.mul_(torch.as_tensor(rng.uniform(0.7, 1.3, (3, 3)).astype(np.float32)))
        plain = response(linear, camera, xy)
        with torch.autocast('cpu', dtype=torch.bfloat16):
            autocast = response(linear, camera, xy)
    assert torch.equal(plain, autocast)
    mapper = CaptureMapper(16, 2, 'gain')
    torch.nn.init.normal_(mapper.rgb.weight, std=0.1)
    mapper.eval()
    rgb = linear_to_srgb(linear)
    with torch.no_grad(), torch.autocast('cpu', dtype=torch.bfloat16):
        mapped = mapper(rgb, xy)
        h = torch.cat([rgb, xy], dim=-1)
        for layer in mapper.hidden:
            h = torch.relu(layer(h))
        expected = linear_to_srgb(srgb_to_linear(rgb) * torch.exp(mapper.rgb(h))).clamp(0.0, 1.0)
    assert torch.equal(mapped, expected)
    # with crosstalk the mixing stays in fp32 too (bf16 would be 2^-9 of the colour off)
    unmix = np.linalg.inv(np.asarray(CROSSTALK['cam1']))
    with torch.no_grad():
        response.set_crosstalk(np.stack([np.asarray(CROSSTALK[c], np.float32) for c in GAINS]))
        mapper.unmix.copy_(torch.as_tensor(unmix, dtype=torch.float32))
        plain = response(linear, camera, xy)
        with torch.autocast('cpu', dtype=torch.bfloat16):
            assert torch.equal(response(linear, camera, xy), plain)
            unmixed = torch.as_tensor(srgb_to_linear(rgb).double().numpy() @ unmix.T, dtype=torch.float32)
            expected = linear_to_srgb(unmixed * torch.exp(mapper.rgb(h))).clamp(0.0, 1.0)
            assert torch.allclose(mapper(rgb, xy), expected, rtol=0, atol=1e-5)
