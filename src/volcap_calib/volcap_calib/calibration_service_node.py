"""calibration_service: the rig's extrinsic and colour calibration on request.

    ros2 run volcap_calib calibration_service --ros-args -p output:=/rig/calibration.yaml

Listens to every camera of the rig (``/volcap/rig``; ``camN/color/image_raw``,
``camN/color/camera_info``, ``camN/depth/image_raw``, ``camN/depth/camera_info``) while the
board is moved (reliable subscriptions: a board view lost in transport is lost accuracy),
detecting it in a worker thread (a bounded drop-oldest queue keeps the
subscriptions free). ``volcap/calibrate`` (std_srvs/Trigger) solves with every view gathered so
far, writes ``output`` atomically and publishes the result latched on ``volcap/calibration``
(YAML) and ``volcap/camera_poses`` (PoseArray, world = reference colour frame). On failure
the response names the cameras and why, and the previous file and topics stay as they were.
"""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import yaml
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from volcap_core import qos, topics
from volcap_core.calibration import Calibration
from volcap_core.conversions import (
    MessageConversionError,
    camera_info_to_model,
    color_to_rgb,
    depth_to_metres,
    make_header,
    matrix_to_pose,
    stamp_to_ns,
)
from volcap_core.rig import Rig
from volcap_core.ros import Diagnostics, declare_config, run_node
from volcap_core.settings import setting
from volcap_core.sync import SYNC_TOLERANCE_MS, FrameSetSynchronizer
from volcap_core.worker import DropOldestWorker

from .board import BoardConfig
from .calibrate import CalibrationConfig, Calibrator, CameraFrame
from .colour import METHODS
from .extrinsics import CalibrationError, SolverConfig

STREAMS = {'color': topics.COLOR_IMAGE, 'depth': topics.DEPTH_IMAGE}


@dataclass
class CalibrationServiceConfig:
    output: str = setting('calibration.yaml', 'calibration file written on success')
    cameras: tuple[str, ...] = setting(tuple(topics.camera_names(8)), 'camera namespaces to listen to (the rig '
                                       'description says which of them are calibrated)', read_only=True)
    board_file: str = setting('', 'board YAML (empty: the volcap board)', read_only=True)
    reference: str = setting('', 'camera whose colour frame is the world (empty: the first)')
    collect_phase: str = setting(topics.CALIBRATION_PHASE, 'gather frame sets only in this announced phase '
                                 '(empty: always)')
    use_depth: bool = setting(True, 'add depth-to-board-plane residuals to the solve')
    colour_method: str = setting('', 'force a colour model (empty: leave-one-out choice)',
                                 choices=('', *METHODS))
    queue_size: int = setting(16, 'frame sets waiting for detection before the oldest is dropped', 1, 1000,
                              read_only=True)
    drain_timeout_s: float = setting(60.0, 'how long a calibrate call waits for queued frame sets to be detected',
                                     0.0, 3600.0)
    sync_tolerance_ms: float = setting(SYNC_TOLERANCE_MS, 'stamp tolerance of a frame set', 0.0, 100.0,
                                       read_only=True)


