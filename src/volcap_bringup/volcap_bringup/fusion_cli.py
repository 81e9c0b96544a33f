"""`volcap run`, `volcap wire`, `volcap live`, `volcap view`, `volcap operator` and `volcap fuse-frames`."""
from __future__ import annotations

from pathlib import Path

from volcap_core.errors import BadInput
from volcap_core.files import write_json
from volcap_core.settings import add_arguments, config_from_args
from volcap_fusion.config import FusionConfig
from volcap_pipeline import FOLDER_FUSION

from .graph import LiveConfig, RunConfig


def cmd_run(args) -> int:
    from .run_graph import run
    cfg = config_from_args(RunConfig, args, bag=args.bag, calibration=args.calibration, out=args.out,
                           progress=not args.quiet)
    report = run(cfg)
    print('\n'.join(report.lines()))
    return 0 if report.ok else 1


def cmd_wire(args) -> int:
    from volcap_pipeline.wire_bag import WireBagConfig, record_wire, wire_summary
    cfg = config_from_args(WireBagConfig, args, bag=args.bag, calibration=args.calibration, out=args.out,
                           progress=not args.quiet)
    report = record_wire(cfg)
    print(wire_summary(report))
    print(f'per camera and frame (ms): {report.ms_per_camera_frame}')
    print(f'play it to the fusion host alone: volcap live --bag {report.path} --calibration {args.calibration}')
    return 0


def cmd_live(args) -> int:
    from .live import run_live, summary_figures
    from .live_controller import LiveController
    cfg = config_from_args(LiveConfig, args, calibration=args.calibration,
                           cameras=args.cameras.split(',') if args.cameras else None)
    result = run_live(cfg, on_summary=None if args.quiet else lambda s: print(LiveController.line(s), flush=True))
    result['figures'] = summary_figures(result['summaries'], cfg.warmup_s)
    f = result['figures']
    if f['meshes_per_s'] is not None:
        print(f'after the {cfg.warmup_s:.0f} s warm-up: {f["meshes_per_s"]:.2f} meshes/s from {f["input_fps"]:.1f} '
              f'sets/s in, {100 * (f["complete_share"] or 0):.0f} % fused from every camera, latency p95 '
              f'{f["latency_ms_p95_max"] or 0:.0f} ms at most')
    if args.json:
        write_json(args.json, result)
        print(f'wrote {args.json}')
    failed = {n: c for n, c in result['node_exit_codes'].items() if c not in (0, None)}
    if failed:
        print(f'nodes that exited with an error: {failed}')
    return 1 if failed else 0


def cmd_view(args) -> int:
    from .view import ViewConfig, run_view
    if not args.live and not args.folder:
        raise BadInput('give a sequence folder (DIR/frames of `volcap run --out DIR`) or --live')

    def ready(url: str) -> None:
        what = 'the newest mesh on /volcap/mesh/glb' if args.live else f'the sequence in {args.folder}'
        print(f'volcap view: open {url} ({what}); Ctrl-C stops', flush=True)
    run_view(ViewConfig(Path(args.folder) if args.folder else None, args.live, args.host, args.port, args.ws_port),
             ready)
    return 0


def cmd_operator(args) -> int:
    from volcap_core.topics import camera_names

    from .operator_view import OperatorConfig, run_operator
    cameras = tuple(c for c in args.cameras.split(',') if c) if args.cameras else tuple(camera_names(args.n))
    cfg = OperatorConfig(cameras, args.hz, color_transport=args.color_transport, web_port=args.web_port,
                         grpc_port=args.grpc_port)
    run_operator(cfg, lambda url: print(f'volcap operator: open {url} ({len(cameras)} cameras at {args.hz:g} Hz, '
                                        'the fused model); Ctrl-C stops', flush=True))
    return 0


