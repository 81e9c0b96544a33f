"""`volcap operator`: a camera's colour image, its cleaned depth and the fused model published by
a graph reach the bridge (another process) and are forwarded to Rerun, whose web viewer loads in
Chromium from this machine alone."""
import subprocess
import sys
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from visualization_msgs.msg import Marker

from volcap_core import qos, topics
from volcap_core.calibration import Calibration, CameraCalibration, StudioFrame
from volcap_core.camera import CameraModel
from volcap_core.conversions import camera_model_to_info, numpy_to_image
from volcap_core.gltf_marker import glb_marker
from volcap_fusion.glb import EncodeConfig, encode
from volcap_fusion.tsdf import FusedModel

pytestmark = pytest.mark.ros


def _forwarded(probe) -> dict:
    counts = {}
    for _, msg in probe.got['/' + topics.DIAGNOSTICS]:
        for s in msg.status:
            if s.name.endswith('operator view'):
                counts = {kv.key: int(kv.value) for kv in s.values if kv.key.startswith('forwarded_')}
    return counts


@pytest.mark.timeout(180)
def test_operator_view_forwards_images_depth_and_model(ros_context, probe_factory, browser, free_port):
    probe = probe_factory([('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    node = probe.node
    color = node.create_publisher(Image, '/cam0/' + topics.COLOR_IMAGE, qos.DRIVER)
    info = node.create_publisher(CameraInfo, '/cam0/' + topics.COLOR_INFO, qos.DRIVER)
    depth = node.create_publisher(Image, '/cam0/' + topics.DEPTH_CLEAN, qos.DRIVER)
    mesh = node.create_publisher(Marker, '/' + topics.MESH_GLB, qos.DRIVER)
    calibration = Calibration('cam0', 'cam0_color_optical_frame', {'cam0': CameraCalibration(np.eye(4))})
    calibration.studio = StudioFrame(np.eye(4), details={'source': 'floor'})
    node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED).publish(String(data=calibration.to_yaml()))
    bridge = subprocess.Popen([sys.executable, '-m', 'volcap_bringup.cli', 'operator', '--cameras', 'cam0', '--hz', '5',
                               '--web-port', str(free_port), '--grpc-port', str(free_port + 1)],
                              stdout=subprocess.PIPE, text=True)
    try:
        line = bridge.stdout.readline()
        assert 'open http' in line, line
        url = line.split('open ', 1)[1].split(' ', 1)[0]
        assert probe.spin_until(lambda: color.get_subscription_count() and depth.get_subscription_count()
                                and mesh.get_subscription_count(), timeout=60)
        rgb = np.zeros((360, 640, 3), np.uint8)
        rgb[:, :320] = (200, 40, 30)
        depth_mm = np.full((360, 640), 1500, np.uint16)
        model = FusedModel(np.array([[0, 0, 0], [0.5, 0, 0], [0, 0, 1.0]], np.float32),
                           np.full((3, 3), 120, np.uint8), np.array([[0, 1, 2]], np.int32))
        glb = encode(model, EncodeConfig()).data

        def send():
            stamp = time.time_ns()
            info.publish(camera_model_to_info(CameraModel(640, 360, 305.0, 305.0, 319.5, 179.5), stamp,
                                              'cam0_color_optical_frame'))
            color.publish(numpy_to_image(rgb, 'rgb8', stamp, 'cam0_color_optical_frame'))
            depth.publish(numpy_to_image(depth_mm, '16UC1', stamp, 'cam0_color_optical_frame'))
            mesh.publish(glb_marker(glb, stamp, 'volcap_studio', 'frame.glb'))
        done = lambda: all(_forwarded(probe).get(f'forwarded_{k}', 0) >= 1 for k in ('color', 'depth', 'model'))
        for _ in range(10):
            send()
            if probe.spin_until(done, timeout=2):
                break
        assert done(), _forwarded(probe)
        page = browser.new_page(viewport={'width': 900, 'height': 600})
        panics = []
        page.on('console', lambda m: panics.append(m.text) if 'panic' in m.text.lower() else None)
        page.goto(url)
        page.wait_for_selector('canvas', timeout=60_000)
        page.wait_for_timeout(3000)
        assert not panics, panics
        page.close()
    finally:
        bridge.terminate()
        bridge.wait(20)
