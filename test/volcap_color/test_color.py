"""volcap_color without ROS: the compiled image corrector, correspondences against ground truth,
the chart-free fit and the baselines on known colour differences, and `volcap eval colour` /
`volcap colour-fit` end to end on the small studio bag."""

import numpy as np
import pytest

from volcap_color.apply import ImageCorrector
from volcap_color.baselines import brown_lowe, fit_reinhard, moulon, propagate, propagation_tree
from volcap_color.chart_free import chart_free_fit
from volcap_color.correspondence import Matches
from volcap_core.color import ColorModel, linear_to_srgb, srgb_to_linear

MATRIX = np.array([[1.1, 0.05, -0.02], [0.03, 0.92, 0.01], [-0.04, 0.02, 1.2]])


@pytest.mark.parametrize('model', [
    ColorModel('paper_diagonal', np.diag([1.1, 0.9, 1.05])),
    ColorModel('matrix_3x3', MATRIX),
    ColorModel('affine_3x4', np.hstack([MATRIX, [[0.01], [-0.01], [0.0]]])),
    ColorModel('gamma_3x3', MATRIX, (1.1, 0.95, 1.02)),
    ColorModel('gamma_3x3', MATRIX, (1.1, 0.95, 1.02), post=np.hstack([np.eye(3) * 0.9, [[0.02], [0], [0]]])),
    ColorModel('root_polynomial_2', np.hstack([np.eye(3) * 1.05, np.full((3, 3), 0.02)])),
], ids=lambda m: m.method + ('+post' if m.post is not None else ''))
def test_compiled_corrector_matches_the_exact_model(model):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (90, 160, 3), dtype=np.uint8)
    corrector = ImageCorrector(model)
    diff = np.abs(corrector(image).astype(int) - model.apply_image(image).astype(int))
    if corrector.kind == 'lut':      # trilinear 33^3 table of a smooth polynomial
        assert diff.max() <= 3 and diff.mean() < 0.15
    else:
        assert diff.max() <= 1 and diff.mean() < 0.02
    with pytest.raises(ValueError, match='uint8 RGB'):
        corrector(image[:, :, 0])


def test_color_model_post_map_round_trips():
    m = ColorModel('gamma_3x3', MATRIX, (1.1, 0.95, 1.02), post=np.hstack([np.eye(3) * 0.9, np.zeros((3, 1))]))
    again = ColorModel.from_dict(m.to_dict())
    rgb = np.random.default_rng(1).random((50, 3))
    assert np.allclose(again.apply(rgb), m.apply(rgb))
    assert np.allclose(m.apply_linear(srgb_to_linear(rgb)),
                       0.9 * ColorModel('gamma_3x3', MATRIX, (1.1, 0.95, 1.02)).apply_linear(srgb_to_linear(rgb)))
    with pytest.raises(ValueError, match='3x4'):
        ColorModel('paper_diagonal', np.eye(3), post=np.zeros((3, 4)))






def _synthetic_matches(cameras, distort, n=4000, outliers=0.0, seed=0):
    """Correspondences of a ring of cameras: each sees true linear colours through ``distort[c]``."""
    rng = np.random.default_rng(seed)
    out = {}
    for i, a in enumerate(cameras):
        b = cameras[(i + 1) % len(cameras)]
        truth = 0.05 + 0.6 * rng.random((n, 3))
        ca, cb = distort[a](truth), distort[b](truth)
        bad = rng.random(n) < outliers
        cb[bad] = rng.random((bad.sum(), 3)) * 0.9 + 0.05
        out[(a, b)] = Matches(a, b, np.zeros((n, 2), np.int32), np.zeros((n, 2), np.float32),
                              linear_to_srgb(ca), linear_to_srgb(cb), 0.05)
    return out


def _affine_camera(seed):
    rng = np.random.default_rng(seed)
    M = np.eye(3) * rng.uniform(0.7, 1.2, 3) + rng.normal(0, 0.03, (3, 3))
    o = rng.normal(0, 0.01, 3)
    return lambda lin: np.clip(lin @ M.T + o, 0, 1)


def test_chart_free_fit_makes_cameras_agree_despite_outliers():
    cams = [f'cam{i}' for i in range(6)]
    distort = {c: _affine_camera(i) for i, c in enumerate(cams)}
    matches = _synthetic_matches(cams, distort, outliers=0.1)
    models = chart_free_fit(matches, cams, 'affine_3x4', 'mean')
    clean = _synthetic_matches(cams, distort, seed=5)
    for (a, b), m in clean.items():
        before = np.abs(m.colors_a - m.colors_b).mean()
        after = np.abs(models[a].apply(m.colors_a) - models[b].apply(m.colors_b)).mean()
        assert after < 0.003 < 0.1 * before
    mean = np.mean([m.matrix for m in models.values()], axis=0)
    assert np.allclose(mean, np.hstack([np.eye(3), np.zeros((3, 1))]), atol=1e-3)
    fixed = chart_free_fit(matches, cams, 'gain_offset', 'cam2')
    assert np.allclose(fixed['cam2'].matrix, np.hstack([np.eye(3), np.zeros((3, 1))]), atol=1e-4)
    with pytest.raises(ValueError, match='reference'):
        chart_free_fit(matches, cams, 'affine_3x4', 'cam9')


