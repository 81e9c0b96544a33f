"""`volcap run`, `volcap live`, `volcap view`, `volcap operator` and `volcap fuse-frames`."""
from __future__ import annotations

from pathlib import Path

from volcap_core.errors import BadInput
from volcap_core.files import write_json
from volcap_fusion import VOXEL_SIZE

from .graph import DRIVERS


def cmd_run(args) -> int:
    from .run_graph import RunConfig, run
    cfg = RunConfig(args.bag, args.calibration, args.out, voxel_size=args.voxel, rate=args.rate,
                    composed=args.composed, depth_upsample=args.depth_upsample, full_depth=not args.half_depth,
                    progress=not args.quiet)
    report = run(cfg)
    print('\n'.join(report.lines()))
    return 0 if report.ok else 1


def cmd_live(args) -> int:
    from .live import LiveConfig, run_live, summary_figures
    from .live_controller import LiveController
    cfg = LiveConfig(args.calibration, bag=args.bag, driver=args.driver, registered=args.registered,
                     color_format=args.color_format, cameras=args.cameras.split(',') if args.cameras else None,
                     voxel_size=args.voxel, depth_scale=args.depth_scale, every=args.every,
                     latency_budget_ms=args.latency_budget_ms, composed=args.composed, output_dir=args.output_dir or '',
                     rig_file=args.rig_file or '', seconds=args.seconds, warmup_s=args.warmup,
                     source_nice=args.source_nice, rate=args.rate)
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
    from volcap_fusion.tsdf import FusionConfig
    from volcap_pipeline.rig import fuse_folder
    intrinsics = args.intrinsics or str(Path(args.folder) / 'intrinsics.K.txt')
    box = {'box_center': tuple(args.box_center)} if args.box_center else {}
    cfg = FusionConfig(voxel_size=args.voxel, weight_threshold=args.weight_threshold, depth_max=args.depth_max,
                       capture_volume=args.capture_volume, box_size=tuple(args.box_size), **box)
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
    r.add_argument('--composed', action='store_true', help='run every node in this process')
    r.add_argument('--voxel', type=float, default=VOXEL_SIZE, help='TSDF voxel size (m)')
    r.add_argument('--depth-upsample', type=int, default=1, help='depth resampled this many times finer')
    r.add_argument('--half-depth', action='store_true',
                   help="clean depth at the filter's default half colour size (less to clean and send, coarser)")
    r.add_argument('--rate', type=float, default=0.04,
                   help='playback speed; the graph must keep up to fuse every frame set (2 cores: 0.04, '
                        'about 1.2 frame sets/s)')
    r.add_argument('--quiet', action='store_true')
    r.set_defaults(func=cmd_run)

    live = sub.add_parser('live', help='the graph on live topics (camera drivers, or a bag looped at real time), '
                                       'kept real time by admitting only the frame sets it can process')
    live.add_argument('--calibration', required=True)
    live.add_argument('--bag', help='loop this bag at real time with fresh stamps instead of camera drivers')
    live.add_argument('--driver', default='volcap', choices=DRIVERS, help="whose topics the cameras publish")
    live.add_argument('--registered', action='store_true', help='the driver registers depth to colour')
    live.add_argument('--color-format', default='raw', choices=('raw', 'jpeg'))
    live.add_argument('--rig-file', help='rig description YAML for the depth-to-colour extrinsic')
    live.add_argument('--rate', type=float, default=1.0, help='with --bag, its playback speed (1: real time)')
    live.add_argument('--source-nice', type=int, default=0,
                      help="with --bag, the player's niceness (e.g. 10: it yields the CPU to the graph, as "
                           "drivers on cores of their own would)")
    live.add_argument('--cameras', help='comma-separated camera namespaces (default: the calibration\'s)')
    live.add_argument('--voxel', type=float, default=0.01, help='TSDF voxel size (m)')
    live.add_argument('--depth-scale', type=float, default=0.5, help='cleaned depth size as a fraction of colour')
    live.add_argument('--every', type=int, default=0, help='admit one frame set in N (0: from the measured load)')
    live.add_argument('--latency-budget-ms', type=float, default=1000.0)
    live.add_argument('--composed', action='store_true', help='run every node in this process')
    live.add_argument('--output-dir', help='also write the sequence here')
    live.add_argument('--seconds', type=float, help='stop after this long (default: Ctrl-C)')
    live.add_argument('--warmup', type=float, default=10.0, help='seconds left out of the final figures')
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
    f.add_argument('--voxel', type=float, default=0.01)
    f.add_argument('--weight-threshold', type=float, default=1.0)
    f.add_argument('--depth-max', type=float, default=6.5, help='depth beyond this is not fused (m)')
    f.add_argument('--capture-volume', choices=('auto', 'data'), default='auto',
                   help='auto: a --box-size box where the cameras converge, else the bounds of all depth; '
                        'data: always the bounds of all depth')
    f.add_argument('--box-size', type=float, nargs=3, default=(2.6, 2.6, 2.6), metavar=('X', 'Y', 'Z'))
    f.add_argument('--box-center', type=float, nargs=3, metavar=('X', 'Y', 'Z'),
                   help='a fixed capture box centre (world frame of the poses)')
    f.add_argument('--stride', type=int, default=1, help='use every Nth frame')
    f.add_argument('--quiet', action='store_true')
    f.set_defaults(func=cmd_fuse_frames)
