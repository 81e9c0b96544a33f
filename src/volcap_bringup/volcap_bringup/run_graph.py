"""`volcap run`: a bag through the whole graph, as on a rig.

bag_player, a camera_pipeline per camera (``split_stages``: a depth_filter and a color_corrector),
and tsdf_fusion each run in their own process (``ros2 run`` style; ``composed``: all in this process on one executor). This process
publishes the calibration (latched, as calibration_service does on a rig) and hosts
``RendererProbe``, a subscriber standing in for a telepresence renderer: it receives every
fused cloud and mesh and measures latency from the moment a frame set entered the graph (its
first colour image reached the probe) to the moment its mesh arrived.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from volcap_core import topics, wire
from volcap_core.bag_reader import BagReader
from volcap_core.calibration import Calibration
from volcap_core.errors import BadInput
from volcap_core.files import write_json
from volcap_core.frames import camera_topics, read_rig
from volcap_core.rig import Rig

from .graph import NodeSpec, RunConfig, camera_nodes, rig_graph, stream_remaps
from .probe import RendererProbe
from .session import GraphSession, spec_name

# Offline, a frame set waits this long for a late camera and an image for its partner: a loaded
# host may serve streams seconds apart, and every frame counts.
OFFLINE_TIMEOUT_MS = 10_000.0
STABILITY_FRAMES = 30      # metrics.json scores the frame-to-frame change of this many first frames (0.2 s a pair)


def graph_parameters(bag: Path, rig: Rig, cameras: list[str], frames_dir: Path, cfg: RunConfig, played: list[str],
                     layout: dict[str, dict[str, str]]) -> list[NodeSpec]:
    """(package, executable, namespace, parameters, remaps) of every node of the graph."""
    # Offline, every frame set counts: reliable inputs, a long frame-set timeout, a deep queue.
    fusion = {'voxel_size': cfg.voxel_size, 'output_dir': str(frames_dir), 'reliable': True, 'in_order': False,
              'depth_upsample': cfg.depth_upsample, 'queue_size': 100, 'frame_timeout_ms': OFFLINE_TIMEOUT_MS}
    expected = expected_subscribers(cameras, layout, played, probe=True, split_stages=cfg.split_stages)
    player = {'bag': str(bag), 'rate': cfg.rate, 'topics': played, 'wait_for_subscribers': 60.0,
              'exit_when_done': not cfg.composed, 'subscribers': [f'{t}={n}' for t, n in expected.items() if n]}
    # The nodes sit on whatever topics the bag holds (volcap's or a vendor driver's), as on a rig.
    maps = {c: stream_remaps(c, layout[c]) for c in cameras}
    filters = {c: {'reliable': True, 'pair_timeout_ms': OFFLINE_TIMEOUT_MS, **maps[c][1]} for c in cameras}
    if cfg.half_depth:
        # Half-size clean depth puts a 6 mm pixel footprint under 4 mm voxels (2.7 mm accuracy
        # on the demo bag, 1.3 mm at full size), for 5 ms less cleaning per camera.
        for c in cameras:
            color = rig.camera(c).color
            filters[c].update(output_width=color.width // 2, output_height=color.height // 2)
    corrector = {'reliable': True, **maps[cameras[0]][1]}
    return rig_graph(cameras, ('volcap_driver', 'bag_player', player), filters, corrector, fusion,
                     remaps={c: maps[c][0] for c in cameras}, split_stages=cfg.split_stages)


def expected_subscribers(cameras: list[str], layout: dict[str, dict[str, str]], played: list[str],
                         probe: bool = False, controller: bool = False, split_stages: bool = False
                         ) -> dict[str, int]:
    """How many subscribers each played topic gets in the rig graph (the player waits for all of
    them): each camera's pipeline on its colour and depth (with ``split_stages`` a filter and a
    corrector on colour, a filter on depth), the pipelines and the fusion on the phase;
    ``probe`` adds the renderer probe on the first colour, ``controller`` the live controller on
    the first and last cameras' camera_info."""
    expected = {t: 0 for t in played}
    on_color = len(camera_nodes(split_stages))      # each per-camera node reads the colour
    for c in cameras:
        expected[layout[c]['color']] = on_color + (probe and c == cameras[0])
        watched = controller and c in (cameras[0], cameras[-1])     # the live controller's clock
        expected[layout[c]['color_info']] = on_color + watched
        expected[layout[c]['depth']] = 1
        expected[layout[c]['depth_info']] = 1 + watched
    for t, n in ((topics.RIG, len(cameras)), (topics.TF_STATIC, len(cameras)), (topics.PHASE, len(cameras) + 1)):
        if t in expected:       # played: the bag has it
            expected[t] = n
    return expected