def test_chart_anchor_sets_the_absolute_level():
    cams = ['cam0', 'cam1', 'cam2']
    distort = {c: _affine_camera(i + 10) for i, c in enumerate(cams)}
    matches = _synthetic_matches(cams, distort)
    rng = np.random.default_rng(3)
    patches = 0.05 + 0.6 * rng.random((48, 3))
    anchor = {c: (linear_to_srgb(distort[c](patches)), linear_to_srgb(patches)) for c in cams}
    models = chart_free_fit(matches, cams, 'affine_3x4', 'chart', anchor=anchor)
    for c in cams:
        assert np.abs(models[c].apply(anchor[c][0]) - anchor[c][1]).mean() < 0.003


def test_gain_baselines_recover_gains_and_the_tree_starts_at_the_centre():
    cams = ['cam0', 'cam1', 'cam2', 'cam3']
    gains = {'cam0': 1.0, 'cam1': 0.8, 'cam2': 1.2, 'cam3': 0.9}
    distort = {c: (lambda g: lambda lin: lin * g)(g) for c, g in gains.items()}
    chain = {k: m for k, m in _synthetic_matches(cams, distort).items() if k != ('cam3', 'cam0')}
    root, parents = propagation_tree(chain, cams)
    assert root in ('cam1', 'cam2') and parents[root] is None
    rgb = np.full((1, 3), 0.5)
    for mapping in (moulon(chain, cams, reference='cam0'), propagate(chain, cams, fit_reinhard)):
        corrected = {c: mapping[c](linear_to_srgb(srgb_to_linear(rgb) * gains[c]))[0] for c in cams}
        spread = np.ptp([v for v in corrected.values()], axis=0)
        assert spread.max() < 0.02, corrected
    bl = brown_lowe(chain, cams)
    corrected = [bl[c](linear_to_srgb(srgb_to_linear(rgb) * gains[c]))[0, 1] for c in cams]
    assert np.ptp(corrected) < np.ptp([linear_to_srgb(srgb_to_linear(rgb) * g)[0, 1] for g in gains.values()]) / 2




def test_model_choice_is_the_simplest_family_that_fits_and_leaves_a_consistent_rig_alone():
    from volcap_color.model_choice import choose_chart_free_model, held_out_scores
    cams = [f'cam{i}' for i in range(4)]
    gains = {c: np.array(g) for c, g in zip(cams, [(1.0, 1.0, 1.0), (0.8, 0.9, 1.1), (1.2, 1.0, 0.85), (0.9, 1.1, 1)])}
    by_gain = _synthetic_matches(cams, {c: (lambda g: lambda lin: lin * g)(g) for c, g in gains.items()})
    assert choose_chart_free_model(by_gain, cams).model == 'gain'
    crosstalk = {c: (lambda M: lambda lin: np.clip(lin @ M.T, 0, 1))(np.eye(3) * 0.85 + 0.05 * (i % 2) + 0.05)
                 for i, c in enumerate(cams)}
    by_matrix = _synthetic_matches(cams, crosstalk)
    choice = choose_chart_free_model(by_matrix, cams)
    assert choice.model == 'matrix_3x3', choice.scores
    assert choice.scores['matrix_3x3']['de2000'] < 0.5 * choice.scores['gain']['de2000']
    # A rig that already agrees (sensor noise only): whatever is chosen does not make it worse.
    rng = np.random.default_rng(4)
    agree = _synthetic_matches(cams, {c: (lambda lin: np.clip(lin + rng.normal(0, 0.004, lin.shape), 0, 1))
                                      for c in cams})
    choice = choose_chart_free_model(agree, cams)
    before = held_out_scores(agree, None)['de2000']
    assert choice.scores[choice.model]['de2000'] <= before * 1.02, choice.scores


def test_a_pixel_mapping_followed_by_a_colour_model_applies_both_in_turn():
    """``PixelMapping.followed_by``: the mapping (which may depend on the pixel) first, then the
    model on its sRGB output; a model that doubles linear light doubles the mapping's linear output."""
    from volcap_color.baselines import PixelMapping
    mapping = PixelMapping(lambda rgb, xy: rgb * (0.5 + 0.5 * xy[:, :1]), (4, 2))
    model = ColorModel('matrix_3x3', np.diag([2.0, 1.0, 0.5]))
    rgb = np.array([[0.2, 0.4, 0.6], [0.3, 0.3, 0.3]])
    pixels = np.array([[0, 0], [3, 1]])
    first = mapping(rgb, pixels)
    both = mapping.followed_by(model)(rgb, pixels)
    assert both == pytest.approx(model.apply(first))
    assert srgb_to_linear(both)[:, 1] == pytest.approx(srgb_to_linear(first)[:, 1])
    assert srgb_to_linear(both)[:, 0] == pytest.approx(2 * srgb_to_linear(first)[:, 0])
    assert first == pytest.approx(rgb * np.array([[0.5625], [0.9375]]))     # x = 0.125 and 0.875: the pixel counts
