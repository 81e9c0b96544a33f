"""tsdf_fusion: every camera's cleaned depth and corrected colour fused into one coloured
mesh per time step.

    ros2 run volcap_fusion tsdf_fusion --ros-args -p voxel_size:=0.006 -p output_dir:=/data/take1

Subscribes, per camera of the calibration on ``/volcap/calibration`` (or the ``cameras``
parameter): ``<cam>/depth/image_clean`` with its camera_info, ``<cam>/color/image_corrected``
and ``<cam>/color/camera_info``. A frame set is the cameras' images with the same stamp (within
``sync_tolerance_ms``); one still incomplete after ``frame_timeout_ms`` is fused from the
cameras that arrived, and the missing ones are reported on ``volcap/diagnostics``.

Fusion runs on a worker thread fed by a bounded drop-oldest queue, so a slow volume never
stalls the subscriptions: when fusion falls behind, the oldest waiting frame sets are dropped
(and counted). Publishes ``/volcap/points`` (PointCloud2, world frame) and ``/volcap/mesh``
(Marker TRIANGLE_LIST with vertex colours; decimated above ``marker_max_triangles``), and with
``output_dir`` writes the volumetric sequence (PLY + GLB per time step, ``sequence.jsonl``).
While a session phase is announced on ``/volcap/phase``, only the ``phases`` listed are fused.
"""
from __future__ import annotations

import sys
import threading
import time
from collections import deque

import numpy as np
import yaml
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import Marker

from volcap_core import qos, topics
from volcap_core.calibration import Calibration
from volcap_core.camera import depth_to_millimetres
from volcap_core.conversions import (MessageConversionError, camera_info_to_model, color_to_rgb, depth_to_metres,
                                     image_to_numpy, mesh_to_marker_cdr, points_to_pointcloud2, stamp_to_ns)
from volcap_core.ros import Diagnostics, declare, run_node
from volcap_core.sync import FrameSet, FrameSetSynchronizer

from .sequence import SequenceWriter
from .tsdf import CameraView, FusionConfig, TsdfFusion, pick_device

ALL = 'all'


