"""`volcap live`: the graph on live topics, kept real time by admission control.

Every node runs with its live defaults (keep-last queues, one frame set waiting for fusion) and
``live_controller`` publishes the admission rule on ``/volcap/admission`` from the measured load,
so the graph drops whole frame sets early (the same ones in every stage) instead of queueing
them. The frame source is the cameras' drivers (``driver``) or, standing in for them, a bag
looped at real time with fresh stamps: one pass from the start (the filters learn the clean
plate), then the capture part over and over. A wire bag (``volcap wire``) starts the fusion host
alone, fed with the recorded wire as the camera hosts would send it. This process publishes the calibration (latched,
as calibration_service does), hosts the controller and prints its figures once a second; with
``probe`` it also hosts a renderer stand-in that receives every mesh and times it.
"""
from __future__ import annotations

import os
import time
from typing import Callable

import numpy as np
import psutil

from volcap_core import topics, wire
from volcap_core.bag_reader import BagReader
from volcap_core.calibration import Calibration
from volcap_core.errors import BadInput
from volcap_core.frames import camera_topics, read_rig
from volcap_pipeline.wire_bag import WIRE_STREAMS, is_wire_bag, wire_cameras

from .graph import (
    LIVE_FRAME_TIMEOUT_MS,
    LiveConfig,
    NodeSpec,
    camera_remaps,
    live_controller,
    rig_graph,
    stream_remaps,
)
from .probe import RendererProbe
from .run_graph import expected_subscribers, graph_subscriptions, played_topics
from .session import GraphSession


def _capture_offset_s(reader: BagReader) -> float:
    """Seconds into the bag where the capture phase starts (0 when no phase is announced)."""
    for m in reader.messages([topics.PHASE]):
        if topics.parse_phase(m.decode().data) == topics.CAPTURE:
            return max(0.0, (m.stamp_ns - reader.start_ns) / 1e9)
    return 0.0


def fusion_host_nodes(cfg: LiveConfig, cameras: list[str], bag_cameras: list[str], fusion: dict
                      ) -> tuple[list[NodeSpec], list[str], dict]:
    """The fusion host alone, fed by a recorded wire (``volcap wire``) looped at real time with
    fresh stamps, as the camera hosts would send it: the player, tsdf_fusion on the wire and the
    live controller watching the wire's camera_info."""
    missing = [c for c in cameras if c not in bag_cameras]
    if missing:
        raise BadInput(f'cameras {missing} are not in the wire bag {cfg.bag} (it has {", ".join(bag_cameras)})')
    played = [topics.camera_topic(c, t) for c in cameras for t in WIRE_STREAMS]
    watched = {topics.camera_topic(c, t) for c in (cameras[0], cameras[-1])
               for t in (wire.WIRE_COLOR_INFO, wire.WIRE_DEPTH_INFO)}
    expected = {t: 1 + (t in watched) for t in played}
    source = ('volcap_driver', 'bag_player', '', {
        'bag': str(cfg.bag), 'rate': cfg.rate, 'loop': True, 'restamp': True, 'loop_offset': 0.0,
        'max_lag_ms': 100.0, 'topics': played, 'wait_for_subscribers': 60.0, 'exit_when_done': False,
        'subscribers': [f'{t}={n}' for t, n in expected.items()]}, {})
    fusion_node = ('volcap_fusion', 'tsdf_fusion', '', {**fusion, 'input': 'wire'}, {})
    info = {'color/camera_info': wire.WIRE_COLOR_INFO, 'depth/camera_info': wire.WIRE_DEPTH_INFO}
    controller = live_controller(cameras, {'every': cfg.every, 'latency_budget_ms': cfg.latency_budget_ms},
                                 remaps={c: info for c in cameras})
    layout = {c: {'wire': True} for c in cameras}
    return [source, fusion_node, controller], cameras, layout


