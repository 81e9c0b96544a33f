"""depth_filter: one camera's depth registered to colour and cleaned.

    ros2 run volcap_filter depth_filter --ros-args -r __ns:=/cam0

Subscribes (relative names, so a launch remaps them onto a vendor driver's topics)
``color/image_raw`` (or JPEG ``color/image_raw/compressed`` with ``color_transport:=compressed``),
``color/camera_info``, ``depth/image_raw`` (native, or registered by the driver: same frame id as
the colour), ``depth/camera_info``, and the session phase on ``/volcap/phase``. Native depth takes
its depth-to-colour extrinsic from the ``rig_file`` parameter, ``/volcap/rig`` or the driver's
``/tf_static`` (looked up between the two camera_info frame ids). Publishes
``depth/image_clean`` (16UC1 mm, colour geometry at the output size) with its camera_info and
``points`` (xyz + rgb, colour optical frame; built only while someone subscribes). In a live
graph only the frame sets admitted on ``/volcap/admission`` are cleaned (the same ones in every
camera's stages, ``volcap_core.admission``). The clean plate is learnt during the
``clean_plate`` phase, or on the ``~/capture_clean_plate`` service. Every threshold is a
parameter and can be changed while running.
"""
from __future__ import annotations

import time
from pathlib import Path

import yaml
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from volcap_core import qos, topics
from volcap_core.camera import depth_to_millimetres
from volcap_core.cdr import image_to_cdr
from volcap_core.conversions import (
    MessageConversionError,
    camera_info_to_model,
    camera_model_to_info,
    color_message_to_rgb,
    depth_to_metres,
    points_to_pointcloud2,
    stamp_to_ns,
)
from volcap_core.rig import Rig
from volcap_core.rig_source import RigResolver
from volcap_core.ros import (
    AdmissionListener,
    Diagnostics,
    StaticTransformListener,
    color_message_type,
    declare_config,
    node_main,
    subscribe_color,
)
from volcap_core.sync import FrameSetSynchronizer, tolerance_ns_from_ms

from .mask import BackgroundModel
from .pipeline import DepthFilterConfig
from .session import CleanPlateSession, DepthFilterNodeConfig, FramePair, Outcome

# An empty stage for a moment (between takes, a board phase) is normal; this many cleaned frames
# in a row with no depth left is worth a look.
EMPTY_WARN_FRAMES = 10


def decode(pair: tuple[Image, Image]):
    return color_message_to_rgb(pair[0]), depth_to_metres(pair[1])


