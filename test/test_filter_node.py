"""depth_filter in its own process: a replayed studio bag in, clean depth and points out on
every camera; bad frames are reported on diagnostics and the node keeps going."""

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String

from volcap_bringup.processes import start_node
from volcap_core import qos, topics
from volcap_core.conversions import (camera_model_to_info, image_to_numpy, numpy_to_image,
                                     pointcloud2_to_points)
from volcap_driver.frames import frame_sets
from volcap_driver.synth.session import GroundTruth

from test_nodes import Probe, play

pytestmark = pytest.mark.ros


def test_filter_nodes_clean_a_replayed_bag_on_every_camera(studio_bag, ros_context, procs):
    cams = GroundTruth(studio_bag).rig.names
    outputs = [(f'/{c}/{t}', kind, qos.SENSOR) for c in cams
               for t, kind in ((topics.DEPTH_CLEAN, Image), (topics.POINTS, PointCloud2))]
    probe = Probe(ros_context, outputs)
    try:
        for c in cams:
            procs.append(start_node('volcap_filter', 'depth_filter', {}, namespace=c))
        played = [f'{c}/{t}' for c in cams for t in (topics.COLOR_IMAGE, topics.COLOR_INFO, topics.DEPTH_IMAGE,
                                                      topics.DEPTH_INFO)] + [topics.RIG, topics.PHASE]
        play(procs, studio_bag, wait_for_subscribers=60.0, topics=played, rate=0.5)
        probe.assert_all_arrive([t for t, _, _ in outputs], timeout=150)
    finally:
        probe.close()
    for c in cams:
        _, img = probe.got[f'/{c}/{topics.DEPTH_CLEAN}'][-1]
        depth = image_to_numpy(img)
        assert img.encoding == '16UC1' and depth.shape == (360, 640)
        assert img.header.frame_id == f'{c}_color_optical_frame'
        valid = depth[depth > 0]
        assert valid.size > 1000 and valid.min() >= 100 and valid.max() <= 2500
        _, cloud = probe.got[f'/{c}/{topics.POINTS}'][-1]
        xyz, rgb = pointcloud2_to_points(cloud)
        assert len(xyz) > 1000 and rgb is not None


def test_bad_frames_are_reported_and_skipped(studio_bag, ros_context, procs):
    cam = 'cam1'
    frame = next(fs for fs in frame_sets(studio_bag, phases=('capture',))).cameras[cam]
    rig = GroundTruth(studio_bag).rig
    probe = Probe(ros_context, [(f'/{cam}/{topics.DEPTH_CLEAN}', Image, qos.SENSOR),
                                ('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    node = probe.node
    pubs = {t: node.create_publisher(k, f'/{cam}/{t}', qos.DRIVER)
            for t, k in ((topics.COLOR_IMAGE, Image), (topics.COLOR_INFO, CameraInfo), (topics.DEPTH_IMAGE, Image),
                         (topics.DEPTH_INFO, CameraInfo))}
    rig_pub = node.create_publisher(String, '/' + topics.RIG, qos.LATCHED)
    try:
        procs.append(start_node('volcap_filter', 'depth_filter', {'mask_mode': 'none'}, namespace=cam))
        # The node's diagnostics writer must be matched too, or its first report can be lost.
        assert probe.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values())
                                and node.count_publishers('/' + topics.DIAGNOSTICS), timeout=60)
        color_frame, depth_frame = f'{cam}_color_optical_frame', f'{cam}_depth_optical_frame'
        stamp = [1_000_000_000]

        def send(depth, encoding='16UC1', infos=True):
            stamp[0] += 100_000_000
            if infos:
                pubs[topics.COLOR_INFO].publish(camera_model_to_info(frame.color_model, stamp[0], color_frame))
                pubs[topics.DEPTH_INFO].publish(camera_model_to_info(frame.depth_model, stamp[0], depth_frame))
            probe.spin_until(lambda: False, 0.2)
            pubs[topics.COLOR_IMAGE].publish(numpy_to_image(frame.color, 'rgb8', stamp[0], color_frame))
            pubs[topics.DEPTH_IMAGE].publish(numpy_to_image(depth, encoding, stamp[0], depth_frame))

        def diagnostic(text):
            return any(text in s.message for _, m in probe.got['/' + topics.DIAGNOSTICS] for s in m.status)

        def reported(text, *frame_args, **frame_kwargs):
            # Resent every 2 s: a frame sent while discovery settles may be lost, the node is not at fault.
            for _ in range(10):
                send(*frame_args, **frame_kwargs)
                if probe.spin_until(lambda: diagnostic(text), 2):
                    return True
            return False

        good = np.round(frame.depth * 1000).astype(np.uint16)
        assert reported('no camera_info yet', good, infos=False)
        assert reported('waiting for the rig', good)
        rig_pub.publish(String(data=rig.to_yaml()))
        assert reported('camera_info says', good[:100, :100].copy())
        assert reported('no valid pixel', np.zeros_like(good))
        assert reported('depth image expected', good.astype(np.uint8), encoding='mono8')
        send(good)
        assert probe.spin_until(lambda: probe.got[f'/{cam}/{topics.DEPTH_CLEAN}'], 30)
        assert procs[-1].poll() is None
    finally:
        probe.close()