def live_nodes(cfg: LiveConfig, calibration: Calibration) -> tuple[list[NodeSpec], list[str], dict]:
    """(node specs in start order with the controller last, cameras, per-camera topic layout).
    A wire bag (``volcap wire``) starts the fusion host alone (``fusion_host_nodes``)."""
    cameras = list(cfg.cameras or calibration.cameras)
    absent = [c for c in cameras if c not in calibration.cameras]
    if absent:
        raise BadInput(f'cameras {absent} are not in the calibration {cfg.calibration}')
    if cfg.bag is not None:
        with BagReader(cfg.bag) as reader:
            bag_cameras = wire_cameras(reader) if is_wire_bag(reader) else None
        if bag_cameras is not None:
            fusion = {'voxel_size': cfg.voxel_size, 'output_dir': cfg.output_dir,
                      'frame_timeout_ms': LIVE_FRAME_TIMEOUT_MS * cfg.latency_budget_ms / 1000.0}
            return fusion_host_nodes(cfg, cameras, bag_cameras, fusion)
    filters = {c: {} for c in cameras}
    corrector: dict = {}
    fusion = {'voxel_size': cfg.voxel_size, 'output_dir': cfg.output_dir,
              'frame_timeout_ms': LIVE_FRAME_TIMEOUT_MS * cfg.latency_budget_ms / 1000.0}
    source = None
    if cfg.bag is not None:
        with BagReader(cfg.bag) as reader:
            rig = read_rig(reader)
            layout = camera_topics(reader, rig.names)
            loop_offset = _capture_offset_s(reader)
            missing = [c for c in cameras if c not in layout]
            if missing:
                raise BadInput(f'cameras {missing} are not in {cfg.bag}')
            played = played_topics(reader, cameras, layout)
        maps = {c: stream_remaps(c, layout[c]) for c in cameras}
        for c in cameras:
            filters[c].update(maps[c][1])
        corrector.update(maps[cameras[0]][1])
        remaps = {c: maps[c][0] for c in cameras}
        expected = expected_subscribers(cameras, layout, played, controller=True, split_stages=cfg.split_stages)
        source = ('volcap_driver', 'bag_player', {
            'bag': str(cfg.bag), 'rate': cfg.rate, 'loop': True, 'restamp': True, 'loop_offset': loop_offset,
            'max_lag_ms': 100.0,      # a camera drops what it cannot send in time
            'topics': played, 'wait_for_subscribers': 60.0, 'exit_when_done': False,
            'subscribers': [f'{t}={n}' for t, n in expected.items() if n]})
    else:
        remaps = {c: camera_remaps(cfg.driver, cfg.registered) for c in cameras}
        color = topics.COLOR_COMPRESSED if cfg.color_format == 'jpeg' else topics.COLOR_IMAGE
        layout = {c: {'color': topics.camera_topic(c, remaps[c].get(color, color)),
                      'depth': topics.camera_topic(c, remaps[c].get(topics.DEPTH_IMAGE, topics.DEPTH_IMAGE))}
                  for c in cameras}
        if cfg.color_format == 'jpeg':
            corrector['color_transport'] = 'compressed'
            for c in cameras:
                filters[c]['color_transport'] = 'compressed'
    if cfg.rig_file:
        for c in cameras:
            filters[c]['rig_file'] = cfg.rig_file
    for c in cameras:
        filters[c]['output_scale'] = cfg.depth_scale
    nodes = rig_graph(cameras, source, filters, corrector, fusion, remaps=remaps, split_stages=cfg.split_stages)
    nodes.append(live_controller(cameras, {'every': cfg.every, 'latency_budget_ms': cfg.latency_budget_ms},
                                 remaps=remaps))
    return nodes, cameras, layout


def _process_cpu_s(procs: dict[str, psutil.Process]) -> dict[str, float]:
    out = {}
    for name, p in procs.items():
        try:
            t = p.cpu_times()
            out[name] = t.user + t.system + t.children_user + t.children_system
        except psutil.Error:
            out[name] = float('nan')
    return out