def played_topics(reader: BagReader, cameras: list[str], layout: dict[str, dict[str, str]]) -> list[str]:
    """What the graph's bag player plays: every camera's streams, and the session's rig, phase
    and the drivers' static transforms where the bag has them (a volcap bag carries
    ``/volcap/rig``, a vendor driver's recording ``/tf_static``; asking for one it lacks would
    read as a warning on a healthy run)."""
    return ([t for c in cameras for t in layout[c].values()]
            + [t for t in (topics.RIG, topics.PHASE, topics.TF_STATIC) if t in reader.topics])


def run_graph(cfg: RunConfig) -> dict:
    """Replays ``bag`` through the graph; the sequence lands in ``out/frames``. Returns the
    probe's and the nodes' figures (written to ``out/metrics.json`` by the caller)."""
    bag, out, calibration_path, progress = Path(cfg.bag), Path(cfg.out), cfg.calibration, cfg.progress
    calibration = Calibration.load(calibration_path)
    with BagReader(bag) as reader:
        rig = read_rig(reader)
        layout = camera_topics(reader, rig.names)
        capture_sets = _capture_sets(reader, layout[rig.names[0]]['color'])
        duration = (reader.end_ns - reader.start_ns) / 1e9
        bag_damage = reader.damage       # what the scan met; the player reports the same as it plays
        cameras = [c for c in rig.names if c in calibration.cameras]
        if not cameras:
            raise BadInput(f'no camera of {bag} is in the calibration {calibration_path}')
        played = played_topics(reader, cameras, layout)
    frames_dir = out / 'frames'
    if frames_dir.exists() and any(frames_dir.iterdir()):
        raise FileExistsError(f'{frames_dir} already holds a sequence; choose another --out')
    nodes = graph_parameters(bag, rig, cameras, frames_dir, cfg, played, layout)
    t_start = time.monotonic()
    with GraphSession('volcap_run', calibration) as session:
        probe = session.host(RendererProbe(layout[cameras[0]]['color'], clouds=True))
        # The player starts last, once every node subscribes: frames sent earlier would be lost.
        player, graph = nodes[0], nodes[1:]
        session.start_graph(graph, cfg.composed)
        session.wait_until_subscribed(graph_subscriptions(cameras, layout, cfg.split_stages), timeout=120.0)
        if cfg.composed:
            player_node = session.compose(player)

            def playing():
                return player_node.playing
        else:
            player_proc = session.start(player)

            def playing():
                return player_proc.poll() is None
        bar = tqdm(total=capture_sets, desc='fused frame sets', unit='set', disable=not progress)
        state = {'count': 0, 'change': time.monotonic(), 'ended': None}

        def finished() -> bool:
            # every capture set fused, or playback over and no new mesh for settle_s
            now, count = time.monotonic(), probe.mesh_count
            if count != state['count']:
                bar.update(count - state['count'])
                state['count'], state['change'] = count, now
            if state['ended'] is None and not playing():
                state['ended'] = now
            return state['ended'] is not None and (count >= capture_sets or
                                                   now - max(state['change'], state['ended']) > cfg.settle_s)
        session.spin_until(finished, timeout=120 + duration / cfg.rate * 3)
        bar.close()
        session.spin_for(1.0)      # the last clouds still in flight
        failures = [node.writer_failure for node in session.hosted if getattr(node, 'writer_failure', '')]
        summary = probe.summary()
    codes = session.exit_codes
    return {'mode': 'composed' if cfg.composed else 'processes', 'cameras': cameras,
            'calibration': str(Path(calibration_path).resolve()), 'capture_frame_sets_in_bag': capture_sets,
            'bag_damage': bag_damage,
            'recording_failure': '; '.join(failures), 'playback_rate': cfg.rate, 'voxel_size': cfg.voxel_size,
            'wall_s': time.monotonic() - t_start, 'probe': summary,
            'node_exit_codes': {spec_name(n): codes.get(spec_name(n), codes.get(n[1])) for n in nodes},
            'node_stop_s': {name: round(s, 2) for name, s in session.stop_seconds.items()}}


