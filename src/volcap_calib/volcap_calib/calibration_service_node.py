"""calibration_service: the rig's extrinsic and colour calibration on request.

    ros2 run volcap_calib calibration_service --ros-args -p output:=/rig/calibration.yaml

Listens to every camera of the rig (``camN/color/image_raw`` or, with
``color_transport:=compressed``, ``camN/color/image_raw/compressed``;
``camN/color/camera_info``, ``camN/depth/image_raw``, ``camN/depth/camera_info``) while the
board is moved. The rig is the ``rig_file`` parameter, else ``/volcap/rig`` (bags), else
assembled from the cameras' camera_info and the vendor drivers' ``/tf_static`` (registered depth
needs no transform). Subscriptions are reliable (a board view lost in transport is lost
accuracy); the board is detected in a worker thread (a bounded drop-oldest queue keeps the
subscriptions free). ``volcap/calibrate`` (std_srvs/Trigger) solves with every view gathered so
far, writes ``output`` atomically and publishes the result latched on ``volcap/calibration``
(YAML, with the studio frame fitted to the floor in the cameras' depth) and
``volcap/camera_poses`` (PoseArray of the cameras' colour frames in the studio frame). On failure the
response names the cameras and why, and the previous file and topics stay as they were.
"""
from __future__ import annotations

import time
from pathlib import Path

import yaml
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from volcap_core import qos, topics
from volcap_core.calibration import Calibration
from volcap_core.conversions import (
    MessageConversionError,
    camera_info_to_model,
    color_message_to_rgb,
    depth_to_metres,
    make_header,
    matrix_to_pose,
    stamp_to_ns,
)
from volcap_core.rig_source import RigResolver
from volcap_core.ros import Diagnostics, StaticTransformListener, declare_config, node_main, subscribe_color
from volcap_core.sync import FrameSetSynchronizer, tolerance_ns_from_ms
from volcap_core.worker import DropOldestWorker

from .board import BoardConfig
from .calibrate import BoardView
from .extrinsics import CalibrationError
from .session import CalibrationServiceConfig, CalibrationSession

STREAMS = ('color', 'depth')


