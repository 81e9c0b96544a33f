"""Small rclpy helpers shared by the nodes: start-up and shutdown, parameters declared from a
config dataclass (``volcap_core.settings``), diagnostics on ``volcap/diagnostics``, the colour
subscription of either transport, a ``/tf_static`` listener and the live admission rule."""
from __future__ import annotations

import ctypes
import logging
import os
import signal
import struct
import sys
import threading
import time
from typing import Callable, NoReturn

import rclpy
import rclpy.logging
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage

from . import qos, settings, topics, transport
from .admission import Admission, AdmissionRule
from .cdr import cdr_stamp_ns
from .conversions import tf_message_to_transforms
from .diagnostics import diagnostic_array, diagnostic_status
from .errors import BadInput
from .tf import StaticTransforms

RCLError = _rclpy.RCLError


def make_executor():
    """The executor a node process spins: rclpy's C++ EventsExecutor, which takes 1.2 ms of CPU per
    2.7 MB image where the SingleThreadedExecutor takes 2.0 ms (bench/live.py, receive side);
    ``VOLCAP_EXECUTOR=single`` selects the SingleThreadedExecutor (for comparisons)."""
    if os.environ.get('VOLCAP_EXECUTOR') == 'single':
        return SingleThreadedExecutor()
    return EventsExecutor()


def run_node(factory: Callable[[], Node], args=None) -> int:
    """Create the node and spin it until Ctrl-C / SIGTERM or until it shuts the context down
    itself; then clean up. Returns the node's ``exit_code`` (0 unless it set one).

    Once spinning, the signals only set a flag the spin loop reads: rclpy's own handler shuts the
    context down at once and raises KeyboardInterrupt a moment later, at the next Python
    instruction, which could land in the clean-up and kill the process by SIGINT (seen as exit
    -2). While the node is still starting, a signal interrupts the start."""
    transport.configure()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    context = rclpy.get_default_context()
    stopping, spinning = threading.Event(), threading.Event()

    def on_signal(*_):
        stopping.set()
        if not spinning.is_set():
            raise KeyboardInterrupt
    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = None
    executor = None
    try:
        node = factory()
        executor = make_executor()
        executor.add_node(node)
        spinning.set()
        # Short spins: the signal flag is read between them (not inside C++).
        while node.context.ok() and not stopping.is_set():
            executor.spin_once(timeout_sec=0.2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, OSError) as e:   # bad parameters or files: say so plainly, no traceback
        rclpy.logging.get_logger('volcap').fatal(f'cannot start: {e}')
        return 2
    finally:
        spinning.set()                   # from here on a signal only sets the flag
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        try:
            rclpy.try_shutdown()
        except RCLError:
            pass
        # rclpy's shutdown leaves the context, and with it the DDS participant, to the garbage
        # collector; destroyed here, the participant leaves before the process ends (node_main
        # skips the interpreter's teardown).
        context.destroy()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return getattr(node, 'exit_code', 0)  # 0 too when interrupted while starting


def node_main(factory: Callable[[], Node], args=None) -> NoReturn:
    """A node process's ``main``: ``run_node``, then end the process at once with its exit code.

    Once ``run_node`` returns, everything a node owns is finished: its files are closed by
    ``destroy_node``, rclpy is shut down, the DDS participant has left and the ROS log is
    flushed. What remains is the interpreter's teardown (module clean-up, its garbage
    collections over torch's, Open3D's and numba's objects, C++ static destructors), which
    kept a rig's ten node processes alive 2.8-3.5 s after SIGINT (median; once 20 s) on 2 cores,
    against 0.30-0.39 s (at most 0.66 s) without it (bench/shutdown.py), and past the graph
    session's grace on a loaded CI runner (a camera pipeline killed, exit -9). So Python's
    buffers and ``logging`` are flushed and the process exits with ``os._exit``, as a forked
    worker does. For a node process only: never call it
    in a process that goes on. A node that raises out of ``run_node`` (a bug) ends as Python
    does, with its traceback and exit code 1."""
    code = run_node(factory, args)
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):   # a closed pipe or stream: nothing left to say there
            pass
    # and C's stdio: rcutils writes the ROS log lines there (stdout, fully buffered into a pipe,
    # with RCUTILS_LOGGING_USE_STDOUT=1), and os._exit does not flush it
    ctypes.CDLL(None).fflush(None)
    os._exit(code)


def declare(node: Node, name: str, default, description: str, low=None, high=None, read_only=False):
    """Declare a parameter with its description and, for numbers, its allowed range."""
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if low is not None and high is not None and not isinstance(default, (bool, str)):
        first = default[0] if isinstance(default, list) and default else default
        if isinstance(first, int) and not isinstance(first, bool):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
        elif isinstance(first, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                                  step=0.0)]
    return node.declare_parameter(name, default, descriptor).value


