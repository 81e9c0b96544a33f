"""The tsdf_fusion node with real publishers and subscribers: eight cameras' cleaned depth and
corrected colour (the studio's ideal views of a person) and a calibration with a studio frame go
in; the compressed GLB comes out on volcap/mesh/glb, and this process (not the node's) decodes it
with meshoptimizer and finds the mesh the node wrote, within the quantisation bounds, upright in
the studio frame; its size, bitrate and encode time are on the diagnostics (input:=full: the
separate stages' full-size topics; the wire is test_wire_fusion's and test_vendor_drivers'). `volcap view --live`
shows it in Chromium."""
import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from visualization_msgs.msg import Marker

from volcap_bringup.processes import start_node
from volcap_core import qos, topics
from volcap_core.calibration import Calibration, CameraCalibration, StudioFrame
from volcap_core.color import delta_e2000
from volcap_core.conversions import camera_model_to_info, numpy_to_image, pose_to_matrix
from volcap_core.gltf_marker import GLTF_IN_STUDIO
from volcap_core.poses import invert
from volcap_fusion.glb import decode_glb
from volcap_fusion.sequence import read_manifest, read_ply
from volcap_fusion.tsdf import raycasting_scene
from volcap_studio.ideal import ring_views

pytestmark = pytest.mark.ros
VOXEL = 0.01
STEP = VOXEL / 2                # the node's default position_step: half its voxel


def _calibration(views) -> Calibration:
    """World = cam0's colour frame (as a board calibration gives it), studio frame known."""
    T_cam0_studio = invert(views[0][2])
    calibration = Calibration('cam0', 'cam0_color_optical_frame',
                              {name: CameraCalibration(T_cam0_studio @ T, f'{name}_color_optical_frame')
                               for name, _, T, _ in views})
    calibration.studio = StudioFrame(T_cam0_studio, details={'source': 'floor'})
    return calibration


def _camera_publishers(node, views) -> dict:
    """(camera, topic) -> publisher of each camera's cleaned depth and corrected colour with infos."""
    pubs = {}
    for name, *_ in views:
        for topic, kind in ((topics.DEPTH_CLEAN, Image), (topics.DEPTH_CLEAN_INFO, CameraInfo),
                            (topics.COLOR_CORRECTED, Image), (topics.COLOR_CORRECTED_INFO, CameraInfo)):
            pubs[(name, topic)] = node.create_publisher(kind, f'/{name}/{topic}', qos.EVERY_FRAME)
    return pubs


