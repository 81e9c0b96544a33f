"""calibration_service in its own process: a replayed calibration bag, then volcap/calibrate;
success publishes the latched calibration and camera poses, failure leaves the file alone."""
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from std_msgs.msg import String
from std_srvs.srv import Trigger

from volcap_bringup.processes import start_node
from volcap_core import qos, topics
from volcap_core.calibration import Calibration
from volcap_studio.session import GroundTruth

pytestmark = pytest.mark.ros


def _played(bag):
    cams = GroundTruth(bag).rig.names
    return [f'{c}/{t}' for c in cams for t in (topics.COLOR_IMAGE, topics.COLOR_INFO, topics.DEPTH_IMAGE,
                                               topics.DEPTH_INFO)] + [topics.RIG, topics.PHASE]


def _replay_and_call(bag, probe, procs, output):
    gt = GroundTruth(bag)
    sets = len(gt.frames_in(topics.CALIBRATION_PHASE))
    probe.subscribe('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)
    procs.append(start_node('volcap_calib', 'calibration_service', {'output': str(output), 'cameras': gt.rig.names}))
    # The player stays up after the bag ends so that its latched rig description stays available.
    procs.append(start_node('volcap_driver', 'bag_player', {'bag': str(bag), 'wait_for_subscribers': 60.0,
                                                            'topics': _played(bag), 'exit_when_done': False,
                                                            'rate': 0.05}))   # spaced: sensor QoS drops bursts

    def gathered():
        return any(s.message.endswith(f'in {sets} frame sets') for _, m in probe.got['/' + topics.DIAGNOSTICS]
                   for s in m.status if 'calibration_service' in s.name)
    assert probe.spin_until(gathered, timeout=120), 'the service did not gather the board views'
    client = probe.node.create_client(Trigger, '/' + topics.CALIBRATE)
    assert client.wait_for_service(timeout_sec=30)
    future = client.call_async(Trigger.Request())
    assert probe.spin_until(future.done, timeout=180), 'calibrate call did not return'
    return future.result()


def test_calibrate_service_publishes_latched_calibration(calib_bag, ros_context, procs, tmp_path, probe_factory):
    output = tmp_path / 'calibration.yaml'
    probe = probe_factory([])
    try:
        result = _replay_and_call(calib_bag, probe, procs, output)
        assert result.success, result.message
        assert output.exists() and set(Calibration.load(output).cameras) == {'cam0', 'cam1'}
        # a subscriber that arrives afterwards still gets both (transient local)
        probe.subscribe('/' + topics.CALIBRATION, String, qos.LATCHED)
        probe.subscribe('/' + topics.CAMERA_POSES, PoseArray, qos.LATCHED)
        assert probe.spin_until(lambda: probe.got['/' + topics.CALIBRATION] and probe.got['/' + topics.CAMERA_POSES],
                                timeout=30)
        published = Calibration.from_yaml(probe.got['/' + topics.CALIBRATION][-1][1].data)
        assert published.reference == 'cam0'
        assert len(probe.got['/' + topics.CAMERA_POSES][-1][1].poses) == 2
    finally:
        probe.close()


def test_calibrate_service_failure_names_the_camera_and_keeps_the_file(calib_bag_blind_camera, ros_context, procs,
                                                                       tmp_path, probe_factory):
    output = tmp_path / 'calibration.yaml'
    output.write_text('previous calibration\n')
    probe = probe_factory([])
    try:
        result = _replay_and_call(calib_bag_blind_camera, probe, procs, output)
        assert not result.success
        assert 'cam2' in result.message and 'unchanged' in result.message
        assert output.read_text() == 'previous calibration\n'
    finally:
        probe.close()
