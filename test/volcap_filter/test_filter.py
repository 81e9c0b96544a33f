"""Depth registration, flying-pixel filters, masks and the depth evaluation, without ROS."""

import cv2
import numpy as np
import pytest

from volcap_core.errors import BadInput
from volcap_core.rig import rig_camera_from_k4a
from volcap_filter.flying import FlyingPixelConfig, complete_inside, fill_sparse_returns, flying_pixels, paper_flying_pixels
from volcap_filter.mask import BackgroundModel, MaskConfig, chroma_key_mask, foreground_mask
from volcap_filter.pipeline import DepthCleaner, DepthFilterConfig, sanitise_depth
from volcap_filter.registration import DepthRegistration


@pytest.fixture(scope='module')
def k4a(shared_data):
    return rig_camera_from_k4a(shared_data / 'azure_kinect' / 'calibration.json', 'cam0')


def test_projection_matches_opencv(k4a):
    reg = DepthRegistration(k4a.depth, k4a.color, k4a.T_color_depth, (1280, 720))
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 3.0, (576, 640)).astype(np.float32)
    uv, zc = reg.project(depth)
    v, u = rng.integers(150, 420, 50), rng.integers(150, 490, 50)
    p = k4a.depth.pixel_rays()[v, u] * depth[v, u, None]
    q = (k4a.T_color_depth[:3, :3] @ p.T).T + k4a.T_color_depth[:3, 3]
    np.testing.assert_allclose(uv[v, u], k4a.color.project(q), atol=1e-3)
    np.testing.assert_allclose(zc[v, u], q[:, 2], rtol=1e-5)


def test_registration_has_no_holes_and_keeps_steps_apart(k4a):
    depth = np.full((576, 640), 2.0, np.float32)
    reg = DepthRegistration(k4a.depth, k4a.color, k4a.T_color_depth, (1280, 720))   # output denser than depth
    out = reg.register(depth).depth
    footprint = cv2.morphologyEx((out > 0).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8))
    core = cv2.erode(footprint, np.ones((21, 21), np.uint8)).astype(bool)
    assert core.mean() > 0.5
    assert (out[core] > 0).all(), 'forward warping left holes'
    single = np.zeros(out.shape, np.float32)   # what splatting pixels alone gives
    uv = reg.project(depth)[0].reshape(-1, 2)
    ok = np.isfinite(uv).all(axis=1)
    x, y = np.round(uv[ok]).astype(int).T
    inb = (x >= 0) & (x < 1280) & (y >= 0) & (y < 720)
    single[y[inb], x[inb]] = 1
    assert (single[core] == 0).mean() > 0.2
    depth[200:380, 250:400] = 1.0          # a box in front of the wall
    out = reg.register(depth).depth
    # No surface invented between box and wall: depths are ~1 m or ~2 m, nothing in between.
    vals = out[out > 0]
    assert ((vals > 1.1) & (vals < 1.9)).sum() == 0


def test_registration_pass_through_and_size_errors(k4a):
    reg = DepthRegistration(k4a.color, k4a.color, np.eye(4), registered=True)
    depth = np.zeros((720, 1280), np.float32)
    depth[100:200, 300:500] = 1.5
    r = reg.register(depth)
    assert r.depth.shape == (360, 640)
    assert np.isclose(r.depth[75, 200], 1.5) and r.depth[10, 10] == 0
    with pytest.raises(ValueError, match='camera_info says'):
        reg.register(np.zeros((10, 10), np.float32))
    with pytest.raises(ValueError, match='4x4'):
        DepthRegistration(k4a.depth, k4a.color, np.eye(3))


def _step_scene(rng, noise=0.003):
    """Fronto-parallel near surface (left, 1.5 m) over a far one (right, 3 m) with one column
    of mixed pixels between them, a speckle blob and noise."""
    z = np.full((200, 200), 3.0, np.float32)
    z[:, :100] = 1.5
    z += rng.normal(0, noise, z.shape).astype(np.float32)
    z[:, 100] = rng.uniform(1.7, 2.8, 200)
    flying = np.zeros(z.shape, bool)
    flying[:, 100] = True
    z[40:43, 40:43] += 0.3     # speckle
    return z, flying


