"""`volcap demo`: the pipeline end to end on generated data, scored.

With ``eval_cli`` the only command-line module that may import ``volcap_eval``: the demo ends
by scoring what the pipeline made against the synthetic ground truth.
"""
from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from volcap_core.settings import add_arguments, config_from_args, setting
from volcap_studio.config import BOARD_LAYOUTS


@dataclass
class DemoConfig:
    """What the demo renders and how long its steps run (the defaults: `make demo`)."""
    frames: int = setting(30, 'capture frames of the moving subject', 1, 10_000)
    board_poses: int = setting(16, 'calibration board poses (16: enough shared views to chain the four stands)',
                               1, 1000)
    # pairs: as the calibration's advice guides an operator, so the demo calibrates every camera
    # within the target (the sweep's 16 poses leave cam2-cam7 weak: docs/benchmarks.md)
    board_layout: str = setting('pairs', 'how the board is held: pairs (between neighbouring stands, as the '
                                "calibration's advice guides) or sweep (turned through every direction)",
                                choices=BOARD_LAYOUTS)
    seed: int = setting(0, 'seed of the synthetic studio', 0, 2**31 - 1)
    colour: bool = setting(True, 'run the colour steps: the short neural harmonisation and every colour method '
                           'scored (a third of the demo\'s time)')
    colour_frames: int = setting(4, 'capture frame sets the colour steps use', 2, 1000)
    # the default training with fewer samples per D, so the demo stays a few minutes (docs/color.md)
    harmonise_epochs: int = setting(12, 'epochs of colour field E in the short neural run', 1, 10_000)
    # E's time grows with its samples: the temporally averaged depth of 4 frame sets gives ~700 k,
    # 83 s of E alone on 2 cores (docs/benchmarks.md, issue 29)
    harmonise_points: int = setting(400_000, 'surface samples for colour field E in the short neural run', 1,
                                    100_000_000)
    mapper_epochs: int = setting(60, 'epochs of each camera\'s network D in the short neural run', 1, 10_000)
    scored_frames: int = setting(5, 'fused frames scored against the ground truth', 1, 10_000)
    run_rate: float = setting(0.04, 'playback speed of the graph run (2 cores: 0.04 fuses every frame set)',
                              0.001, 10.0)

    def harmonise(self) -> dict:
        # The short run's E takes about 290 steps: too few to fill finer cells, a larger table or
        # the views' registration, which help a full run on real texture. Measured on the demo's
        # studio (seed 0 / 7, pairwise / truth CIEDE2000): 4 mm cells, 2^16 entries, unregistered
        # 3.46 / 2.59 and 3.33 / 2.98; the full run's layout (2.8 mm, 2^18, registered) 3.63 /
        # 2.77 and 3.40 / 3.00 (docs/benchmarks.md, issue 29)
        return {'points': self.harmonise_points, 'field_epochs': self.harmonise_epochs, 'mapper_points': 30_000,
                'mapper_epochs': self.mapper_epochs, 'grid_cell_mm': 4.0, 'grid_log2_table': 16,
                'register_views': False}