class CalibrationService(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('calibration_service', **node_options)
        self.cfg = declare_config(self, CalibrationServiceConfig, self._on_config)
        self.cameras = list(self.cfg.cameras)
        self.board = BoardConfig.from_yaml(self.cfg.board_file) if self.cfg.board_file else BoardConfig.from_yaml()
        self.diagnostics = Diagnostics(self, 'calibration service')
        self.rig: Rig | None = None
        self.calibrator: Calibrator | None = None
        # Frame sets are gathered from the start (a bag may play its images before the latched
        # rig description arrives); detection waits for the rig.
        self.sync = FrameSetSynchronizer(self.cameras, tuple(STREAMS),
                                         tolerance_ns=int(self.cfg.sync_tolerance_ms * 1e6),
                                         timeout_ns=500_000_000, max_pending=4)
        self.infos: dict[tuple[str, str], CameraInfo] = {}
        self.phase = None
        self.detected_sets = 0
        self.lock = threading.Lock()          # guards the calibrator
        self.worker = DropOldestWorker(self._detect, self.cfg.queue_size, 'board-detection',
                                       on_error=self._on_detection_error, ready=lambda: self.calibrator is not None)

        self.pub_calibration = self.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
        self.pub_poses = self.create_publisher(PoseArray, '/' + topics.CAMERA_POSES, qos.LATCHED)
        self.create_subscription(String, '/' + topics.RIG, self._on_rig, qos.LATCHED)
        self.create_subscription(String, '/' + topics.PHASE, self._on_phase, qos.LATCHED)
        self.create_service(Trigger, '/' + topics.CALIBRATE, self._on_calibrate)
        for cam in self.cameras:
            for stream, rel in STREAMS.items():
                self.create_subscription(Image, topics.camera_topic(cam, rel),
                                         lambda m, c=cam, s=stream: self._on_image(m, c, s), qos.EVERY_FRAME)
            for stream, rel in (('color', topics.COLOR_INFO), ('depth', topics.DEPTH_INFO)):
                self.create_subscription(CameraInfo, topics.camera_topic(cam, rel),
                                         lambda m, c=cam, s=stream: self.infos.__setitem__((c, s), m), qos.EVERY_FRAME)
        self.create_timer(1.0, self._report)
        self.create_timer(0.2, lambda: self._enqueue(self.sync.poll(time.monotonic_ns())))
        self.output = Path(self.cfg.output)
        if self.output.exists():
            try:
                self._publish(Calibration.load(self.output))
                self.get_logger().info(f'published the existing calibration {self.output}')
            except (ValueError, KeyError, yaml.YAMLError) as e:
                self.diagnostics.report('warn', f'existing {self.output} is unusable: {e}')
        self.get_logger().info('calibration_service started')

    def _on_config(self, cfg: CalibrationServiceConfig) -> None:
        self.cfg = cfg
        self.output = Path(cfg.output)

    # inputs -----------------------------------------------------------------------------------
    def _on_rig(self, msg: String) -> None:
        try:
            rig = Rig.from_yaml(msg.data)
        except (ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('error', f'unusable rig description: {e}')
            return
        unheard = [c for c in rig.names if c not in self.cameras]
        if unheard:
            self.diagnostics.report('error', f'rig cameras {unheard} are not in the cameras parameter; '
                                             'restart with them listed')
            return
        if self.rig is not None and rig.names == self.rig.names:
            self.rig = rig
            return
        changed = self.rig is not None
        self.rig = rig
        with self.lock:
            self.calibrator = self._new_calibrator()
        self.worker.poke()
        if changed:
            self.diagnostics.report('warn', 'the rig changed: views gathered so far were dropped')
        self.get_logger().info(f'calibrating {len(rig.names)} cameras: {", ".join(rig.names)}')

    def _new_calibrator(self) -> Calibrator:
        c = self.cfg
        cfg = CalibrationConfig(reference=c.reference or None, use_depth=c.use_depth,
                                colour_method=c.colour_method or None,
                                solver=SolverConfig(depth_weight=1.0 if c.use_depth else 0.0))
        return Calibrator(self.rig, self.board, cfg)

    def _on_phase(self, msg: String) -> None:
        try:
            self.phase = (yaml.safe_load(msg.data) or {}).get('phase')
        except (yaml.YAMLError, AttributeError):
            pass

    def _collecting(self) -> bool:
        phase = self.cfg.collect_phase
        return not phase or self.phase is None or self.phase == phase

    def _on_image(self, msg: Image, camera: str, stream: str) -> None:
        if self._collecting():
            self._enqueue(self.sync.add(camera, stamp_to_ns(msg.header.stamp), msg, stream=stream,
                                        now_ns=time.monotonic_ns()))

    def _enqueue(self, frame_sets) -> None:
        for fs in frame_sets:
            self.worker.submit(fs)

    # detection (worker thread) ----------------------------------------------------------------
    def _detect(self, fs) -> None:
        frames, problems = {}, []
        for cam in self.rig.names:
            color, depth = fs.get(cam, 'color'), fs.get(cam, 'depth')
            info_c, info_d = self.infos.get((cam, 'color')), self.infos.get((cam, 'depth'))
            if color is None or info_c is None:
                continue
            has_depth = depth is not None and info_d is not None
            try:
                frames[cam] = CameraFrame(color_to_rgb(color), camera_info_to_model(info_c),
                                          depth_to_metres(depth) if has_depth else None,
                                          camera_info_to_model(info_d) if has_depth else None)
            except (MessageConversionError, ValueError) as e:
                problems.append(f'{cam}: {e}')
        with self.lock:
            if self.calibrator is not None and frames:
                self.calibrator.add(self.detected_sets, frames)
                self.detected_sets += 1
        if problems:
            self.diagnostics.report('warn', f'frame set {fs.stamp_ns} skipped for ' + '; '.join(problems))

    def _on_detection_error(self, fs, e: Exception) -> None:
        self.diagnostics.report('error', f'frame set {fs.stamp_ns} not detected: {type(e).__name__}: {e}')

    def _drain(self) -> bool:
        self._enqueue(self.sync.flush())
        return self.worker.wait_idle(self.cfg.drain_timeout_s)

    # service ----------------------------------------------------------------------------------
    def _on_calibrate(self, request, response):
        if self.rig is None or self.calibrator is None:
            response.success = False
            response.message = f'no rig description on /{topics.RIG} yet ({self.worker.pending} frame sets waiting)'
            return response
        if not self._drain():
            self.diagnostics.report('warn', f'{self.worker.pending} frame sets still queued after '
                                            f'{self.cfg.drain_timeout_s} s; '
                                            'solving without them')
        t0 = time.monotonic()
        with self.lock:
            calibrator = self.calibrator
            try:
                outcome = calibrator.solve()
            except CalibrationError as e:
                response.success = False
                response.message = f'calibration failed, {self.output} unchanged: {e}'
                self.diagnostics.report('error', response.message, failed_cameras=','.join(sorted(e.cameras)))
                return response
        calibration = outcome.calibration
        try:
            calibration.save(self.output)
        except OSError as e:
            response.success, response.message = False, f'could not write {self.output}: {e}'
            self.diagnostics.report('error', response.message)
            return response
        self._publish(calibration)
        worst = max(calibration.cameras.items(), key=lambda kv: kv[1].reproj_rms_px or 0.0)
        response.success = True
        response.message = (f'calibrated {len(calibration.cameras)} cameras from {calibrator.views} frame sets in '
                            f'{time.monotonic() - t0:.1f} s; worst reprojection {worst[0]} '
                            f'{worst[1].reproj_rms_px:.3f} px; wrote {self.output}')
        if outcome.colour_errors:
            response.message += '; no colour model for ' + ', '.join(
                f'{c} ({why})' for c, why in outcome.colour_errors.items())
        self.diagnostics.report('ok', response.message)
        return response

    def _publish(self, calibration: Calibration) -> None:
        self.pub_calibration.publish(String(data=calibration.to_yaml()))
        poses = PoseArray(header=make_header(time.time_ns(), calibration.world_frame))
        poses.poses = [matrix_to_pose(cam.T_world_color) for cam in calibration.cameras.values()]
        self.pub_poses.publish(poses)

    def _report(self) -> None:
        if self.calibrator is None:
            return
        with self.lock:
            observations, views = len(self.calibrator.observations), self.calibrator.views
        self.diagnostics.report('ok', f'{observations} board observations in {views} frame sets',
                                observations=observations, frame_sets=views, queued=self.worker.pending,
                                dropped=self.worker.dropped)

    def destroy_node(self):
        self.worker.stop(timeout=2.0)
        return super().destroy_node()


def main(args=None):
    sys.exit(run_node(CalibrationService, args))


if __name__ == '__main__':
    main()