def test_paper_eq5_flags_steps_and_horizontal_ignores_vertical_ones():
    z, flying = _step_scene(np.random.default_rng(0), noise=0.001)
    flagged = paper_flying_pixels(z, 'all')
    assert flagged[flying].mean() > 0.95
    # It also removes the true edge pixels on both sides of the step (its weakness).
    assert flagged[:, 99].mean() > 0.9 and flagged[:, 101].mean() > 0.9
    assert flagged[40:43, 40:43].sum() >= 8 and not flagged[:, 50:90].any()   # a blob's core survives
    horizontal_step = np.full((50, 50), 1.5, np.float32)
    horizontal_step[25:] = 3.0
    assert not paper_flying_pixels(horizontal_step, 'horizontal').any()
    assert paper_flying_pixels(horizontal_step, 'all')[24:26].all()
    with pytest.raises(ValueError):
        paper_flying_pixels(z, 'diagonal')


def test_our_filter_removes_mixed_pixels_and_speckle_but_keeps_edges():
    z, flying = _step_scene(np.random.default_rng(0))
    flagged = flying_pixels(z, 500.0)
    assert flagged[flying].mean() > 0.97
    assert flagged[40:43, 40:43].all(), 'speckle blob kept'
    edges = np.zeros(z.shape, bool)
    edges[2:-2, [99, 101]] = True
    assert flagged[edges].mean() < 0.1, 'true boundary pixels removed'
    interior = np.zeros(z.shape, bool)
    interior[5:-5, 5:95] = True
    interior[35:48, 35:48] = False
    assert flagged[interior].mean() < 0.005
    with pytest.raises(ValueError):
        flying_pixels(z, 500.0, FlyingPixelConfig(min_axes=5))


def _shoe_scene(rng, density=0.18):
    """A dark shoe (2.0 m, tilted) standing in front of the floor behind it (2.4 m, dense), the
    sensor returning a random ``density`` of the shoe's pixels; real mixed pixels along the
    shoe's top edge (between the shoe and the floor) and along the edge of a near box (1.5 m);
    a few random dropouts in the floor."""
    h, w = 200, 200
    yy, xx = np.mgrid[:h, :w]
    truth = np.full((h, w), 2.4, np.float32)
    shoe = (yy >= 100) & (yy < 140) & (xx >= 40) & (xx < 110)
    truth[shoe] = (2.0 + 0.0008 * (xx - 40) - 0.0005 * (yy - 100))[shoe]
    box = (yy >= 20) & (yy < 70) & (xx >= 140) & (xx < 190)
    truth[box] = 1.5
    z = truth + rng.normal(0, 0.003, truth.shape).astype(np.float32)
    z[shoe & (rng.random(truth.shape) > density)] = 0.0
    z[~shoe & ~box & (rng.random(truth.shape) < 0.02)] = 0.0
    mixed = np.zeros(truth.shape, bool)
    mixed[99, 40:110] = rng.random(70) < 0.85                    # shoe top against the floor behind
    mixed[20:70, 139] = True                                     # the box's edge
    z[mixed] = np.where(yy[mixed] == 99, rng.uniform(2.06, 2.34, mixed.sum()), rng.uniform(1.6, 2.3, mixed.sum()))
    return z, truth, shoe, mixed