def declare_config(node: Node, cls, on_change: Callable | None = None):
    """Declare every setting of the config class ``cls`` as a parameter (description, range,
    read-only) and return the config built from the parameters' values. With ``on_change``,
    settings that are not read-only can be changed while running: the new config is validated
    as a whole and handed to ``on_change(config)``; an invalid one is refused with the reason."""
    specs = settings.settings(cls)
    for s in specs:
        text = s.description + (f' ({"|".join(map(str, s.choices))})' if s.choices else '')
        declare(node, s.name, s.parameter_default, text, s.low, s.high, s.read_only)
    names = [s.name for s in specs]

    def current() -> dict:
        return {n: node.get_parameter(n).value for n in names}

    cfg = settings.build(cls, current())
    if on_change is not None:
        def changed(params) -> SetParametersResult:
            mine = {p.name: p.value for p in params if p.name in names}
            if not mine:
                return SetParametersResult(successful=True)
            try:
                new = settings.build(cls, {**current(), **mine})
            except (ValueError, TypeError) as e:
                return SetParametersResult(successful=False, reason=str(e))
            on_change(new)
            return SetParametersResult(successful=True)
        node.add_on_set_parameters_callback(changed)
    return cfg


class Diagnostics:
    """Publishes one node's status on ``volcap/diagnostics``: at once on every report, and the
    latest status again every ``period`` seconds (so late subscribers see it). Errors and
    warnings also go to the log, once until the message changes (a state reported every second
    would flood it)."""

    def __init__(self, node: Node, name: str, period: float = 1.0):
        self.node = node
        self.name = name
        # Absolute: nodes run inside camera namespaces, diagnostics are rig level.
        self.pub = node.create_publisher(DiagnosticArray, '/' + topics.DIAGNOSTICS, qos.EVENTS)
        self._last = None
        self._logged = None
        node.create_timer(period, self._republish)

    def report(self, level: str, message: str, **values) -> None:
        if (level, message) != self._logged:
            if level == 'error':
                self.node.get_logger().error(message)
            elif level == 'warn':
                self.node.get_logger().warning(message)
            self._logged = (level, message)
        self._last = diagnostic_status(f'{self.node.get_name()}: {self.name}', level, message, values)
        self._republish()

    def _republish(self) -> None:
        if self._last is not None and self.node.context.ok():
            self.pub.publish(diagnostic_array([self._last], time.time_ns()))


def color_message_type(transport: str):
    """The message type of a ``color_transport`` setting."""
    return CompressedImage if transport == 'compressed' else Image


def subscribe_color(node: Node, transport: str, callback: Callable, profile, camera: str = '', raw: bool = False):
    """The colour subscription of a ``color_transport`` setting: ``color/image_raw`` (Image) or
    ``color/image_raw/compressed`` (JPEG CompressedImage), under ``camera`` when given; ``raw``
    hands the callback the serialised message (see ``AdmissionListener.admitted_message``)."""
    topic = topics.COLOR_COMPRESSED if transport == 'compressed' else topics.COLOR_IMAGE
    return node.create_subscription(color_message_type(transport), topics.camera_topic(camera, topic) if camera
                                    else topic, callback, profile, raw=raw)


class StaticTransformListener:
    """The drivers' ``/tf_static`` gathered into ``transforms`` (what tf2's static listener
    does); ``on_update`` runs after each message. Unusable transforms are reported, not fatal."""

    def __init__(self, node: Node, diagnostics: Diagnostics, on_update: Callable[[], None] | None = None):
        self.transforms = StaticTransforms()
        self.diagnostics = diagnostics
        self.on_update = on_update
        node.create_subscription(TFMessage, '/' + topics.TF_STATIC, self._on_message, qos.TF_STATIC)

    def _on_message(self, msg: TFMessage) -> None:
        try:
            for parent, child, T in tf_message_to_transforms(msg):
                self.transforms.add(parent, child, T)
        except ValueError as e:
            self.diagnostics.report('warn', f'unusable /tf_static transform: {e}')
        if self.on_update is not None:
            self.on_update()


class AdmissionListener(Admission):
    """A stage's ``Admission`` kept up to date from the latched ``/volcap/admission`` (published
    by ``volcap live``): without one, every frame is admitted. A malformed rule is reported and
    the rules already in force are kept."""

    def __init__(self, node: Node, diagnostics: Diagnostics):
        super().__init__()
        self.node, self.diagnostics = node, diagnostics
        node.create_subscription(String, '/' + topics.ADMISSION, self._on_rule, qos.LATCHED)

    def _on_rule(self, msg: String) -> None:
        try:
            rule = AdmissionRule.from_text(msg.data)
        except ValueError as e:
            self.diagnostics.report('warn', f'admission rule ignored: {e}')
            return
        if rule.every != self.current.every:
            self.node.get_logger().info(f'admitting one frame set in {rule.every} from stamp {rule.since_ns}')
        self.update(rule)

    def admitted_message(self, stream, data: bytes, kind):
        """The message of a serialised frame when its capture stamp is admitted, else None: frames
        that are not admitted are never deserialised. ValueError for a message that is not CDR."""
        try:
            if not self.admit(stream, cdr_stamp_ns(data)):
                return None
            return deserialize_message(data, kind)
        except (struct.error, RuntimeError) as e:     # RMWError: not a message of this type
            raise BadInput(f'not a serialised {kind.__name__}: {e}') from None
