"""The graph session: the one place a volcap command starts ROS, runs a node graph and stops it.

    with GraphSession('volcap_run', calibration=cal) as session:
        probe = session.host(RendererProbe(...))
        session.start_graph(nodes, composed=False)            # processes, or composed in this one
        session.wait_until_subscribed(needed, timeout=120)
        session.spin_until(lambda: len(probe.meshes) >= n, timeout=600)
    codes = session.exit_codes

On entry it configures the transport (volcap's Fast DDS profile), initialises rclpy and makes
one executor with a host node of its own, which publishes what the graph needs from the command
(the calibration, latched, as calibration_service does on a rig) and answers graph queries. The
command adds nodes it hosts (probes, the live controller, composed nodes) and starts node
processes (``ros2 run`` style). On exit, whatever happened, it signals the processes in reverse
start order (the source first, so no stage reports the others' absence while they stop) and
waits for them together (``processes.stop_all_timed``; ``stop_seconds`` keeps how long each took), destroys
the hosted nodes and shuts rclpy down. `volcap run`, `volcap live`, the demo, `volcap monitor`,
`volcap view --live`, `volcap operator` and the ROS tests all use it; nodes in their own process
use ``volcap_core.ros.run_node``.
"""
from __future__ import annotations

import subprocess
import time
from typing import Callable

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String

from volcap_core import qos, topics, transport
from volcap_core.calibration import Calibration
from volcap_core.errors import GraphError
from volcap_core.ros import make_executor

from .graph import NodeSpec
from .processes import compose, start_node, stop_all_timed


def spec_name(spec: NodeSpec) -> str:
    """``executable/namespace`` (or the executable in the root namespace): how a node is named in
    exit codes and CPU tables."""
    _, executable, namespace, _, _ = spec
    return f'{executable}{"/" + namespace if namespace else ""}'


