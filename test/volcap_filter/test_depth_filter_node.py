"""depth_filter in its own process: a replayed studio bag in, clean depth and points out on
every camera; bad frames are reported on diagnostics and the node keeps going."""

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String

from volcap_bringup.processes import start_node
from volcap_core import qos, topics
from volcap_core.camera import depth_to_millimetres
from volcap_core.conversions import camera_model_to_info, image_to_numpy, numpy_to_image, pointcloud2_to_points, stamp_to_ns
from volcap_core.frames import frame_sets
from volcap_studio.session import GroundTruth

pytestmark = pytest.mark.ros


def test_filter_nodes_clean_a_replayed_bag_on_every_camera(studio_bag, ros_context, procs, play, probe_factory):
    cams = GroundTruth(studio_bag).rig.names
    # The board frames come first and may be all background; the checks are on the capture frames.
    capture_from = min(fs.stamp_ns for fs in frame_sets(studio_bag, phases=(topics.CAPTURE,))) - 5_000_000
    outputs = [(f'/{c}/{t}', kind, qos.EVERY_FRAME) for c in cams
               for t, kind in ((topics.DEPTH_CLEAN, Image), (topics.POINTS, PointCloud2))]
    probe = probe_factory(outputs)

    def captured(topic):
        return [m for _, m in probe.got[topic] if stamp_to_ns(m.header.stamp) >= capture_from]

    try:
        for c in cams:
            procs.append(start_node('volcap_filter', 'depth_filter', {}, namespace=c))
        played = [f'{c}/{t}' for c in cams for t in (topics.COLOR_IMAGE, topics.COLOR_INFO, topics.DEPTH_IMAGE,
                                                     topics.DEPTH_INFO)] + [topics.RIG, topics.PHASE]
        play(studio_bag, wait_for_subscribers=60.0, topics=played, rate=0.5)
        assert probe.spin_until(lambda: all(captured(t) for t, _, _ in outputs), timeout=150), \
            f'no capture frame on {[t for t, _, _ in outputs if not captured(t)]}'
    finally:
        probe.close()
    for c in cams:
        img = captured(f'/{c}/{topics.DEPTH_CLEAN}')[-1]
        depth = image_to_numpy(img)
        assert img.encoding == '16UC1' and depth.shape == (720, 1280)     # the colour size: the default
        assert img.header.frame_id == f'{c}_color_optical_frame'
        valid = depth[depth > 0]
        assert valid.size > 1000 and valid.min() >= 100 and valid.max() <= 2500
        xyz, rgb = pointcloud2_to_points(captured(f'/{c}/{topics.POINTS}')[-1])
        assert len(xyz) > 1000 and rgb is not None


def _one_camera(ros_context, cam, profile, probe_factory):
    """A probe on the camera's clean depth (reliable: the tests send single frames) and the
    diagnostics, and publishers for its inputs and the rig."""
    probe = probe_factory([(f'/{cam}/{topics.DEPTH_CLEAN}', Image, qos.EVERY_FRAME),
                           ('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    pubs = {t: probe.node.create_publisher(k, f'/{cam}/{t}', profile)
            for t, k in ((topics.COLOR_IMAGE, Image), (topics.COLOR_INFO, CameraInfo), (topics.DEPTH_IMAGE, Image),
                         (topics.DEPTH_INFO, CameraInfo))}
    return probe, pubs, probe.node.create_publisher(String, '/' + topics.RIG, qos.LATCHED)


def _inputs_matched(probe, pubs):
    # The node's diagnostics writer must be matched too, or its first report can be lost.
    return probe.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values())
                            and probe.node.count_publishers('/' + topics.DIAGNOSTICS), timeout=60)


def _diagnosed(probe, text):
    return any(text in s.message for _, m in probe.got['/' + topics.DIAGNOSTICS] for s in m.status)


