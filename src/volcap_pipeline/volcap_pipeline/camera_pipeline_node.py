"""camera_pipeline: one camera's whole job in one process, beside its driver.

    ros2 run volcap_pipeline camera_pipeline --ros-args -r __ns:=/cam0

The per-camera work of a rig (``volcap run``, ``volcap live`` and the launch file start one per
camera namespace), driving ``volcap_pipeline.camera.CameraPipeline``: the camera's colour and
depth are received once, and each admitted frame is registered, masked against the clean plate,
cleared of flying pixels and colour-corrected in this process. It takes the inputs, parameters
and services of ``depth_filter`` (its node class is extended here) and the colour parameters of
``color_corrector`` (``passthrough``, ``neural_models``; the model comes from the latched
``/volcap/calibration``).

Publishes, relative to the namespace, the compact wire the fusion host takes
(``volcap_core.wire``; ``wire:=false`` turns it off): the cleaned depth's foreground region as
``compressedDepth`` PNG on ``wire/depth/image/compressedDepth`` and the corrected colour of that
region as JPEG on ``wire/color/image/compressed``, each with its camera_info (``roi`` /
``binning``) on ``wire/depth/camera_info`` and ``wire/color/camera_info``. Only while someone
subscribes (or with ``wire:=false``): ``depth/image_clean``
(16UC1 mm on the colour grid at the output size) with its camera_info, ``color/image_corrected`` (rgb8, the colour image's size and
header) with ``color/image_corrected/camera_info`` for every cleaned frame while someone
subscribes to it, and ``points`` (while subscribed). The two separate nodes stay available for
a rig that wants them apart; their topics are the same, so fusion takes either.
"""
from __future__ import annotations

from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String

from volcap_color.config import ColorCorrectionConfig
from volcap_color.corrector import CameraCorrection
from volcap_core import qos, topics, wire
from volcap_core.cdr import image_to_cdr
from volcap_core.conversions import camera_model_to_info
from volcap_core.diagnostics import LEVELS
from volcap_core.ros import declare_config, node_main
from volcap_filter.depth_filter_node import DepthFilter, decode
from volcap_filter.mask import BackgroundModel
from volcap_filter.pipeline import DepthFilterConfig
from volcap_filter.session import CleanPlateSession, Outcome

from .camera import CameraPipeline, WireConfig


class CameraPipelineNode(DepthFilter):
    role = 'camera pipeline'

    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        self.pipeline: CameraPipeline | None = None
        super().__init__('camera_pipeline', **node_options)
        self.color_cfg = declare_config(self, ColorCorrectionConfig, self._on_color_config)
        correction = CameraCorrection(self.camera, self.color_cfg.passthrough)
        if self.color_cfg.neural_models:
            message = correction.load_neural(self.color_cfg.neural_models)
            if correction.neural:
                self.get_logger().info(message)
            else:
                self.diagnostics.report('error', message)
        self.pipeline.correction = correction
        self.pub_color = self.create_publisher(Image, topics.COLOR_CORRECTED, qos.DRIVER)
        self.pub_color_info = self.create_publisher(CameraInfo, topics.COLOR_CORRECTED_INFO, qos.DRIVER)
        self.wire_cfg = declare_config(self, WireConfig, self._on_wire_config)
        self.wire_bytes = 0
        self.wire_frames = 0
        self.wire_ms: dict[str, float] = {}
        if self.wire_cfg.wire:
            self.pub_wire = {name: self.create_publisher(kind, topic, qos.DRIVER) for name, kind, topic in (
                ('depth_info', CameraInfo, wire.WIRE_DEPTH_INFO), ('color_info', CameraInfo, wire.WIRE_COLOR_INFO),
                ('depth', CompressedImage, wire.WIRE_DEPTH), ('color', CompressedImage, wire.WIRE_COLOR))}
        self.create_subscription(String, '/' + topics.CALIBRATION, self._on_calibration, qos.LATCHED)

    def make_session(self, cfg: DepthFilterConfig, background: BackgroundModel | None) -> CleanPlateSession:
        self.pipeline = CameraPipeline(self.camera, cfg, output_size=(self.node_cfg.output_width,
                                                                      self.node_cfg.output_height),
                                       output_scale=self.node_cfg.output_scale, decode=decode,
                                       max_held=self.node_cfg.max_held_frames, background=background)
        return self.pipeline.session

    def _on_wire_config(self, cfg: WireConfig) -> None:
        self.wire_cfg = cfg

    def full_depth_wanted(self) -> bool:
        return not self.wire_cfg.wire or self.pub_depth.get_subscription_count() > 0

    def _on_color_config(self, cfg: ColorCorrectionConfig) -> None:
        self.color_cfg = cfg
        self.pipeline.correction.passthrough = cfg.passthrough

    def _on_calibration(self, msg: String) -> None:
        used, message = self.pipeline.correction.set_calibration(msg.data)
        if used or self.pipeline.correction.neural:
            self.get_logger().info(message)
        else:
            self.diagnostics.report('warn', message)

    def _publish(self, o: Outcome) -> None:
        super()._publish(o)
        if self.wire_cfg.wire:
            self._publish_wire(o)
        if not self.pub_color.get_subscription_count():
            return       # nobody takes the full-size colour: it is not corrected either
        color = self.pipeline.correct(o.color, keep=False)     # serialised at once: no copy
        if color is None:
            return       # no colour model and passthrough off
        stamp, frame = o.pair.stamp_ns, o.pair.frame_id
        # camera_info first, so a subscriber rarely sees the image before it
        self.pub_color_info.publish(camera_model_to_info(self.session.models['color'], stamp, frame))
        self.pub_color.publish(image_to_cdr(color, 'rgb8', stamp, frame))

    def _publish_wire(self, o: Outcome) -> None:
        stamp, frame = o.pair.stamp_ns, o.pair.frame_id
        out = self.pipeline.wire(o.result.depth, o.cleaner.output_model, o.color, self.session.models['color'],
                                 stamp, frame, self.wire_cfg)
        if out is None:
            return       # no colour model and passthrough off
        pub = self.pub_wire
        pub['depth_info'].publish(out.depth_info)       # camera_info first, as for the full-size images
        pub['color_info'].publish(out.color_info)
        pub['depth'].publish(out.depth)
        pub['color'].publish(out.color)
        self.wire_bytes += out.bytes
        self.wire_frames += 1
        self.wire_ms = {k: round(v, 2) for k, v in out.timings_ms.items()}

    def status(self) -> tuple[str, str, dict]:
        level, message, values = super().status()
        if self.wire_frames:
            values = {**values, 'wire_frames': self.wire_frames,
                      'wire_kbytes_per_frame': round(self.wire_bytes / self.wire_frames / 1000, 1),
                      **{f'wire_{k}': v for k, v in self.wire_ms.items()}}
        color_level, color_message, color_values = self.pipeline.correction.status()
        if LEVELS[color_level] > LEVELS[level]:
            level = color_level
        if color_level != 'ok' or level == 'ok':
            message = f'{message}; {color_message.removeprefix(self.camera + ": ")}'
        return level, message, {**values, **{f'color_{k}': v for k, v in color_values.items()}}


def main(args=None):
    node_main(CameraPipelineNode, args)


if __name__ == '__main__':
    main()
