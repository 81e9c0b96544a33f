"""Topic names and the session phase messages."""
from volcap_core import topics


def test_phase_messages_are_parsed_and_anything_else_is_none():
    assert topics.parse_phase('{phase: clean_plate, frames: 3}') == topics.CLEAN_PLATE
    assert topics.parse_phase('phase: capture') == topics.CAPTURE
    for text in ('', 'just text', '[1, 2]', '{phase: [a]}', '{frames: 3}', 'phase: {'):
        assert topics.parse_phase(text) is None, text


def test_camera_topics_are_relative():
    assert topics.camera_topic('cam3', topics.DEPTH_CLEAN) == 'cam3/depth/image_clean'
    assert topics.camera_names(3) == ['cam0', 'cam1', 'cam2']


def test_a_phase_change_may_say_from_which_stamp_it_holds():
    assert topics.parse_phase_change('{phase: capture, frames: 2, since_ns: 1500}') == (topics.CAPTURE, 1500)
    assert topics.parse_phase_change('{phase: capture, frames: 2}') == (topics.CAPTURE, None)
    assert topics.parse_phase_change('{phase: capture, since_ns: soon}') == (topics.CAPTURE, None)
    assert topics.parse_phase_change('not: [a phase') == (None, None)
