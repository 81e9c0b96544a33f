"""depth_filter: one camera's depth registered to colour and cleaned.

    ros2 run volcap_filter depth_filter --ros-args -r __ns:=/cam0

Subscribes (sensor-data QoS, relative names) ``color/image_raw``, ``color/camera_info``,
``depth/image_raw``, ``depth/camera_info``, plus the rig on ``/volcap/rig`` (factory
depth-to-colour extrinsic) and the session phase on ``/volcap/phase``. Publishes
``depth/image_clean`` (16UC1 mm, colour geometry at the output size) with its camera_info and
``points`` (xyz + rgb, colour optical frame). The clean plate is learnt during the
``clean_plate`` phase, or on the ``~/capture_clean_plate`` service. Every threshold is a
parameter and can be changed while running.
"""
from __future__ import annotations

import sys
import time
from collections import deque
from dataclasses import fields
from pathlib import Path

import numpy as np
import yaml
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from volcap_core import qos, topics
from volcap_core.camera import depth_to_millimetres
from volcap_core.conversions import (MessageConversionError, camera_info_to_model, camera_model_to_info,
                                     color_to_rgb, depth_to_metres, numpy_to_image, points_to_pointcloud2,
                                     stamp_to_ns)
from volcap_core.rig import Rig
from volcap_core.ros import Diagnostics, declare, run_node
from volcap_core.sync import FrameSetSynchronizer

from .flying import FlyingPixelConfig
from .mask import BackgroundModel, MaskConfig
from .pipeline import FLYING_METHODS, MASK_MODES, DepthCleaner, DepthFilterConfig
from .registration import DepthRegistration

# name: (default, description, low, high)
FLYING_PARAMS = {
    'noise_base': (0.0008, 'ToF depth noise sigma at 0 m (m); sigma(z) = base + quad z^2', 0.0, 0.05),
    'noise_quad': (0.0010, 'ToF depth noise growth (m per m^2)', 0.0, 0.05),
    'noise_sigmas': (3.0, 'second-difference tolerance on smooth surfaces, in sigmas', 0.5, 20.0),
    'edge_sigmas': (1.0, 'one-sided tolerance for pixels at a depth step, in sigmas', 0.1, 20.0),
    'curvature': (0.004, 'second-difference allowance per metre of depth for curved surfaces', 0.0, 0.1),
    'max_incidence_deg': (75.0, 'steeper surfaces than this incidence angle count as depth steps', 30.0, 89.0),
    'min_axes': (3, 'axes (of 4) along which a pixel must continue a surface', 1, 4),
    'min_component_px': (30, 'connected pieces of depth smaller than this are removed (0 = off)', 0, 10000),
}
MASK_PARAMS = {
    'noise_floor': (3.0, 'colour sigma floor of the clean plate (8-bit levels)', 0.5, 50.0),
    'chroma_sigmas': (6.0, 'chromaticity distortion beyond which a pixel is foreground (sigmas)', 0.5, 100.0),
    'min_difference': (12.0, 'smallest colour difference to the clean plate that can be foreground', 0.0, 255.0),
    'shadow_min': (0.55, 'brightness ratio down to which a darker pixel may be shadow', 0.05, 1.0),
    'highlight_max': (1.25, 'brightness ratio above which a pixel is foreground', 1.0, 5.0),
    'depth_margin': (0.05, 'metres in front of the clean-plate depth that count as foreground', 0.0, 2.0),
    'min_area_frac': (0.0005, 'foreground blobs smaller than this fraction of the image are dropped', 0.0, 0.5),
    'min_range': (0.1, 'range gate near limit (m)', 0.0, 20.0),
    'max_range': (2.5, 'range gate far limit (m)', 0.05, 20.0),
}
PIPELINE_PARAMS = {
    'range_gate': (True, 'drop depth outside [min_range, max_range]', None, None),
    'chroma_threshold': (40.0, 'chroma-key distance (Cr, Cb) beyond which a pixel is foreground', 1.0, 255.0),
    'boundary_px': (2, 'mask boundary band (output px) where depth behind the inside is dropped', 0, 20),
    'boundary_tolerance': (0.03, 'how far behind the nearby inside band depth may lie (m)', 0.0, 1.0),
    'temporal_alpha': (0.0, 'temporal EMA weight of a new frame on stable pixels (0 = off)', 0.0, 1.0),
    'sor_neighbors': (0, 'statistical outlier removal neighbours on the cloud (0 = off)', 0, 100),
    'sor_std_ratio': (2.5, 'statistical outlier removal threshold (std ratios)', 0.1, 10.0),
}