class TsdfFusionNode(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('tsdf_fusion', **node_options)
        self.wanted = [c for c in declare(self, 'cameras', [ALL], 'cameras to fuse ("all": every calibrated camera)',
                                          read_only=True) if c]
        center = declare(self, 'box_center', [0.0], 'capture box centre x, y, z in the world frame (m); one value: '
                                                    'where the cameras point', read_only=True)
        cfg = FusionConfig(
            voxel_size=declare(self, 'voxel_size', 0.004, 'TSDF voxel edge (m)', 0.0005, 0.1, read_only=True),
            trunc_voxels=declare(self, 'trunc_voxels', 4.0, 'SDF truncation in voxels', 1.0, 32.0, read_only=True),
            weight_threshold=declare(self, 'weight_threshold', 1.0, 'observations a voxel needs to be meshed',
                                     0.0, 100.0, read_only=True),
            block_resolution=declare(self, 'block_resolution', 8, 'voxels per block edge (4, 8 or 16)', 4, 16,
                                     read_only=True),
            block_count=declare(self, 'block_count', 40000, 'initial voxel block capacity', 1, 10_000_000,
                                read_only=True),
            depth_max=declare(self, 'depth_max', 3.0, 'depth beyond this is not fused (m)', 0.1, 6.5, read_only=True),
            depth_upsample=declare(self, 'depth_upsample', 1, 'depth resampled this many times finer', 1, 4,
                                   read_only=True),
            edge_tolerance=declare(self, 'edge_tolerance', 0.02, 'depth step (m) that separates surfaces', 0.0, 1.0,
                                   read_only=True),
            box_size=tuple(declare(self, 'box_size', [2.6, 2.6, 2.6], 'capture box edge lengths (m)',
                                   read_only=True)),
            box_center=tuple(center) if len(center) == 3 else None,
            device=pick_device(declare(self, 'device', 'auto', 'CPU:0, CUDA:0 or auto (CUDA when Open3D has it)',
                                       read_only=True)))
        self.fusion = TsdfFusion(cfg)   # validates: bad values stop the node with the reason
        tolerance_ms = declare(self, 'sync_tolerance_ms', 5.0, 'stamp tolerance within a frame set', 0.0, 100.0,
                               read_only=True)
        self.timeout_ns = int(declare(self, 'frame_timeout_ms', 300.0, 'after this, fuse the cameras that arrived',
                                      1.0, 10_000.0, read_only=True) * 1e6)
        self.tolerance_ns = int(tolerance_ms * 1e6)
        self.min_cameras = declare(self, 'min_cameras', 1, 'fewer cameras than this: the frame set is skipped', 1, 64)
        self.queue = deque(maxlen=declare(self, 'queue_size', 2, 'frame sets waiting for fusion (oldest dropped)',
                                          1, 100, read_only=True))
        self.phases = [p for p in declare(self, 'phases', [topics.CAPTURE], 'session phases to fuse while one is '
                                          'announced on /volcap/phase') if p]
        self.reliable = declare(self, 'reliable', False, 'subscribe reliably (offline replay: lose no frame)',
                                read_only=True)
        self.marker_max_triangles = declare(self, 'marker_max_triangles', 150_000,
                                            'the mesh marker is decimated above this', 1000, 10_000_000)
        output_dir = declare(self, 'output_dir', '', 'write the sequence (PLY + GLB per time step) here',
                             read_only=True)
        formats = [f for f in declare(self, 'output_formats', ['ply', 'glb'], 'sequence file formats',
                                      read_only=True) if f]
        self.writer = SequenceWriter(output_dir, tuple(formats)) if output_dir else None

        self.diagnostics = Diagnostics(self, 'tsdf fusion')
        self.calibration: Calibration | None = None
        self.cameras: list[str] = []
        self.sync: FrameSetSynchronizer | None = None
        self.infos: dict[tuple[str, str], CameraInfo] = {}
        self.camera_subscriptions = []
        self.phase = None
        self.stats = {'fused': 0, 'dropped': 0, 'incomplete': 0, 'skipped': 0, 'errors': 0}
        self.last = {}
        self.lock = threading.Condition()
        self.running = True

        self.create_subscription(String, '/' + topics.CALIBRATION, self._on_calibration, qos.LATCHED)
        self.create_subscription(String, '/' + topics.PHASE, self._on_phase, qos.LATCHED)
        self.pub_points = self.create_publisher(PointCloud2, '/' + topics.FUSED_POINTS, qos.DRIVER)
        self.pub_mesh = self.create_publisher(Marker, '/' + topics.MESH, qos.DRIVER)
        self.create_timer(0.05, self._poll)
        self.create_timer(1.0, self._report)
        self.worker = threading.Thread(target=self._work, name='tsdf_fusion_worker', daemon=True)
        self.worker.start()
        self.get_logger().info(f'tsdf_fusion started: {cfg.voxel_size * 1000:.1f} mm voxels on {cfg.device}'
                               + (f', writing {output_dir}' if output_dir else ''))

    # inputs -------------------------------------------------------------------------------
    def _on_calibration(self, msg: String) -> None:
        try:
            calibration = Calibration.from_yaml(msg.data)
        except (ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('error', f'unusable calibration: {e}')
            return
        cameras = list(calibration.cameras) if self.wanted == [ALL] else self.wanted
        absent = [c for c in cameras if c not in calibration.cameras]
        if absent:
            self.diagnostics.report('error', f'cameras {absent} are not in the calibration; calibration ignored')
            return
        self.calibration = calibration
        if cameras != self.cameras:
            self._subscribe(cameras)

    def _subscribe(self, cameras: list[str]) -> None:
        for sub in self.camera_subscriptions:
            self.destroy_subscription(sub)
        profile = qos.EVERY_FRAME if self.reliable else qos.SENSOR
        subs = []
        # camera_info first: the executor serves ready subscriptions in creation order
        for cam in cameras:
            for topic, stream in ((topics.DEPTH_CLEAN_INFO, 'depth'), (topics.COLOR_INFO, 'color')):
                subs.append(self.create_subscription(
                    CameraInfo, f'/{cam}/{topic}', lambda m, c=cam, s=stream: self.infos.__setitem__((c, s), m),
                    profile))
        for cam in cameras:
            for topic, stream in ((topics.DEPTH_CLEAN, 'depth'), (topics.COLOR_CORRECTED, 'color')):
                subs.append(self.create_subscription(
                    Image, f'/{cam}/{topic}', lambda m, c=cam, s=stream: self._on_image(c, s, m), profile))
        self.camera_subscriptions = subs
        self.cameras = cameras
        self.sync = FrameSetSynchronizer(cameras, ('depth', 'color'), tolerance_ns=self.tolerance_ns,
                                         timeout_ns=self.timeout_ns, max_pending=4)
        self.get_logger().info(f'fusing {len(cameras)} cameras: {", ".join(cameras)}')

    def _on_phase(self, msg: String) -> None:
        try:
            self.phase = (yaml.safe_load(msg.data) or {}).get('phase')
        except (yaml.YAMLError, AttributeError):
            pass

    def _on_image(self, camera: str, stream: str, msg: Image) -> None:
        if self.sync is None:
            return
        self._emit(self.sync.add(camera, stamp_to_ns(msg.header.stamp), msg, stream=stream,
                                 now_ns=time.monotonic_ns()))

    def _poll(self) -> None:
        if self.sync is not None:
            self._emit(self.sync.poll(time.monotonic_ns()))

    def _emit(self, sets: list[FrameSet]) -> None:
        for fs in sets:
            if self.phase is not None and self.phases and self.phase not in self.phases:
                continue
            if not fs.complete:
                self.stats['incomplete'] += 1
            with self.lock:
                if len(self.queue) == self.queue.maxlen:
                    self.stats['dropped'] += 1
                self.queue.append((fs, self.calibration))
                self.lock.notify()

    # fusion (worker thread) ---------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self.lock:
                while self.running and not self.queue:
                    self.lock.wait()
                if not self.running:
                    return
                fs, calibration = self.queue.popleft()
            try:
                self._fuse(fs, calibration)
            except Exception as e:   # the worker must outlive any one bad frame set
                self.stats['errors'] += 1
                self.diagnostics.report('error', f'frame set {fs.stamp_ns} not fused: {type(e).__name__}: {e}')

    def _fuse(self, fs: FrameSet, calibration: Calibration) -> None:
        t0 = time.perf_counter()
        views, problems = [], {}
        for cam in self.cameras:
            depth_msg, color_msg = fs.get(cam, 'depth'), fs.get(cam, 'color')
            if depth_msg is None or color_msg is None:
                continue
            try:
                views.append(self._view(cam, depth_msg, color_msg, calibration))
            except (MessageConversionError, ValueError, KeyError) as e:
                problems[cam] = str(e)
        missing = sorted({c for c, _ in fs.missing} | set(problems))
        if problems:
            self.diagnostics.report('warn', 'cameras left out of frame set: '
                                    + '; '.join(f'{c}: {e}' for c, e in problems.items()))
        if len(views) < self.min_cameras:
            self.stats['skipped'] += 1
            self.diagnostics.report('warn', f'frame set {fs.stamp_ns} skipped: {len(views)} of {len(self.cameras)} '
                                            f'cameras (missing {", ".join(missing)})')
            return
        if missing:
            self.diagnostics.report('warn', f'frame set {fs.stamp_ns} fused without {", ".join(missing)}')
        model = self.fusion.fuse(views)
        frame = calibration.world_frame
        self.pub_points.publish(points_to_pointcloud2(model.vertices, model.colors, fs.stamp_ns, frame))
        marker = model.decimated(self.marker_max_triangles, 2 * self.fusion.cfg.voxel_size)
        self.pub_mesh.publish(mesh_to_marker_cdr(marker.vertices, marker.colors, marker.triangles, fs.stamp_ns,
                                                 frame))
        if self.writer is not None:
            self.writer.write(model, fs.stamp_ns, missing)
        self.stats['fused'] += 1
        self.last = {'fusion_ms': round(sum(model.timings_ms.values()), 1),
                     'total_ms': round((time.perf_counter() - t0) * 1000, 1), 'cameras': len(views),
                     'vertices': len(model.vertices), 'triangles': len(model.triangles)}

    def _view(self, cam: str, depth_msg: Image, color_msg: Image, calibration: Calibration) -> CameraView:
        infos = self.infos.get((cam, 'depth')), self.infos.get((cam, 'color'))
        if None in infos:
            raise ValueError('no camera_info yet')
        if depth_msg.encoding == '16UC1':
            depth_mm = image_to_numpy(depth_msg)
        else:   # 32FC1 metres (NaN = no depth), or a clear error for anything else
            depth_mm = depth_to_millimetres(depth_to_metres(depth_msg))
        return CameraView(cam, depth_mm, camera_info_to_model(infos[0]), color_to_rgb(color_msg),
                          camera_info_to_model(infos[1]), calibration.T_world_color(cam))

    def _report(self) -> None:
        if self.calibration is None:
            self.diagnostics.report('warn', f'waiting for the calibration on /{topics.CALIBRATION}')
            return
        with self.lock:
            waiting = len(self.queue)
        self.diagnostics.report('ok', f'{self.stats["fused"]} frame sets fused', waiting=waiting, **self.stats,
                                **self.last)

    def destroy_node(self):
        with self.lock:
            self.running = False
            self.lock.notify_all()
        self.worker.join(timeout=10.0)
        return super().destroy_node()


def main(args=None):
    sys.exit(run_node(TsdfFusionNode, args))


if __name__ == '__main__':
    main()