def test_bad_frames_are_reported_and_skipped(studio_bag, ros_context, procs, probe_factory):
    cam = 'cam1'
    frame = next(fs for fs in frame_sets(studio_bag, phases=('capture',))).cameras[cam]
    rig = GroundTruth(studio_bag).rig
    probe, pubs, rig_pub = _one_camera(ros_context, cam, qos.DRIVER, probe_factory)
    try:
        procs.append(start_node('volcap_filter', 'depth_filter', {'mask_mode': 'none'}, namespace=cam))
        assert _inputs_matched(probe, pubs)
        color_frame, depth_frame = f'{cam}_color_optical_frame', f'{cam}_depth_optical_frame'
        stamp = [1_000_000_000]

        def send(depth, encoding='16UC1', infos=True, depth_info=None):
            stamp[0] += 100_000_000
            if infos:
                pubs[topics.COLOR_INFO].publish(camera_model_to_info(frame.color_model, stamp[0], color_frame))
                info = camera_model_to_info(frame.depth_model, stamp[0], depth_frame)
                for field, value in (depth_info or {}).items():
                    setattr(info, field, value)
                pubs[topics.DEPTH_INFO].publish(info)
            probe.spin_until(lambda: False, 0.2)
            pubs[topics.COLOR_IMAGE].publish(numpy_to_image(frame.color, 'rgb8', stamp[0], color_frame))
            pubs[topics.DEPTH_IMAGE].publish(numpy_to_image(depth, encoding, stamp[0], depth_frame))

        def reported(text, *frame_args, **frame_kwargs):
            # Resent every 2 s: a frame sent while discovery settles may be lost, the node is not at fault.
            for _ in range(10):
                send(*frame_args, **frame_kwargs)
                if probe.spin_until(lambda: _diagnosed(probe, text), 2):
                    return True
            return False

        good = depth_to_millimetres(frame.depth)
        assert reported('no camera_info yet', good, infos=False)
        assert reported('waiting for the depth-to-colour extrinsic', good)
        rig_pub.publish(String(data=rig.to_yaml()))
        assert reported('camera_info says', good[:100, :100].copy())
        assert reported('no valid pixel', np.zeros_like(good))
        assert reported('depth image expected', good.astype(np.uint8), encoding='mono8')
        # camera_info a node must not trust: a size that would exhaust memory, NaN distortion
        assert reported('pixels a side', good, depth_info={'width': 1_000_000, 'height': 1_000_000})
        assert reported('distortion coefficients must be finite', good, depth_info={'d': [float('nan')] * 5})
        send(good)
        assert probe.spin_until(lambda: probe.got[f'/{cam}/{topics.DEPTH_CLEAN}'], 30)
        assert procs[-1].poll() is None
    finally:
        probe.close()


def test_frames_that_come_before_their_camera_info_are_held_not_lost(studio_bag, ros_context, procs, probe_factory):
    """Images and camera_info are separate topics: a clean-plate frame whose camera_info comes
    after it, even after the phase has ended, is still learnt, and a capture frame still cleaned."""
    cam = 'cam2'
    plate = next(fs for fs in frame_sets(studio_bag, phases=(topics.CLEAN_PLATE,))).cameras[cam]
    frame = next(fs for fs in frame_sets(studio_bag, phases=(topics.CAPTURE,))).cameras[cam]
    rig = GroundTruth(studio_bag).rig
    probe, pubs, rig_pub = _one_camera(ros_context, cam, qos.EVERY_FRAME, probe_factory)
    phase_pub = probe.node.create_publisher(String, '/' + topics.PHASE, qos.LATCHED)
    color_frame, depth_frame = f'{cam}_color_optical_frame', f'{cam}_depth_optical_frame'

    def images(f, stamp):
        pubs[topics.COLOR_IMAGE].publish(numpy_to_image(f.color, 'rgb8', stamp, color_frame))
        pubs[topics.DEPTH_IMAGE].publish(numpy_to_image(depth_to_millimetres(f.depth), '16UC1', stamp, depth_frame))

    def infos(f, stamp):
        pubs[topics.COLOR_INFO].publish(camera_model_to_info(f.color_model, stamp, color_frame))
        pubs[topics.DEPTH_INFO].publish(camera_model_to_info(f.depth_model, stamp, depth_frame))

    def status(key):
        values = [{kv.key: kv.value for kv in s.values} for _, m in probe.got['/' + topics.DIAGNOSTICS]
                  for s in m.status]
        return [v[key] for v in values if key in v]

    try:
        rig_pub.publish(String(data=rig.to_yaml()))
        phase_pub.publish(String(data=f'phase: {topics.CLEAN_PLATE}'))
        procs.append(start_node('volcap_filter', 'depth_filter', {'reliable': True}, namespace=cam))
        assert _inputs_matched(probe, pubs) and probe.spin_until(
            lambda: rig_pub.get_subscription_count() and phase_pub.get_subscription_count(), 30)
        probe.spin_until(lambda: False, 1.0)   # the latched rig and phase reach the node first
        images(plate, 1_000_000_000)
        assert probe.spin_until(lambda: _diagnosed(probe, 'no camera_info yet; 1 frame(s) held'), 30)
        phase_pub.publish(String(data=f'phase: {topics.CAPTURE}'))
        probe.spin_until(lambda: False, 1.0)
        infos(plate, 1_000_000_000)
        images(frame, 2_000_000_000)
        assert probe.spin_until(lambda: probe.got[f'/{cam}/{topics.DEPTH_CLEAN}'], 30)
        assert probe.spin_until(lambda: '1' in status('clean_plate_frames'), 10)
        assert status('mask')[-1] == 'clean_plate' and status('skipped')[-1] == '0'
        depth = image_to_numpy(probe.got[f'/{cam}/{topics.DEPTH_CLEAN}'][-1][1])
        assert 1000 < np.count_nonzero(depth) < 0.5 * depth.size   # the subject kept, the studio masked out
    finally:
        probe.close()