def _capture_sets(reader: BagReader, color_topic: str) -> int:
    """Frame sets the fusion will fuse: one camera's colour images in the capture phase (all
    of them when the bag announces no phase)."""
    changes = sorted((m.stamp_ns, topics.parse_phase(m.decode().data))
                     for m in reader.messages([topics.PHASE]))
    stamps = [m.stamp_ns for m in reader.messages([color_topic])]
    if not changes:
        return len(stamps)
    starts = np.array([s for s, _ in changes])
    phases = [p for _, p in changes]
    at = np.searchsorted(starts, stamps, side='right') - 1
    return sum(1 for k in at if k >= 0 and phases[k] == topics.CAPTURE)


def graph_subscriptions(cameras: list[str], layout: dict, split_stages: bool = False
                        ) -> dict[str, set[tuple[str, str]]]:
    """What a rig graph is up with: every camera's raw colour subscribed by its per-camera nodes
    (``graph.camera_nodes``), its raw depth by the one that cleans depth, and its cleaned depth
    and corrected colour by the fusion (the camera pipelines' wire; with ``split_stages`` the
    full-size images), as (namespace, node) per fully qualified topic."""
    per_camera = camera_nodes(split_stages)
    fused = ((topics.DEPTH_CLEAN, topics.COLOR_CORRECTED) if split_stages
             else (wire.WIRE_DEPTH, wire.WIRE_COLOR))

    def wanted(cam):
        ns = '/' + cam
        return {layout[cam]['color']: {(ns, n) for n in per_camera},
                layout[cam]['depth']: {(ns, per_camera[0])},
                **{topics.camera_topic(cam, t): {('/', 'tsdf_fusion')} for t in fused}}
    return {'/' + t: nodes for cam in cameras for t, nodes in wanted(cam).items()}


@dataclass
class RunReport:
    metrics: dict              # as written to ``out/metrics.json``
    out: Path

    @property
    def failed_nodes(self) -> dict:
        return {k: c for k, c in self.metrics['node_exit_codes'].items() if c not in (0, None)}

    @property
    def ok(self) -> bool:
        return bool(self.metrics['frames_written']) and not self.failed_nodes

    def lines(self) -> list[str]:
        m, p = self.metrics, self.metrics['probe']
        out = [f'{m["frames_written"]} of {m["capture_frame_sets_in_bag"]} capture frame sets fused into '
               f'{self.out / "frames"} ({m["mode"]}); the renderer probe received {p["meshes_received"]} meshes and '
               f'{p["clouds_received"]} clouds']
        if p['latency_ms_median'] is not None:
            out.append(f'latency from entering the graph to the mesh: median {p["latency_ms_median"]:.0f} ms, '
                       f'p95 {p["latency_ms_p95"]:.0f} ms; mesh rate {p["mesh_rate_hz"] or 0:.2f} Hz')
        if m.get('recording_failure'):
            out.append(m['recording_failure'])
        if m.get('bag_damage'):
            out.append(f'damaged bag, every readable frame set used: {m["bag_damage"]}')
        if m.get('stability'):
            from volcap_fusion.stability import format_stability
            out.append(f'{format_stability(m["stability"])} (the first {m["stability"]["first_frames"]} frames; '
                       'every change counts, the subject\'s motion too)')
        if 'figures_error' in m:
            out.append(f'no figures: {m["figures_error"]}')
        if 'raw_vs_clean_error' in m:
            out.append(f'no raw-vs-clean figure: {m["raw_vs_clean_error"]}')
        out.append(f'metrics: {self.out / "metrics.json"}  renders: {self.out / "renders"}')
        stops = m.get('node_stop_s') or {}
        if stops:
            slowest = max(stops, key=stops.get)
            out.append(f'{len(stops)} node processes stopped within {stops[slowest]:.2f} s of SIGINT '
                       f'(the last: {slowest})')
        if self.failed_nodes:
            out.append(f'nodes that exited with an error: {self.failed_nodes}')
        return out


