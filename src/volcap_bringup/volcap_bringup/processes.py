"""Every volcap node in one table, started as a separate process (as `ros2 run` does on a rig) or
hosted in this one (`compose`)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import yaml

# Every volcap node: (package, executable) -> (module, node class). `ros2 run` style processes
# run the module; a composed process instantiates the class.
NODES = {
    ('volcap_driver', 'bag_player'): ('volcap_driver.bag_player_node', 'BagPlayer'),
    ('volcap_driver', 'recorder'): ('volcap_driver.recorder_node', 'Recorder'),
    ('volcap_studio', 'synthetic_rig'): ('volcap_studio.synthetic_rig_node', 'SyntheticRig'),
    ('volcap_calib', 'calibration_service'): ('volcap_calib.calibration_service_node', 'CalibrationService'),
    ('volcap_filter', 'depth_filter'): ('volcap_filter.depth_filter_node', 'DepthFilter'),
    ('volcap_color', 'color_corrector'): ('volcap_color.color_corrector_node', 'ColorCorrector'),
    ('volcap_pipeline', 'camera_pipeline'): ('volcap_pipeline.camera_pipeline_node', 'CameraPipelineNode'),
    ('volcap_fusion', 'tsdf_fusion'): ('volcap_fusion.tsdf_fusion_node', 'TsdfFusionNode'),
    ('volcap_bringup', 'live_controller'): ('volcap_bringup.live_controller', 'LiveController'),
}


def ros_args(params: dict) -> list[str]:
    args = ['--ros-args']
    for key, value in params.items():
        text = yaml.safe_dump(value, default_flow_style=True).strip()
        if text.endswith('\n...'):
            text = text[:-4].strip()
        args += ['-p', f'{key}:={text}']
    return args


def start_node(package: str, executable: str, params: dict | None = None, env: dict | None = None,
               namespace: str = '', remaps: dict[str, str] | None = None, wrapper: tuple[str, ...] = (),
               **popen) -> subprocess.Popen:
    """Run a node in its own process (``python -m`` its module, with this interpreter),
    optionally in a namespace (``-r __ns:=/cam0``, as a launch file does), with topic remaps
    (``-r color/image_raw:=rgb/image_raw``, as onto a vendor driver's topics) and under a
    ``wrapper`` command (``('ip', 'netns', 'exec', 'host1')``: on another test host)."""
    module, _ = NODES[(package, executable)]
    full_env = dict(os.environ)
    full_env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    full_env.update(env or {})
    args = ros_args(params or {}) + (['-r', f'__ns:=/{namespace.strip("/")}'] if namespace else [])
    for source, target in (remaps or {}).items():
        args += ['-r', f'{source}:={target}']
    return subprocess.Popen([*wrapper, sys.executable, '-m', module, *args], env=full_env, **popen)


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGINT (a clean node shutdown), then SIGKILL if it does not exit in time."""
    return stop_all([proc], timeout)[0]


def stop_all(procs: list[subprocess.Popen], timeout: float = 10.0) -> list[int]:
    """``stop_all_timed``'s exit codes."""
    return [code for code, _ in stop_all_timed(procs, timeout)]


def stop_all_timed(procs: list[subprocess.Popen], timeout: float = 10.0) -> list[tuple[int, float | None]]:
    """SIGINT to every process in the order given; each exit is timed by polling them all for up
    to ``timeout`` s. Those still running then are waited for one by one, ``timeout`` s more each,
    and killed (SIGKILL) at the end of their wait: so a hung process is killed no sooner than
    2 x ``timeout`` s after the signals (the first of them 20 s at the default; the old rule,
    sequential waits alone, killed it at 10 s). They shut down together: a rig's ten processes
    stopped one by one took 10-16 s. A loaded CI run once had a camera pipeline killed under the
    old rule while it sat in the interpreter's teardown (2.6-3.3 s a process unloaded), which
    ``volcap_core.ros.node_main`` now skips: bench/shutdown.py, 0.3-0.4 s a process.

    Returns (exit code, seconds from the signals to the exit) per process; the seconds are None for
    a process that had ended before (no signal sent, its code kept)."""
    signalled = []
    for proc in procs:
        signalled.append(proc.poll() is None)
        if signalled[-1]:
            proc.send_signal(signal.SIGINT)
    start = time.monotonic()
    seconds: list[float | None] = [None] * len(procs)

    def reap() -> bool:
        now = time.monotonic()
        for i, proc in enumerate(procs):
            if signalled[i] and seconds[i] is None and proc.poll() is not None:
                seconds[i] = now - start
        return all(s is not None for s, sent in zip(seconds, signalled) if sent)
    while not reap() and time.monotonic() - start < timeout:
        time.sleep(0.02)             # polled, so each process's exit is timed, not just reaped
    for i, proc in enumerate(procs):
        if signalled[i] and seconds[i] is None:
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            seconds[i] = time.monotonic() - start
    return [(proc.returncode, s) for proc, s in zip(procs, seconds)]


def compose(package: str, executable: str, namespace: str = '', params: dict | None = None,
            remaps: dict[str, str] | None = None, **node_options):
    """The node instantiated in this process (rclpy already up), as a composed graph hosts it."""
    from importlib import import_module

    from rclpy.parameter import Parameter
    module, cls = NODES[(package, executable)]
    overrides = [Parameter(k, value=v) for k, v in (params or {}).items()]
    if remaps:
        node_options['cli_args'] = ['--ros-args'] + [a for k, v in remaps.items() for a in ('-r', f'{k}:={v}')]
    return getattr(import_module(module), cls)(namespace=namespace or None, parameter_overrides=overrides,
                                               **node_options)