def test_a_dark_shoe_on_the_floor_is_kept_and_closed_and_real_flying_pixels_still_go():
    """Issue 30's feet: the shoe returns depth on a random 18 % of its pixels, so no return has
    the neighbours the axis tests need; without the sparse-return rescue almost all of it goes.
    With it most returns stay, the holes between them get depth on the shoe's surface, and every
    mixed pixel (beside the shoe and at an ordinary step) is still removed, none filled."""
    z, truth, shoe, mixed = _shoe_scene(np.random.default_rng(5))
    returns = shoe & (z > 0) & ~mixed
    axis_only = flying_pixels(z, 500.0, FlyingPixelConfig(sparse_radius=0))
    assert axis_only[returns].mean() > 0.9                       # the failure: the shoe removed
    removed = flying_pixels(z, 500.0)
    assert removed[mixed].all(), 'a mixed pixel came back'
    # 78 % here (a return needs others on its surface on every side); 74-78 % of the studio's
    # shoe returns (bench/feet.py)
    assert 1 - removed[returns].mean() > 0.6, 'sparse returns not kept'
    assert removed[(z > 0) & ~shoe & ~mixed].mean() < 0.01    # the floor and the box untouched
    gated = np.where(removed, np.float32(0.0), z)
    filled = fill_sparse_returns(gated, removed, 500.0)
    holes = shoe & (gated == 0) & ~mixed
    assert (filled[holes] > 0).mean() > 0.5, 'the shoe not closed'
    # every fill on the true surface within 3 sigma (none between the shoe and the floor behind
    # it), none where a flying pixel was removed
    assert np.abs(filled - truth)[filled > 0].max() < 0.015
    assert not filled[removed].any()
    assert not fill_sparse_returns(gated, removed, 500.0, FlyingPixelConfig(sparse_radius=0)).any()


def test_the_silhouette_completes_the_shoe_down_to_its_sole():
    """Issue 30's feet: the returns kept and the holes closed between them leave the strip along
    the shoe's sole empty (no return there has its surface on every side: the floor is below).
    Completing inside the silhouette fills the holes between the depth first, then extends the
    shoe's plane to the silhouette's edge; nothing outside the silhouette is touched, nothing is
    filled off the shoe's surface, and without the extending passes the sole stays empty."""
    z, truth, shoe, mixed = _shoe_scene(np.random.default_rng(5))
    removed = flying_pixels(z, 500.0)
    depth = np.where(removed, np.float32(0.0), z)
    depth += fill_sparse_returns(depth, removed, 500.0)
    sole = shoe & (np.mgrid[:200, :200][0] >= 134)
    assert (depth[sole] > 0).mean() < 0.5                        # the failure: the sole's strip is a hole
    between = depth.copy()
    complete_inside(between, shoe, 500.0, 4, 0)
    completed = depth.copy()
    n = complete_inside(completed, shoe, 500.0, 4, 2)
    assert n == np.count_nonzero(completed != depth)
    assert (completed[shoe] > 0).mean() > 0.98, 'the shoe not completed'
    assert (completed[sole] > 0).mean() > 0.95, 'the sole not reached'
    assert (completed[sole] > 0).mean() > (between[sole] > 0).mean() + 0.3
    assert np.array_equal(completed[~shoe], depth[~shoe]), 'depth outside the silhouette changed'
    new = completed != depth
    assert np.abs(completed - truth)[new].max() < 0.015, 'a completion off the shoe\'s surface'
    assert np.abs(completed - truth)[new].mean() < 0.004
    # OpenCV's inpainting cannot stand in: it takes every pixel outside its mask as known, so the
    # zeros beyond the silhouette (masked as the cleaner has them) pull the shoe towards 0 m
    masked = np.where(shoe, depth, np.float32(0.0))
    inpainted = cv2.inpaint(masked, (shoe & (masked == 0)).view(np.uint8), 4, cv2.INPAINT_TELEA)
    assert np.median(np.abs(inpainted - truth)[new]) > 0.1     # 1.0 m; the completion's median is 1.0 mm
    assert np.median(np.abs(completed - truth)[new]) < 0.002
    assert complete_inside(depth.copy(), np.zeros_like(shoe), 500.0, 4, 2) == 0
    assert complete_inside(depth.copy(), shoe, 500.0, 0, 2) == 0
    with pytest.raises(BadInput):
        complete_inside(depth.astype(np.float64), shoe, 500.0, 4, 2)


def _room(rng, shape=(120, 160)):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    wall = np.stack([120 + 40 * np.sin(xx / 9.0), 110 + 30 * np.cos(yy / 7.0), 100 + 0 * xx], axis=2)
    return lambda: np.clip(wall + rng.normal(0, 2, wall.shape), 0, 255).astype(np.uint8)