def cmd_fuse_frames(args) -> int:
    from volcap_pipeline.rig import fuse_folder
    intrinsics = args.intrinsics or str(Path(args.folder) / 'intrinsics.K.txt')
    cfg = config_from_args(FusionConfig, args, defaults=FOLDER_FUSION)
    report = fuse_folder(args.folder, intrinsics, cfg, args.out, stride=args.stride)
    c = report['distance_to_bare_open3d']
    print(f'fused {report["frames"]} frames into {args.out} ({report["triangles"]} triangles), capture volume from '
          f'the {report["capture_volume"]}: {100 * report["depth_left_out"]:.1f} % of the depth left out; '
          f'{100 * report["depth_within_2cm"]:.1f} % of the depth points within 2 cm of the mesh (bare Open3D '
          f'{100 * report["bare_depth_within_2cm"]:.1f} %); against the bare Open3D mesh: mean {c["mean_mm"]:.2f} mm, '
          f'p95 {c["p95_mm"]:.2f} mm; render {report["render"]}')
    return 0


def add_parsers(sub) -> None:
    r = sub.add_parser('run', help='replay a bag through the whole graph and write the volumetric sequence')
    r.add_argument('bag')
    r.add_argument('--calibration', required=True)
    r.add_argument('--out', required=True, help='output folder (frames/, metrics.json, renders/)')
    add_arguments(r, RunConfig)
    r.add_argument('--quiet', action='store_true')
    r.set_defaults(func=cmd_run)

    from volcap_pipeline.wire_bag import WireBagConfig
    w = sub.add_parser('wire', help='run every camera\'s pipeline over a raw bag and record the compact wire the '
                                    'camera hosts send the fusion host (volcap live --bag plays it to the fusion '
                                    'host alone)')
    w.add_argument('bag')
    w.add_argument('--calibration', required=True)
    w.add_argument('--out', required=True, help='wire bag directory to create')
    add_arguments(w, WireBagConfig)
    w.add_argument('--quiet', action='store_true')
    w.set_defaults(func=cmd_wire)

    live = sub.add_parser('live', help='the graph on live topics (camera drivers, or a bag looped at real time), '
                                       'kept real time by admitting only the frame sets it can process')
    live.add_argument('--calibration', required=True)
    live.add_argument('--cameras', help='comma-separated camera namespaces (default: the calibration\'s)')
    add_arguments(live, LiveConfig)
    live.add_argument('--json', help='write every second\'s figures here at the end')
    live.add_argument('--quiet', action='store_true')
    live.set_defaults(func=cmd_live)

    v = sub.add_parser('view', help='play a fused sequence (or the live mesh) in the browser: three.js on localhost')
    v.add_argument('folder', nargs='?', help='sequence folder (sequence.jsonl; DIR/frames of volcap run)')
    v.add_argument('--live', action='store_true', help='show the newest mesh of a running graph (volcap/mesh/glb)')
    v.add_argument('--host', default='127.0.0.1', help='address to serve on (default: this machine only)')
    v.add_argument('--port', type=int, default=8080, help='HTTP port of the page')
    v.add_argument('--ws-port', type=int, default=0, help='WebSocket port of --live (default: port + 1)')
    v.set_defaults(func=cmd_view)

    o = sub.add_parser('operator', help="the operator's live view: camera images, cleaned depth and the fused "
                       'model in Rerun\'s web viewer, served on localhost')
    o.add_argument('--cameras', default='', help='comma-separated camera namespaces (default: cam0..cam<n-1>)')
    o.add_argument('--n', type=int, default=8, help='number of cameras when --cameras is not given')
    o.add_argument('--hz', type=float, default=2.0, help='frames forwarded per stream and second')
    o.add_argument('--color-transport', choices=('raw', 'compressed'), default='raw')
    o.add_argument('--web-port', type=int, default=9090)
    o.add_argument('--grpc-port', type=int, default=9876)
    o.set_defaults(func=cmd_operator)

    f = sub.add_parser('fuse-frames', help='fuse a folder of posed RGB-D frames (frame-NNNNNN.color/depth/pose)')
    f.add_argument('folder')
    f.add_argument('--intrinsics', help='3x3 intrinsic matrix (text; default FOLDER/intrinsics.K.txt)')
    f.add_argument('--out', required=True, help='mesh PLY (a .json report and .png render are written beside it)')
    add_arguments(f, FusionConfig, ['voxel_size', 'weight_threshold', 'depth_max', 'capture_volume', 'box_size',
                                    'box_center'], defaults=FOLDER_FUSION)
    f.add_argument('--stride', type=int, default=1, help='use every Nth frame')
    f.add_argument('--quiet', action='store_true')
    f.set_defaults(func=cmd_fuse_frames)