def run_live(cfg: LiveConfig, on_summary: Callable[[dict], None] | None = None,
             stop_when: Callable[[dict], bool] | None = None) -> dict:
    """Runs the live graph for ``cfg.seconds`` (or until Ctrl-C), or until ``stop_when(progress)``
    holds: progress is ``{'meshes': all the probe's meshes, 'meshes_after_warmup': those that
    arrived after the warm-up, 'summaries': the controller's summaries so far}`` (a condition to
    wait on, so a loaded machine takes longer instead of failing). Returns the controller's
    summaries, the probe's meshes and each process's CPU seconds after the warm-up."""
    calibration = Calibration.load(cfg.calibration)
    nodes, cameras, layout = live_nodes(cfg, calibration)
    summaries: list[dict] = []
    clock = {'started': None}     # when the frames started (the graph takes a while to come up)

    def summarised(s: dict) -> None:
        started = clock['started']
        s['t_s'] = round(time.monotonic() - started, 2) if started is not None else -1.0   # -1: starting up
        summaries.append(s)
        if on_summary is not None:
            on_summary(s)

    controller_spec = nodes[-1]
    source = nodes[0] if cfg.bag is not None else None
    graph = nodes[1:-1] if source else nodes[:-1]
    window: dict = {}
    probe = None
    with GraphSession('volcap_live', calibration, executor='events') as session:
        try:
            probe = session.host(RendererProbe(reliable=False)) if cfg.probe else None
            session.compose(controller_spec, on_summary=summarised)
            session.start_graph(graph, cfg.composed)
            if any('wire' in v for v in layout.values()):     # the fusion host alone, on a recorded wire
                wanted = {'/' + topics.camera_topic(c, t): {('/', 'tsdf_fusion')} for c in cameras
                          for t in (wire.WIRE_DEPTH, wire.WIRE_COLOR)}
            else:
                wanted = graph_subscriptions(cameras, layout, cfg.split_stages)
            session.wait_until_subscribed(wanted, timeout=120.0)
            if source is not None:
                nice = cfg.source_nice
                session.start(source, preexec_fn=(lambda: os.nice(nice)) if nice else None)
            ps = {name: psutil.Process(p.pid) for name, p in session.processes.items()}
            ps['volcap_live'] = psutil.Process()
            started = clock['started'] = time.monotonic()
            warm = started + cfg.warmup_s

            # spins for cfg.seconds (or until Ctrl-C, or stop_when), noting the CPU times once the
            # warm-up has passed; a node process that exits ends the run (GraphError)
            def done() -> bool:
                if not window and time.monotonic() >= warm:
                    window.update(cpu_start=_process_cpu_s(ps), t=time.monotonic(),
                                  meshes_before=len(probe.meshes) if probe else 0)
                if stop_when is None:
                    return False
                meshes = probe.meshes if probe else []
                after = len(meshes) - window['meshes_before'] if window else 0
                return stop_when({'meshes': meshes, 'meshes_after_warmup': after, 'summaries': summaries})
            session.spin_until(done, cfg.seconds, fail_on_exit=True)
            if window:
                window['cpu_end'] = _process_cpu_s(ps)
                window['s'] = time.monotonic() - window['t']
        except KeyboardInterrupt:
            pass
    result = {'cameras': cameras, 'voxel_size': cfg.voxel_size, 'mode': 'composed' if cfg.composed else 'processes',
              'depth_scale': cfg.depth_scale, 'summaries': summaries,
              'node_exit_codes': {n: c for n, c in session.exit_codes.items() if n != 'live_controller'}}
    if 'cpu_end' in window:
        result['window_s'] = window['s']
        result['cpu_s'] = {n: window['cpu_end'][n] - window['cpu_start'][n] for n in window['cpu_end']}
    if probe is not None:
        result['meshes'] = probe.meshes
        result['meshes_in_window'] = len(probe.meshes) - window['meshes_before'] if 'cpu_end' in window else None
    return result


def latency_ms(meshes: list[tuple[int, int, int]]) -> np.ndarray:
    """Capture stamp to arrival at the probe, per mesh (stamps on the wall clock: live)."""
    return np.array([(arrival - stamp) / 1e6 for arrival, stamp, _ in meshes])


def summary_figures(summaries: list[dict], warmup_s: float) -> dict:
    """The live figures over the run after the warm-up: mean rates, the share of meshes fused from
    every camera, the worst p95 latency the fusion reported, drops per stage per second."""
    after = [s for s in summaries if s['t_s'] >= warmup_s]
    if not after:
        return {'meshes_per_s': None, 'input_fps': None, 'complete_share': None, 'latency_ms_p95_max': None}
    meshes = np.array([s['meshes_per_s'] for s in after])
    shares = [(s['complete_share'], s['meshes_per_s']) for s in after if s['complete_share'] is not None]
    p95 = [s['latency_ms_p95'] for s in after if s['latency_ms_p95'] is not None]
    p50 = [s['latency_ms_p50'] for s in after if s['latency_ms_p50'] is not None]
    stages = {stage: keys for s in after for stage, keys in s['drops_per_s'].items()}   # any that reported
    drops = {stage: {k: float(np.mean([s['drops_per_s'].get(stage, {}).get(k, 0.0) for s in after])) for k in keys}
             for stage, keys in stages.items()}
    weight = sum(m for _, m in shares)
    return {'seconds': len(after), 'meshes_per_s': float(meshes.mean()),
            'input_fps': float(np.mean([s['input_fps'] for s in after])),
            'complete_share': sum(c * m for c, m in shares) / weight if weight else None,
            'latency_ms_p50_median': float(np.median(p50)) if p50 else None,
            'latency_ms_p95_max': float(np.max(p95)) if p95 else None,
            'admit_every_median': float(np.median([s['admit_every'] for s in after])),
            'cpu_busy_mean': float(np.mean([s['cpu_busy'] for s in after])), 'drops_per_s': drops}