class CalibrationService(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('calibration_service', **node_options)
        cfg = declare_config(self, CalibrationServiceConfig, self._on_config)
        self.cameras = list(cfg.cameras)
        board = BoardConfig.from_yaml(cfg.board_file) if cfg.board_file else BoardConfig.from_yaml()
        self.session = CalibrationSession(cfg, board)
        self.diagnostics = Diagnostics(self, 'calibration service')
        # Frame sets are gathered from the start (a bag may play its images before the latched
        # rig description arrives); detection waits for the rig.
        self.sync = FrameSetSynchronizer(self.cameras, STREAMS,
                                         tolerance_ns=tolerance_ns_from_ms(cfg.sync_tolerance_ms),
                                         timeout_ns=500_000_000, max_pending=4)
        self.infos: dict[tuple[str, str], CameraInfo] = {}
        self.rigs = RigResolver(self.cameras, cfg.tf_prefix)
        self.phase = None
        self.coverage_summary = ''
        self.worker = DropOldestWorker(self._detect, cfg.queue_size, 'board-detection',
                                       on_error=self._on_detection_error, ready=lambda: self.session.ready)

        self.pub_calibration = self.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
        self.pub_poses = self.create_publisher(PoseArray, '/' + topics.CAMERA_POSES, qos.LATCHED)
        if cfg.rig_file:
            self._set_rig(cfg.rig_file, lambda: self.rigs.set_file(cfg.rig_file))
        self.create_subscription(String, '/' + topics.RIG, self._on_rig, qos.LATCHED)
        self.tf = StaticTransformListener(self, self.diagnostics, lambda: self._set_rig('/tf_static', self.rigs.refresh))
        self.rigs.transforms = self.tf.transforms
        self.create_subscription(String, '/' + topics.PHASE, self._on_phase, qos.LATCHED)
        self.create_service(Trigger, '/' + topics.CALIBRATE, self._on_calibrate)
        for cam in self.cameras:
            subscribe_color(self, cfg.color_transport, lambda m, c=cam: self._on_image(m, c, 'color'), qos.EVERY_FRAME,
                            camera=cam)
            self.create_subscription(Image, topics.camera_topic(cam, topics.DEPTH_IMAGE),
                                     lambda m, c=cam: self._on_image(m, c, 'depth'), qos.EVERY_FRAME)
            for stream, rel in (('color', topics.COLOR_INFO), ('depth', topics.DEPTH_INFO)):
                self.create_subscription(CameraInfo, topics.camera_topic(cam, rel),
                                         lambda m, c=cam, s=stream: self._on_info(m, c, s), qos.EVERY_FRAME)
        self.create_timer(1.0, self._report)
        self.create_timer(0.2, lambda: self._enqueue(self.sync.poll(time.monotonic_ns())))
        output = Path(cfg.output)
        if output.exists():
            try:
                self._publish(Calibration.load(output))
                self.get_logger().info(f'published the existing calibration {output}')
            except ValueError as e:
                self.diagnostics.report('warn', f'existing {output} is unusable: {e}')
        self.get_logger().info('calibration_service started')

    def _on_config(self, cfg: CalibrationServiceConfig) -> None:
        self.session.cfg = cfg

    # inputs -----------------------------------------------------------------------------------
    def _on_rig(self, msg: String) -> None:
        self._set_rig(f'/{topics.RIG}', lambda: self.rigs.offer_description(msg.data))

    def _set_rig(self, source: str, resolve) -> None:
        """``resolve()``: the rig the resolver chose from what just arrived from ``source`` (None:
        nothing changed; a rig file wins over /volcap/rig, which wins over camera_info +
        /tf_static)."""
        try:
            rig = resolve()
            warning = self.session.set_rig(rig) if rig is not None else None
        except (OSError, ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('error', f'unusable rig description from {source}: {e}')
            return
        if self.rigs.waiting:
            self.diagnostics.report('warn', 'no depth-to-colour extrinsic on /tf_static yet for '
                                    + ', '.join(self.rigs.waiting))
        if rig is None:
            return
        self.worker.poke()
        if warning:
            self.diagnostics.report('warn', warning)
        names = self.session.rig.names
        self.get_logger().info(f'calibrating {len(names)} cameras ({self.rigs.source}): {", ".join(names)}')

    def _on_info(self, msg: CameraInfo, camera: str, stream: str) -> None:
        known = (camera, stream) in self.infos
        self.infos[(camera, stream)] = msg
        if not known:
            self._set_rig(f'{camera} camera_info', lambda: self.rigs.add_camera_info(
                camera, stream, camera_info_to_model(msg), msg.header.frame_id))

    def _on_phase(self, msg: String) -> None:
        self.phase = topics.parse_phase(msg.data)

    def _on_image(self, msg: Image | CompressedImage, camera: str, stream: str) -> None:
        if self.session.collecting(self.phase):
            self._enqueue(self.sync.add(camera, stamp_to_ns(msg.header.stamp), msg, stream=stream,
                                        now_ns=time.monotonic_ns()))

    def _enqueue(self, frame_sets) -> None:
        for fs in frame_sets:
            self.worker.submit(fs)

    # detection (worker thread) ----------------------------------------------------------------
    def _detect(self, fs) -> None:
        frames, problems = {}, []
        for cam in self.session.rig.names:
            color, depth = fs.get(cam, 'color'), fs.get(cam, 'depth')
            info_c, info_d = self.infos.get((cam, 'color')), self.infos.get((cam, 'depth'))
            if color is None or info_c is None:
                continue
            has_depth = depth is not None and info_d is not None
            try:
                frames[cam] = BoardView(color_message_to_rgb(color), camera_info_to_model(info_c),
                                          depth_to_metres(depth) if has_depth else None,
                                          camera_info_to_model(info_d) if has_depth else None)
            except (MessageConversionError, ValueError) as e:
                problems.append(f'{cam}: {e}')
        self.session.add(frames)
        if problems:
            self.diagnostics.report('warn', f'frame set {fs.stamp_ns} skipped for ' + '; '.join(problems))

    def _on_detection_error(self, fs, e: Exception) -> None:
        self.diagnostics.report('error', f'frame set {fs.stamp_ns} not detected: {type(e).__name__}: {e}')

    # service ----------------------------------------------------------------------------------
    def _on_calibrate(self, request, response):
        if not self.session.ready:
            response.success = False
            response.message = (f'no cameras yet: waiting for camera_info on {", ".join(self.cameras)} (and the '
                                f'depth-to-colour extrinsic on /tf_static, a rig_file or /{topics.RIG}); '
                                f'{self.worker.pending} frame sets waiting')
            return response
        self._enqueue(self.sync.flush())
        timeout = self.session.cfg.drain_timeout_s
        if not self.worker.wait_idle(timeout):
            self.diagnostics.report('warn', f'{self.worker.pending} frame sets still queued after {timeout} s; '
                                            'solving without them')
        output = self.session.cfg.output
        try:
            solved = self.session.solve()
        except CalibrationError as e:
            response.success, response.message = False, f'calibration failed, {output} unchanged: {e}'
            self.diagnostics.report('error', response.message, failed_cameras=','.join(sorted(e.cameras)))
            return response
        except OSError as e:
            response.success, response.message = False, f'could not write {output}: {e}'
            self.diagnostics.report('error', response.message)
            return response
        self._publish(solved.calibration)
        response.success, response.message = True, solved.message
        self.diagnostics.report('warn' if solved.weak else 'ok', response.message,
                                weak_cameras=','.join(solved.weak))
        return response

    def _publish(self, calibration: Calibration) -> None:
        try:
            text = calibration.checked_yaml()
        except ValueError as e:
            self.diagnostics.report('error', f'calibration not published (the nodes would refuse it): {e}')
            return
        self.pub_calibration.publish(String(data=text))
        frame, T_frame_world = calibration.output_frame()
        poses = PoseArray(header=make_header(time.time_ns(), frame))
        poses.poses = [matrix_to_pose(T_frame_world @ cam.T_world_color) for cam in calibration.cameras.values()]
        self.pub_poses.publish(poses)

    def _report(self) -> None:
        self._set_rig('/tf_static', self.rigs.refresh)     # cameras whose extrinsic arrived since
        if not self.session.ready:
            return
        observations, views = self.session.counts()
        coverage = self.session.coverage()
        summary = coverage.summary()
        if summary != self.coverage_summary and observations:
            self.get_logger().info(f'board coverage: {summary}')
            self.coverage_summary = summary
        # The counts end the message: tools and tests read "... in N frame sets" from its end.
        self.diagnostics.report('ok', f'{summary}; {observations} board observations in {views} frame sets',
                                observations=observations, frame_sets=views, queued=self.worker.pending,
                                dropped=self.worker.dropped, linked=','.join(coverage.linked),
                                unlinked=','.join(coverage.unlinked), weak=','.join(coverage.weak),
                                advice=' '.join(coverage.advice))

    def destroy_node(self):
        self.worker.stop(timeout=2.0)
        return super().destroy_node()


def main(args=None):
    node_main(CalibrationService, args)


if __name__ == '__main__':
    main()
