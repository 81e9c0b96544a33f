import hashlib

import cv2
import numpy as np
import open3d as o3d
import pytest
import yaml
from sensor_msgs.msg import Image

from volcap_calib.board import BoardConfig
from volcap_core import topics
from volcap_core.bag_reader import BagReader
from volcap_core.conversions import camera_info_to_model, image_to_numpy, stamp_to_ns
from volcap_core.poses import invert, transform_points
from volcap_studio.session import GroundTruth, synthesize
from volcap_studio.studio import SynthConfig, board_poses, make_rig

CAMS = [f'cam{i}' for i in range(8)]


def messages(bag, topic):
    with BagReader(bag) as r:
        return [m.decode() for m in r.messages([topic])]


def test_bag_follows_the_topic_contract(studio_bag):
    gt = GroundTruth(studio_bag)
    with BagReader(studio_bag) as r:
        tps = r.topics
        assert r.latched_topics == {topics.RIG, topics.PHASE}
        counts = {}
        for m in r.messages():
            counts[m.topic] = counts.get(m.topic, 0) + 1
    n_sets = len(gt.frames)
    assert n_sets == 5
    for cam in CAMS:
        for name, kind in ((topics.COLOR_IMAGE, 'Image'), (topics.DEPTH_IMAGE, 'Image'),
                           (topics.COLOR_INFO, 'CameraInfo'), (topics.DEPTH_INFO, 'CameraInfo')):
            assert tps[f'{cam}/{name}'] == f'sensor_msgs/msg/{kind}'
            assert counts[f'{cam}/{name}'] == n_sets
    rig_msgs = messages(studio_bag, topics.RIG)
    assert len(rig_msgs) == 1 and yaml.safe_load(rig_msgs[0].data)['cameras'][0]['name'] == 'cam0'
    phases = [yaml.safe_load(m.data) for m in messages(studio_bag, topics.PHASE)]
    assert [{k: p[k] for k in ('phase', 'frames')} for p in phases] == [
        {'phase': 'clean_plate', 'frames': 1}, {'phase': 'calibration', 'frames': 2}, {'phase': 'capture', 'frames': 2}]
    # each phase holds from a stamp between its first frame set and the one before it
    gt = GroundTruth(studio_bag)
    for p in phases:
        first = min(f['stamp_ns'] for f in gt.frames if f['phase'] == p['phase'])
        before = [f['stamp_ns'] for f in gt.frames if f['stamp_ns'] < first]
        assert (max(before) if before else 0) < p['since_ns'] < first, p


def test_images_cameras_infos_and_stamps(studio_bag):
    gt = GroundTruth(studio_bag)
    cam = gt.rig.camera('cam3')
    color = messages(studio_bag, 'cam3/color/image_raw')
    depth = messages(studio_bag, 'cam3/depth/image_raw')
    assert color[0].encoding == 'rgb8' and (color[0].width, color[0].height) == (1280, 720)
    assert depth[0].encoding == '16UC1' and (depth[0].width, depth[0].height) == (640, 576)
    assert color[0].header.frame_id == cam.color_frame != depth[0].header.frame_id == cam.depth_frame
    assert camera_info_to_model(messages(studio_bag, 'cam3/color/camera_info')[0]) == cam.color
    assert camera_info_to_model(messages(studio_bag, 'cam3/depth/camera_info')[0]) == cam.depth
    for frame, msg in zip(gt.frames, color):
        # Hardware sync: every camera within ~1 ms of the nominal frame time.
        assert abs(stamp_to_ns(msg.header.stamp) - frame['stamp_ns']) <= 1_000_000
        assert stamp_to_ns(msg.header.stamp) == frame['stamps']['cam3']['color']
    d = image_to_numpy(depth[-1]).astype(np.float64) / 1000
    valid = d[d > 0]
    assert valid.size > 0.2 * d.size and 0.2 <= valid.min() and valid.max() < 3.86 + 0.35  # range + speckle