def test_clean_plate_mask_separates_subject_and_ignores_shadow():
    rng = np.random.default_rng(3)
    frame = _room(rng)
    model = BackgroundModel()
    for _ in range(3):
        model.add(frame())
    img = frame()
    subject = np.zeros(img.shape[:2], bool)
    subject[30:100, 60:100] = True
    img[subject] = (200, 40, 40)
    img[30:100, 100:130] = (img[30:100, 100:130] * 0.7).astype(np.uint8)   # its shadow on the wall
    mask = foreground_mask(img, None, model, MaskConfig())
    iou = (mask & subject).sum() / (mask | subject).sum()
    assert iou > 0.97
    assert not mask[30:100, 102:130].any(), 'shadow taken for foreground'


def test_depth_joins_color_misses_that_touch_the_subject():
    rng = np.random.default_rng(4)
    frame = _room(rng)
    model = BackgroundModel()
    bg_depth = np.full((120, 160), 3.0, np.float32)
    model.add(frame(), bg_depth)
    img = frame()
    img[20:60, 60:100] = (220, 200, 30)        # coloured top part
    depth = bg_depth.copy()
    depth[20:110, 60:100] = 1.5                 # whole subject in depth; its lower part is wall-coloured
    mask = foreground_mask(img, depth, model, MaskConfig(max_range=4.0))
    assert mask[20:110, 62:98].mean() > 0.98
    assert mask.sum() < 1.1 * 90 * 40


def test_chroma_key():
    img = np.zeros((80, 80, 3), np.uint8)
    img[:] = (0, 177, 64)
    img[20:60, 30:50] = (180, 150, 120)
    mask = chroma_key_mask(img)
    assert mask[20:60, 30:50].all() and mask.sum() == 40 * 20


def test_background_model_round_trip(tmp_path):
    m = BackgroundModel()
    with pytest.raises(ValueError):
        m.save(str(tmp_path / 'bg.npz'))
    m.add(np.full((4, 5, 3), 10, np.uint8), np.ones((2, 2), np.float32))
    m.save(str(tmp_path / 'bg.npz'))
    loaded = BackgroundModel.load(str(tmp_path / 'bg.npz'))
    assert loaded.frames == 1 and loaded.depth.shape == (2, 2)
    with pytest.raises(ValueError, match='clean-plate frame'):
        m.add(np.zeros((3, 3, 3), np.uint8))


def test_cleaner_rejects_bad_frames(k4a):
    cleaner = DepthCleaner(DepthRegistration(k4a.depth, k4a.color, k4a.T_color_depth))
    color = np.zeros((720, 1280, 3), np.uint8)
    with pytest.raises(ValueError, match='no valid pixel'):
        cleaner.process(color, np.full((576, 640), np.nan, np.float32))
    with pytest.raises(ValueError, match='colour image is'):
        cleaner.process(np.zeros((10, 10, 3), np.uint8), np.ones((576, 640), np.float32))
    assert np.array_equal(sanitise_depth(np.array([np.nan, np.inf, -1, 2.0])), [0, 0, 0, 2.0])
    with pytest.raises(ValueError):
        DepthCleaner(cleaner.registration, DepthFilterConfig(mask_mode='magic'))


