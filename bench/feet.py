"""Where the feet go: the lowest part of a synthetic subject followed through the depth sensor,
the depth filter's stages and the fusion, per height band, on one capture frame set.

For every camera, the ground truth's clean depth of the subject gives the surface points each
depth sensor faces; those in a height band (studio frame, above the subject's lowest point) are
followed through:

- the sensor: did it return depth there, and within 1 cm of the truth;
- the flying-pixel filter: is the return kept;
- the foreground mask and the cleaned output: is there depth within 3 cm of the truth in the
  cleaned image (registered to colour);

then the whole set is fused (the graph's defaults, and ``--weight-threshold`` values to compare)
and the share of the observable surface within 5 mm is given per band, as `volcap eval fusion`
scores it, and for the lowest 15 cm together (weighted by observable samples). With
``--eval-depth`` the same filter settings are scored by `volcap eval depth` on every capture frame
set of the bag (flying-pixel recall and precision, valid depth kept, the fills), so a setting's
feet come with what it costs in flying pixels. With ``--ceiling`` the ground truth's clean depth
of the subject is fused the same way (everywhere; only on the pixels the cleaner kept or filled;
the cleaner's own depth there), which shows how much of a loss is the fusion's own, the holes'
and the depth values'. Also
printed: the cleaned output's depth error where it has the surface, and the fused model's
distance to the observable surface, per band.

    python bench/feet.py BAG [--bands 0,0.06,0.09,0.15,0.5] [--weight-threshold 0.5 1.0] [--sparse-radius 0]
        [--eval-depth] [--ceiling]
"""
import argparse
import json
from pathlib import Path

import numpy as np
import open3d as o3d

from volcap_core.camera import depth_to_millimetres
from volcap_core.poses import invert, transform_points
from volcap_eval.depth import evaluate_depth
from volcap_eval.fusion import dropout_rate, observable, surface_samples
from volcap_filter.pipeline import DepthFilterConfig
from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion, raycasting_scene
from volcap_pipeline.replay import cleaned_frame_sets
from volcap_studio.session import GroundTruth


