"""color_corrector: one camera's colour model from the calibration, applied at full rate.

    ros2 run volcap_color color_corrector --ros-args -r __ns:=/cam0

Subscribes ``color/image_raw`` (rgb8, bgr8, rgba8 or bgra8) and the latched
``/volcap/calibration``; publishes ``color/image_corrected`` (rgb8, same size, same header). A new
calibration is picked up as it is published, without a restart. Until a calibration with a
colour model for this camera arrives, images are passed through unchanged (``passthrough``,
default) or dropped; either way ``/volcap/diagnostics`` says so.

With ``neural_models`` (a ``volcap harmonise`` output folder) the camera's exported neural
mapping (``<camera>.lut.npz``, a region LUT) is applied instead, and calibrations no longer
change the model; a folder without this camera's LUT is reported and the calibration's model
is used.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

from volcap_core import qos, topics
from volcap_core.calibration import Calibration
from volcap_core.color import ColourModel
from volcap_core.conversions import MessageConversionError, color_to_rgb, numpy_to_image, stamp_to_ns
from volcap_core.ros import Diagnostics, declare_config, run_node
from volcap_core.settings import setting

from .apply import ImageCorrector, RegionLut


@dataclass
class ColorCorrectorConfig:
    camera: str = setting('', 'camera name in the calibration (empty: the last part of the namespace)',
                          read_only=True)
    passthrough: bool = setting(True, 'publish uncorrected images while there is no colour model (false: drop '
                                'them)')
    neural_models: str = setting('', 'volcap harmonise output folder: apply its neural mapping for this camera '
                                 'instead of the calibration\'s colour model ("" = off)', read_only=True)
    reliable: bool = setting(False, 'subscribe reliably (offline replay: lose no frame)', read_only=True)


class ColorCorrector(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('color_corrector', **node_options)
        self.cfg = declare_config(self, ColorCorrectorConfig, self._on_config)
        self.camera = self.cfg.camera or self.get_namespace().strip('/').split('/')[-1] or 'cam0'
        self.diagnostics = Diagnostics(self, f'colour corrector {self.camera}')
        self.corrector: ImageCorrector | None = None
        self._buffer: np.ndarray | None = None
        self.model_text = 'none'
        self.neural = False
        self.neural_problem = ''
        if self.cfg.neural_models:
            self._load_neural(Path(self.cfg.neural_models) / f'{self.camera}.lut.npz')
        self.corrected = self.passed = self.skipped = 0
        self.ms: list[float] = []
        self.pub = self.create_publisher(Image, topics.COLOR_CORRECTED, qos.DRIVER)
        self.create_subscription(String, '/' + topics.CALIBRATION, self._on_calibration, qos.LATCHED)
        inputs = qos.EVERY_FRAME if self.cfg.reliable else qos.SENSOR
        self.create_subscription(Image, topics.COLOR_IMAGE, self._on_image, inputs)
        self.create_timer(1.0, self._report)
        self.get_logger().info(f'color_corrector started for {self.camera}')

    def _on_config(self, cfg: ColorCorrectorConfig) -> None:
        self.cfg = cfg

    def _load_neural(self, path: Path) -> None:
        try:
            lut = RegionLut.load(path)
        except ValueError as e:
            self.neural_problem = f'neural mapping not used, falling back to the calibration: {e}'
            self.diagnostics.report('error', self.neural_problem)
            return
        self.corrector, self.neural = ImageCorrector(lut), True
        n, (nx, ny) = lut.table.shape[0], lut.grid
        self.model_text = f'neural (region LUT {n}^3 x {nx}x{ny}, {path.parent})'
        self.get_logger().info(f'{self.camera}: colour model {self.model_text}')

    def _on_calibration(self, msg: String) -> None:
        if self.neural:
            self.get_logger().info(f'{self.camera}: new calibration; keeping the neural mapping')
            return
        try:
            calibration = Calibration.from_yaml(msg.data)
            cam = calibration.cameras.get(self.camera)
            if cam is None:
                raise ValueError(f'the calibration has no camera {self.camera!r} '
                                 f'(it has {", ".join(calibration.cameras)})')
            if cam.colour is None:
                raise ValueError(f'the calibration has no colour model for {self.camera}')
            model = ColourModel.from_dict(cam.colour)
            corrector = ImageCorrector(model)
        except (ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('warn', f'calibration not used, keeping {self.model_text}: {e}')
            return
        self.corrector = corrector
        self.model_text = f'{model.method}{" + harmonisation" if model.post is not None else ""} ({corrector.kind})'
        self.get_logger().info(f'{self.camera}: colour model {self.model_text}')

    def _on_image(self, msg: Image) -> None:
        try:
            rgb = color_to_rgb(msg)
        except (MessageConversionError, ValueError) as e:
            self.skipped += 1
            self.diagnostics.report('error', f'{self.camera}: image skipped: {e}')
            return
        if self.corrector is None:
            if not self.cfg.passthrough:
                return
            out = rgb
            self.passed += 1
        else:
            t0 = time.perf_counter()
            out = self._buffer = self.corrector(rgb, self._buffer)   # published as a copy, so reusable
            self.ms.append((time.perf_counter() - t0) * 1e3)
            self.corrected += 1
        self.pub.publish(numpy_to_image(out, 'rgb8', stamp_to_ns(msg.header.stamp), msg.header.frame_id))

    def _report(self) -> None:
        if self.corrector is None:
            self.diagnostics.report('warn', f'{self.camera}: no colour model yet; images are '
                                            f'{"passed through" if self.cfg.passthrough else "dropped"}'
                                            + (f'; {self.neural_problem}' if self.neural_problem else ''),
                                    passed=self.passed, skipped=self.skipped)
            return
        ms = float(np.median(self.ms[-100:])) if self.ms else 0.0
        problem = f'; {self.neural_problem}' if self.neural_problem else ''
        self.diagnostics.report('warn' if problem else 'ok',
                                f'{self.camera}: {self.corrected} frames corrected with {self.model_text}{problem}',
                                corrected=self.corrected, passed=self.passed, skipped=self.skipped,
                                median_ms=round(ms, 2))
        self.ms = self.ms[-100:]


def main(args=None):
    sys.exit(run_node(ColorCorrector, args))


if __name__ == '__main__':
    main()
