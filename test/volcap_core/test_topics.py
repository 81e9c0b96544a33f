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