def run(cfg: RunConfig) -> RunReport:
    """`volcap run`: the bag through the graph, then renders of the first, middle and last fused
    frames, the raw-vs-clean figure (paper 000 Figs. 16/18) and ``metrics.json``."""
    from volcap_fusion.sequence import MANIFEST, read_manifest
    out = Path(cfg.out)
    metrics = run_graph(cfg)
    frames = read_manifest(out / 'frames') if (out / 'frames' / MANIFEST).exists() else []
    metrics['frames_written'] = len(frames)
    metrics['frames'] = frames
    calibration = Calibration.load(cfg.calibration)
    cameras = metrics['cameras']
    _, T_frame_world = calibration.output_frame()       # the frames are in the studio frame
    poses = {c: T_frame_world @ calibration.T_world_color(c) for c in cameras}
    on_floor = calibration.studio is not None and calibration.studio.details.get('source') == 'floor'

    if len(frames) >= 2:
        metrics['stability'] = _stability(out / 'frames', frames[:STABILITY_FRAMES])
    try:      # the figures are extra: on a full disk the sequence and metrics.json still count
        _figures(cfg, out, frames, poses, on_floor, metrics)
    except OSError as e:
        metrics['figures_error'] = str(e)
    write_json(out / 'metrics.json', metrics)
    return RunReport(metrics, out)


def _stability(frames_dir: Path, frames: list[dict]) -> dict:
    """Frame-to-frame change of the first fused frames (``volcap_fusion.stability``): with no
    ground truth every change counts, the subject's own motion too."""
    from volcap_fusion.sequence import read_ply
    from volcap_fusion.stability import sequence_stability
    report = sequence_stability(read_ply(frames_dir / f['ply']) for f in frames)
    report['first_frames'] = len(frames)
    return report


def _figures(cfg: RunConfig, out: Path, frames: list[dict], poses: dict, on_floor: bool, metrics: dict) -> None:
    """Renders of the first, middle and last frames and the raw-vs-clean figure."""
    from volcap_fusion.sequence import read_ply
    from volcap_fusion.tsdf import FusionConfig
    from volcap_pipeline.render import render_rows
    from volcap_pipeline.rig import raw_fusion
    if frames:
        picks = sorted({0, len(frames) // 2, len(frames) - 1})
        metrics['renders'] = [str(render_rows([(f'frame {k}', read_ply(out / 'frames' / frames[k]['ply']))],
                                              list(poses.values()),
                                              out / 'renders' / f'frame_{k:06d}.png')) for k in picks]
        middle = frames[len(frames) // 2]
        try:
            raw = raw_fusion(cfg.bag, middle['stamp_ns'], poses, FusionConfig(voxel_size=cfg.voxel_size), on_floor)
            clean = read_ply(out / 'frames' / middle['ply'])
            metrics['raw_vs_clean'] = str(render_rows([('raw depth + raw colour', raw),
                                                       ('volcap: cleaned + corrected', clean)], list(poses.values()),
                                                      out / 'renders' / 'raw_vs_clean.png', frame_on=clean))
        except ValueError as e:     # the figure is extra: the sequence and metrics are kept
            metrics['raw_vs_clean_error'] = str(e)