def _reprojection_errors(gt, frame, src, dst, n=400):
    arrays = gt.arrays(frame['index'])
    cam_s, cam_d = gt.rig.camera(src).depth, gt.rig.camera(dst).depth
    zs = arrays[f'{src}/depth_clean']
    v, u = np.nonzero(arrays[f'{src}/depth_subject'] & (zs > 0))
    pick = np.random.default_rng(0).choice(len(v), size=min(n, len(v)), replace=False)
    u, v = u[pick], v[pick]
    xy = cam_s.undistort_pixels(np.stack([u, v], axis=1).astype(float))
    p_src = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) * zs[v, u][:, None]
    p_world = transform_points(gt.T_world_depth(src), p_src)
    p_dst = transform_points(invert(gt.T_world_depth(dst)), p_world)
    px = cam_d.project(p_dst)
    zd = arrays[f'{dst}/depth_clean']
    errors = []
    for (pu, pv), p in zip(px, p_dst):
        iu, iv = int(np.floor(pu)), int(np.floor(pv))
        if not (0 <= iu < cam_d.width - 1 and 0 <= iv < cam_d.height - 1):
            continue
        patch = zd[iv:iv + 2, iu:iu + 2].astype(np.float64)
        if (patch <= 0).any() or patch.max() - patch.min() > 0.005:
            continue
        fu, fv = pu - iu, pv - iv
        z = (patch[0, 0] * (1 - fu) * (1 - fv) + patch[0, 1] * fu * (1 - fv) + patch[1, 0] * (1 - fu) * fv
             + patch[1, 1] * fu * fv)
        if abs(z - p[2]) > 0.02:        # occluded in dst: another surface is in front
            continue
        q = np.append(cam_d.undistort_pixels(np.array([[pu, pv]]))[0], 1.0) * z
        errors.append(np.linalg.norm(q - p))
    return np.array(errors)


def test_ground_truth_reprojects_across_cameras_within_1mm(studio_bag):
    gt = GroundTruth(studio_bag)
    frame = gt.frames_in('capture')[0]
    errors = np.concatenate([_reprojection_errors(gt, frame, 'cam0', dst) for dst in ('cam1', 'cam2', 'cam7')])
    assert len(errors) > 200
    assert np.percentile(errors, 95) < 0.001


def test_ground_truth_depth_lies_on_the_subject_mesh(studio_bag):
    gt = GroundTruth(studio_bag)
    frame = gt.frames_in('capture')[1]
    mesh = o3d.t.geometry.TriangleMesh.from_legacy(gt.subject_mesh(frame['index']))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    arrays = gt.arrays(frame['index'])
    cam = gt.rig.camera('cam5').depth
    v, u = np.nonzero(arrays['cam5/depth_subject'])
    z = arrays['cam5/depth_clean'][v, u]
    xy = cam.undistort_pixels(np.stack([u, v], axis=1).astype(float))
    p = transform_points(gt.T_world_depth('cam5'), np.concatenate([xy, np.ones((len(xy), 1))], axis=1) * z[:, None])
    dist = scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
    assert len(dist) > 1000 and np.percentile(dist, 99) < 1e-4


def test_depth_noise_flying_pixels_and_dropouts(studio_bag):
    gt = GroundTruth(studio_bag)
    tof = gt.doc['config']['tof']
    msgs = messages(studio_bag, 'cam0/depth/image_raw')
    flying_err, normalised, n_flying = [], [], 0
    for frame in gt.frames_in('capture'):
        arrays = gt.arrays(frame['index'])
        measured = image_to_numpy(msgs[frame['index']]).astype(np.float64) / 1000
        clean = arrays['cam0/depth_clean'].astype(np.float64)
        fly = arrays['cam0/flying']
        n_flying += fly.sum()
        flying_err.append(np.abs(measured - clean)[fly])
        ok = (measured > 0) & ~fly & ~arrays['cam0/speckle'] & (clean > 0)
        sigma = tof['noise_base'] + tof['noise_quad'] * clean[ok] ** 2
        normalised.append((measured - clean)[ok] / sigma)
        assert not (measured[arrays['cam0/dropped']] > 0).any()
    flying_err, normalised = np.concatenate(flying_err), np.concatenate(normalised)
    assert n_flying > 50
    assert np.median(flying_err) > 0.1            # mixed pixels float well off the surface behind them
    # Noise follows sigma(z) = base + quad z^2: Gaussian after normalising (median |N(0,1)| = 0.674).
    assert np.median(np.abs(normalised)) == pytest.approx(0.674, abs=0.05)
    assert abs(np.median(normalised)) < 0.05


def test_color_differs_between_cameras_as_in_a_studio(studio_bag):
    gt = GroundTruth(studio_bag)
    responses = [gt.doc['cameras'][c]['color_response'] for c in CAMS]
    assert len({round(r['gain'], 6) for r in responses}) == 8
    # The same white wall patch of the clean plate looks different in each camera's mean colour.
    means = np.array([image_to_numpy(messages(studio_bag, f'{c}/color/image_raw')[0]).reshape(-1, 3).mean(0)
                      for c in CAMS])
    chroma = means / means.sum(axis=1, keepdims=True)
    assert np.ptp(chroma[:, 0]) > 0.02 and np.ptp(chroma[:, 2]) > 0.02 and np.ptp(means.sum(axis=1)) > 60


