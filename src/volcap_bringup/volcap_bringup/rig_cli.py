"""`volcap rig` (a rig description from the camera makers' factory data) and `volcap monitor`
(the live rig's health in the terminal and on /volcap/diagnostics).

    volcap rig --k4a cam0=front.json --k4a cam1=back.json --out rig.yaml
    volcap rig --orbbec cam0=depth_to_color.yaml,color_info.yaml,depth_info.yaml --out rig.yaml
    volcap rig --bag drivers_recording --out rig.yaml
    volcap monitor --cameras 8 --driver azure_kinect [--seconds 60] [--json health.json]
"""
from __future__ import annotations

import math
import time
from pathlib import Path

from volcap_core.errors import BadInput


def _named(spec: str, option: str) -> tuple[str, str]:
    name, sep, value = spec.partition('=')
    if not sep or not name or not value:
        raise BadInput(f'{option} takes CAMERA=VALUE, got {spec!r}')
    return name, value


def cmd_rig(args) -> int:
    from volcap_core.bag_reader import BagReader
    from volcap_core.files import atomic_write
    from volcap_core.frames import read_rig
    from volcap_core.rig import Rig, rig_camera_from_k4a, rig_camera_from_orbbec

    cameras = []
    for spec in args.k4a:
        name, path = _named(spec, '--k4a')
        cameras.append(rig_camera_from_k4a(Path(path), name, args.color_mode, args.depth_mode))
    for spec in args.orbbec:
        name, files = _named(spec, '--orbbec')
        paths = files.split(',')
        if len(paths) != 3:
            raise BadInput('--orbbec takes CAMERA=DEPTH_TO_COLOR.yaml,COLOR_INFO.yaml,DEPTH_INFO.yaml')
        cameras.append(rig_camera_from_orbbec(name, *(Path(p) for p in paths)))
    if args.bag:
        with BagReader(args.bag) as reader:
            cameras += read_rig(reader).cameras
    if not cameras:
        raise BadInput('give at least one --k4a, --orbbec or --bag')
    rig = Rig(cameras, name=args.name)
    atomic_write(args.out, lambda f: f.write(rig.to_yaml()), binary=False)
    for cam in rig.cameras:
        t = cam.T_color_depth[:3, 3] * 1000
        print(f'{cam.name}: colour {cam.color.width}x{cam.color.height}, depth {cam.depth.width}x{cam.depth.height}, '
              f'depth-to-colour translation ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) mm')
    print(f'wrote {args.out}: pass it as rig_file to depth_filter and calibration_service, or put it into a bag '
          'folder as rig.yaml')
    return 0


def cmd_monitor(args) -> int:
    from rich.console import Console
    from rich.live import Live

    from volcap_core.files import write_json

    from .monitor import RigMonitor, health_table
    from .session import GraphSession

    cameras = [f'cam{i}' for i in range(int(args.cameras[0]))] if len(args.cameras) == 1 and \
        args.cameras[0].isdigit() else list(args.cameras)
    console = Console()
    with GraphSession('volcap_monitor_cli') as session:
        node = session.host(RigMonitor(cameras, args.driver, args.registered,
                                       'compressed' if args.color_format == 'jpeg' else 'raw', args.window))
        end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
        try:
            with Live(health_table(node.report), console=console, refresh_per_second=2,
                      auto_refresh=False, transient=False) as live:
                next_draw = 0.0
                while time.monotonic() < end:
                    session.spin_once(0.1)
                    if time.monotonic() >= next_draw:
                        live.update(health_table(node.health.report(time.time_ns())), refresh=True)
                        next_draw = time.monotonic() + 1.0
        except KeyboardInterrupt:
            pass
        report = node.health.report(time.time_ns())
    for warning in report.warnings:
        console.print(f'[yellow]warning:[/yellow] {warning}')
    if args.json:
        write_json(args.json, report.to_dict())
    return 0


def add_parsers(sub) -> None:
    r = sub.add_parser('rig', help='a rig description (rig.yaml) from Azure Kinect or Orbbec factory data')
    r.add_argument('--k4a', '--from-k4a', dest='k4a', action='append', default=[], metavar='CAMERA=calibration.json',
                   help='an Azure Kinect factory calibration (k4arecorder attachment or device dump); repeatable')
    r.add_argument('--color-mode', default='720P', help='Azure Kinect colour mode of --k4a cameras')
    r.add_argument('--depth-mode', default='NFOV_UNBINNED', help='Azure Kinect depth mode of --k4a cameras')
    r.add_argument('--orbbec', '--from-orbbec', dest='orbbec', action='append', default=[],
                   metavar='CAMERA=depth_to_color.yaml,color_info.yaml,depth_info.yaml',
                   help='OrbbecSDK_ROS2 topics saved with `ros2 topic echo --once` (enable_publish_extrinsic:=true '
                        'for depth_to_color); repeatable')
    r.add_argument('--bag', '--from-bag', dest='bag', help='a recording of the drivers: camera_info and /tf_static of every camera')
    r.add_argument('--name', default='volcap', help='rig name')
    r.add_argument('--out', required=True, help='rig YAML to write')
    r.set_defaults(func=cmd_rig)

    m = sub.add_parser('monitor', help='live per-camera rate, drops, colour-depth offset and drift')
    m.add_argument('--cameras', nargs='+', default=['8'], help='camera namespaces, or their number (cam0..)')
    m.add_argument('--driver', default='volcap', choices=('volcap', 'azure_kinect', 'orbbec'),
                   help='whose topics the cameras publish')
    m.add_argument('--registered', action='store_true', help='the driver publishes depth registered to colour')
    m.add_argument('--color-format', default='raw', choices=('raw', 'jpeg'))
    m.add_argument('--window', type=float, default=10.0, help='seconds of stamps each figure is computed over')
    m.add_argument('--seconds', type=float, default=0.0, help='stop after this long (0: at Ctrl-C)')
    m.add_argument('--json', help='write the last health report here')
    m.set_defaults(func=cmd_monitor)