def cmd_demo(args) -> int:
    from volcap_calib.run import CalibrateConfig
    from volcap_calib.run import run as calibrate
    from volcap_core.bag_reader import BagReader
    from volcap_core.files import write_json
    from volcap_eval.fusion import evaluate_fusion, format_seams
    from volcap_eval.stability import evaluate_stability
    from volcap_fusion.stability import format_stability
    from volcap_studio.session import GroundTruth, synthesize
    from volcap_studio.studio import SynthConfig

    from .monitor import StreamMonitor, format_rates
    from .processes import stop
    from .run_graph import RunConfig
    from .run_graph import run as run_graph
    from .session import GraphSession

    demo = config_from_args(DemoConfig, args)
    out = Path(args.out)
    bag = out / 'studio'
    cfg = SynthConfig(cameras=8, frames=demo.frames, board_poses=demo.board_poses, board_layout=demo.board_layout,
                      background_frames=3, seed=demo.seed)
    if bag.exists() and _same_config(bag, cfg):
        print(f'[1/7] reusing the studio bag {bag}')
    else:
        print(f'[1/7] rendering a synthetic 8-camera studio session into {bag}')
        out.mkdir(parents=True, exist_ok=True)
        synthesize(bag, cfg, overwrite=True)
    with BagReader(bag) as reader:
        duration = (reader.end_ns - reader.start_ns) / 1e9
    cameras = GroundTruth(bag).rig.names
    print(f'[2/7] replaying {duration:.1f} s through bag_player (its own process) into a subscriber')
    with GraphSession('volcap_demo') as session:
        monitor = session.host(StreamMonitor(cameras))
        player = session.start(('volcap_driver', 'bag_player', '', {
            'bag': str(bag), 'exit_when_done': True, 'wait_for_subscribers': 10.0, 'topics': monitor.topics}, {}))
        session.spin_until(lambda: player.poll() is not None, timeout=duration + 60)
        session.spin_for(0.5)
        code = stop(player)
        monitor.finish()
        summary = monitor.summary()
    print(format_rates(summary))
    write_json(out / 'demo_rates.json', summary)
    print(f'bag: {bag}  ground truth: {bag / "ground_truth"}  rates: {out / "demo_rates.json"}')
    if code != 0:
        print(f'bag_player exited with {code}', file=sys.stderr)
        return 1
    if summary['frame_sets_complete'] == 0:
        return 1
    calibration = out / 'calibration.yaml'
    print(f'[3/7] calibrating the rig from the board views: volcap calibrate -> {calibration}')
    print('\n'.join(calibrate(CalibrateConfig(bag, calibration)).lines()))

    if demo.colour:
        _colour_steps(demo, bag, calibration, out)
    else:
        print('[4/7] [5/7] colour steps left out (--no-colour)')

    run = out / 'run'
    if run.exists():
        shutil.rmtree(run)       # a run refuses to overwrite a sequence; the demo makes a new one
    print(f'[6/7] the whole graph on the bag (bag_player, camera_pipeline x{len(cameras)}, tsdf_fusion, each its '
          f'own process): volcap run -> {run}')
    result = run_graph(RunConfig(bag, calibration, run, rate=demo.run_rate))
    print('\n'.join(result.lines()))
    if not result.ok:
        return 1

    print(f'[7/7] the fused sequence against the ground truth: volcap eval fusion -> {out / "fusion.json"}')
    fusion = evaluate_fusion(run, bag, max_frames=demo.scored_frames)
    write_json(out / 'fusion.json', fusion)
    print(f'{fusion["frames"]} frames: accuracy {fusion["accuracy_mm"]:.2f} mm, completeness '
          f'{100 * fusion["completeness"]:.1f} % of the observable surface, '
          f'{100 * (fusion["completeness_feet"] or 0):.1f} % of its lowest 15 cm (feet)')
    print(format_seams(fusion['seams']))
    stability = evaluate_stability(run, bag, frames=demo.scored_frames, progress=False)
    write_json(out / 'stability.json', stability)
    print(f'{format_stability(stability)} ({stability["scored"]}): volcap eval stability -> {out / "stability.json"}')
    print(f'play it: volcap view {run / "frames"}')
    print(f'meshes: {run / "frames"} (PLY + GLB per frame set)  renders: {run / "renders"} '
          f'(raw vs cleaned: {run / "renders" / "raw_vs_clean.png"})  metrics: {run / "metrics.json"}')
    return 0


def _colour_steps(demo: DemoConfig, bag: Path, calibration: Path, out: Path) -> None:
    """Steps 4 and 5: the short neural harmonisation and every colour method on the same
    correspondences, scored against the truth."""
    from volcap_color import neural
    from volcap_color.config import HarmoniseConfig
    from volcap_color.correspondence import cameras_in
    from volcap_core.calibration import Calibration
    from volcap_core.files import write_json
    from volcap_eval.color import ColorEvalConfig
    from volcap_eval.color import format_report as format_color
    from volcap_eval.color import run as evaluate_color
    from volcap_pipeline import harmonise
    from volcap_pipeline.replay import capture_views

    models = out / 'neural'
    print(f'[4/7] neural colour harmonisation (paper 001), a short run of volcap harmonise -> {models}')
    t0 = time.perf_counter()
    rig_calibration = Calibration.load(calibration)
    sets = capture_views(bag, rig_calibration, demo.colour_frames)
    report = harmonise.run(sets, cameras_in(sets, rig_calibration), HarmoniseConfig(**demo.harmonise()), models,
                           sources={'bag': str(bag), 'calibration': str(calibration)},
                           views_seconds=time.perf_counter() - t0, chart_models=neural.chart_models(rig_calibration))
    print('\n'.join(report.lines()))

    print(f'[5/7] colour: every method on the same correspondences: volcap eval colour -> {out / "colour.json"}, '
          f'{out / "figures"}')
    color = evaluate_color(bag, calibration, ColorEvalConfig(frames=demo.colour_frames), neural=models,
                           figures=out / "figures")
    write_json(out / 'colour.json', color)
    print(format_color(color))


def _same_config(bag: Path, cfg) -> bool:
    from dataclasses import asdict

    from volcap_studio.session import GroundTruth
    try:
        stored = GroundTruth(bag).doc['config']
    except (FileNotFoundError, KeyError):
        return False
    wanted = asdict(cfg)
    return all(stored.get(k) == (list(v) if isinstance(v, tuple) else v) for k, v in wanted.items()
               if k not in ('k4a_calibration', 'bunny_mesh'))


def add_parsers(sub) -> None:
    d = sub.add_parser('demo', help='the pipeline end to end on generated data')
    d.add_argument('--out', default='demo_out', help='output folder (the bag, calibration, colour, the run)')
    add_arguments(d, DemoConfig)
    d.set_defaults(func=cmd_demo)