def test_cleaner_on_a_studio_frame_gives_points_and_temporal_state(studio_bag):
    from volcap_core.frames import frame_sets
    from volcap_studio.session import GroundTruth
    rig = GroundTruth(studio_bag).rig
    cleaner = None
    for fs in frame_sets(studio_bag, phases=('clean_plate', 'capture')):
        f = fs.cameras['cam2']
        if cleaner is None:
            reg = DepthRegistration(f.depth_model, f.color_model, rig.camera('cam2').T_color_depth)
            cleaner = DepthCleaner(reg, DepthFilterConfig(temporal_alpha=0.5, sor_neighbors=16))
            # without temporal state, with and without the completion inside the mask
            completed = DepthCleaner(reg, DepthFilterConfig(temporal_alpha=0))
            uncompleted = DepthCleaner(reg, DepthFilterConfig(temporal_alpha=0, complete_radius=0))
        if fs.phase == 'clean_plate':
            for c in (cleaner, completed, uncompleted):
                c.learn_background(f.color, f.depth)
            continue
        result = cleaner.process(f.color, f.depth)
    xyz, rgb = cleaner.points(result)
    assert result.depth.shape == (360, 640) and result.mask.shape == (720, 1280)
    assert len(xyz) > 2000 and rgb.dtype == np.uint8 and xyz.shape == rgb.shape
    assert np.all((xyz[:, 2] > 0.1) & (xyz[:, 2] < 2.5))
    # the completion gives depth only to holes inside the mask, and leaves every other pixel as it was
    with_, without = completed.process(f.color, f.depth), uncompleted.process(f.color, f.depth)
    fg = cv2.resize(with_.mask.view(np.uint8) * np.uint8(255), (640, 360), interpolation=cv2.INTER_AREA) > 127
    changed = with_.depth != without.depth
    assert changed.any() and np.all(fg[changed]) and not np.any(without.depth[changed])










def test_depth_a_driver_registered_survives_cleaning(k4a_bag):
    """The real Azure Kinect frame registered as the drivers do (640x576 over 1280x720 leaves
    empty rows and columns every 4-6 px): every pixel borders a hole, so the flying-pixel test
    alone removes all of it; with the lattice bridged the surface stays and the holes stay holes."""
    from volcap_core.bag_reader import BagReader
    from volcap_core.frames import frame_sets, read_rig
    from volcap_filter.flying import fill_lattice_gaps
    from volcap_studio.vendor import register_like_driver
    with BagReader(k4a_bag) as reader:
        cam = read_rig(reader).cameras[0]
    frame = next(frame_sets(k4a_bag)).cameras['cam0']
    aligned = register_like_driver(frame.depth, cam)
    valid = aligned > 0
    borders_hole = cv2.erode(valid.view(np.uint8), np.ones((3, 3), np.uint8)) == 0
    assert borders_hole[valid].mean() > 0.9                            # the lattice of a real driver
    # the failure this guards against: the axis tests alone (the sparse-return rescue keeps some)
    assert flying_pixels(aligned, cam.color.fx, FlyingPixelConfig(sparse_radius=0))[valid].mean() > 0.99
    cleaner = DepthCleaner(DepthRegistration(cam.color, cam.color, np.eye(4), (1280, 720), registered=True),
                           DepthFilterConfig())
    clean = cleaner.process(frame.color, aligned).depth
    in_range = valid & (aligned > 0.1) & (aligned < 2.5)
    assert np.count_nonzero(clean) > 0.9 * np.count_nonzero(in_range)
    assert not np.any(clean[~valid])                                   # nothing invented in the holes
    # bridged, the lattice covers what volcap's own registration of the native depth covers
    native = DepthRegistration(cam.depth, cam.color, cam.T_color_depth, (1280, 720)).register(frame.depth).depth
    bridged = fill_lattice_gaps(aligned, cam.color.fx)
    assert np.count_nonzero(bridged) > 0.95 * np.count_nonzero(native)


@pytest.mark.parametrize('damage', ['truncated', 'garbage', 'no sums', 'wrong shape'])
def test_a_damaged_clean_plate_file_is_a_clear_error(tmp_path, damage):
    path = tmp_path / 'bg.npz'
    m = BackgroundModel()
    m.add(np.full((4, 5, 3), 10, np.uint8), np.ones((2, 2), np.float32))
    m.save(str(path))
    if damage == 'truncated':
        path.write_bytes(path.read_bytes()[:100])
    elif damage == 'garbage':
        path.write_bytes(b'not a clean plate')
    elif damage == 'no sums':
        np.savez(path, n=1, depth=np.zeros(0))
    else:
        np.savez(path, n=1, sum=np.zeros((4, 5)), sum2=np.zeros((4, 5)), depth=np.zeros(0))
    with pytest.raises(ValueError, match='clean plate'):
        BackgroundModel.load(str(path))


