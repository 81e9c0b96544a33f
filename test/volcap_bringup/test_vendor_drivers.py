"""volcap's unchanged nodes on the vendor drivers' topics, with remapping only: the real Azure
Kinect frame published as the Azure Kinect ROS driver and OrbbecSDK_ROS2 publish it (topics,
encodings incl. JPEG, camera_info, frame ids, /tf_static, colour stamped apart from depth),
native and registered depth; and a two-camera studio in a driver's layout calibrated and fused."""
import json
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from volcap_bringup.cli import main
from volcap_bringup.graph import camera_remaps, rig_graph
from volcap_bringup.processes import start_node
from volcap_core import qos, topics, wire
from volcap_core.bag_reader import BagReader
from volcap_core.calibration import Calibration, CameraCalibration
from volcap_core.conversions import compressed_to_rgb, image_to_numpy
from volcap_core.frames import frame_sets, read_rig
from volcap_core.poses import invert
from volcap_studio.session import GroundTruth
from volcap_studio.vendor import frame_ids, frame_messages, tf_static_message, write_vendor_bag

pytestmark = pytest.mark.ros

# As the drivers publish: reliable, keep-last 1 (their queue size); /tf_static as tf2 does.
DRIVER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
COLOR_DELAY_NS = 8_000_000


class VendorDriver:
    """Publishes frames in a driver's layout from the probe's node, stamps advancing at 10 Hz."""

    def __init__(self, node, layout, rig_cameras, registered, color_format):
        self.node, self.layout, self.cams = node, layout, rig_cameras
        self.registered, self.color_format = registered, color_format
        self.pubs = {}
        self.stamp = 1_700_000_000_000_000_000
        tf = node.create_publisher(type(tf_static_message(layout, rig_cameras)), '/tf_static', qos.TF_STATIC)
        tf.publish(tf_static_message(layout, rig_cameras))
        self.tf = tf

    def publish(self, frames: dict) -> None:
        """``frames``: camera -> (rgb, depth metres)."""
        for cam in self.cams:
            rgb, depth = frames[cam.name]
            for topic, msg in frame_messages(self.layout, cam.name, cam, rgb, depth, self.stamp, self.registered,
                                             self.color_format, COLOR_DELAY_NS):
                if topic not in self.pubs:
                    self.pubs[topic] = self.node.create_publisher(type(msg), topic, DRIVER_QOS)
                self.pubs[topic].publish(msg)
        self.stamp += 100_000_000


@pytest.mark.parametrize('layout,registered,color_format', [
    ('azure_kinect', False, 'jpeg'), ('azure_kinect', True, 'raw'), ('orbbec', False, 'raw'),
    ('orbbec', True, 'jpeg')])
