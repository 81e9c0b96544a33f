"""The fusion node's frame-set step without ROS: complete, incomplete and empty frame sets,
unusable cameras and the min_cameras policy."""
import numpy as np
import pytest

from volcap_core import topics
from volcap_core.camera import CameraModel
from volcap_fusion.frame_sets import ALL, frame_set_views, fused_cameras, fused_phase
from volcap_fusion.tsdf import CameraView

LENS = CameraModel(32, 24, 25.0, 25.0, 15.5, 11.5)
CAMERAS = ['cam0', 'cam1', 'cam2']


def to_view(camera, part):
    depth_mm, rgb = part
    return CameraView(camera, depth_mm, LENS, rgb, LENS, np.eye(4))


def good():
    return np.full((24, 32), 1500, np.uint16), np.zeros((24, 32, 3), np.uint8)


def test_a_complete_frame_set_gives_every_view():
    plan = frame_set_views(7, CAMERAS, {c: good() for c in CAMERAS}, to_view, min_cameras=1)
    assert [v.name for v in plan.views] == CAMERAS and plan.missing == [] and not plan.skipped


def test_missing_and_unusable_cameras_are_left_out_and_named():
    depth, rgb = good()
    parts = {'cam0': (depth, rgb), 'cam2': (depth[:, :10], rgb)}     # cam1 absent, cam2 mis-sized
    plan = frame_set_views(7, CAMERAS, parts, to_view, min_cameras=1)
    assert [v.name for v in plan.views] == ['cam0']
    assert plan.missing == ['cam1', 'cam2'] and 'camera_info says' in plan.problems['cam2']
    assert not plan.skipped


def test_fewer_than_min_cameras_skips_the_set():
    plan = frame_set_views(7, CAMERAS, {'cam1': good()}, to_view, min_cameras=2)
    assert plan.skipped == 'frame set 7 skipped: 1 of 3 cameras (missing cam0, cam2)'


def test_an_empty_frame_set_is_skipped():
    plan = frame_set_views(7, CAMERAS, {}, to_view, min_cameras=1)
    assert plan.views == [] and plan.missing == CAMERAS and plan.skipped.startswith('frame set 7 skipped: 0 of 3')


def test_phase_filter():
    phases = (topics.CAPTURE,)
    assert fused_phase(None, phases) and fused_phase(topics.CAPTURE, phases)
    assert not fused_phase(topics.CLEAN_PLATE, phases) and fused_phase(topics.CLEAN_PLATE, ())


def test_cameras_to_fuse_come_from_the_calibration_or_the_parameter():
    assert fused_cameras(CAMERAS, [ALL]) == CAMERAS
    assert fused_cameras(CAMERAS, ['cam2', 'cam0']) == ['cam2', 'cam0']
    with pytest.raises(ValueError, match=r"\['cam9'\] are not in the calibration"):
        fused_cameras(CAMERAS, ['cam0', 'cam9'])


def test_a_frame_set_keeps_the_phase_it_was_captured_in():
    from volcap_fusion.frame_sets import PhaseTimeline
    timeline = PhaseTimeline()
    assert timeline.at(5) is None
    timeline.change('clean_plate')
    for stamp in (10, 20):
        timeline.frame(stamp)
    timeline.change('capture')          # sent after the frames stamped 20 and before
    timeline.frame(30)
    # A set stamped 20 emitted now (it waited for a late camera) is still clean plate.
    assert timeline.at(20) == 'clean_plate' and timeline.at(10) == 'clean_plate'
    assert timeline.at(30) == 'capture' and timeline.at(25) == 'capture'


def test_a_phase_change_with_its_stamp_holds_however_late_the_frames_come():
    """The fusion sees the camera pipelines' output, which trails the player's phase messages:
    when `capture` is announced the last calibration views may still be in the pipelines. With
    ``since_ns`` they keep their phase; placed by arrival they would be fused as capture."""
    from volcap_fusion.frame_sets import PhaseTimeline
    timeline = PhaseTimeline()
    timeline.change('calibration', since_ns=0)
    timeline.frame(10)                            # the pipelines have delivered up to 10 ...
    timeline.change('capture', since_ns=100)      # ... when the player announces capture from 100
    for stamp in (20, 30, 40, 110):
        timeline.frame(stamp)
    assert [timeline.at(s) for s in (20, 30, 40, 99)] == ['calibration'] * 4
    assert timeline.at(100) == 'capture' and timeline.at(110) == 'capture'
    arrival = PhaseTimeline()
    arrival.change('calibration')
    arrival.frame(10)
    arrival.change('capture')
    assert arrival.at(30) == 'capture'            # what happened before since_ns