def test_parameters_change_while_running_and_invalid_combinations_are_refused(ros_context):
    """Parameters come from the config dataclasses (volcap_core.ros.declare_config): a change is
    validated as a whole configuration, read-only ones are refused, good ones reach the session."""
    from rclpy.parameter import Parameter

    from volcap_filter.depth_filter_node import DepthFilter
    node = DepthFilter(context=ros_context, namespace='cam3')
    try:
        assert node.session.camera == 'cam3' and node.session.output_size == (0, 0)
        assert node.get_parameter('max_range').value == 2.5
        descriptor = node.describe_parameter('min_axes')
        assert descriptor.integer_range[0].from_value == 1 and descriptor.integer_range[0].to_value == 4
        ok, = node.set_parameters([Parameter('boundary_px', value=4)])
        assert ok.successful and node.session.cfg.boundary_px == 4
        bad, = node.set_parameters([Parameter('min_range', value=3.0)])     # in range, but beyond max_range
        assert not bad.successful and 'min_range < max_range' in bad.reason
        assert node.session.cfg.mask.min_range == 0.1 and node.get_parameter('min_range').value == 0.1
        fixed, = node.set_parameters([Parameter('output_width', value=640)])
        assert not fixed.successful                                           # read-only
        ok, = node.set_parameters([Parameter('publish_points', value=False)])
        assert ok.successful and node.node_cfg.publish_points is False
    finally:
        node.destroy_node()


def test_an_operator_captures_a_clean_plate_that_is_saved_and_loaded_again(studio_bag, ros_context, procs,
                                                                             probe_factory, tmp_path):
    """On a rig nobody announces phases: the operator empties the stage and calls
    ~/capture_clean_plate; the plate learnt from the next frames is saved to background_file, and
    a node started later with that file masks the studio from its very first frame."""
    from std_srvs.srv import Trigger

    from volcap_bringup.processes import stop
    cam = 'cam1'
    plate = next(fs for fs in frame_sets(studio_bag, phases=(topics.CLEAN_PLATE,))).cameras[cam]
    frame = next(fs for fs in frame_sets(studio_bag, phases=(topics.CAPTURE,))).cameras[cam]
    rig = GroundTruth(studio_bag).rig
    saved = tmp_path / 'plates' / f'{cam}.npz'
    saved.parent.mkdir()
    probe, pubs, rig_pub = _one_camera(ros_context, cam, qos.EVERY_FRAME, probe_factory)
    color_frame, depth_frame = f'{cam}_color_optical_frame', f'{cam}_depth_optical_frame'
    stamp = [1_000_000_000]

    def send(f):
        stamp[0] += 100_000_000
        pubs[topics.COLOR_INFO].publish(camera_model_to_info(f.color_model, stamp[0], color_frame))
        pubs[topics.DEPTH_INFO].publish(camera_model_to_info(f.depth_model, stamp[0], depth_frame))
        pubs[topics.COLOR_IMAGE].publish(numpy_to_image(f.color, 'rgb8', stamp[0], color_frame))
        pubs[topics.DEPTH_IMAGE].publish(numpy_to_image(depth_to_millimetres(f.depth), '16UC1', stamp[0], depth_frame))

    def cleaned_after(count):
        assert probe.spin_until(lambda: len(probe.got[f'/{cam}/{topics.DEPTH_CLEAN}']) > count, 30)
        return image_to_numpy(probe.got[f'/{cam}/{topics.DEPTH_CLEAN}'][-1][1])

    params = {'reliable': True, 'background_file': str(saved), 'clean_plate_frames': 1}
    try:
        rig_pub.publish(String(data=rig.to_yaml()))
        node = start_node('volcap_filter', 'depth_filter', params, namespace=cam)
        procs.append(node)
        assert _inputs_matched(probe, pubs) and probe.spin_until(lambda: rig_pub.get_subscription_count(), 30)
        send(frame)      # no plate yet: everything in range is kept
        unmasked = np.count_nonzero(cleaned_after(0))
        client = probe.node.create_client(Trigger, f'/{cam}/depth_filter/capture_clean_plate')
        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(Trigger.Request())
        assert probe.spin_until(future.done, 30) and future.result().success, future.result()
        send(plate)      # the empty stage: learnt, not cleaned
        assert probe.spin_until(saved.exists, 30)
        send(frame)
        masked = np.count_nonzero(cleaned_after(1))
        assert 1000 < masked < 0.5 * unmasked                 # the studio masked out, the subject kept
        assert stop(node) == 0
        procs.remove(node)

        count = len(probe.got[f'/{cam}/{topics.DEPTH_CLEAN}'])
        procs.append(start_node('volcap_filter', 'depth_filter', params, namespace=cam))
        assert _inputs_matched(probe, pubs)
        send(frame)      # the first frame of the new node is already masked by the saved plate
        again = np.count_nonzero(cleaned_after(count))
        assert abs(again - masked) < 0.02 * masked
    finally:
        probe.close()