def test_board_is_detectable_by_the_camera_it_faces(studio_bag):
    gt = GroundTruth(studio_bag)
    board = BoardConfig.from_yaml()
    detector = cv2.aruco.CharucoDetector(board.charuco_board())
    frame = gt.frames_in('calibration')[0]       # the first pose faces the front stand (cam0, cam1)
    best = 0
    for cam in ('cam0', 'cam1'):
        img = image_to_numpy(messages(studio_bag, f'{cam}/color/image_raw')[frame['index']])
        corners, ids, _, _ = detector.detectBoard(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
        best = max(best, 0 if ids is None else len(ids))
    assert best >= 20


def test_every_camera_sees_the_board_in_some_poses(shared_data):
    cfg = SynthConfig(board_poses=12)
    rng = np.random.default_rng(0)
    rig, T_studio_color = make_rig(cfg, rng)
    board = BoardConfig.from_yaml()
    corners = board.charuco_corners()
    seen = {c.name: 0 for c in rig.cameras}
    pairs = set()
    for T_board in board_poses(cfg, board, rng):
        viewers = []
        for cam in rig.cameras:
            T_cam_board = invert(T_studio_color[cam.name]) @ T_board
            pts = transform_points(T_cam_board, corners)
            facing = T_cam_board[:3, 2] @ (T_cam_board[:3, 3] / np.linalg.norm(T_cam_board[:3, 3])) > 0.3
            px = cam.color.project(pts)
            inside = (pts[:, 2] > 0).all() and ((px >= 0) & (px < [cam.color.width, cam.color.height])).all()
            if facing and inside:
                viewers.append(cam.name)
                seen[cam.name] += 1
        pairs |= {(a, b) for a in viewers for b in viewers if a < b}
    assert min(seen.values()) >= 2
    # The views chain every camera to cam0 through shared board poses.
    linked, frontier = {'cam0'}, ['cam0']
    while frontier:
        a = frontier.pop()
        for x, y in pairs:
            for p, q in ((x, y), (y, x)):
                if p == a and q not in linked:
                    linked.add(q)
                    frontier.append(q)
    assert linked == set(seen)


def _digest(path):
    h = hashlib.sha256()
    with BagReader(path) as r:
        for m in r.messages():
            # Decoded, not raw CDR: the serialiser leaves its alignment padding uninitialised.
            msg = m.decode()
            h.update(f'{m.topic} {m.stamp_ns}'.encode())
            if isinstance(msg, Image):
                h.update(f'{msg.header} {msg.encoding}'.encode() + bytes(msg.data))
            else:
                h.update(repr(msg).encode())
    for f in sorted((path / 'ground_truth' / 'frames').glob('*.npz')):
        with np.load(f) as npz:
            for k in sorted(npz.files):
                h.update(npz[k].tobytes())
    return h.hexdigest()


@pytest.mark.slow
def test_synth_is_deterministic_for_a_seed(tmp_path, shared_data):
    cfg = dict(cameras=2, frames=1, board_poses=1, background_frames=0)
    a = synthesize(tmp_path / 'a', SynthConfig(seed=5, **cfg), progress=False)
    b = synthesize(tmp_path / 'b', SynthConfig(seed=5, **cfg), progress=False)
    c = synthesize(tmp_path / 'c', SynthConfig(seed=6, **cfg), progress=False)
    assert _digest(a.path) == _digest(b.path) != _digest(c.path)
    with pytest.raises(FileExistsError):
        synthesize(tmp_path / 'a', SynthConfig(seed=5, **cfg), progress=False)


@pytest.mark.slow
def test_bunny_scene_and_bad_options(tmp_path, shared_data):
    s = synthesize(tmp_path / 'bunny', SynthConfig(cameras=1, frames=1, board_poses=0, background_frames=0,
                                                   scene='bunny'), progress=False)
    gt = GroundTruth(s.path)
    assert gt.arrays(0)['cam0/depth_subject'].sum() > 1000
    assert set(gt.arrays(0, suffix='/dropped')) == {f'cam{i}/dropped' for i in range(len(gt.rig.cameras))}
    with pytest.raises(ValueError, match='scene'):
        SynthConfig(scene='dragon')
    with pytest.raises(FileNotFoundError, match='VOLCAP_DATA'):
        SynthConfig(k4a_calibration=str(tmp_path / 'missing.json'))
