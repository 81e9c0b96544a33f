"""color_corrector: one camera's colour model from the calibration, applied at full rate.

    ros2 run volcap_color color_corrector --ros-args -r __ns:=/cam0

Subscribes ``color/image_raw`` (rgb8, bgr8, rgba8 or bgra8; or JPEG ``color/image_raw/compressed``
with ``color_transport:=compressed``), ``color/camera_info`` and the latched
``/volcap/calibration``; publishes ``color/image_corrected`` (rgb8, same size, same header) and,
with each image, its ``color/image_corrected/camera_info`` (so a consumer needs only this
camera's relative topics). In a live graph only the frame sets admitted on
``/volcap/admission`` are corrected (``volcap_core.admission``). A new
calibration is picked up as it is published, without a restart. Until a calibration with a
colour model for this camera arrives, images are passed through unchanged (``passthrough``,
default) or dropped; either way ``/volcap/diagnostics`` says so.

With ``neural_models`` (a ``volcap harmonise`` output folder) the camera's exported neural
mapping (``<camera>.lut.npz``, a region LUT) is applied instead, and calibrations no longer
change the model; a folder without this camera's LUT is reported and the calibration's model
is used.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from volcap_core import qos, topics
from volcap_core.cdr import image_to_cdr
from volcap_core.conversions import MessageConversionError, color_message_to_rgb, stamp_to_ns
from volcap_core.ros import AdmissionListener, Diagnostics, color_message_type, declare_config, node_main, subscribe_color
from volcap_core.settings import color_transport_setting, setting

from .config import ColorCorrectionConfig
from .corrector import CameraCorrection


@dataclass
class ColorCorrectorConfig(ColorCorrectionConfig):
    camera: str = setting('', 'camera name in the calibration (empty: the last part of the namespace)',
                          read_only=True)
    reliable: bool = setting(False, 'subscribe reliably with a deeper queue (offline replay: lose no frame)',
                             read_only=True)
    color_transport: str = color_transport_setting()


class ColorCorrector(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('color_corrector', **node_options)
        self.cfg = declare_config(self, ColorCorrectorConfig, self._on_config)
        camera = self.cfg.camera or self.get_namespace().strip('/').split('/')[-1] or 'cam0'
        self.diagnostics = Diagnostics(self, f'colour corrector {camera}')
        self.correction = CameraCorrection(camera, self.cfg.passthrough)
        if self.cfg.neural_models:
            message = self.correction.load_neural(self.cfg.neural_models)
            if self.correction.neural:
                self.get_logger().info(message)
            else:
                self.diagnostics.report('error', message)
        self.info: CameraInfo | None = None
        self.work_s = 0.0          # process CPU time spent on admitted frames
        self.pub = self.create_publisher(Image, topics.COLOR_CORRECTED, qos.DRIVER)
        self.pub_info = self.create_publisher(CameraInfo, topics.COLOR_CORRECTED_INFO, qos.DRIVER)
        self.create_subscription(String, '/' + topics.CALIBRATION, self._on_calibration, qos.LATCHED)
        self.admission = AdmissionListener(self, self.diagnostics)
        inputs = qos.EVERY_FRAME if self.cfg.reliable else qos.CAMERA
        self.create_subscription(CameraInfo, topics.COLOR_INFO, self._on_info, inputs)
        # Serialised: a frame set that is not admitted is dropped before it is deserialised.
        self.color_type = color_message_type(self.cfg.color_transport)
        subscribe_color(self, self.cfg.color_transport, self._on_image, inputs, raw=True)
        self.create_timer(1.0, self._report)
        self.get_logger().info(f'color_corrector started for {camera}')

    def _on_config(self, cfg: ColorCorrectorConfig) -> None:
        self.cfg = cfg
        self.correction.passthrough = cfg.passthrough

    def _on_calibration(self, msg: String) -> None:
        used, message = self.correction.set_calibration(msg.data)
        if used or self.correction.neural:
            self.get_logger().info(message)
        else:
            self.diagnostics.report('warn', message)

    def _on_info(self, msg: CameraInfo) -> None:
        self.info = msg

    def _on_image(self, data: bytes) -> None:
        started = time.process_time()
        try:
            msg = self.admission.admitted_message('color', data, self.color_type)
            if msg is None:
                return
            stamp = stamp_to_ns(msg.header.stamp)
            out = self.correction.apply(color_message_to_rgb(msg))
        except (MessageConversionError, ValueError) as e:
            self.correction.skipped += 1
            self.diagnostics.report('error', f'{self.correction.camera}: image skipped: {e}')
            return
        if out is None:
            return
        if self.info is not None:
            # camera_info first, so a subscriber rarely sees the image before it
            self.info.header = msg.header
            self.pub_info.publish(self.info)
        self.pub.publish(image_to_cdr(out, 'rgb8', stamp, msg.header.frame_id))
        self.work_s += time.process_time() - started

    def _report(self) -> None:
        level, message, values = self.correction.status()
        self.diagnostics.report(level, message, dropped=self.correction.skipped, work_s=round(self.work_s, 3),
                                **values, **self.admission.counts())


def main(args=None):
    node_main(ColorCorrector, args)


if __name__ == '__main__':
    main()
