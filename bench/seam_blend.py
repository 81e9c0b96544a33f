"""Colour seams: does blending the cameras by how well each sees a vertex hide them? (issue 30)

The fusion colours a vertex with the TSDF's average: every camera that saw the voxel counts the
same, whatever its angle to the surface and however near its own silhouette. The issue suggests
blending by viewing angle and distance to the depth edge. This bench recolours each fused
model's vertices from the cameras' images with such weights and scores what a viewer sees
(``volcap_fusion.seams``: the model's colour step across the edges where the best camera changes
against every other edge, and the flicker of ``volcap_fusion.stability``):

- visibility: the camera's cleaned depth at the vertex's pixel within the TSDF's truncation of
  the vertex;
- facing: |cos| of the angle between the vertex normal and the camera's ray, to ``--powers``;
- distance to the depth edge: zero next to a hole or a depth step of 2 cm, rising linearly to
  one at ``edge_px`` pixels;
- the TSDF's (carried, time-averaged) colour blended in with ``tsdf_weight`` per unit of the
  cameras' weight (at most one), and alone where no camera sees the vertex.

Turning studios (``volcap synth``, the stability bench's renders), cleaned by the camera
pipeline's own code and fused with the true poses as the graph fuses, each camera's colour
either as recorded or its true colours (``--colours true``: a perfect colour correction, so what
is left is shading that changes with the view and registration).

    python bench/seam_blend.py [--seeds 3 8] [--frames 6] [--colours true|camera]

It is a prototype measured against the fusion, not part of it: docs/benchmarks.md says why.
"""
import argparse
import copy
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stability import commit, studio, truth_frame  # noqa: E402 (bench/ is on the path)

from volcap_core.camera import depth_to_millimetres  # noqa: E402
from volcap_core.poses import invert, matrix_from_list, transform_points  # noqa: E402
from volcap_core.sampling import sample_bilinear  # noqa: E402
from volcap_eval.fusion import true_color_image  # noqa: E402
from volcap_filter.pipeline import DepthFilterConfig  # noqa: E402
from volcap_fusion.seams import SeamView, seam_score, vertex_normals  # noqa: E402
from volcap_fusion.stability import sequence_stability  # noqa: E402
from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion  # noqa: E402
from volcap_pipeline.replay import cleaned_frame_sets  # noqa: E402
from volcap_studio.session import GroundTruth  # noqa: E402

STEP_MM = 20.0      # a depth step that separates surfaces (the fusion's edge_tolerance)
EDGE_LIMIT_PX = 16.0    # the widest ramp of the variants


def edge_distance(depth_mm: np.ndarray, step_mm: float, limit_px: float) -> tuple[np.ndarray, tuple[int, int]]:
    """Distance in pixels (capped at ``limit_px``) from each pixel with depth to the nearest pixel
    without depth or across a depth step of more than ``step_mm`` (+1 %), over the bounding box of
    the depth (its origin returned): a camera's silhouettes and occlusion edges."""
    rows, cols = np.flatnonzero(depth_mm.any(axis=1)), np.flatnonzero(depth_mm.any(axis=0))
    if rows.size == 0:
        return np.zeros((0, 0), np.float32), (0, 0)
    y0, y1, x0, x1 = max(rows[0] - 1, 0), rows[-1] + 2, max(cols[0] - 1, 0), cols[-1] + 2
    d = depth_mm[y0:y1, x0:x1].astype(np.float32)
    valid = d > 0
    # a depth step: a 3x3 neighbour farther than the step (its own depth's 1 % added)
    near = cv2.erode(np.where(valid, d, np.float32(1e9)), np.ones((3, 3), np.uint8))
    far = cv2.dilate(d, np.ones((3, 3), np.uint8))
    inner = valid & (d - near <= step_mm + 0.01 * d) & (far - d <= step_mm + 0.01 * d)
    dist = cv2.distanceTransform(inner.astype(np.uint8), cv2.DIST_L2, 3)
    return np.minimum(dist, np.float32(limit_px)), (x0, y0)