def _log_scene(rng, radius=0.03, distance=2.5, focal=500.0, returned=0.2, noise=0.001):
    """A dark horizontal log (a shoe's top, an ankle: a cylinder of ``radius`` m) at ``distance``
    m, facing a ``focal`` px camera: its true depth, its silhouette and a random ``returned``
    share of its pixels with depth (Gaussian ``noise`` m), the rest holes."""
    h, w = 60, 160
    v = (np.mgrid[:h, :w][0] - (h - 1) / 2) / focal        # ray slope in y
    # the ray (x, v, 1) z meets y^2 + (z - c)^2 = r^2 (the axis along x at depth c)
    c = distance + radius
    a, b, k = v * v + 1, -2 * c, c * c - radius * radius
    disc = b * b - 4 * a * k
    log = disc > 0
    truth = np.where(log, (-b - np.sqrt(np.where(log, disc, 0))) / (2 * a), 0).astype(np.float32)
    log[:, :10] = log[:, -10:] = False
    truth[~log] = 0
    depth = np.where(log & (rng.random(truth.shape) < returned), truth + rng.normal(0, noise, truth.shape), 0)
    return depth.astype(np.float32), truth, log


def test_holes_on_a_curved_surface_take_the_quadric_through_their_returns():
    """A plane through the returns around a hole on a convex patch lies behind its middle (the
    patch's sagitta: 5-10 mm over a 9x9 window at 2.5 m on a shoe), more than the 5 mm the fused
    score allows; the quadric follows the curve. Planes only (``curved_support`` 0) against the
    default, on the same dark log: the sparse fill and the completion's first pass both; and what
    the quadric costs a noisy flat wall."""
    depth, truth, log = _log_scene(np.random.default_rng(2))
    # the filter's noise model told the scene's (1 mm at 2.5 m): the plane's miss is then beyond a sigma
    quiet = dict(noise_base=0.0005, noise_quad=0.0002)
    planes, quadrics = FlyingPixelConfig(curved_support=0, **quiet), FlyingPixelConfig(**quiet)
    errors = {}
    for name, cfg in (('planes', planes), ('quadrics', quadrics)):
        removed = np.zeros(depth.shape, bool)
        filled = depth + fill_sparse_returns(depth, removed, 500.0, cfg)
        completed = filled.copy()
        complete_inside(completed, log, 500.0, 4, 0, cfg)
        new = log & (depth == 0) & (completed > 0)
        errors[name] = (np.abs(completed - truth)[new], new.sum() / (log & (depth == 0)).sum())
        bias = np.median((completed - truth)[new])
        if name == 'planes':
            assert bias > 0.0015, 'the planes should lie behind the log'    # the failure (2 mm here)
    (plane_err, plane_share), (quad_err, quad_share) = errors['planes'], errors['quadrics']
    assert np.median(quad_err) < 0.5 * np.median(plane_err)
    assert np.median(quad_err) < 0.0025
    assert quad_share > plane_share + 0.2          # planes that miss by over 3 sigma fill nothing (here 0.66 / 0.95)
    # What it costs a flat wall with the same noise: where the noise makes a plane miss its
    # returns by a sigma, the quadric follows the noise a little (median 0.18-0.20 -> 0.26 mm on
    # seeds 2-4: the still studio's extra 0.01-0.02 mm of jitter), never off the wall
    rng = np.random.default_rng(2)
    flat = np.where(rng.random(depth.shape) < 0.2, 2.5 + rng.normal(0, 0.001, depth.shape), 0).astype(np.float32)
    fills = [fill_sparse_returns(flat, np.zeros(flat.shape, bool), 500.0, c) for c in (planes, quadrics)]
    assert not np.array_equal(*fills)                                # the gate opens on noise too
    (plane_fills, quad_fills) = [f[f > 0] for f in fills]
    assert abs(len(quad_fills) - len(plane_fills)) < 0.01 * len(plane_fills)
    assert np.median(np.abs(quad_fills - 2.5)) < 0.0004 and np.abs(quad_fills - 2.5).max() < 0.003
