"""`volcap run`, `volcap eval fusion` and `volcap fuse-frames`."""
from __future__ import annotations

from volcap_core.files import write_json
from volcap_fusion import VOXEL_SIZE


def cmd_run(args) -> int:
    from .run_graph import RunConfig, run
    cfg = RunConfig(args.bag, args.calibration, args.out, voxel_size=args.voxel, rate=args.rate,
                    composed=args.composed, depth_upsample=args.depth_upsample, full_depth=not args.half_depth,
                    progress=not args.quiet)
    report = run(cfg)
    print('\n'.join(report.lines()))
    return 0 if report.ok else 1


def cmd_eval_fusion(args) -> int:
    from volcap_eval.fusion import evaluate_fusion
    report = evaluate_fusion(args.dir, args.bag, progress=not args.quiet, max_frames=args.frames)
    print(f'{report["frames"]} frames: accuracy {report["accuracy_mm"]:.2f} mm (mean distance to the subject), '
          f'completeness {100 * report["completeness"]:.1f} % of the observable surface within '
          f'{report["completeness_threshold_mm"]:.0f} mm ({100 * report["completeness_all"]:.1f} % of all of it)')
    if args.json:
        write_json(args.json, report)
        print(f'wrote {args.json}')
    return 0


def cmd_fuse_frames(args) -> int:
    from volcap_eval.fusion import fuse_folder
    from volcap_fusion.tsdf import FusionConfig
    cfg = FusionConfig(voxel_size=args.voxel, weight_threshold=args.weight_threshold, depth_max=args.depth_max)
    report = fuse_folder(args.folder, args.intrinsics, cfg, args.out, stride=args.stride)
    c = report['distance_to_bare_open3d']
    print(f'fused {report["frames"]} frames into {args.out} ({report["triangles"]} triangles); against a bare Open3D '
          f'integration of the same frames: mean {c["mean_mm"]:.2f} mm, p95 {c["p95_mm"]:.2f} mm; '
          f'render {report["render"]}')
    return 0


def add_parsers(sub, esub) -> None:
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

    e = esub.add_parser('fusion', help='fused sequence against the synthetic ground truth')
    e.add_argument('dir', help='a volcap run output folder')
    e.add_argument('bag', help='the synthetic bag it was made from')
    e.add_argument('--json', help='write the report here')
    e.add_argument('--frames', type=int, default=None, help='score only the first N frames')
    e.add_argument('--quiet', action='store_true')
    e.set_defaults(func=cmd_eval_fusion)

    f = sub.add_parser('fuse-frames', help='fuse a folder of posed RGB-D frames (frame-NNNNNN.color/depth/pose)')
    f.add_argument('folder')
    f.add_argument('--intrinsics', required=True, help='3x3 intrinsic matrix (text)')
    f.add_argument('--out', required=True, help='mesh PLY (a .json report and .png render are written beside it)')
    f.add_argument('--voxel', type=float, default=0.01)
    f.add_argument('--weight-threshold', type=float, default=1.0)
    f.add_argument('--depth-max', type=float, default=3.0)
    f.add_argument('--stride', type=int, default=1, help='use every Nth frame')
    f.add_argument('--quiet', action='store_true')
    f.set_defaults(func=cmd_fuse_frames)