def blend_colors(model, views, edge_maps: list, normals: np.ndarray, trunc_m: float, edge_px: float,
                 tsdf_weight: float, power: float = 2.0) -> np.ndarray:
    """(N, 3) uint8 vertex colours blended from ``views`` (``tsdf.CameraView``s, posed in the
    vertices' frame) with the weights of the module docstring."""
    vertices, tsdf_colors = model.vertices, model.colors
    n = len(vertices)
    if n == 0:
        return tsdf_colors
    total = np.zeros(n, np.float32)
    acc = np.zeros((n, 3), np.float32)
    v = vertices.astype(np.float32)
    for view, (dist, (x0, y0)) in zip(views, edge_maps):
        T = invert(np.asarray(view.T_world_camera, np.float64)).astype(np.float32)
        local = v @ T[:3, :3].T + T[:3, 3]
        z = local[:, 2]
        idx = np.flatnonzero(z > 0.05)
        if not len(idx):
            continue
        dm = view.depth_model
        dpx = dm.project(local[idx])
        u, w = np.rint(dpx[:, 0]).astype(np.int64), np.rint(dpx[:, 1]).astype(np.int64)
        inside = (u >= 0) & (u < dm.width) & (w >= 0) & (w < dm.height)
        idx, dpx, u, w = idx[inside], dpx[inside], u[inside], w[inside]
        seen = view.depth_mm[w, u].astype(np.float32) / 1000.0
        visible = (seen > 0) & (np.abs(z[idx] - seen) <= trunc_m)
        idx, dpx, u, w = idx[visible], dpx[visible], u[visible], w[visible]
        if not len(idx):
            continue
        edge = np.minimum(dist[w - y0, u - x0], np.float32(edge_px)) / np.float32(edge_px)
        ray = local[idx] / np.linalg.norm(local[idx], axis=1, keepdims=True)
        normal = normals[idx] @ T[:3, :3].T
        cos = np.abs(np.sum(normal * ray, axis=1))
        weight = (cos ** power * edge).astype(np.float32)
        keep = weight > 0
        idx, weight = idx[keep], weight[keep]
        cpx = dpx[keep] if view.color_model == dm else view.color_model.project(local[idx])
        colour = sample_bilinear(view.color, cpx).astype(np.float32)
        total[idx] += weight
        acc[idx] += weight[:, None] * colour
    prior = tsdf_weight * np.minimum(total, 1.0) + (total <= 0)
    out = (acc + prior[:, None] * tsdf_colors.astype(np.float32)) / (total + prior)[:, None]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


VARIANTS = {'TSDF average (the fusion)': None,
            'facing^2, edge 8 px, TSDF 0.5': (2.0, 8.0, 0.5),
            'facing^2, edge 16 px, TSDF 0.5': (2.0, 16.0, 0.5),
            'facing^2, edge 8 px, TSDF 2': (2.0, 8.0, 2.0),
            'facing^1, edge 8 px, TSDF 0.5': (1.0, 8.0, 0.5),
            'equal, no edge ramp, no TSDF': (0.0, 1e-3, 0.0),
            'equal, edge 8 px, no TSDF': (0.0, 8.0, 0.0),
            'equal, edge 8 px, TSDF 1': (0.0, 8.0, 1.0)}


