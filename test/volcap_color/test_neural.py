"""Neural colour harmonisation (paper 001) on a tiny scene: E's loss falls, D reproduces E's
reference colour on pixels of a frame it was not trained on, the live region LUT matches D,
training is deterministic and resumes from its checkpoint; `volcap harmonise` and
`volcap eval colour --neural` end to end on the small studio bag."""

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


def _view(name: str, eye, turn: float, size=(128, 96)) -> View:
    """A textured sphere at the origin seen from ``eye``; each camera has its own channel gains
    and vignetting, and the texture turns by ``turn`` radians between frames."""
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
    albedo = np.stack([0.45 + 0.25 * np.sin(14 * q[:, 0]), 0.4 + 0.2 * np.cos(11 * q[:, 1]),
                       0.35 + 0.2 * np.sin(9 * q[:, 2] + 1)], axis=1)
    u = cam.pixel_rays()[..., :2].reshape(-1, 2)
    vignette = 1.0 - 0.25 * np.sum((u / np.abs(u).max(0)) ** 2, axis=1) / 2
    linear = np.clip(albedo * np.asarray(GAINS[name]) * vignette[:, None], 0, 1)
    linear[disc <= 0] = 0.05
    color = np.round(linear_to_srgb(linear) * 255).astype(np.uint8).reshape(h, w, 3)
    z = (t * (rays[:, 2])).astype(np.float32)          # depth along the optical axis
    depth = np.where(disc > 0, z, 0.0).astype(np.float32).reshape(h, w)
    return View(name, color, depth, cam, T)


def _sets(frames=2):
    eyes = {'cam0': (1.2, 0.0, 0.2), 'cam1': (0.6, 1.04, 0.1), 'cam2': (0.6, -1.04, 0.3)}
    return [[_view(n, e, 0.15 * f) for n, e in eyes.items()] for f in range(frames)]


TINY = HarmoniseConfig(points=30_000, field_epochs=60, field_batch=1000, field_lr=2e-3, field_width=64,
                       point_frequencies=6, camera_frequencies=2, mapper_points=1500, mapper_epochs=60,
                       mapper_batch=100, mapper_lr=2e-3, mapper_width=64, mapper_layers=4, reference='cam0',
                       lut_colors=17, lut_grid=(5, 4), precision='fp32', device='cpu')


@pytest.fixture(scope='module')
def trained(tmp_path_factory):
    sets = _sets()
    out = tmp_path_factory.mktemp('neural')
    harm = harmonise(sets[:1], list(GAINS), TINY, out, progress=False)
    return sets, harm, out


def test_training_lowers_the_loss_and_d_reproduces_e_on_held_out_pixels(trained):
    sets, harm, _ = trained
    field = harm.report['field']['losses']
    assert len(field) == TINY.field_epochs and field[-1] < 0.01 * field[0]
    for cam in GAINS:
        losses = harm.report['mappers'][cam]['losses']
        assert losses[-1] < 0.01 * losses[0]
        err = harm.report['mapper_error'][cam]          # pixels of the training frame D did not train on
        assert err['pixels'] > 100 and err['rms_levels'] < 3.0, (cam, err)
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
    sets, harm, _ = trained
    for cam in GAINS:
        lut = bake_region_lut(harm, cam)
        err = export_error(harm, cam, lut, [v.color for v in sets[1] if v.name == cam])
        assert err['mean_levels'] < 0.6 and err['p99_levels'] <= 3, (cam, err)
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
