"""Temporal averaging of cleaned depth and colour (``volcap_filter.temporal``): noise falls where
the scene holds still; motion, a texture sliding over a still surface and holes restart a pixel;
a still pixel the sensor missed is held a while."""
import numpy as np

from volcap_filter.temporal import TemporalFilter

NOISE = (0.0008, 0.0010)     # the flying-pixel filter's ToF noise model: 4.8 mm at 2 m


def scene(rng, offset=0.0, color_noise=2.0, texture_shift=0):
    z = np.zeros((100, 120), np.float32)
    z[20:80, 30:90] = 2.0 + offset
    sigma = NOISE[0] + NOISE[1] * 4.0
    depth = np.where(z > 0, z + rng.normal(0, sigma, z.shape), 0).astype(np.float32)
    x = np.arange(240)
    stripes = np.where(((x + texture_shift) // 8) % 2 == 0, 60.0, 180.0)
    color = np.broadcast_to(stripes[None, :, None], (200, 240, 3)) + rng.normal(0, color_noise, (200, 240, 3))
    return depth, np.clip(color, 0, 255).astype(np.uint8)


def test_still_depth_and_colour_are_averaged():
    rng = np.random.default_rng(0)
    f = TemporalFilter(0.1, 15, *NOISE)
    for _ in range(12):
        depth, color = scene(rng)
        out, out_color, still = f.update(depth.copy(), color)     # the depth is filtered in place
    inner = np.s_[30:70, 40:80]
    assert still[20:80, 30:90].mean() > 0.9
    assert np.std(out[inner] - 2.0) < 0.5 * np.std(depth[inner] - 2.0)
    truth = np.where(((np.arange(240) // 8) % 2 == 0), 60.0, 180.0)
    err = lambda c: np.abs(c[60:140, 80:160].astype(float) - truth[None, 80:160, None]).mean()
    assert err(out_color) < 0.6 * err(color)
    assert (out[depth == 0] == 0).all()          # no depth where the frame has none


def test_motion_and_sliding_texture_restart_the_average():
    rng = np.random.default_rng(1)
    f = TemporalFilter(0.1, 15, *NOISE)
    for _ in range(6):
        f.update(*scene(rng))
    for k in range(1, 4):          # the surface comes 3 mm closer every frame: no lag
        depth, color = scene(rng, offset=-0.003 * k)
        out, _, still = f.update(depth.copy(), color)
        assert still[20:80, 30:90].mean() < 0.2
        assert abs(float(np.mean(out[30:70, 40:80])) - (2.0 - 0.003 * k)) < 0.0007
    f = TemporalFilter(0.1, 15, *NOISE)
    for _ in range(6):
        f.update(*scene(rng))
    depth, color = scene(rng, texture_shift=4)     # depth still, the stripes moved by half a stripe
    before = color.copy()
    _, out_color, still = f.update(depth, color)
    assert (color == before).all()       # the frame's colour is not written
    x = np.arange(240)
    moved = ((x // 8) % 2) != (((x + 4) // 8) % 2)          # the columns whose stripe changed
    region = np.s_[40:160, 60:180]
    changed = np.broadcast_to(moved[None, 60:180], (120, 120))
    # where the texture moved the new colour passes unaveraged (no smear); elsewhere it is averaged
    assert np.abs(out_color[region].astype(int) - color[region].astype(int))[changed].max() <= 1
    assert not still[20:80, 30:90][:, moved[60:180:2]].any()


def test_a_new_size_or_holes_start_again():
    rng = np.random.default_rng(2)
    f = TemporalFilter(0.1, 15, *NOISE)
    f.update(*scene(rng))
    depth, color = scene(rng)
    depth[40:50, 50:60] = 0
    out, _, still = f.update(depth.copy(), color)
    assert not still[40:50, 50:60].any() and (out[40:50, 50:60] == 0).all()
    small = np.full((50, 60), 2.0, np.float32)
    out, _, still = f.update(small, np.zeros((100, 120, 3), np.uint8))
    assert not still.any() and (out == small).all()


def test_a_still_surface_the_sensor_misses_is_held_for_a_while_and_one_that_left_is_not():
    """Dark material returns a random few of its pixels each frame: where a still pixel with a
    history gets none, its mean stands in (one frame fewer each time). Where the subject left,
    the colour changed, and the pixel goes."""
    rng = np.random.default_rng(3)
    f = TemporalFilter(0.1, 15, *NOISE)
    for _ in range(6):
        f.update(*scene(rng))
    depth, color = scene(rng)
    missed = (rng.random(depth.shape) < 0.5) & (depth > 0)      # half the surface not returned
    depth[missed] = 0
    color[80:120, 100:120] = 255                                  # ... and where the block [40:60, 50:60] left, white
    depth[40:60, 50:60] = 0
    out, out_color, still = f.update(depth.copy(), color)
    held = missed.copy()
    held[40:60, 50:60] = False
    # (a pixel the motion test restarted a frame ago, about 1.5 %, has no history to hold)
    assert (out[held] > 0).mean() > 0.95 and np.abs(out[held & (out > 0)] - 2.0).max() < 0.015   # 3 sigma
    assert (out[40:60, 50:60] == 0).all() and not still[40:60, 50:60].any()
    assert np.abs(out_color[80:120, 100:120].astype(int) - 255).max() <= 1   # the new colour, unaveraged
    # a pixel missed frame after frame is held as many frames as it had averaged, less one
    f = TemporalFilter(0.1, 15, *NOISE)
    for _ in range(6):
        f.update(*scene(rng))
    frames_held = 0
    for _ in range(10):
        depth, color = scene(rng)
        depth[30:40, 60:70] = 0
        out, _, _ = f.update(depth.copy(), color)
        frames_held += bool((out[30:40, 60:70] > 0).mean() > 0.9)
    assert (out[30:40, 60:70] == 0).all() and 3 <= frames_held <= 6, frames_held