def run_studio(bag: Path, colours: str) -> dict:
    gt = GroundTruth(bag)
    T_sw = np.asarray(gt.doc['T_studio_world'], float)
    cfg = FusionConfig()
    fusion = TsdfFusion(cfg)
    sequences = {k: [] for k in VARIANTS}
    seams = {k: [] for k in VARIANTS}
    blend_ms, stamps = [], []
    for fs, cleaned in cleaned_frame_sets(bag, {'default': DepthFilterConfig()}):
        stamps.append(fs.stamp_ns)
        views = []
        for cam, c in cleaned['default'].items():
            color = true_color_image(gt, cam, c.color) if colours == 'true' else c.color
            views.append(CameraView(cam, depth_to_millimetres(c.result.depth), c.cleaner.output_model, color,
                                    c.frame.color_model, T_sw @ gt.T_world_color(cam)))
        model = fusion.fuse(views, on_floor=True)
        t0 = time.perf_counter()
        # shared by every variant: the normals and each camera's distance to its depth edges
        normals = vertex_normals(model) if len(model.triangles) else np.zeros((0, 3))
        edge_maps = [edge_distance(v.depth_mm, STEP_MM, EDGE_LIMIT_PX) for v in views]
        shared_ms = (time.perf_counter() - t0) * 1e3
        seam_views = [SeamView(v.name, v.color, v.color_model, v.T_world_camera) for v in views]
        for name, variant in VARIANTS.items():
            recoloured = copy.copy(model)
            if variant is not None:
                t0 = time.perf_counter()
                recoloured.colors = blend_colors(model, views, edge_maps, normals, cfg.trunc_voxels * cfg.voxel_size,
                                                 variant[1], variant[2], variant[0])
                blend_ms.append(shared_ms + (time.perf_counter() - t0) * 1e3)
            if len(stamps) > 2:         # the filter's first two sets are its average filling
                s = seam_score(recoloured, seam_views)
                seams[name].append((s['model_step_seam_de'], s['model_step_other_de'], s['seam_de']))
            in_world = copy.copy(recoloured)
            in_world.vertices = transform_points(invert(T_sw), recoloured.vertices).astype(np.float32)
            sequences[name].append(in_world)
    poses = {s: matrix_from_list(truth_frame(gt, s)['T_world_subject']) for s in stamps}
    settled = stamps[2:]
    rows = {}
    for name in VARIANTS:
        stability = sequence_stability(sequences[name][2:],
                                       motion=lambda k: poses[settled[k + 1]] @ invert(poses[settled[k]]))
        a = np.asarray(seams[name], float)
        rows[name] = {'step_seam': float(a[:, 0].mean()), 'step_other': float(a[:, 1].mean()),
                      'excess': float(a[:, 0].mean() - a[:, 1].mean()), 'seam_de': float(a[:, 2].mean()),
                      'flicker_de': stability['flicker_de']}
    return {'vertices': int(len(model.vertices)), 'blend_ms': float(np.median(blend_ms)), 'variants': rows}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[3, 8])
    ap.add_argument('--frames', type=int, default=6)
    ap.add_argument('--colours', default='true', choices=('true', 'camera'))
    ap.add_argument('--work', default='bench_out/stability')
    ap.add_argument('--json', default='bench_out/seam_blend.json')
    args = ap.parse_args()
    results = {}
    for seed in args.seeds:
        t0 = time.perf_counter()
        r = run_studio(studio(Path(args.work), seed, args.frames, 'turn'), args.colours)
        results[seed] = r
        print(f'\nseed {seed}, turning, {args.colours} colours ({r["vertices"]} vertices, a blend '
              f'{r["blend_ms"]:.0f} ms a frame set on this machine; {time.perf_counter() - t0:.0f} s)\n')
        print('| vertex colour | step at seams | step elsewhere | excess | cameras apart at seams | flicker |')
        print('|---|---|---|---|---|---|')
        for name, v in r['variants'].items():
            print(f'| {name} | {v["step_seam"]:.2f} | {v["step_other"]:.2f} | {v["excess"]:.2f} | '
                  f'{v["seam_de"]:.2f} | {v["flicker_de"]:.2f} |', flush=True)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'commit': commit(), 'frames': args.frames, 'colours': args.colours,
                               'results': results}, indent=2))
    print(f'wrote {out}')


if __name__ == '__main__':
    main()
