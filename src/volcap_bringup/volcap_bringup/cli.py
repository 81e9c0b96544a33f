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
    volcap wire BAG --calibration calibration.yaml --out WIREBAG
    volcap live --calibration calibration.yaml [--bag BAG | --bag WIREBAG] [--seconds S]
    volcap view DIR | --live [--port 8080]
    volcap operator [--cameras cam0,cam1] [--hz 2] [--web-port 9090]
    volcap eval fusion DIR BAG [--json OUT.json] [--calibration CAL] [--no-seams]
    volcap eval stability DIR [BAG] [--first K] [--frames N]
    volcap fuse-frames FOLDER --intrinsics K.txt --out mesh.ply [--voxel 0.01]
    volcap demo [--out DIR]
"""
from __future__ import annotations

import argparse
import sys
import time

from volcap_core.errors import BadBag, VolcapError
from volcap_core.settings import add_arguments, config_from_args

from . import calib_cli, color_cli, demo_cli, eval_cli, fusion_cli, rig_cli


def cmd_synth(args) -> int:
    from volcap_studio.config import SynthConfig
    from volcap_studio.session import synthesize
    cfg = config_from_args(SynthConfig, args)
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
    from volcap_core.bag_reader import BagReader
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
    # what is readable is listed; the damage is the user's to act on (volcap bag recover): exit 2
    return BadBag.exit_code if readable is not None and bag.damage else 0


def cmd_bag_recover(args) -> int:
    from volcap_core.bag_recovery import recover
    result = recover(args.bag, args.out, args.compression)
    print(f'wrote {args.out}: {result.messages} messages')
    print(f'lost: {result.damage}' if result.damage else f'{args.bag} was whole: nothing lost')
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='volcap', description='volumetric capture pipeline tools')
    sub = p.add_subparsers(dest='command', required=True)

    s = sub.add_parser('synth', help='render a synthetic studio session to a bag with ground truth')
    s.add_argument('--out', required=True, help='bag directory to write')
    from volcap_studio.config import SynthConfig
    add_arguments(s, SynthConfig, ['cameras', 'frames', 'board_poses', 'board_layout', 'background_frames', 'scene',
                                   'seed', 'fps', 'k4a_calibration'])
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

    eval_cli.add_parsers(esub)
    rig_cli.add_parsers(sub)
    calib_cli.add_parsers(sub)
    color_cli.add_parsers(sub)
    fusion_cli.add_parsers(sub)
    demo_cli.add_parsers(sub)

    return p


def main(argv=None) -> int:
    """Runs one command. A user's mistake (``VolcapError``: bad input, bad bag, weak calibration,
    missing device; or a file the system refuses: missing, unreadable, disk full) is one line on
    stderr and the error's exit code (2; 3 for a weak calibration). Anything else is a bug in
    volcap: Python's traceback and exit 1."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except VolcapError as e:
        print(f'volcap {args.command}: error: {e}', file=sys.stderr)
        return e.exit_code
    except OSError as e:
        print(f'volcap {args.command}: error: {e}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
