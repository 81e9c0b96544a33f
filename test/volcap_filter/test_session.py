"""The depth filter's clean-plate session, without ROS: phase order, late camera models and rig,
held frames, re-learning and rebuilding the cleaner when its inputs change."""
import numpy as np
import pytest

from volcap_core import topics
from volcap_core.camera import CameraModel
from volcap_core.rig import Rig, RigCamera
from volcap_filter.pipeline import DepthFilterConfig
from volcap_filter.session import CleanPlateSession, FramePair

COLOR = CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5)
DEPTH = CameraModel(32, 24, 25.0, 25.0, 15.5, 11.5)


def _rig(offset=0.0):
    T = np.eye(4)
    T[0, 3] = offset
    return Rig([RigCamera('cam0', COLOR, DEPTH, T)])


def _pair(stamp, subject=False, registered=False):
    color = np.full((COLOR.height, COLOR.width, 3), 90, np.uint8)
    depth = np.full((DEPTH.height, DEPTH.width), 2.0, np.float32)
    if subject:   # a bright box 1 m in front of the wall
        color[12:36, 16:48] = (230, 40, 40)
        depth[6:18, 8:24] = 1.0
    return FramePair(stamp, 'cam0_color_optical_frame', registered, (color, depth))


def _session(**kw):
    return CleanPlateSession('cam0', DepthFilterConfig(), lambda arrays: arrays, **kw)


def _kinds(outcomes):
    return [o.kind for o in outcomes]


def _ready(session, rig=True):
    if rig:
        session.set_rig(_rig())
    session.set_model('color', COLOR)
    session.set_model('depth', DEPTH)


def test_clean_plate_phase_is_learnt_then_capture_is_cleaned_against_it():
    s = _session()
    _ready(s)
    s.set_phase(topics.CLEAN_PLATE)
    assert _kinds(s.add(_pair(1))) == ['learnt'] and _kinds(s.add(_pair(2))) == ['learnt']
    assert _kinds(s.set_phase(topics.CAPTURE)) == ['plate_done']
    assert s.background.frames == 2
    out = s.add(_pair(3, subject=True))
    assert _kinds(out) == ['cleaned']
    result = out[0].result
    assert result.depth.shape == (COLOR.height, COLOR.width)   # full colour size by default
    assert result.mask is not None and result.mask[24, 32] and not result.mask[2, 2]
    kept = result.depth > 0
    assert kept[24, 32] and not kept[2, 2]     # the wall (clean plate) is masked out, the subject kept


def test_frames_before_their_camera_models_or_rig_are_held_then_cleaned_in_order():
    s = _session(max_held=4)
    s.set_phase(topics.CLEAN_PLATE)
    out = s.add(_pair(1)) + s.add(_pair(2))
    assert _kinds(out) == ['held', 'held'] and 'camera_info' in out[0].message
    s.set_model('color', COLOR)
    assert _kinds(s.set_model('depth', DEPTH)) == ['held']       # still no depth-to-colour extrinsic
    assert 'rig' in s.waiting_for(_pair(3))
    s.set_phase(topics.CAPTURE)      # the plate phase ends while its frames are still held
    out = s.set_rig(_rig())
    # held clean-plate frames are learnt in their own phase, then the plate is complete
    assert _kinds(out) == ['learnt', 'learnt', 'plate_done']
    assert s.background.frames == 2


def test_registered_depth_needs_no_rig():
    s = _session()
    _ready(s, rig=False)
    assert _kinds(s.add(_pair(1, subject=True, registered=True))) == ['cleaned']


def test_held_frames_beyond_the_limit_are_skipped_oldest_first():
    s = _session(max_held=2)
    out = []
    for k in range(4):
        out += s.add(_pair(k))
    skipped = [o for o in out if o.kind == 'skipped']
    assert [o.pair.stamp_ns for o in skipped] == [0, 1]
    assert [p.stamp_ns for p, _ in s.held] == [2, 3]


def test_an_empty_plate_phase_is_reported():
    s = _session(max_held=0)
    s.set_phase(topics.CLEAN_PLATE)
    out = s.add(_pair(1)) + s.set_phase(topics.CAPTURE)
    assert _kinds(out) == ['skipped', 'skipped']
    assert 'no frame learnt' in out[-1].message


def test_capture_request_relearns_the_plate_and_the_cleaner_follows_new_inputs():
    s = _session()
    _ready(s)
    s.set_phase(topics.CLEAN_PLATE)
    s.add(_pair(1))
    s.set_phase(topics.CAPTURE)
    first = s.add(_pair(2, subject=True))[0].cleaner
    s.capture_clean_plate(2)                 # operator asks for a new plate mid-capture
    assert s.background.frames == 0
    assert _kinds(s.add(_pair(3)) + s.add(_pair(4))) == ['learnt', 'learnt', 'plate_done']
    assert _kinds(s.add(_pair(5, subject=True))) == ['cleaned']
    assert s.cleaner is first                # same inputs: the cleaner is kept
    s.set_rig(_rig(offset=0.05))             # a new extrinsic rebuilds it, with the same plate
    cleaned = s.add(_pair(6, subject=True))[0]
    assert cleaned.cleaner is not first and cleaned.cleaner.background is s.background
    s.set_model('color', COLOR.scaled(32, 24))
    assert s.add(_pair(7, subject=True))[0].kind == 'failed'   # the image no longer matches its camera_info
    s.set_config(DepthFilterConfig(boundary_px=0))
    assert s.cleaner.cfg.boundary_px == 0          # the running cleaner takes a new config at once


def test_a_missing_clean_plate_is_told_once_capture_frames_are_cleaned_without_one():
    s = _session()
    _ready(s)
    assert not s.missing_clean_plate                 # a graph starting: no frame yet
    s.set_phase(topics.CALIBRATION_PHASE)
    assert _kinds(s.add(_pair(1))) == ['cleaned']
    assert not s.missing_clean_plate                 # the board phase needs no plate
    s.set_phase(topics.CLEAN_PLATE)
    s.add(_pair(2))
    s.set_phase(topics.CAPTURE)
    s.add(_pair(3, subject=True))
    assert s.has_clean_plate and not s.missing_clean_plate
    bare = _session()                                # a driver with no session phase, no plate
    _ready(bare)
    assert _kinds(bare.add(_pair(1, subject=True))) == ['cleaned']
    assert bare.missing_clean_plate
    bare.capture_clean_plate(1)                      # the operator asked: being learnt
    assert not bare.missing_clean_plate
    unmasked = CleanPlateSession('cam0', DepthFilterConfig(mask_mode='none'), lambda arrays: arrays)
    _ready(unmasked)
    unmasked.add(_pair(1, subject=True))
    assert not unmasked.missing_clean_plate          # nothing asks for a plate


def test_a_rig_without_this_camera_is_refused():
    s = _session()
    with pytest.raises(KeyError):
        s.set_rig(Rig([RigCamera('cam5', COLOR, DEPTH)]))
    assert s.rig is None