class GraphSession:
    """A node graph run from this process: rclpy, one executor, the hosted nodes and the node
    processes, stopped cleanly on exit (see the module docstring)."""

    def __init__(self, name: str = 'volcap', calibration: Calibration | None = None, executor: str = 'single'):
        """``executor``: ``single`` (rclpy's SingleThreadedExecutor: a command that mostly waits)
        or ``events`` (``volcap_core.ros.make_executor``: a command that receives frames)."""
        if executor not in ('single', 'events'):
            raise ValueError(f"executor must be 'single' or 'events', got {executor!r}")
        self.name = name
        self.calibration = calibration
        self.executor_kind = executor
        self.processes: dict[str, subprocess.Popen] = {}
        self.hosted: list[Node] = []
        self._hosted_names: dict[int, str] = {}       # id(node) -> its spec name (composed nodes)
        self.exit_codes: dict[str, int | None] = {}
        self.stop_seconds: dict[str, float] = {}      # per process: from its SIGINT to its exit
        self.node: Node | None = None
        self.executor = None
        self._started = False

    # start and stop ---------------------------------------------------------------------------
    def __enter__(self) -> GraphSession:
        transport.configure()
        rclpy.init()
        self._started = True
        try:
            self.executor = SingleThreadedExecutor() if self.executor_kind == 'single' else make_executor()
            self.node = Node(self.name)
            self.executor.add_node(self.node)
            if self.calibration is not None:
                self.publish_calibration(self.calibration)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stops every process (reverse start order) and hosted node, then rclpy. Idempotent."""
        names = list(reversed(self.processes))
        stopped = stop_all_timed([self.processes[n] for n in names])
        self.exit_codes.update((n, code) for n, (code, _) in zip(names, stopped))
        self.stop_seconds.update((n, s) for n, (_, s) in zip(names, stopped) if s is not None)
        self.processes.clear()
        for node in reversed(self.hosted):
            name = self._hosted_names.get(id(node), node.get_name())
            self.exit_codes[name] = getattr(node, 'exit_code', 0)
            if self.executor is not None:
                self.executor.remove_node(node)
            node.destroy_node()
        self.hosted = []
        if self.executor is not None:
            self.executor.shutdown()
            self.executor = None
        if self.node is not None:
            self.node.destroy_node()
            self.node = None
        if self._started:
            rclpy.try_shutdown()
            self._started = False

    # what the graph needs from this process ---------------------------------------------------
    def publish_calibration(self, calibration: Calibration) -> None:
        """The calibration on ``/volcap/calibration``, latched (as calibration_service does)."""
        if not hasattr(self, '_calibration_pub'):
            self._calibration_pub = self.node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
        self._calibration_pub.publish(String(data=calibration.to_yaml()))

    def host(self, node: Node) -> Node:
        """Spin ``node`` (a probe, a controller, a composed node) in this process until the end."""
        self.executor.add_node(node)
        self.hosted.append(node)
        return node

    def release(self, node: Node) -> None:
        """Stop spinning a hosted ``node`` before the end, and destroy it."""
        if node in self.hosted:
            self.hosted.remove(node)
            if self.executor is not None:
                self.executor.remove_node(node)
            node.destroy_node()

    def compose(self, spec: NodeSpec, **node_options) -> Node:
        """The node of ``spec`` instantiated and hosted in this process."""
        node = self.host(compose(*spec, **node_options))
        self._hosted_names[id(node)] = spec_name(spec)
        return node

    def start(self, spec: NodeSpec, **popen) -> subprocess.Popen:
        """The node of ``spec`` in its own process (``ros2 run`` style)."""
        package, executable, namespace, params, remaps = spec
        proc = start_node(package, executable, params, namespace=namespace, remaps=remaps, **popen)
        self.processes[spec_name(spec)] = proc
        return proc

    def start_graph(self, specs: list[NodeSpec], composed: bool = False) -> None:
        """Every node of ``specs``: each in its own process, or all hosted here (``composed``)."""
        for spec in specs:
            if composed:
                self.compose(spec)
            else:
                self.start(spec)

    # spinning -----------------------------------------------------------------------------------
    def spin_once(self, timeout: float = 0.05) -> None:
        self.executor.spin_once(timeout_sec=timeout)

    def spin_until(self, done: Callable[[], bool], timeout: float | None = None,
                   fail_on_exit: bool = False) -> bool:
        """Spin until ``done()`` (True) or ``timeout`` seconds (False; None: no limit).
        ``fail_on_exit``: a node process that exits meanwhile is a ``GraphError``."""
        end = None if timeout is None else time.monotonic() + timeout
        while end is None or time.monotonic() < end:
            self.spin_once()
            if done():
                return True
            if fail_on_exit:
                dead = self.exited()
                if dead:
                    raise GraphError(f'{dead[0]} exited with code {self.processes[dead[0]].returncode}')
        return done()

    def ok(self) -> bool:
        """rclpy is still up (a signal or another shutdown ends it)."""
        return self.node is not None and self.node.context.ok()

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.spin_once()

    def exited(self) -> list[str]:
        """The node processes that have ended."""
        return [name for name, p in self.processes.items() if p.poll() is not None]

    def wait_until_subscribed(self, needed: dict[str, set[tuple[str, str]]], timeout: float) -> None:
        """Until every topic of ``needed`` has a subscription from each of its (namespace, node)
        pairs: by node, as the graph names them (an endpoint not yet discovered, or left by a
        process that just ended, has no known node). ``GraphError`` after ``timeout`` seconds, or
        when a node process exits first."""
        def missing():
            return {t: nodes - {(i.node_namespace, i.node_name) for i in self.node.get_subscriptions_info_by_topic(t)}
                    for t, nodes in needed.items()}
        if self.spin_until(lambda: not any(missing().values()), timeout, fail_on_exit=True):
            return
        late = {t: sorted(n) for t, n in missing().items() if n}
        raise GraphError(f'the graph did not come up within {timeout:.0f} s: no subscription yet from '
                         f'{list(late.items())[:3]}')