class DepthFilter(Node):
    """The node. ``volcap_pipeline``'s camera_pipeline node extends it (the same inputs, decisions
    and depth outputs, with the colour correction added) through ``node_name``, ``role`` and
    ``make_session``."""

    role = 'depth filter'

    def __init__(self, node_name: str = 'depth_filter', **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__(node_name, **node_options)
        self.node_cfg = declare_config(self, DepthFilterNodeConfig, self._on_node_config)
        cfg = declare_config(self, DepthFilterConfig, lambda c: self.session.set_config(c))
        self.camera = self.node_cfg.camera or self.get_namespace().strip('/').split('/')[-1] or 'cam0'
        self.diagnostics = Diagnostics(self, f'{self.role} {self.camera}')
        background = None
        path = self.node_cfg.background_file
        if path and Path(path).exists():
            try:
                background = BackgroundModel.load(path)
                self.get_logger().info(f'loaded a {background.frames}-frame clean plate from {path}')
            except ValueError as e:      # keep running: a new clean plate is learnt, the file is kept
                self.diagnostics.report('error', f'{e}; learning a new clean plate (the file stays until then)')
        self.session = self.make_session(cfg, background)
        self.sync = FrameSetSynchronizer([self.camera], ('color', 'depth'),
                                         tolerance_ns=tolerance_ns_from_ms(self.node_cfg.sync_tolerance_ms),
                                         timeout_ns=int(self.node_cfg.pair_timeout_ms * 1e6),
                                         max_pending=4)
        self.figures_requested = False
        self.processed = self.skipped = 0
        self.empty_streak = 0      # consecutive cleaned frames with no depth left
        self.last_ms = 0.0
        self.work_s = 0.0          # process CPU time spent on admitted frames

        # Created before the image subscriptions: the executor serves ready subscriptions in
        # creation order, so a phase change or camera_info sent with a frame is seen before it.
        self.rigs = RigResolver([self.camera], self.node_cfg.tf_prefix)
        if self.node_cfg.rig_file:
            self._load_rig_file(self.node_cfg.rig_file)
        self.create_subscription(String, '/' + topics.RIG, self._on_rig, qos.LATCHED)
        self.tf = StaticTransformListener(self, self.diagnostics, lambda: self._use_rig(self.rigs.refresh()))
        self.rigs.transforms = self.tf.transforms
        self.create_subscription(String, '/' + topics.PHASE, self._on_phase, qos.LATCHED)
        self.admission = AdmissionListener(self, self.diagnostics)
        inputs = qos.EVERY_FRAME if self.node_cfg.reliable else qos.CAMERA
        self.create_subscription(CameraInfo, topics.COLOR_INFO, lambda m: self._on_info(m, 'color'), inputs)
        self.create_subscription(CameraInfo, topics.DEPTH_INFO, lambda m: self._on_info(m, 'depth'), inputs)
        # Serialised: a frame set that is not admitted is dropped before it is deserialised.
        color_type = color_message_type(self.node_cfg.color_transport)
        subscribe_color(self, self.node_cfg.color_transport, lambda m: self._on_image(m, 'color', color_type), inputs,
                        raw=True)
        self.create_subscription(Image, topics.DEPTH_IMAGE, lambda m: self._on_image(m, 'depth', Image), inputs,
                                 raw=True)
        self.pub_depth = self.create_publisher(Image, topics.DEPTH_CLEAN, qos.DRIVER)
        self.pub_info = self.create_publisher(CameraInfo, topics.DEPTH_CLEAN_INFO, qos.DRIVER)
        self.pub_points = self.create_publisher(PointCloud2, topics.POINTS, qos.DRIVER)
        self.create_service(Trigger, '~/capture_clean_plate', self._on_capture_clean_plate)
        self.create_service(Trigger, '~/save_figures', self._on_save_figures)
        self.create_timer(1.0, self._report)
        self.get_logger().info(f'{node_name} started for {self.camera}')

    def make_session(self, cfg: DepthFilterConfig, background: BackgroundModel | None) -> CleanPlateSession:
        return CleanPlateSession(self.camera, cfg, decode, (self.node_cfg.output_width, self.node_cfg.output_height),
                                 self.node_cfg.max_held_frames, background, self.node_cfg.output_scale)

    def _on_node_config(self, cfg: DepthFilterNodeConfig) -> None:
        self.node_cfg = cfg

    # inputs -------------------------------------------------------------------------------
    def _load_rig_file(self, path: str) -> None:
        try:
            self._use_rig(self.rigs.set_file(path))
        except (OSError, ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('error', f'{self.camera}: unusable rig_file {path}: {e}')

    def _on_rig(self, msg: String) -> None:
        try:
            self._use_rig(self.rigs.offer_description(msg.data))   # None: the operator's rig file wins
        except (ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('error', f'unusable rig description: {e}')

    def _use_rig(self, rig: Rig | None) -> None:
        """A rig the resolver chose (None: nothing changed)."""
        if rig is not None:
            self._handle(self.session.set_rig(rig))
            self.get_logger().info(f'depth-to-colour extrinsic from the {self.rigs.source}')

    def _on_phase(self, msg: String) -> None:
        self._handle(self.session.set_phase(topics.parse_phase(msg.data)))

    def _on_capture_clean_plate(self, request, response):
        self.session.capture_clean_plate(self.node_cfg.clean_plate_frames)
        response.success = True
        response.message = (f'learning the clean plate from the next {self.node_cfg.clean_plate_frames} frames; '
                            'keep the stage empty')
        return response

    def _on_save_figures(self, request, response):
        self.figures_requested = True
        response.success = True
        response.message = f'the next processed frame goes to {self.node_cfg.figure_dir}'
        return response

    def _on_info(self, msg: CameraInfo, stream: str) -> None:
        try:
            model = camera_info_to_model(msg)
        except (MessageConversionError, ValueError) as e:
            self.diagnostics.report('error', f'{self.camera}: unusable {stream} camera_info: {e}')
            return
        rig = self.rigs.add_camera_info(self.camera, stream, model, msg.header.frame_id)
        self._handle(self.session.set_model(stream, model))
        self._use_rig(rig)

    def _on_image(self, data: bytes, stream: str, kind) -> None:
        started = time.process_time()
        try:
            msg = self.admission.admitted_message(stream, data, kind)
        except ValueError as e:
            self.diagnostics.report('error', f'{self.camera}: unreadable {stream} message: {e}')
            return
        if msg is None:
            return
        stamp = stamp_to_ns(msg.header.stamp)
        for fs in self.sync.add(self.camera, stamp, msg, stream=stream, now_ns=time.monotonic_ns()):
            if not fs.complete:
                self.skipped += 1
                self.diagnostics.report('warn', f'{self.camera}: no matching {fs.missing[0][1]} image for stamp '
                                                f'{fs.stamp_ns}; frame skipped')
                continue
            color, depth = fs.get(self.camera, 'color'), fs.get(self.camera, 'depth')
            # Registered depth shares the colour's frame id (Azure Kinect depth_to_rgb, Orbbec
            # depth_registration); the colour image's frame id decides, as camera_info may lag.
            pair = FramePair(stamp_to_ns(color.header.stamp), color.header.frame_id,
                             depth.header.frame_id == color.header.frame_id, (color, depth))
            self._handle(self.session.add(pair))
        self.work_s += time.process_time() - started

    # outcomes -----------------------------------------------------------------------------
    def _handle(self, outcomes: list[Outcome]) -> None:
        for o in outcomes:
            if o.kind == 'cleaned':
                self._publish(o)
            elif o.kind == 'plate_done':
                self._clean_plate_done(o.message)
            elif o.kind == 'held':
                # images often arrive before their camera_info or the rig: held, not lost (a pair
                # held too long is skipped, and that is a warning)
                self.diagnostics.report('ok', o.message)
            elif o.kind in ('skipped', 'failed'):
                self.skipped += o.pair is not None
                self.diagnostics.report('error' if o.kind == 'failed' else 'warn', o.message)

    def _publish(self, o: Outcome) -> None:
        t0 = time.perf_counter()
        stamp, frame = o.pair.stamp_ns, o.pair.frame_id
        if self.full_depth_wanted():
            # camera_info first, so a subscriber rarely sees the image before it
            self.pub_info.publish(camera_model_to_info(o.cleaner.output_model, stamp, frame))
            self.pub_depth.publish(image_to_cdr(depth_to_millimetres(o.result.depth), '16UC1', stamp, frame))
        if self.node_cfg.publish_points and self.pub_points.get_subscription_count():
            xyz, rgb = o.cleaner.points(o.result)
            self.pub_points.publish(points_to_pointcloud2(xyz, rgb, stamp, frame))
        if self.figures_requested:
            self._save_figures(o)
        self.processed += 1
        self.empty_streak = 0 if o.result.depth.any() else self.empty_streak + 1
        self.last_ms = sum(o.result.timings_ms.values()) + (time.perf_counter() - t0) * 1000.0

    def full_depth_wanted(self) -> bool:
        """Whether ``depth/image_clean`` is published: always here (it is this node's output);
        the camera pipeline sends it only while someone subscribes."""
        return True

    def _clean_plate_done(self, message: str) -> None:
        self.get_logger().info(message)
        path = self.node_cfg.background_file
        if path:
            try:
                self.session.background.save(path)
            except OSError as e:
                self.diagnostics.report('error', f'{self.camera}: could not save the clean plate: {e}')

    def _save_figures(self, o: Outcome) -> None:
        from volcap_core.figures import write_png

        from .figures import depth_panels, mask_panels
        self.figures_requested = False
        out = Path(self.node_cfg.figure_dir)
        try:
            if o.result.mask is not None:
                write_png(out / f'{self.camera}_mask.png', mask_panels(o.color, o.result.mask))
            write_png(out / f'{self.camera}_depth.png', depth_panels(o.depth, o.result))
        except OSError as e:
            self.diagnostics.report('error', f'{self.camera}: could not write figures: {e}')

    def _report(self) -> None:
        if self.skipped and self.processed == 0:
            return   # the last warning or error stays the published status
        level, message, values = self.status()
        self.diagnostics.report(level, message, **values)

    def status(self) -> tuple[str, str, dict]:
        """(level, message, values) of the once-a-second diagnostics."""
        session = self.session
        values = dict(processed=self.processed, skipped=self.skipped, dropped=self.skipped,
                      last_ms=round(self.last_ms, 1), work_s=round(self.work_s, 3),
                      clean_plate_frames=session.background.frames, mask=session.cfg.mask_mode,
                      **self.admission.counts())
        if self.empty_streak >= EMPTY_WARN_FRAMES:
            # the count is in the values: the message (and its one log line) stays while it lasts
            return 'warn', (f'{self.camera}: cleaned frames have no depth left (empty stage, or the range gate / '
                            'clean plate removes everything)'), dict(values, empty_frames=self.empty_streak)
        if session.missing_clean_plate:
            service = f'{self.get_fully_qualified_name()}/capture_clean_plate'
            return 'warn', (f'{self.camera}: no clean plate learnt: depth is published unmasked; empty the stage and '
                            f'call {service} (std_srvs/srv/Trigger)'), dict(values, mask='none (no clean plate)')
        if session.cfg.mask_mode == 'clean_plate' and not session.has_clean_plate:
            values['mask'] = 'none (no clean plate yet)'
        return 'ok', f'{self.camera}: {self.processed} frames cleaned', values


def main(args=None):
    node_main(DepthFilter, args)


if __name__ == '__main__':
    main()
