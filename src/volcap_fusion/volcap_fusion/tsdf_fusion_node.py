"""tsdf_fusion: every camera's cleaned depth and corrected colour fused into one coloured
mesh per time step.

    ros2 run volcap_fusion tsdf_fusion --ros-args -p voxel_size:=0.006 -p output_dir:=/data/take1

Subscribes, per camera of the calibration on ``/volcap/calibration`` (or the ``cameras``
parameter), relative names only, with ``input:=wire`` (the default) the camera pipelines' compact
wire (``volcap_core.wire``): ``<cam>/wire/depth/image/compressedDepth`` and
``<cam>/wire/color/image/compressed`` with ``<cam>/wire/depth/camera_info`` and
``<cam>/wire/color/camera_info`` (each region's roi / binning, paired with its image by stamp);
with ``input:=full`` ``<cam>/depth/image_clean`` and ``<cam>/color/image_corrected``, each with
its camera_info (``.../camera_info``, published by the depth filter and the colour corrector).
A frame set is the cameras' images with the same stamp (within
``sync_tolerance_ms``); one still incomplete after ``frame_timeout_ms`` is fused from the
cameras that arrived, and the missing ones are reported on ``volcap/diagnostics``.

Fusion runs on a worker thread fed by a bounded drop-oldest queue (one set waits by default),
so a slow volume never stalls the subscriptions and no backlog builds: when fusion falls
behind, the oldest waiting frame sets are dropped (and counted). In a live graph only the frame
sets admitted on ``/volcap/admission`` are gathered (``volcap_core.admission``).

Output is in the calibration's studio frame (``volcap_studio``: +Z up, origin on the floor),
each only while someone subscribes: ``/volcap/points`` (PointCloud2), ``/volcap/mesh`` (Marker
TRIANGLE_LIST with vertex colours, simplified above ``marker_max_triangles``) and
``/volcap/mesh/glb`` (Marker MESH_RESOURCE whose ``mesh_file`` holds the frame's GLB: the
triangle budget and encoding of the ``encoding`` parameters, meshopt by default). Diagnostics
carry the latency from capture stamp to publication (p50/p95 over the last 10 s, when the
stamps are the rig's clock), the GLB's size, bitrate and encode time. With ``output_dir``
writes the volumetric sequence (``volcap_fusion.sequence``).
While a session phase is announced on ``/volcap/phase``, only the ``phases`` listed are fused.
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import Marker

from volcap_core import qos, topics, wire
from volcap_core.calibration import Calibration
from volcap_core.camera import depth_to_millimetres
from volcap_core.cdr import mesh_to_marker_cdr
from volcap_core.conversions import (
    camera_info_to_model,
    color_to_rgb,
    depth_to_metres,
    image_to_numpy,
    points_to_pointcloud2,
    stamp_to_ns,
)
from volcap_core.errors import BadInput
from volcap_core.gltf_marker import glb_marker
from volcap_core.health import SilenceWatch
from volcap_core.ros import AdmissionListener, Diagnostics, declare_config, node_main
from volcap_core.sync import FrameSet, FrameSetSynchronizer, tolerance_ns_from_ms
from volcap_core.worker import DropOldestWorker

from .frame_sets import WIRE, FusionNodeConfig, PhaseTimeline, fused_cameras, fused_phase
from .glb import EncodeConfig, simplify
from .rig import FusedSet, RigFusion, wire_view
from .sequence import SequenceWriter, frame_rate
from .tsdf import CameraView, FusionConfig, TsdfFusion, open3d_device

# Latency percentiles cover the frame sets published in the last this many seconds.
LATENCY_WINDOW_S = 10.0


class TsdfFusionNode(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('tsdf_fusion', **node_options)
        self.node_cfg = declare_config(self, FusionNodeConfig, self._on_node_config)
        cfg = declare_config(self, FusionConfig)
        fusion = TsdfFusion(cfg)   # validates: bad values stop the node with the reason
        encoding = declare_config(self, EncodeConfig).for_voxel(cfg.voxel_size)
        encoding.validate()
        self.wanted = [c for c in self.node_cfg.cameras if c]
        output_dir = self.node_cfg.output_dir
        formats = tuple(f for f in self.node_cfg.output_formats if f)
        # the rig pipeline (views -> model -> GLB -> sequence), driven with the received messages
        self.rig = RigFusion(fusion, encoding, self.node_cfg.min_cameras,
                             SequenceWriter(output_dir, formats, encoding) if output_dir else None)
        self.writer_failure = ''          # why the sequence stopped being written (a full disk)
        self.silence = SilenceWatch(self.node_cfg.silent_periods)
        self.short_of: list[str] = []            # cameras missing from the last fused frame set
        self.glb_stamps: deque[int] = deque(maxlen=64)

        self.diagnostics = Diagnostics(self, 'tsdf fusion')
        self.started = time.monotonic()
        self.calibration: Calibration | None = None
        self.cameras: list[str] = []
        self.sync: FrameSetSynchronizer | None = None
        self.infos: dict[tuple[str, str], CameraInfo] = {}
        self.camera_subscriptions = []
        self.phases = PhaseTimeline()
        self.stats = {'fused': 0, 'fused_complete': 0, 'incomplete': 0, 'skipped': 0, 'empty': 0, 'out_of_order': 0}
        self.newest_submitted = -1
        self.latency_ms: deque[tuple[float, float]] = deque(maxlen=256)    # (monotonic s, ms)
        self.work_s = 0.0      # process CPU time while fusing (includes the receiving meanwhile)
        self.last = {}
        self.worker = DropOldestWorker(self._fuse, self.node_cfg.queue_size, 'tsdf_fusion_worker',
                                       on_error=self._on_fusion_error)

        self.create_subscription(String, '/' + topics.CALIBRATION, self._on_calibration, qos.LATCHED)
        self.create_subscription(String, '/' + topics.PHASE, self._on_phase, qos.LATCHED)
        self.admission = AdmissionListener(self, self.diagnostics)
        self.pub_points = self.create_publisher(PointCloud2, '/' + topics.FUSED_POINTS, qos.DRIVER)
        self.pub_mesh = self.create_publisher(Marker, '/' + topics.MESH, qos.DRIVER)
        self.pub_glb = self.create_publisher(Marker, '/' + topics.MESH_GLB, qos.DRIVER)
        self.create_timer(0.05, self._poll)
        self.create_timer(1.0, self._report)
        self.get_logger().info(f'tsdf_fusion started: {cfg.voxel_size * 1000:.1f} mm voxels on '
                               f'{open3d_device(cfg.device)}' + (f', writing {output_dir}' if output_dir else ''))

    def _on_node_config(self, cfg: FusionNodeConfig) -> None:
        self.node_cfg = cfg
        self.rig.min_cameras = cfg.min_cameras      # may change while running

    # inputs -------------------------------------------------------------------------------
    def _on_calibration(self, msg: String) -> None:
        try:
            calibration = Calibration.from_yaml(msg.data)
        except ValueError as e:
            kept = 'keeping the last good one' if self.calibration is not None else 'none yet'
            self.diagnostics.report('error', f'unusable calibration on /{topics.CALIBRATION} ({kept}): {e}')
            return
        try:
            cameras = fused_cameras(list(calibration.cameras), self.wanted)
        except ValueError as e:
            self.diagnostics.report('error', f'{e}; calibration ignored')
            return
        self.calibration = calibration
        if cameras != self.cameras:
            self._subscribe(cameras)

    def _subscribe(self, cameras: list[str]) -> None:
        for sub in self.camera_subscriptions:
            self.destroy_subscription(sub)
        profile = qos.EVERY_FRAME if self.node_cfg.reliable else qos.CAMERA
        subs = []
        if self.node_cfg.input == WIRE:
            # Each region has its own camera_info (roi): they are paired by stamp in the frame set.
            streams = ('depth_info', 'color_info', 'depth', 'color')
            kinds = {'depth_info': (CameraInfo, wire.WIRE_DEPTH_INFO), 'color_info': (CameraInfo, wire.WIRE_COLOR_INFO),
                     'depth': (CompressedImage, wire.WIRE_DEPTH), 'color': (CompressedImage, wire.WIRE_COLOR)}
            for cam in cameras:
                for stream in streams:
                    kind, topic = kinds[stream]
                    subs.append(self.create_subscription(
                        kind, topics.camera_topic(cam, topic), lambda m, c=cam, s=stream: self._on_image(c, s, m),
                        profile))
            self._start_sync(cameras, subs, streams)
            return
        # camera_info first: the executor serves ready subscriptions in creation order
        for cam in cameras:
            for topic, stream in ((topics.DEPTH_CLEAN_INFO, 'depth'), (topics.COLOR_CORRECTED_INFO, 'color')):
                subs.append(self.create_subscription(
                    CameraInfo, topics.camera_topic(cam, topic), lambda m, c=cam, s=stream: self.infos.__setitem__((c, s), m),
                    profile))
        for cam in cameras:
            for topic, stream in ((topics.DEPTH_CLEAN, 'depth'), (topics.COLOR_CORRECTED, 'color')):
                subs.append(self.create_subscription(
                    Image, topics.camera_topic(cam, topic), lambda m, c=cam, s=stream: self._on_image(c, s, m), profile))
        self._start_sync(cameras, subs, ('depth', 'color'))

    def _start_sync(self, cameras: list[str], subs: list, streams: tuple[str, ...]) -> None:
        self.camera_subscriptions = subs
        self.cameras = cameras
        self.sync = FrameSetSynchronizer(cameras, streams,
                                         tolerance_ns=tolerance_ns_from_ms(self.node_cfg.sync_tolerance_ms),
                                         timeout_ns=int(self.node_cfg.frame_timeout_ms * 1e6), max_pending=4)
        self.get_logger().info(f'fusing {len(cameras)} cameras ({self.node_cfg.input}): {", ".join(cameras)}')

    def _on_phase(self, msg: String) -> None:
        self.phases.change(*topics.parse_phase_change(msg.data))

    def _on_image(self, camera: str, stream: str, msg: Image | CompressedImage | CameraInfo) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        if stream == 'depth':                   # one frame per camera and frame set
            self.silence.arrived(camera, time.monotonic_ns())
        self.phases.frame(stamp)
        if self.sync is None or not self.admission.admit((camera, stream), stamp):
            return
        self._emit(self.sync.add(camera, stamp, msg, stream=stream, now_ns=time.monotonic_ns()))

    def _poll(self) -> None:
        if self.sync is not None:
            self._emit(self.sync.poll(time.monotonic_ns()))

    def _emit(self, sets: list[FrameSet]) -> None:
        for fs in sets:
            if not fused_phase(self.phases.at(fs.stamp_ns), self.node_cfg.phases):
                continue
            if self.node_cfg.in_order and fs.stamp_ns < self.newest_submitted:
                self.stats['out_of_order'] += 1
                continue
            self.newest_submitted = max(self.newest_submitted, fs.stamp_ns)
            if not fs.complete:
                self.stats['incomplete'] += 1
            self.worker.submit((fs, self.calibration, list(self.cameras)))

    # fusion (worker thread) ---------------------------------------------------------------
    def _fuse(self, item) -> None:
        fs, calibration, cameras = item
        t0, cpu0 = time.perf_counter(), time.process_time()
        try:
            self._fuse_set(fs, calibration, cameras, t0)
        finally:
            self.work_s += time.process_time() - cpu0

    def _fuse_set(self, fs: FrameSet, calibration: Calibration, cameras: list[str], t0: float) -> None:
        if self.node_cfg.input == WIRE:
            streams, to_view = ('depth', 'depth_info', 'color', 'color_info'), wire_view
        else:
            streams, to_view = ('depth', 'color'), self._view
        pairs = {c: tuple(fs.get(c, s) for s in streams) for c in cameras}
        parts = {c: p for c, p in pairs.items() if None not in p}
        fused = self.rig.fuse(fs.stamp_ns, calibration, cameras, parts, lambda c, p, T: to_view(c, *p, T),
                              glb=bool(self.pub_glb.get_subscription_count()))
        plan, model, encoded, frame = fused.plan, fused.model, fused.encoded, fused.frame
        if plan.problems:
            self.diagnostics.report('warn', 'cameras left out of frame set: '
                                    + '; '.join(f'{c}: {e}' for c, e in plan.problems.items()))
        if plan.skipped:
            self.stats['skipped'] += 1
            self.diagnostics.report('warn', plan.skipped)
            return
        if plan.missing:
            self.diagnostics.report('warn', f'frame set {fs.stamp_ns} fused without {", ".join(plan.missing)}')
        if fused.empty:
            self.stats['empty'] += 1
            self.last = {'cameras': len(plan.views), 'vertices': 0}
            return
        if self.pub_points.get_subscription_count():
            self.pub_points.publish(points_to_pointcloud2(model.vertices, model.colors, fs.stamp_ns, frame))
        if self.pub_mesh.get_subscription_count():
            marker = simplify(model, self.node_cfg.marker_max_triangles)
            self.pub_mesh.publish(mesh_to_marker_cdr(marker.vertices, marker.colors, marker.triangles, fs.stamp_ns,
                                                     frame))
        stream = {}
        if encoded is not None:
            self.glb_stamps.append(fs.stamp_ns)
            rate = frame_rate(list(self.glb_stamps)) or 0.0
            stream = {'glb_bytes': len(encoded.data), 'glb_triangles': encoded.triangles,
                      'glb_mbit_per_s': round(len(encoded.data) * 8 * rate / 1e6, 2),
                      'encode_ms': round(sum(encoded.timings_ms.values()), 1)}
            if self.pub_glb.get_subscription_count():
                self.pub_glb.publish(glb_marker(encoded.data, fs.stamp_ns, frame, f'{fs.stamp_ns}.glb'))
        latency_ms = (time.time_ns() - fs.stamp_ns) / 1e6
        if 0 <= latency_ms < 60_000:      # stamps on the rig's clock (live), not a replayed bag's
            self.latency_ms.append((time.monotonic(), latency_ms))
        if self.rig.writer is not None:
            self._write(fused)
        self.short_of = plan.missing
        self.stats['fused'] += 1
        self.stats['fused_complete'] += not plan.missing
        self.last = {'fusion_ms': round(sum(model.timings_ms.values()), 1),
                     'total_ms': round((time.perf_counter() - t0) * 1000, 1), 'cameras': len(plan.views),
                     'vertices': len(model.vertices), 'triangles': len(model.triangles), **stream}

    def _write(self, fused: FusedSet) -> None:
        """One frame into the sequence. A failed write (a full disk) stops the recording, whole up
        to the last frame, while fusion and the live stream go on."""
        try:
            self.rig.write(fused)
        except OSError as e:
            writer, self.rig.writer = self.rig.writer, None
            self.writer_failure = (f'recording stopped: {e}; the sequence holds {writer.written} whole frames '
                                   f'in {writer.folder}')
            try:
                writer.close()
            except OSError as close_error:
                self.writer_failure += f' (its manifest.json is stale: {close_error})'
            self.get_logger().error(self.writer_failure)
            self.diagnostics.report('error', self.writer_failure)
            self.exit_code = 1             # the take is short: say so when the node stops

    def _on_fusion_error(self, item, e: Exception) -> None:
        self.diagnostics.report('error', f'frame set {item[0].stamp_ns} not fused: {type(e).__name__}: {e}')

    def _view(self, cam: str, depth_msg: Image, color_msg: Image, T_frame_color: np.ndarray) -> CameraView:
        infos = self.infos.get((cam, 'depth')), self.infos.get((cam, 'color'))
        if None in infos:
            raise BadInput('no camera_info yet')
        if depth_msg.encoding == '16UC1':
            depth_mm = image_to_numpy(depth_msg)
        else:   # 32FC1 metres (NaN = no depth), or a clear error for anything else
            depth_mm = depth_to_millimetres(depth_to_metres(depth_msg))
        return CameraView(cam, depth_mm, camera_info_to_model(infos[0]), color_to_rgb(color_msg),
                          camera_info_to_model(infos[1]), T_frame_color)

    def _report(self) -> None:
        if self.calibration is None:
            # a graph starting: the latched calibration arrives once discovery matches the
            # publisher; waiting past the grace is something to act on (no calibrate step, a
            # calibration for other cameras, another ROS domain)
            waited = time.monotonic() - self.started
            self.diagnostics.report('warn' if waited > self.node_cfg.calibration_grace_s else 'ok',
                                    f'waiting for the calibration on /{topics.CALIBRATION}')
            return
        w = self.worker
        now = time.monotonic_ns()
        self.silence.frames = self.node_cfg.silent_periods
        silent = self.silence.silent(self.cameras, now)
        fused = f'{self.stats["fused"]} frame sets fused'
        quiet_s = self.silence.idle_s(now)
        if not silent and quiet_s > 1.0:
            fused += f'; idle: no camera has delivered for {quiet_s:.0f} s'     # a phase without output, or the end
        errors, warnings = [], []
        if silent:
            # the names only: the message (and so the log line) stays the same while the silence lasts
            errors.append('silent cameras (no frames while the others deliver): ' + ', '.join(silent))
        elif self.short_of:
            warnings.append(f'running short of cameras: the last frame set lacked {", ".join(self.short_of)}')
        if self.writer_failure:
            errors.append(self.writer_failure)
        if self.last.get('vertices') == 0:
            warnings.append('empty stage: the last frame set had no depth inside the capture box')
        level = 'error' if errors else 'warn' if warnings else 'ok'
        message = '; '.join(errors + warnings + [fused])
        latency = {}
        recent = [ms for t, ms in self.latency_ms if t > time.monotonic() - LATENCY_WINDOW_S]
        if recent:
            p50, p95 = np.percentile(recent, [50, 95])
            latency = {'latency_ms_p50': round(float(p50), 1), 'latency_ms_p95': round(float(p95), 1)}
        self.diagnostics.report(level, message, waiting=w.pending,
                                dropped=w.dropped + self.stats['skipped'] + self.stats['out_of_order'],
                                queue_dropped=w.dropped, errors=w.errors,
                                work_s=round(self.work_s, 3), **self.stats, **self.last, **latency,
                                silent_cameras=','.join(silent), short_of=','.join(self.short_of),
                                silent_s=','.join(f'{s:.1f}' for s in silent.values()),
                                **self.admission.counts())

    def destroy_node(self):
        self.worker.stop()
        if self.rig.writer is not None:
            self.rig.writer.close()
        return super().destroy_node()


def main(args=None):
    node_main(TsdfFusionNode, args)


if __name__ == '__main__':
    main()
