"""camera_pipeline in its own process, one per camera of a replayed studio bag: colour and depth
received once, cleaned depth and corrected colour out, and the same images as the offline
replay of the same bag through CameraPipeline (the node drives the same class)."""
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Image
from std_msgs.msg import String

from volcap_bringup.processes import start_node
from volcap_color.corrector import CameraCorrection
from volcap_core import qos, topics
from volcap_core.calibration import Calibration, CameraCalibration
from volcap_core.camera import depth_to_millimetres
from volcap_core.conversions import image_to_numpy, stamp_to_ns
from volcap_core.frames import frame_sets
from volcap_filter.pipeline import DepthFilterConfig
from volcap_pipeline.replay import cleaned_frame_sets
from volcap_studio.session import GroundTruth

pytestmark = pytest.mark.ros


def _calibration(cameras, gain):
    """Every camera with a 3x3 model that scales linear RGB by ``gain``."""
    color = {'method': 'matrix_3x3', 'matrix': (np.eye(3) * gain).tolist()}
    return Calibration(cameras[0], f'{cameras[0]}_color_optical_frame',
                       {c: CameraCalibration(np.eye(4), f'{c}_color_optical_frame', color=color) for c in cameras})


def test_every_camera_is_cleaned_and_corrected_as_the_replay_does(studio_bag, ros_context, procs, play,
                                                                  probe_factory):
    cams = GroundTruth(studio_bag).rig.names
    calibration = _calibration(cams, 0.25)
    capture_from = min(fs.stamp_ns for fs in frame_sets(studio_bag, phases=(topics.CAPTURE,))) - 5_000_000
    outputs = [(f'/{c}/{t}', Image, qos.EVERY_FRAME) for c in cams for t in (topics.DEPTH_CLEAN, topics.COLOR_CORRECTED)]
    probe = probe_factory(outputs + [('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    calib_pub = probe.node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
    calib_pub.publish(String(data=calibration.to_yaml()))

    def captured(topic):
        return {stamp_to_ns(m.header.stamp): m for _, m in probe.got[topic] if stamp_to_ns(m.header.stamp) >= capture_from}

    def statuses():
        return {s.name: {v.key: v.value for v in s.values} for _, m in probe.got['/' + topics.DIAGNOSTICS]
                for s in m.status if s.name.startswith('camera_pipeline')}

    try:
        for c in cams:
            procs.append(start_node('volcap_pipeline', 'camera_pipeline', {'reliable': True}, namespace=c))
        # Every pipeline has its colour model before the bag plays: its process is up and past
        # discovery, as on a rig where the cameras run long before a take (a node still starting
        # may see a frame before the phase it was sent in, and learn no clean plate).
        assert probe.spin_until(lambda: sum('color_median_ms' in v for v in statuses().values()) == len(cams), 60)
        played = [f'{c}/{t}' for c in cams for t in (topics.COLOR_IMAGE, topics.COLOR_INFO, topics.DEPTH_IMAGE,
                                                     topics.DEPTH_INFO)] + [topics.RIG, topics.PHASE]
        # the player starts once every pipeline subscribes (each camera's streams have one
        # subscriber, their pipeline: received once)
        play(studio_bag, wait_for_subscribers=60.0, topics=played,
             subscribers=[f'{t}=1' for t in played[:-2]] + [f'{t}={len(cams)}' for t in played[-2:]])
        assert probe.spin_until(lambda: all(len(captured(t)) == 2 for t, _, _ in outputs), timeout=150), \
            {t: len(captured(t)) for t, _, _ in outputs}
        # each one's diagnostics carry both halves of the job
        assert probe.spin_until(lambda: all(int(v.get('processed', 0)) >= 2 and int(v['color_corrected']) >= 2
                                            for v in statuses().values()), timeout=30), statuses()
    finally:
        probe.close()

    # the offline replay of the same bag through CameraPipeline: the same depth, the same colour
    # (a frame set's stamp is within a few ms of each camera's own)
    offline = [(fs.stamp_ns, cleaned['volcap']) for fs, cleaned in
               cleaned_frame_sets(studio_bag, {'volcap': DepthFilterConfig()})]
    for c in cams:
        correction = CameraCorrection(c)
        assert correction.set_calibration(calibration.to_yaml())[0]
        depth, color = captured(f'/{c}/{topics.DEPTH_CLEAN}'), captured(f'/{c}/{topics.COLOR_CORRECTED}')
        assert sorted(depth) == sorted(color) and len(color) == len(offline), c
        for stamp, msg in color.items():
            assert msg.encoding == 'rgb8' and msg.header.frame_id == f'{c}_color_optical_frame'
            set_stamp, cleaned = min(offline, key=lambda o: abs(o[0] - stamp))
            assert abs(set_stamp - stamp) < 5_000_000
            ours = cleaned[c]
            np.testing.assert_array_equal(image_to_numpy(msg), correction.apply(ours.result.source_color))
            live_mm = image_to_numpy(depth[stamp]).astype(np.int32)
            replay_mm = depth_to_millimetres(ours.result.depth).astype(np.int32)
            assert live_mm.shape == replay_mm.shape == ours.frame.color.shape[:2]
            assert np.count_nonzero(live_mm) > 1000
            np.testing.assert_array_equal(live_mm, replay_mm, err_msg=c)      # the same decisions, bit for bit