@pytest.mark.timeout(300)
def test_glb_stream_decodes_in_another_process_within_the_bounds(ros_context, procs, probe_factory, tmp_path,
                                                                 browser, free_port):
    views = ring_views()
    out = tmp_path / 'frames'
    procs.append(start_node('volcap_fusion', 'tsdf_fusion', {
        'voxel_size': VOXEL, 'output_dir': str(out), 'reliable': True, 'frame_timeout_ms': 5000.0, 'input': 'full',
        'max_triangles': 20_000}))
    probe = probe_factory([('/' + topics.MESH_GLB, Marker, qos.EVERY_FRAME),
                           ('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    node = probe.node
    node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED).publish(
        String(data=_calibration(views).to_yaml()))
    pubs = _camera_publishers(node, views)
    assert probe.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values()), timeout=60)
    viewer = subprocess.Popen([sys.executable, '-m', 'volcap_bringup.cli', 'view', '--live', '--port',
                               str(free_port)], stdout=subprocess.PIPE, text=True)
    try:
        assert 'open http' in viewer.stdout.readline()
        assert probe.spin_until(lambda: node.count_subscribers('/' + topics.MESH_GLB) >= 2, timeout=60)
        page = browser.new_page(viewport={'width': 400, 'height': 500})
        page.goto(f'http://127.0.0.1:{free_port}/')
        page.wait_for_function("window.volcap && window.volcap.mode === 'live'", timeout=30_000)
        stamp = 2_000_000_000
        for attempt in range(5):     # a set sent while discovery settles may be lost: resend, newer
            stamp += 100_000_000
            for name, camera, _, view in views:
                frame_id = f'{name}_color_optical_frame'
                for topic, info in ((topics.DEPTH_CLEAN, topics.DEPTH_CLEAN_INFO),
                                    (topics.COLOR_CORRECTED, topics.COLOR_CORRECTED_INFO)):
                    pubs[(name, info)].publish(camera_model_to_info(camera, stamp, frame_id))
                probe.spin_until(lambda: False, 0.05)
                pubs[(name, topics.DEPTH_CLEAN)].publish(numpy_to_image(view.depth_mm, '16UC1', stamp, frame_id))
                pubs[(name, topics.COLOR_CORRECTED)].publish(numpy_to_image(view.rgb, 'rgb8', stamp, frame_id))
            # the viewer's reader may match the node's writer after the probe's: resend until
            # the page (not only the probe) has a mesh
            if probe.spin_until(lambda: probe.got['/' + topics.MESH_GLB]
                                and page.evaluate('window.volcap.shown') >= 1, timeout=30):
                break
        assert probe.got['/' + topics.MESH_GLB], 'no GLB on volcap/mesh/glb'
        assert page.evaluate('window.volcap.shown') >= 1, 'the page showed no mesh'
        assert page.evaluate('window.volcap.error') is None
        page.close()
    finally:
        viewer.terminate()
        viewer.wait(10)

    marker = probe.got['/' + topics.MESH_GLB][0][1]
    assert marker.type == Marker.MESH_RESOURCE and marker.header.frame_id == 'volcap_studio'
    assert marker.mesh_resource == f'embedded://{marker.mesh_file.filename}'
    assert np.allclose(pose_to_matrix(marker.pose), GLTF_IN_STUDIO, atol=1e-9)
    decoded, extras = decode_glb(bytes(marker.mesh_file.data))
    stamp_ns = marker.header.stamp.sec * 1_000_000_000 + marker.header.stamp.nanosec
    assert extras['volcap']['stamp_ns'] == str(stamp_ns)
    assert 0 < len(decoded.triangles) <= 20_000
    # The full mesh the node wrote for the same set: the streamed one keeps a subset of its
    # vertices (meshoptimizer moves none), each within the quantisation of the surface.
    entry = next(f for f in read_manifest(out) if f['stamp_ns'] == stamp_ns)
    full = read_ply(out / entry['ply'])
    distance = raycasting_scene(full.vertices, full.triangles).compute_distance(
        o3d.core.Tensor(decoded.vertices)).numpy()
    assert distance.max() <= np.sqrt(3) / 2 * STEP + 1e-4 <= VOXEL / 2
    # each kept vertex's colour is that of a full-mesh vertex within the quantisation step of it
    # (marching-cubes vertices can lie closer together than the step)
    from scipy.spatial import cKDTree
    full_tree = cKDTree(full.vertices)
    _, near = full_tree.query(decoded.vertices, k=8, distance_upper_bound=np.sqrt(3) / 2 * STEP + 1e-4)
    found = near < len(full.vertices)
    assert found[:, 0].all()
    de = delta_e2000(np.repeat(decoded.colors[:, None] / 255.0, 8, axis=1)[found],
                     full.colors[near[found]] / 255.0)
    best = np.full(near.shape, np.inf)
    best[found] = de
    worst = best.min(axis=1).max()
    assert worst <= 1.0
    # upright: the person's 1.8 m stand on the floor (z = 0) of the studio frame
    assert -0.03 < decoded.vertices[:, 2].min() < 0.1 and 1.7 < decoded.vertices[:, 2].max() < 1.9
    assert probe.spin_until(lambda: any(kv.key == 'glb_mbit_per_s' for _, m in probe.got['/' + topics.DIAGNOSTICS]
                                        for s in m.status if s.name.endswith('tsdf fusion') for kv in s.values),
                            timeout=10)


def _diagnostics(probe, since: int = 0) -> list:
    return [s for _, m in probe.got['/' + topics.DIAGNOSTICS][since:] for s in m.status
            if s.name.endswith('tsdf fusion')]


