"""`volcap run`, `volcap eval fusion` and `volcap fuse-frames`."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from volcap_core.files import write_json


def _renders(models: list[tuple[str, object]], poses: list[np.ndarray], path: Path, frame_on=None) -> Path:
    """One row per model: the model from four sides, each framed on itself or all on ``frame_on``."""
    from volcap_filter.figures import write_png
    from volcap_fusion.render import camera_up, orbit_views, turntable
    up = camera_up(poses)
    rows = [turntable(m, orbit_views(m if frame_on is None else frame_on, up), label=label)
            for label, m in models if len(m.triangles)]
    if not rows:
        raise ValueError('nothing to render: every mesh is empty')
    write_png(path, np.vstack(rows))
    return path


def _raw_vs_clean(bag, calibration, cameras: list[str], out: Path, frames: list[dict], voxel: float,
                  poses: list[np.ndarray]) -> Path:
    """Paper 000 Figs. 16/18: the middle frame fused from the raw streams above the graph's
    cleaned-and-corrected fusion of it."""
    from volcap_fusion.evaluate import raw_fusion
    from volcap_fusion.sequence import read_ply
    from volcap_fusion.tsdf import FusionConfig
    frame = frames[len(frames) // 2]
    raw = raw_fusion(bag, frame['stamp_ns'], {c: calibration.T_world_color(c) for c in cameras},
                     FusionConfig(voxel_size=voxel))
    clean = read_ply(out / 'frames' / frame['ply'])
    return _renders([('raw depth + raw colour', raw), ('volcap: cleaned + corrected', clean)], poses,
                    out / 'renders' / 'raw_vs_clean.png', frame_on=clean)


def cmd_run(args) -> int:
    from volcap_core.calibration import Calibration
    from volcap_fusion.sequence import read_manifest, read_ply

    from volcap_fusion.sequence import MANIFEST

    from .run_graph import RunConfig, run_graph
    out = Path(args.out)
    cfg = RunConfig(voxel_size=args.voxel, rate=args.rate, composed=args.composed, depth_upsample=args.depth_upsample,
                    full_depth=not args.half_depth)
    metrics = run_graph(args.bag, args.calibration, out, cfg, progress=not args.quiet)
    frames = read_manifest(out / 'frames') if (out / 'frames' / MANIFEST).exists() else []
    metrics['frames_written'] = len(frames)
    metrics['frames'] = frames
    calibration = Calibration.load(args.calibration)
    poses = [calibration.T_world_color(c) for c in metrics['cameras']]
    if frames:
        picks = sorted({0, len(frames) // 2, len(frames) - 1})
        metrics['renders'] = [str(_renders([(f'frame {k}', read_ply(out / 'frames' / frames[k]['ply']))], poses,
                                           out / 'renders' / f'frame_{k:06d}.png')) for k in picks]
        try:
            metrics['raw_vs_clean'] = str(_raw_vs_clean(args.bag, calibration, metrics['cameras'], out, frames,
                                                        args.voxel, poses))
        except ValueError as e:     # the figure is extra: the sequence and metrics are kept
            metrics['raw_vs_clean_error'] = str(e)
            print(f'no raw-vs-clean figure: {e}')
    write_json(out / 'metrics.json', metrics)
    p = metrics['probe']
    print(f'{len(frames)} of {metrics["capture_frame_sets_in_bag"]} capture frame sets fused into {out / "frames"} '
          f'({metrics["mode"]}); the renderer probe received {p["meshes_received"]} meshes and '
          f'{p["clouds_received"]} clouds')
    if p['latency_ms_median'] is not None:
        print(f'latency from entering the graph to the mesh: median {p["latency_ms_median"]:.0f} ms, '
              f'p95 {p["latency_ms_p95"]:.0f} ms; mesh rate {p["mesh_rate_hz"] or 0:.2f} Hz')
    print(f'metrics: {out / "metrics.json"}  renders: {out / "renders"}')
    bad = {k: c for k, c in metrics['node_exit_codes'].items() if c not in (0, None)}
    if bad:
        print(f'nodes that exited with an error: {bad}')
    return 0 if frames and not bad else 1


def cmd_eval_fusion(args) -> int:
    from volcap_fusion.evaluate import evaluate_fusion
    report = evaluate_fusion(args.dir, args.bag, progress=not args.quiet, max_frames=args.frames)
    print(f'{report["frames"]} frames: accuracy {report["accuracy_mm"]:.2f} mm (mean distance to the subject), '
          f'completeness {100 * report["completeness"]:.1f} % of the observable surface within '
          f'{report["completeness_threshold_mm"]:.0f} mm ({100 * report["completeness_all"]:.1f} % of all of it)')
    if args.json:
        write_json(args.json, report)
        print(f'wrote {args.json}')
    return 0


def cmd_fuse_frames(args) -> int:
    from volcap_fusion.evaluate import fuse_frames, surface_distance
    from volcap_fusion.sequence import write_ply
    from volcap_fusion.tsdf import FusionConfig
    cfg = FusionConfig(voxel_size=args.voxel, weight_threshold=args.weight_threshold, depth_max=args.depth_max)
    t0 = time.monotonic()
    ours, bare, poses = fuse_frames(args.folder, args.intrinsics, cfg, stride=args.stride)
    out = Path(args.out)
    write_ply(out, ours)
    comparison = surface_distance(ours, bare)
    render = _renders([('volcap', ours), ('bare Open3D', bare)], poses, out.with_suffix('.png'))
    report = {'frames': len(poses), 'voxel_size': args.voxel, 'vertices': len(ours.vertices),
              'triangles': len(ours.triangles), 'bare_vertices': len(bare.vertices),
              'distance_to_bare_open3d': comparison, 'seconds': time.monotonic() - t0, 'render': str(render)}
    write_json(out.with_suffix('.json'), report)
    print(f'fused {len(poses)} frames into {out} ({len(ours.triangles)} triangles); against a bare Open3D '
          f'integration of the same frames: mean {comparison["mean_mm"]:.2f} mm, p95 {comparison["p95_mm"]:.2f} mm; '
          f'render {render}')
    return 0


def add_parsers(sub, esub) -> None:
    r = sub.add_parser('run', help='replay a bag through the whole graph and write the volumetric sequence')
    r.add_argument('bag')
    r.add_argument('--calibration', required=True)
    r.add_argument('--out', required=True, help='output folder (frames/, metrics.json, renders/)')
    r.add_argument('--composed', action='store_true', help='run every node in this process')
    r.add_argument('--voxel', type=float, default=0.004, help='TSDF voxel size (m)')
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