class DepthFilter(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('depth_filter', **node_options)
        ns_camera = self.get_namespace().strip('/').split('/')[-1]
        self.camera = declare(self, 'camera', ns_camera or 'cam0', 'camera name in the rig description',
                              read_only=True)
        self.output_size = (declare(self, 'output_width', 0, 'output width (0 = half the colour width)', 0, 8192,
                                    read_only=True),
                            declare(self, 'output_height', 0, 'output height (0 = half the colour height)', 0, 8192,
                                    read_only=True))
        declare(self, 'flying_method', 'volcap', f'flying-pixel filter: {"|".join(FLYING_METHODS)}')
        declare(self, 'mask_mode', 'clean_plate', f'foreground mask: {"|".join(MASK_MODES)}')
        declare(self, 'chroma_key', [0, 177, 64], 'chroma-key colour (R, G, B) for mask_mode chroma')
        for table in (FLYING_PARAMS, MASK_PARAMS, PIPELINE_PARAMS):
            for name, (default, text, low, high) in table.items():
                declare(self, name, default, text, low, high)
        self.clean_plate_frames = declare(self, 'clean_plate_frames', 10,
                                          'frames gathered by ~/capture_clean_plate', 1, 1000)
        self.background_file = declare(self, 'background_file', '',
                                       'clean plate to load at start and save after learning (npz)', read_only=True)
        self.publish_points = declare(self, 'publish_points', True, 'publish the coloured point cloud')
        tolerance_ms = declare(self, 'sync_tolerance_ms', 5.0, 'colour/depth stamp tolerance', 0.0, 100.0,
                               read_only=True)
        self.figure_dir = declare(self, 'figure_dir', '/tmp/volcap_figures', 'where ~/save_figures writes PNGs')
        self.cfg = self._config_from(self._parameter_values())
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.diagnostics = Diagnostics(self, f'depth filter {self.camera}')
        self.sync = FrameSetSynchronizer([self.camera], ('color', 'depth'), tolerance_ns=int(tolerance_ms * 1e6),
                                         timeout_ns=500_000_000, max_pending=4)
        self.infos: dict[str, CameraInfo] = {}
        self.rig: Rig | None = None
        self.cleaner: DepthCleaner | None = None
        self.background = BackgroundModel()
        if self.background_file and Path(self.background_file).exists():
            self.background = BackgroundModel.load(self.background_file)
            self.get_logger().info(f'loaded a {self.background.frames}-frame clean plate from {self.background_file}')
        self.phase = None
        self.learn_remaining = 0
        self.figures_requested = False
        self.processed = self.skipped = 0
        self.last_ms = 0.0
        # Image pairs that came before their camera_info or the rig (other topics, so no ordering
        # across them is guaranteed), each with the phase it arrived in; a late clean-plate frame
        # must still be learnt, not lost.
        self.held: deque[tuple[Image, Image, str | None]] = deque()
        self.max_held = declare(self, 'max_held_frames', 4, 'image pairs kept while their camera_info or the '
                                'rig is still to come', 0, 100, read_only=True)

        # Created before the image subscriptions: the executor serves ready subscriptions in
        # creation order, so a phase change or camera_info sent with a frame is seen before it.
        self.create_subscription(String, '/' + topics.RIG, self._on_rig, qos.LATCHED)
        self.create_subscription(String, '/' + topics.PHASE, self._on_phase, qos.LATCHED)
        inputs = qos.EVERY_FRAME if declare(self, 'reliable', False, 'subscribe reliably (offline replay: lose no '
                                            'frame)', read_only=True) else qos.SENSOR
        self.create_subscription(CameraInfo, topics.COLOR_INFO, lambda m: self._on_info(m, 'color'), inputs)
        self.create_subscription(CameraInfo, topics.DEPTH_INFO, lambda m: self._on_info(m, 'depth'), inputs)
        self.create_subscription(Image, topics.COLOR_IMAGE, lambda m: self._on_image(m, 'color'), inputs)
        self.create_subscription(Image, topics.DEPTH_IMAGE, lambda m: self._on_image(m, 'depth'), inputs)
        self.pub_depth = self.create_publisher(Image, topics.DEPTH_CLEAN, qos.DRIVER)
        self.pub_info = self.create_publisher(CameraInfo, topics.DEPTH_CLEAN_INFO, qos.DRIVER)
        self.pub_points = self.create_publisher(PointCloud2, topics.POINTS, qos.DRIVER)
        self.create_service(Trigger, '~/capture_clean_plate', self._on_capture_clean_plate)
        self.create_service(Trigger, '~/save_figures', self._on_save_figures)
        self.create_timer(1.0, self._report)
        self.get_logger().info(f'depth_filter started for {self.camera}')

    # parameters ---------------------------------------------------------------------------
    def _parameter_values(self) -> dict:
        names = ['flying_method', 'mask_mode', 'chroma_key', *FLYING_PARAMS, *MASK_PARAMS, *PIPELINE_PARAMS]
        return {n: self.get_parameter(n).value for n in names}

    @staticmethod
    def _config_from(values: dict) -> DepthFilterConfig:
        key = tuple(int(v) for v in values['chroma_key'])
        if len(key) != 3 or not all(0 <= v <= 255 for v in key):
            raise ValueError(f'chroma_key must be three values 0-255, got {values["chroma_key"]}')
        cfg = DepthFilterConfig(
            flying_method=values['flying_method'], mask_mode=values['mask_mode'], chroma_key=key,
            flying=FlyingPixelConfig(**{f.name: values[f.name] for f in fields(FlyingPixelConfig)}),
            mask=MaskConfig(**{f.name: values[f.name] for f in fields(MaskConfig)}),
            **{n: values[n] for n in PIPELINE_PARAMS})
        cfg.validate()
        return cfg

    def _on_set_parameters(self, params) -> SetParametersResult:
        values = self._parameter_values()
        values.update({p.name: p.value for p in params if p.name in values})
        try:
            cfg = self._config_from(values)
        except (ValueError, TypeError) as e:
            return SetParametersResult(successful=False, reason=str(e))
        for p in params:
            if p.name == 'publish_points':
                self.publish_points = bool(p.value)
            elif p.name == 'clean_plate_frames':
                self.clean_plate_frames = int(p.value)
            elif p.name == 'figure_dir':
                self.figure_dir = str(p.value)
        self.cfg = cfg
        if self.cleaner is not None:
            self.cleaner.cfg = cfg
        return SetParametersResult(successful=True)

    # inputs -------------------------------------------------------------------------------
    def _on_rig(self, msg: String) -> None:
        try:
            rig = Rig.from_yaml(msg.data)
            rig.camera(self.camera)
        except (ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('error', f'unusable rig description: {e}')
            return
        self.rig = rig
        self.cleaner = None   # rebuilt with the new extrinsic on the next frame
        self._process_held()

    def _on_phase(self, msg: String) -> None:
        try:
            phase = (yaml.safe_load(msg.data) or {}).get('phase')
        except (yaml.YAMLError, AttributeError):
            return
        if phase == topics.CLEAN_PLATE and self.phase != phase:
            self.background = BackgroundModel()
            if self.cleaner is not None:
                self.cleaner.background = self.background
        elif self.phase == topics.CLEAN_PLATE and phase != topics.CLEAN_PLATE and not self._plate_frames_held():
            self._clean_plate_done()   # else once the held clean-plate frames are learnt
        self.phase = phase

    def _on_capture_clean_plate(self, request, response):
        self.background = BackgroundModel()
        if self.cleaner is not None:
            self.cleaner.background = self.background
        self.learn_remaining = self.clean_plate_frames
        response.success = True
        response.message = f'learning the clean plate from the next {self.learn_remaining} frames; keep the stage empty'
        return response

    def _on_save_figures(self, request, response):
        self.figures_requested = True
        response.success = True
        response.message = f'the next processed frame goes to {self.figure_dir}'
        return response

    def _on_info(self, msg: CameraInfo, stream: str) -> None:
        self.infos[stream] = msg
        self._process_held()

    def _on_image(self, msg: Image, stream: str) -> None:
        for fs in self.sync.add(self.camera, stamp_to_ns(msg.header.stamp), msg, stream=stream,
                                now_ns=time.monotonic_ns()):
            if fs.complete:
                self.held.append((fs.get(self.camera, 'color'), fs.get(self.camera, 'depth'), self.phase))
                self._process_held()
            else:
                self.skipped += 1
                self.diagnostics.report('warn', f'{self.camera}: no matching {fs.missing[0][1]} image for stamp '
                                                f'{fs.stamp_ns}; frame skipped')

    # processing ---------------------------------------------------------------------------
    def _waiting_for(self, color_msg: Image, depth_msg: Image) -> str | None:
        """What a frame still needs before it can be cleaned, or None."""
        if 'color' not in self.infos or 'depth' not in self.infos:
            return 'no camera_info yet'
        if depth_msg.header.frame_id != color_msg.header.frame_id and self.rig is None:
            return f'waiting for the rig on /{topics.RIG} (depth-to-colour extrinsic)'
        return None

    def _plate_frames_held(self) -> bool:
        return any(phase == topics.CLEAN_PLATE for _, _, phase in self.held)

    def _late_plate_frame_done(self, phase: str | None) -> None:
        """A held clean-plate frame was learnt or dropped after its phase ended: the plate is
        complete once no other is held."""
        if phase == topics.CLEAN_PLATE and self.phase != topics.CLEAN_PLATE and not self._plate_frames_held():
            self._clean_plate_done()

    def _process_held(self) -> None:
        while self.held:
            color_msg, depth_msg, phase = self.held[0]
            waiting = self._waiting_for(color_msg, depth_msg)
            if waiting is None:
                self.held.popleft()
                self._process(color_msg, depth_msg, phase)
            elif len(self.held) > self.max_held:
                self.held.popleft()
                self.skipped += 1
                self.diagnostics.report('warn', f'{self.camera}: {waiting}; frame skipped')
                self._late_plate_frame_done(phase)
            else:
                self.diagnostics.report('warn', f'{self.camera}: {waiting}; {len(self.held)} frame(s) held')
                return

    def _process(self, color_msg: Image, depth_msg: Image, phase: str | None) -> None:
        t0 = time.perf_counter()
        try:
            cleaner = self._cleaner(color_msg, depth_msg)
            color = color_to_rgb(color_msg)
            depth = depth_to_metres(depth_msg)
            if phase == topics.CLEAN_PLATE or self.learn_remaining > 0:
                cleaner.learn_background(color, depth)
                if self.learn_remaining > 0:
                    self.learn_remaining -= 1
                    if self.learn_remaining == 0:
                        self._clean_plate_done()
                else:
                    self._late_plate_frame_done(phase)
                return
            result = cleaner.process(color, depth)
        except (MessageConversionError, ValueError) as e:
            self.skipped += 1
            self.diagnostics.report('error', f'{self.camera}: frame skipped: {e}')
            return
        stamp = stamp_to_ns(color_msg.header.stamp)
        frame = color_msg.header.frame_id
        mm = depth_to_millimetres(result.depth)
        # camera_info first, so a subscriber rarely sees the image before it
        self.pub_info.publish(camera_model_to_info(cleaner.output_model, stamp, frame))
        self.pub_depth.publish(numpy_to_image(mm, '16UC1', stamp, frame))
        if self.publish_points:
            xyz, rgb = cleaner.points(result)
            self.pub_points.publish(points_to_pointcloud2(xyz, rgb, stamp, frame))
        if self.figures_requested:
            self._save_figures(color, depth, result)
        self.processed += 1
        self.last_ms = (time.perf_counter() - t0) * 1000.0

    def _cleaner(self, color_msg: Image, depth_msg: Image) -> DepthCleaner:
        registered = depth_msg.header.frame_id == color_msg.header.frame_id
        color_model = camera_info_to_model(self.infos['color'])
        depth_model = camera_info_to_model(self.infos['depth'])
        c = self.cleaner
        if c is None or c.registration.color_model != color_model or c.registration.depth_model != depth_model \
                or c.registration.registered != registered:
            T = np.eye(4) if registered else self.rig.camera(self.camera).T_color_depth
            w, h = self.output_size
            size = (w, h) if w and h else None
            c = DepthCleaner(DepthRegistration(depth_model, color_model, T, size, registered=registered), self.cfg)
            c.background = self.background
            self.cleaner = c
        return c

    def _clean_plate_done(self) -> None:
        frames = self.background.frames
        if frames == 0:
            self.diagnostics.report('warn', f'{self.camera}: the clean-plate phase ended with no frame learnt')
            return
        self.get_logger().info(f'{self.camera}: clean plate learnt from {frames} frames')
        if self.background_file:
            try:
                self.background.save(self.background_file)
            except OSError as e:
                self.diagnostics.report('error', f'{self.camera}: could not save the clean plate: {e}')

    def _save_figures(self, color, depth, result) -> None:
        from .figures import depth_panels, mask_panels, write_png
        self.figures_requested = False
        out = Path(self.figure_dir)
        try:
            if result.mask is not None:
                write_png(out / f'{self.camera}_mask.png', mask_panels(color, result.mask))
            write_png(out / f'{self.camera}_depth.png', depth_panels(depth, result))
        except OSError as e:
            self.diagnostics.report('error', f'{self.camera}: could not write figures: {e}')

    def _report(self) -> None:
        if self.skipped and self.processed == 0:
            return   # the last warning or error stays the published status
        mask = 'no clean plate yet' if self.cfg.mask_mode == 'clean_plate' and not self.background.frames else \
            self.cfg.mask_mode
        self.diagnostics.report('ok', f'{self.camera}: {self.processed} frames cleaned', processed=self.processed,
                                skipped=self.skipped, last_ms=round(self.last_ms, 1), mask=mask,
                                clean_plate_frames=self.background.frames)


def main(args=None):
    sys.exit(run_node(DepthFilter, args))


if __name__ == '__main__':
    main()