@pytest.mark.timeout(300)
def test_faults_bad_calibration_silent_camera_and_full_disk(ros_context, procs, probe_factory, small_disk):
    """The fusion node through three faults, never going down: a malformed latched calibration
    (the last good one is kept), a camera that stops and comes back (named while silent, not OK
    while short), and the sequence's disk filling up (recording stops whole, fusion goes on)."""
    views = ring_views()
    out = small_disk(3_000_000) / 'frames'
    procs.append(start_node('volcap_fusion', 'tsdf_fusion', {
        'voxel_size': VOXEL, 'output_dir': str(out), 'reliable': True, 'frame_timeout_ms': 300.0, 'input': 'full',
        'silent_periods': 3.0, 'encoding': 'raw', 'max_triangles': 0}))
    probe = probe_factory([('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    node = probe.node
    calibration_pub = node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
    calibration_pub.publish(String(data=_calibration(views).to_yaml()))
    pubs = _camera_publishers(node, views)
    assert probe.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values()), timeout=60)
    stamp = [2_000_000_000]

    def send(skip=()):
        stamp[0] += 200_000_000
        for name, camera, _, view in views:
            if name in skip:
                continue
            frame_id = f'{name}_color_optical_frame'
            for info in (topics.DEPTH_CLEAN_INFO, topics.COLOR_CORRECTED_INFO):
                pubs[(name, info)].publish(camera_model_to_info(camera, stamp[0], frame_id))
            pubs[(name, topics.DEPTH_CLEAN)].publish(numpy_to_image(view.depth_mm, '16UC1', stamp[0], frame_id))
            pubs[(name, topics.COLOR_CORRECTED)].publish(numpy_to_image(view.rgb, 'rgb8', stamp[0], frame_id))
        probe.spin_until(lambda: False, 0.2)

    def fused():
        values = [{kv.key: kv.value for kv in s.values} for s in _diagnostics(probe)]
        return max([int(v['fused']) for v in values if 'fused' in v], default=0)

    def until(condition, timeout=30, **kwargs):
        deadline = probe.node.get_clock().now().nanoseconds + timeout * 1e9
        while probe.node.get_clock().now().nanoseconds < deadline:
            send(**kwargs)
            if condition():
                return True
        return False

    def reported(level, text, since):
        return any(s.level == level and text in s.message for s in _diagnostics(probe, since))

    assert until(lambda: fused() >= 1)
    # 1. A malformed calibration on the latched topic: refused, the last good one kept.
    since = len(probe.got['/' + topics.DIAGNOSTICS])
    calibration_pub.publish(String(data='version: 1\nreference: cam0\nworld_frame: w\ncameras: [cam0, cam1]\n'))
    assert until(lambda: reported(DiagnosticStatus.ERROR, 'keeping the last good one', since))
    before = fused()
    assert until(lambda: fused() > before)
    # 2. cam3 goes silent: named at ERROR while it is, then fusion is whole again when it returns.
    since = len(probe.got['/' + topics.DIAGNOSTICS])
    silent = 'silent cameras (no frames while the others deliver): cam3'
    assert until(lambda: reported(DiagnosticStatus.ERROR, silent, since), skip=('cam3',))
    named = [{kv.key: kv.value for kv in s.values} for s in _diagnostics(probe, since) if 'silent' in s.message]
    assert named[-1]['silent_cameras'] == 'cam3'
    since = len(probe.got['/' + topics.DIAGNOSTICS])
    assert until(lambda: any('silent' not in s.message and 'short' not in s.message and 'fused' in s.message
                             for s in _diagnostics(probe, since)))
    # 3. The sequence's disk is full by now (3 MB hold about two frames): recording stopped with
    # the file and the free space named, every frame listed is whole, and fusion goes on.
    assert reported(DiagnosticStatus.ERROR, 'disk full', 0) or until(
        lambda: reported(DiagnosticStatus.ERROR, 'disk full', 0))
    message = next(s.message for s in _diagnostics(probe) if 'disk full' in s.message)
    assert 'recording stopped' in message and 'MB free' in message and 'whole frames' in message
    frames = read_manifest(out)
    assert frames and all(len(read_ply(out / f['ply']).triangles) == f['triangles'] for f in frames)
    assert not [p for p in out.iterdir() if p.name.startswith('.')]
    before = fused()
    assert until(lambda: fused() > before)
    assert procs[-1].poll() is None


def test_waiting_for_the_calibration_is_reported_after_the_grace_only(ros_context, procs, probe_factory):
    """A graph starting waits a moment for the latched calibration (discovery): OK, saying so.
    Past ``calibration_grace_s`` (here 0 for the second node) it is something to act on: WARN."""
    probe = probe_factory([('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    procs.append(start_node('volcap_fusion', 'tsdf_fusion', {'voxel_size': VOXEL}, remaps={'__node': 'starting'}))
    procs.append(start_node('volcap_fusion', 'tsdf_fusion', {'voxel_size': VOXEL, 'calibration_grace_s': 0.0},
                            remaps={'__node': 'forgotten'}))

    def levels(node):
        return [s.level for _, m in probe.got['/' + topics.DIAGNOSTICS] for s in m.status
                if s.name.startswith(node + ':') and 'waiting for the calibration' in s.message]
    assert probe.spin_until(lambda: levels('starting') and levels('forgotten'), timeout=60)
    assert levels('starting')[0] == DiagnosticStatus.OK        # its first report, within the grace
    assert levels('forgotten')[0] == DiagnosticStatus.WARN
