"""The `volcap` command line.

    volcap synth --out DIR [--cameras 8] [--frames N] [--board-poses K] [--scene NAME] [--seed S]
    volcap import-k4a MKV --out DIR
    volcap rig --k4a cam0=calibration.json [--orbbec ...] [--bag BAG] --out rig.yaml
    volcap monitor --cameras 8 [--driver azure_kinect] [--seconds S] [--json OUT.json]
    volcap info BAG
    volcap eval depth BAG [--json OUT.json] [--figures DIR] [--frames N]
    volcap eval registration BAG [--out overlay.png] [--json OUT.json]
    volcap board --out board.pdf
    volcap calibrate BAG --out calibration.yaml [--icp]
    volcap eval calib calibration.yaml BAG [--json OUT.json]
    volcap eval chart PHOTO [PHOTO ...] [--json OUT.json] [--figures DIR]
    volcap eval color BAG --calibration calibration.yaml [--json OUT.json] [--figures DIR]
    volcap color-fit BAG --calibration calibration.yaml --out calibration_color.yaml
    volcap run BAG --calibration calibration.yaml --out DIR [--composed] [--voxel 0.004]
    volcap view DIR | --live [--port 8080]
    volcap operator [--cameras cam0,cam1] [--hz 2] [--web-port 9090]
    volcap eval fusion DIR BAG [--json OUT.json]
    volcap fuse-frames FOLDER --intrinsics K.txt --out mesh.ply [--voxel 0.01]
    volcap demo [--out DIR]
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from volcap_core import transport

from . import calib_cli, color_cli, fusion_cli, rig_cli


def cmd_synth(args) -> int:
    from volcap_studio.session import synthesize
    from volcap_studio.studio import SynthConfig
    cfg = SynthConfig(cameras=args.cameras, frames=args.frames, board_poses=args.board_poses,
                      board_layout=args.board_layout, background_frames=args.background_frames, scene=args.scene,
                      seed=args.seed, fps=args.fps,
                      **({'k4a_calibration': args.k4a_calibration} if args.k4a_calibration else {}))
    t0 = time.monotonic()
    summary = synthesize(args.out, cfg, progress=not args.quiet, overwrite=args.overwrite)
    mb = summary.bag_bytes / 1e6
    per_second = mb / max(summary.frame_sets, 1) * cfg.fps
    print(f'wrote {summary.path}: {summary.frame_sets} frame sets, {summary.messages} messages, {mb:.0f} MB '
          f'({per_second:.0f} MB per second of capture) in {time.monotonic() - t0:.0f} s')
    print(f'ground truth: {summary.path / "ground_truth"}')
    return 0


def cmd_import_k4a(args) -> int:
    from volcap_driver.k4a_import import import_k4a
    s = import_k4a(args.mkv, args.out, camera=args.camera, max_frames=args.max_frames, progress=not args.quiet,
                   overwrite=args.overwrite)
    cam = s.rig.cameras[0]
    print(f'wrote {s.path}: {s.color_frames} colour and {s.depth_frames} depth frames from device '
          f'{cam.serial or "?"} (colour {cam.color.width}x{cam.color.height}, depth {cam.depth.width}x{cam.depth.height})')
    return 0


def cmd_info(args) -> int:
    from volcap_core.bag_io import BagReader
    with BagReader(args.bag) as bag:
        counts = bag.topic_counts
        readable = None if args.quick else bag.verify()
        if bag.damage:
            print(f'damaged bag: {bag.damage}')
            print(f'  (`volcap bag recover {args.bag} OUT` writes a whole copy of what is readable)')
        duration = (bag.end_ns - bag.start_ns) / 1e9
        checked = '' if readable is None else f' ({readable} readable, every chunk CRC checked)'
        print(f'{args.bag}: {bag.message_count} messages{checked}, {duration:.3f} s')
        latched = bag.latched_topics
        for topic, msgtype in sorted(bag.topics.items()):
            print(f'  {topic:<36} {msgtype:<28} {counts.get(topic, 0):6d}{"  (latched)" if topic in latched else ""}')
    return 1 if readable is not None and bag.damage else 0


def cmd_bag_recover(args) -> int:
    from volcap_core.bag_io import recover
    result = recover(args.bag, args.out, args.compression)
    print(f'wrote {args.out}: {result.messages} messages')
    print(f'lost: {result.damage}' if result.damage else f'{args.bag} was whole: nothing lost')
    return 0


def cmd_eval_depth(args) -> int:
    from volcap_eval.depth import METHODS, evaluate_depth, format_report, write_report
    methods = tuple(args.methods.split(',')) if args.methods else METHODS
    report = evaluate_depth(args.bag, methods=methods, max_frames=args.frames,
                            figures=Path(args.figures) if args.figures else None, progress=not args.quiet)
    print(format_report(report))
    if args.json:
        write_report(report, Path(args.json))
        print(f'wrote {args.json}')
    return 0


def cmd_eval_registration(args) -> int:
    from volcap_eval.depth import write_report
    from volcap_eval.registration import check_registration
    report = check_registration(args.bag, Path(args.out), camera=args.camera)
    print(f"{report['camera']}: depth edges lie {report['median_offset_px']:.2f} px (median) from colour edges "
          f"over {report['edge_pixels']} edge pixels; best global shift {report['best_shift_px']} px "
          f"(median there {report['median_offset_at_best_shift_px']:.2f} px); overlay {args.out}")
    if args.json:
        write_report(report, Path(args.json))
    return 0


# a third of the default training, so the demo stays a few minutes (docs/color.md gives full-length figures)
DEMO_HARMONISE = {'points': 100_000, 'field_epochs': 40, 'field_lr': 5e-4, 'field_lr_final': 5e-5,
                  'mapper_points': 30_000}


def cmd_demo(args) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from volcap_calib.run import CalibrateConfig
    from volcap_calib.run import run as calibrate
    from volcap_color import neural
    from volcap_color.correspondence import cameras_in
    from volcap_color.neural_config import HarmoniseConfig
    from volcap_core.bag_io import BagReader
    from volcap_core.calibration import Calibration
    from volcap_core.files import write_json
    from volcap_eval.color import ColorEvalConfig
    from volcap_eval.color import format_report as format_color
    from volcap_eval.color import run as evaluate_color
    from volcap_eval.fusion import evaluate_fusion
    from volcap_eval.replay import capture_views
    from volcap_studio.session import GroundTruth, synthesize
    from volcap_studio.studio import SynthConfig

    from .monitor import StreamMonitor, format_rates
    from .processes import start_node, stop
    from .run_graph import RunConfig
    from .run_graph import run as run_graph

    out = Path(args.out)
    bag = out / 'studio'
    # 16 board poses: enough shared views to chain the four stands for the calibration step
    cfg = SynthConfig(cameras=8, frames=args.frames, board_poses=16, background_frames=3, seed=args.seed)
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
    transport.configure()
    rclpy.init()
    monitor = StreamMonitor(cameras)
    executor = SingleThreadedExecutor()
    executor.add_node(monitor)
    player = start_node('volcap_driver', 'bag_player', {'bag': str(bag), 'exit_when_done': True,
                                                        'wait_for_subscribers': 10.0,
                                                        'topics': monitor.topics})
    try:
        deadline = time.monotonic() + duration + 60
        while player.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        code = stop(player)
        monitor.finish()
        summary = monitor.summary()
        executor.shutdown()
        monitor.destroy_node()
        rclpy.try_shutdown()
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

    models = out / 'neural'
    print(f'[4/7] neural colour harmonisation (paper 001), a short run of volcap harmonise -> {models}')
    t0 = time.perf_counter()
    rig_calibration = Calibration.load(calibration)
    sets = capture_views(bag, rig_calibration, 4)
    report = neural.run(sets, cameras_in(sets, rig_calibration), HarmoniseConfig(**DEMO_HARMONISE),
                        models, sources={'bag': str(bag), 'calibration': str(calibration)},
                        views_seconds=time.perf_counter() - t0)
    print('\n'.join(report.lines()))

    print(f'[5/7] colour: every method on the same correspondences: volcap eval colour -> {out / "colour.json"}, '
          f'{out / "figures"}')
    color = evaluate_color(bag, calibration, ColorEvalConfig(frames=4), neural=models, figures=out / "figures")
    write_json(out / 'colour.json', color)
    print(format_color(color))

    run = out / 'run'
    if run.exists():
        shutil.rmtree(run)       # a run refuses to overwrite a sequence; the demo makes a new one
    print(f'[6/7] the whole graph on the bag (bag_player, depth_filter and color_corrector x{len(cameras)}, '
          f'tsdf_fusion, each its own process): volcap run -> {run}')
    result = run_graph(RunConfig(bag, calibration, run))
    print('\n'.join(result.lines()))
    if not result.ok:
        return 1

    print(f'[7/7] the fused sequence against the ground truth: volcap eval fusion -> {out / "fusion.json"}')
    fusion = evaluate_fusion(run, bag, max_frames=5)
    write_json(out / 'fusion.json', fusion)
    print(f'{fusion["frames"]} frames: accuracy {fusion["accuracy_mm"]:.2f} mm, completeness '
          f'{100 * fusion["completeness"]:.1f} % of the observable surface, '
          f'{100 * (fusion["completeness_feet"] or 0):.1f} % of its lowest 15 cm (feet)')
    print(f'play it: volcap view {run / "frames"}')
    print(f'meshes: {run / "frames"} (PLY + GLB per frame set)  renders: {run / "renders"} '
          f'(raw vs cleaned: {run / "renders" / "raw_vs_clean.png"})  metrics: {run / "metrics.json"}')
    return 0


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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='volcap', description='volumetric capture pipeline tools')
    sub = p.add_subparsers(dest='command', required=True)

    s = sub.add_parser('synth', help='render a synthetic studio session to a bag with ground truth')
    s.add_argument('--out', required=True, help='bag directory to write')
    s.add_argument('--cameras', type=int, default=8)
    s.add_argument('--frames', type=int, default=10, help='capture frames of the subject')
    s.add_argument('--board-poses', type=int, default=12, help='calibration board poses')
    s.add_argument('--board-layout', default='sweep', choices=('sweep', 'pairs'),
                   help='sweep: the board turned through every direction; pairs: held between neighbouring stands')
    s.add_argument('--background-frames', type=int, default=3, help='clean-plate frames (no subject)')
    s.add_argument('--scene', default='person', choices=('person', 'bunny'))
    s.add_argument('--seed', type=int, default=0)
    s.add_argument('--fps', type=float, default=30.0)
    s.add_argument('--k4a-calibration', default='', help='factory calibration JSON the rig is modelled on')
    s.add_argument('--overwrite', action='store_true')
    s.add_argument('--quiet', action='store_true')
    s.set_defaults(func=cmd_synth)

    k = sub.add_parser('import-k4a', help='convert an Azure Kinect MKV recording to a bag')
    k.add_argument('mkv')
    k.add_argument('--out', required=True)
    k.add_argument('--camera', default='cam0')
    k.add_argument('--max-frames', type=int, default=None)
    k.add_argument('--overwrite', action='store_true')
    k.add_argument('--quiet', action='store_true')
    k.set_defaults(func=cmd_import_k4a)

    i = sub.add_parser('info', help='topics, types and message counts of a bag')
    i.add_argument('bag')
    i.add_argument('--quick', action='store_true', help='metadata only (skip reading every message and CRC)')
    i.set_defaults(func=cmd_info)

    b = sub.add_parser('bag', help='bag maintenance')
    bsub = b.add_subparsers(dest='bag_command', required=True)
    br = bsub.add_parser('recover', help='copy every readable message of a damaged bag (cut off, corrupt '
                                         'chunks, unfinished split) into a new whole bag')
    br.add_argument('bag')
    br.add_argument('out', help='bag directory to create')
    br.add_argument('--compression', default='none', choices=('none', 'zstd'))
    br.set_defaults(func=cmd_bag_recover)

    e = sub.add_parser('eval', help='score a pipeline stage against ground truth or real data')
    esub = e.add_subparsers(dest='stage', required=True)
    ed = esub.add_parser('depth', help='depth cleaning on a synthetic bag: raw, paper Eq. 5 and ours')
    ed.add_argument('bag')
    ed.add_argument('--json', help='write the report here')
    ed.add_argument('--figures', help='write Fig. 13/15 style PNGs into this folder')
    ed.add_argument('--frames', type=int, default=None, help='score only the first N capture frame sets')
    ed.add_argument('--methods', default='', help='comma-separated subset of raw,paper_horizontal,paper_all,volcap')
    ed.add_argument('--quiet', action='store_true')
    ed.set_defaults(func=cmd_eval_depth)
    er = esub.add_parser('registration', help='edge offset of registered depth against colour (real recordings)')
    er.add_argument('bag')
    er.add_argument('--camera', default=None, help='camera name (default: the first in the rig)')
    er.add_argument('--out', default='registration_overlay.png', help='overlay PNG')
    er.add_argument('--json', help='write the measurements here')
    er.set_defaults(func=cmd_eval_registration)

    rig_cli.add_parsers(sub)
    calib_cli.add_parsers(sub, esub)
    color_cli.add_parsers(sub, esub)
    fusion_cli.add_parsers(sub, esub)

    d = sub.add_parser('demo', help='the pipeline end to end on generated data')
    d.add_argument('--out', default='demo_out')
    d.add_argument('--frames', type=int, default=30)
    d.add_argument('--seed', type=int, default=0)
    d.set_defaults(func=cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (OSError, ValueError, RuntimeError, KeyError) as e:
        print(f'volcap {args.command}: error: {e}', file=sys.stderr)

        return 2


if __name__ == '__main__':
    sys.exit(main())