def test_camera_pipeline_and_fusion_on_a_vendor_driver_with_remaps_only(k4a_bag, layout, registered, color_format,
                                                                         ros_context, procs, probe_factory):
    """One real camera, its camera_pipeline on the driver's topics: cleaned depth, corrected colour
    and, from that camera alone, a mesh."""
    with BagReader(k4a_bag) as reader:
        cam = read_rig(reader).cameras[0]
    frame = next(frame_sets(k4a_bag)).cameras['cam0']
    params = {'color_transport': 'compressed'} if color_format == 'jpeg' else {}
    remaps = camera_remaps(layout, registered)
    outputs = [('/cam0/' + topics.DEPTH_CLEAN, Image), ('/cam0/' + topics.DEPTH_CLEAN_INFO, CameraInfo),
               ('/cam0/' + topics.COLOR_CORRECTED, Image), ('/cam0/' + topics.COLOR_CORRECTED_INFO, CameraInfo),
               ('/' + topics.MESH, Marker), ('/cam0/' + wire.WIRE_DEPTH, CompressedImage),
               ('/cam0/' + wire.WIRE_DEPTH_INFO, CameraInfo), ('/cam0/' + wire.WIRE_COLOR, CompressedImage),
               ('/cam0/' + wire.WIRE_COLOR_INFO, CameraInfo)]
    probe = probe_factory([(t, kind, qos.EVERY_FRAME) for t, kind in outputs]
                          + [('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    try:
        procs.append(start_node('volcap_pipeline', 'camera_pipeline', params, namespace='cam0', remaps=remaps))
        procs.append(start_node('volcap_fusion', 'tsdf_fusion', {'min_cameras': 1, 'voxel_size': 0.01}))
        # the world is this camera's colour frame: a calibration as the service would latch it
        calibration = Calibration('cam0', frame_ids(layout, 'cam0')[0],
                                  {'cam0': CameraCalibration(np.eye(4), frame_ids(layout, 'cam0')[0])})
        latched = probe.node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
        latched.publish(String(data=calibration.to_yaml()))
        driver = VendorDriver(probe.node, layout, [cam], registered, color_format)
        end = time.monotonic() + 90
        while time.monotonic() < end and not all(probe.got[t] for t, _ in outputs):
            driver.publish({'cam0': (frame.color, frame.depth)})
            probe.spin_until(lambda: False, timeout=0.2)
        assert all(probe.got[t] for t, _ in outputs), f'no output on {[t for t, _ in outputs if not probe.got[t]]}'

        def no_plate_warning():
            # no clean plate was learnt: the pipeline says so (WARN, naming the service), not OK
            return any('capture_clean_plate' in s.message and s.level == b'\x01'
                       for _, m in probe.got['/' + topics.DIAGNOSTICS] for s in m.status if 'camera pipeline' in s.name)
        assert probe.spin_until(no_plate_warning, timeout=15)
    finally:
        probe.close()
    color_frame, _ = frame_ids(layout, 'cam0')
    clean = probe.got['/cam0/' + topics.DEPTH_CLEAN][-1][1]
    depth = image_to_numpy(clean)
    assert clean.encoding == '16UC1' and depth.shape == (720, 1280) and clean.header.frame_id == color_frame
    # Native depth is registered by volcap (dense); a driver's registration leaves a lattice of
    # holes (28 % of the pixels valid) and must survive the flying-pixel filter.
    assert (depth > 0).mean() > (0.5 if not registered else 0.25)
    corrected_all = [m for _, m in probe.got['/cam0/' + topics.COLOR_CORRECTED]]
    corrected = corrected_all[-1]
    assert corrected.encoding == 'rgb8' and (corrected.height, corrected.width) == (720, 1280)
    # each corrected image comes with its camera_info (sent just before it, on another topic: a
    # keep-last 2 writer on a loaded machine may replace one before it is delivered)
    infos = {(m.header.stamp.sec, m.header.stamp.nanosec): m for _, m in probe.got['/cam0/' + topics.COLOR_CORRECTED_INFO]}
    paired = [infos[k] for k in ((m.header.stamp.sec, m.header.stamp.nanosec) for m in corrected_all) if k in infos]
    assert paired and len(paired) >= len(corrected_all) / 2, (len(paired), len(corrected_all))
    assert all(abs(info.k[0] - cam.color.fx) < 1e-6 for info in paired)
    mesh = probe.got['/' + topics.MESH][-1][1]
    assert len(mesh.points) > 3000 and mesh.header.frame_id == color_frame     # one camera, default threshold
    # The wire the fusion took: image_transport's formats, crop_decimate's camera_info, and the
    # cleaned depth inside the region sent losslessly (nothing outside it)
    def stamp(m):
        return m.header.stamp.sec, m.header.stamp.nanosec
    wire_msgs = {t: {stamp(m): m for _, m in probe.got['/cam0/' + t]}
                 for t in (wire.WIRE_DEPTH, wire.WIRE_DEPTH_INFO, wire.WIRE_COLOR, wire.WIRE_COLOR_INFO)}
    full = {stamp(m): m for _, m in probe.got['/cam0/' + topics.DEPTH_CLEAN]}
    common = sorted(set(full).intersection(*wire_msgs.values()))
    assert common, 'no stamp with the full depth and the whole wire'
    k = common[-1]
    depth_msg, depth_info = wire_msgs[wire.WIRE_DEPTH][k], wire_msgs[wire.WIRE_DEPTH_INFO][k]
    color_msg, color_info = wire_msgs[wire.WIRE_COLOR][k], wire_msgs[wire.WIRE_COLOR_INFO][k]
    assert depth_msg.format == '16UC1; compressedDepth png' and color_msg.format == 'rgb8; jpeg compressed bgr8'
    assert depth_msg.header.frame_id == color_msg.header.frame_id == color_frame
    assert (depth_info.width, depth_info.height) == (1280, 720) and depth_info.binning_x == depth_info.binning_y == 1
    roi = depth_info.roi
    assert 0 < roi.width * roi.height < 1280 * 720 and roi.x_offset + roi.width <= 1280
    model, region = wire.info_region(depth_info)
    placed, _ = wire.place_region(wire.decode_depth(depth_msg), region, model)
    np.testing.assert_array_equal(placed, image_to_numpy(full[k]))
    # (no clean plate here, so the region is the whole room: the wire's size is bench/live.py's)
    assert compressed_to_rgb(color_msg).shape[:2] == wire.info_region(color_info)[1].shape


def test_a_two_camera_rig_of_vendor_drivers_is_calibrated_and_fused(calib_bag, ros_context, procs, probe_factory,
                                                                    tmp_path):
    """No /volcap/rig, no phase messages: the rig comes from camera_info and /tf_static."""
    with BagReader(calib_bag) as reader:
        cams = read_rig(reader).cameras
    sets = [{name: (f.color, f.depth) for name, f in fs.cameras.items()} for fs in frame_sets(calib_bag)]
    names = [c.name for c in cams]
    output = tmp_path / 'calibration.yaml'
    graph = rig_graph(names, None, {}, {}, {'cameras': names, 'min_cameras': 1}, {'output': str(output)},
                      driver='azure_kinect')
    probe = probe_factory([('/' + topics.MESH, Marker, qos.EVERY_FRAME),
                           ('/' + topics.CALIBRATION, String, qos.LATCHED)])
    try:
        for package, executable, namespace, params, remaps in graph:
            procs.append(start_node(package, executable, params, namespace=namespace, remaps=remaps))
        driver = VendorDriver(probe.node, 'azure_kinect', cams, False, 'raw')
        client = probe.node.create_client(Trigger, '/' + topics.CALIBRATE)
        assert client.wait_for_service(timeout_sec=60)
        for k in range(6):     # every board pose, a few times (the service gathers while it waits)
            driver.publish(sets[k % len(sets)])
            probe.spin_until(lambda: False, timeout=1.0)
        future = client.call_async(Trigger.Request())
        assert probe.spin_until(future.done, timeout=180), 'calibrate call did not return'
        assert future.result().success, future.result().message
        assert probe.spin_until(lambda: probe.got['/' + topics.CALIBRATION], timeout=30)
        end = time.monotonic() + 120
        while time.monotonic() < end and not probe.got['/' + topics.MESH]:
            driver.publish(sets[0])
            probe.spin_until(lambda: False, timeout=0.5)
        assert probe.got['/' + topics.MESH], 'no fused mesh'
    finally:
        probe.close()
    calibration = Calibration.load(output)
    assert set(calibration.cameras) == set(names)
    gt = GroundTruth(calib_bag)
    relative = invert(calibration.cameras['cam0'].T_world_color) @ calibration.cameras['cam1'].T_world_color
    truth = invert(gt.T_world_color('cam0')) @ gt.T_world_color('cam1')
    assert np.linalg.norm(relative[:3, 3] - truth[:3, 3]) < 0.01
    mesh = probe.got['/' + topics.MESH][-1][1]
    assert len(mesh.points) > 3000 and np.isfinite([p.z for p in mesh.points[:100]]).all()


@pytest.mark.timeout(600)
def test_a_bag_recorded_from_the_drivers_goes_through_the_offline_tools(calib_bag, k4a_bag, tmp_path):
    """Fully qualified vendor topics, JPEG colour stamped 8 ms after depth, /tf_static, no volcap
    topics (no rig, no phases): calibrate, run and the evaluations, as on a volcap bag."""
    vendor = tmp_path / 'drivers'
    sets = write_vendor_bag(calib_bag, vendor, 'azure_kinect', color_format='jpeg', color_delay_ns=COLOR_DELAY_NS)
    with BagReader(vendor) as reader:
        assert reader.topics['cam0/rgb/image_raw/compressed'] == 'sensor_msgs/msg/CompressedImage'
        assert not any(t.startswith('volcap/') for t in reader.topics)
    calibration = tmp_path / 'calibration.yaml'
    # two board poses: the calibration is weak by design, and used as it is
    assert main(['calibrate', str(vendor), '--out', str(calibration), '--quiet', '--accept-weak']) == 0
    cal, gt = Calibration.load(calibration), GroundTruth(calib_bag)
    relative = invert(cal.cameras['cam0'].T_world_color) @ cal.cameras['cam1'].T_world_color
    truth = invert(gt.T_world_color('cam0')) @ gt.T_world_color('cam1')
    assert np.linalg.norm(relative[:3, 3] - truth[:3, 3]) < 0.01

    out = tmp_path / 'run'
    assert main(['run', str(vendor), '--calibration', str(calibration), '--out', str(out), '--voxel', '0.01',
                 '--rate', '0.1', '--quiet']) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['capture_frame_sets_in_bag'] == sets and metrics['frames_written'] == sets   # no phase: all capture
    assert all(f['triangles'] > 1000 for f in metrics['frames'])

    color = tmp_path / 'color.json'
    assert main(['eval', 'color', str(vendor), '--calibration', str(calibration), '--json', str(color), '--quiet']) == 0
    assert json.loads(color.read_text())['methods']

    real = tmp_path / 'k4a_drivers'
    write_vendor_bag(k4a_bag, real, 'orbbec', color_format='jpeg', color_delay_ns=COLOR_DELAY_NS)
    report = tmp_path / 'registration.json'
    assert main(['eval', 'registration', str(real), '--out', str(tmp_path / 'overlay.png'), '--json',
                 str(report)]) == 0
    assert json.loads(report.read_text())['median_offset_px'] <= 1.5