def band_of(heights: np.ndarray, bands: list[float]) -> np.ndarray:
    return np.digitize(heights, bands) - 1      # -1 below the first edge, len(bands)-1 above the last


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('bag')
    ap.add_argument('--bands', default='0,0.06,0.09,0.15,0.5,2.0', help='height band edges (m)')
    ap.add_argument('--weight-threshold', type=float, nargs='+', default=[0.5, 1.0])
    ap.add_argument('--json', default='bench_out/feet.json')
    ap.add_argument('--sparse-radius', type=int, help='the flying-pixel filter\'s sparse_radius (0: before dark '
                    'material\'s sparse returns were kept and closed)')
    ap.add_argument('--eval-depth', action='store_true', help='also score these settings with `volcap eval depth`')
    ap.add_argument('--ceiling', action='store_true', help='also fuse the ground truth\'s clean depth of the subject '
                    '(every faced pixel returned exactly): what the fusion makes of perfect depth')
    ap.add_argument('--complete-radius', type=int, help='the depth filter\'s complete_radius (0: before holes inside '
                    'the foreground mask were completed)')
    ap.add_argument('--complete-extend', type=int, help='the depth filter\'s complete_extend')
    ap.add_argument('--curved-support', type=int, help='the flying-pixel config\'s curved_support (0: holes filled '
                    'and completed by planes only, before 2026-12-07)')
    args = ap.parse_args()
    bands = [float(b) for b in args.bands.split(',')]
    names = [f'{bands[k]:.2f}-{bands[k + 1]:.2f} m' for k in range(len(bands) - 1)]
    gt = GroundTruth(args.bag)
    T_sw = np.asarray(gt.doc['T_studio_world'], float)
    captures = gt.frames_in('capture')
    cfg = DepthFilterConfig()
    if args.sparse_radius is not None:
        cfg.flying.sparse_radius = args.sparse_radius
    if args.complete_radius is not None:
        cfg.complete_radius = args.complete_radius
    if args.complete_extend is not None:
        cfg.complete_extend = args.complete_extend
    if args.curved_support is not None:
        cfg.flying.curved_support = args.curved_support
    fs, cleaned = next(cleaned_frame_sets(args.bag, {'volcap': cfg}, limit=1))
    frame = next(f for f in captures if abs(f['stamp_ns'] - fs.stamp_ns) < 20_000_000)
    arrays = gt.arrays(frame['index'])
    truth = gt.subject_mesh(frame['index'])
    gt_v, gt_t = np.asarray(truth.vertices), np.asarray(truth.triangles)
    floor = transform_points(T_sw, gt_v)[:, 2].min()

    # faced, returned, accurate, kept by the filter, in the output; faced with depth in the output
    # (a return or a fill of the holes between sparse returns)
    stages = np.zeros((len(names), 6), np.int64)
    output_errors = [[] for _ in names]     # |output depth - truth| where the output has the surface
    for cam, c in cleaned['volcap'].items():
        depth_model = c.frame.depth_model
        clean = arrays[f'{cam}/depth_clean']
        v, u = np.nonzero(arrays[f'{cam}/depth_subject'] & (clean > 0))
        points_world = transform_points(gt.T_world_depth(cam), depth_model.pixel_rays()[v, u] * clean[v, u, None])
        band = band_of(transform_points(T_sw, points_world)[:, 2] - floor, bands)
        raw = c.frame.depth[v, u]
        returned = raw > 0
        accurate = returned & (np.abs(raw - clean[v, u]) < 0.01)
        kept = accurate & ~c.result.flying[v, u]
        out_model = c.cleaner.output_model
        local = transform_points(invert(gt.T_world_color(cam)), points_world)
        px = np.round(out_model.project(local)).astype(int)
        inside = (px[:, 0] >= 0) & (px[:, 0] < out_model.width) & (px[:, 1] >= 0) & (px[:, 1] < out_model.height)
        output = np.zeros(len(v), bool)
        error = np.full(len(v), np.inf)
        error[inside] = np.abs(c.result.depth[px[inside, 1], px[inside, 0]] - local[inside, 2])
        output = error < 0.03
        for k in range(len(names)):
            sel = band == k
            stages[k] += [sel.sum(), (sel & returned).sum(), (sel & accurate).sum(), (sel & kept).sum(),
                          (sel & accurate & output).sum(), (sel & output).sum()]
            output_errors[k].append(error[sel & output])

    dropped = gt.arrays(frame['index'], suffix='/dropped')
    sensors = [(rc.depth, gt.T_world_depth(rc.name), rc.color, gt.T_world_color(rc.name),
                dropout_rate(dropped[f'{rc.name}/dropped'])) for rc in gt.rig.cameras]
    tof = gt.doc['config']['tof']
    samples, normals = surface_samples(gt_v, gt_t, 200_000)
    seen = observable(samples, normals, raycasting_scene(gt_v, gt_t), sensors, tof['min_range'], tof['max_range'],
                      tof['grazing_cos'])
    sample_band = band_of(transform_points(T_sw, samples)[:, 2] - floor, bands)
    views = [CameraView(cam, depth_to_millimetres(c.result.depth), c.cleaner.output_model, c.frame.color,
                        c.frame.color_model, T_sw @ gt.T_world_color(cam)) for cam, c in cleaned['volcap'].items()]

    distances = {}

    def covered_per_band(views, threshold, key):
        model = TsdfFusion(FusionConfig(weight_threshold=threshold)).fuse(views, on_floor=True)
        vertices = transform_points(invert(T_sw), model.vertices).astype(np.float32)
        distance = raycasting_scene(vertices, model.triangles).compute_distance(
            o3d.core.Tensor(samples.astype(np.float32))).numpy()
        distances[key] = [distance[seen & (sample_band == k)] for k in range(len(names))]
        return [float((d <= 0.005).mean()) if d.size else None for d in distances[key]]

    fused = {threshold: covered_per_band(views, threshold, threshold) for threshold in args.weight_threshold}
    if args.ceiling:
        # Depth on the depth sensor's grid, posed in its optical frame (the colours come out
        # wrong; the geometry is what is scored): the truth everywhere on the subject; the truth
        # only on the pixels the cleaner kept or filled (its sieve); the cleaner's own values there.
        def depth_grid_views(depth_of):
            return [CameraView(cam, depth_to_millimetres(np.where(arrays[f'{cam}/depth_subject'], depth_of(c, cam), 0)),
                               c.frame.depth_model, c.frame.color, c.frame.color_model, T_sw @ gt.T_world_depth(cam))
                    for cam, c in cleaned['volcap'].items()]

        def filled(c):
            return c.result.filled if c.result.filled is not None else np.zeros_like(c.frame.depth)

        def sieve(c):
            return ((c.frame.depth > 0) & ~c.result.flying) | (filled(c) > 0)
        variants = {'truth': lambda c, cam: arrays[f'{cam}/depth_clean'],
                    'truth on the sieve': lambda c, cam: np.where(sieve(c), arrays[f'{cam}/depth_clean'], 0),
                    'own on the sieve': lambda c, cam: np.where(sieve(c), c.frame.depth + filled(c), 0)}
        for key, depth_of in variants.items():
            fused[key] = covered_per_band(depth_grid_views(depth_of), args.weight_threshold[0], key)
    # where the output has the surface, how close it is; and how far the fused model is from the
    # observable surface (a shoe there but off by more than 5 mm, or missing)
    output_error_mm = [np.round(1000 * np.percentile(np.concatenate(e), [50, 90]), 1).tolist()
                       if sum(x.size for x in e) else None for e in output_errors]
    fused_distance_mm = {str(t): [np.round(1000 * np.percentile(d, [50, 90]), 1).tolist() if d.size else None
                                  for d in ds] for t, ds in distances.items()}

    print(f'{Path(args.bag).name}, capture frame set {frame["index"]}; heights above the subject\'s lowest point')
    columns = list(fused)
    header = 'band          faced  returned  accurate  kept(flying)  in output  covered | observable  ' + '  '.join(
        f'fused@{t:g}' if not isinstance(t, str) else t for t in columns)
    print(header)
    rows = []
    for k, name in enumerate(names):
        faced, returned, accurate, kept, output, covered = (int(x) for x in stages[k])
        observable_k = int((seen & (sample_band == k)).sum())
        pct = lambda a, b: f'{100 * a / b:5.1f} %' if b else '    -  '
        print(f'{name:12s} {faced:6d}  {pct(returned, faced)}  {pct(accurate, returned)}  {pct(kept, accurate)}'
              f'     {pct(output, accurate)}  {pct(covered, faced)} | {observable_k:9d}  ' + '  '.join(
                  f'{100 * fused[t][k]:7.1f} %' if fused[t][k] is not None else '      -  ' for t in columns))
        rows.append({'band': name, 'faced': faced, 'returned': returned, 'accurate': accurate, 'kept_by_flying_filter':
                     kept, 'in_cleaned_output': output, 'covered_in_output': covered, 'observable_samples': observable_k,
                     'fused_within_5mm': {str(t): fused[t][k] for t in columns},
                     'output_error_mm_p50_p90': output_error_mm[k],
                     'fused_distance_mm_p50_p90': {t: d[k] for t, d in fused_distance_mm.items()}})
    print('the output\'s depth where it has the surface, |error| p50 / p90 mm: ' + ', '.join(
        f'{name} {e[0]} / {e[1]}' for name, e in zip(names, output_error_mm) if e))
    t0 = str(args.weight_threshold[0])
    print(f'the observable surface\'s distance to the model fused@{t0}, p50 / p90 mm: ' + ', '.join(
        f'{name} {d[0]} / {d[1]}' for name, d in zip(names, fused_distance_mm[t0]) if d))
    low = [k for k in range(len(names)) if bands[k + 1] <= 0.15 + 1e-9]
    n_low = sum(int((seen & (sample_band == k)).sum()) for k in low)
    lowest_15cm = {str(t): sum(fused[t][k] * int((seen & (sample_band == k)).sum()) for k in low
                               if fused[t][k] is not None) / n_low if n_low else None for t in columns}
    print('the lowest 15 cm, weighted by observable samples: ' + '  '.join(
        f'fused@{t}: {100 * v:.1f} %' for t, v in lowest_15cm.items() if v is not None))
    report = {'bag': args.bag, 'frame': frame['index'], 'sparse_radius': cfg.flying.sparse_radius, 'bands': rows,
              'lowest_15cm_fused_within_5mm': lowest_15cm}
    if args.eval_depth:
        depth = evaluate_depth(args.bag, methods=('volcap',), progress=False, configs={'volcap': cfg})
        report['eval_depth'] = d = depth['methods']['volcap']
        print(f"eval depth on {depth['frames']} frame sets: flying recall {d['flying_recall']}, precision "
              f"{d['flying_precision']}, valid kept {d['valid_kept']}, mask IoU {d['mask_iou']}, depth MAE "
              f"{d['depth_mae_mm']} mm, {d['filled_per_frame']} fills per camera frame at {d['filled_mae_mm']} mm")
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(f'wrote {out}')


if __name__ == '__main__':
    main()
