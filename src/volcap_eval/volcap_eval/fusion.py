"""Scores of fused sequences and the fusion of posed RGB-D frame folders.

`volcap eval fusion DIR BAG`: each fused frame of ``DIR/frames`` is matched by capture stamp
to the synthetic bag's ground truth, and scored against the subject mesh at that instant:

- accuracy: mean distance (mm) from the fused mesh's vertices to the ground-truth surface;
- completeness: the fraction of the *observable* ground-truth surface within 5 mm of the fused
  mesh. Observable means that at least one camera's depth sensor sees the point (inside its
  image and range, not occluded, not at a grazing angle beyond what the sensor measures, not on
  a surface too dark in the infrared for the sensor to return depth from most of it) and the
  point lies in that camera's colour image (the cleaned depth is registered to colour). The
  synthetic subject is a union of overlapping solids whose inner faces no camera can see, and
  the soles rest on the floor; ``completeness_all`` scores the whole mesh for reference;
- completeness_feet: the same over the lowest 15 cm of the subject (gravity frame), where the
  floor meets the feet and cleaning is hardest.

- seams (``volcap_fusion.seams``): where the model passes from one camera's best view to
  another's, CIEDE2000 between the colours the two cameras give the same vertex. The cameras'
  colours are the bag's images through the colour models of the calibration the run used (its
  ``metrics.json`` names it; ``calibration`` overrides), posed by the ground truth; beside it the
  same with every camera's true colours (its recorded response inverted), the part no colour
  correction can remove (shading that changes with the view, colour-to-depth registration).

The fused frames are in the studio frame; the sequence header's ``T_world_frame`` takes them
back to the ground truth's world frame.

The fusion itself (`volcap fuse-frames`, the raw-vs-clean figure's raw fusion) is the rig
pipeline's: ``volcap_pipeline.rig``.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from tqdm import tqdm

from volcap_core.calibration import Calibration
from volcap_core.camera import CameraModel
from volcap_core.color import ColorModel
from volcap_core.errors import BadInput
from volcap_core.frames import frame_sets
from volcap_core.poses import invert, transform_points
from volcap_core.topics import CAPTURE
from volcap_fusion.seams import SeamView, seam_score
from volcap_fusion.sequence import T_world_frame, read_ply, read_sequence
from volcap_fusion.tsdf import (
    FusedModel,
    raycasting_scene,
)

COMPLETENESS_MM = 5.0
FEET_M = 0.15               # the lowest this much of the subject is scored on its own (feet, floor contact)
DROPOUT_WINDOW_PX = 7       # neighbourhood over which a sensor's dropout rate is judged
MAX_DROPOUT_RATE = 0.5      # a point is unmeasurable where the sensor drops most returns around it


def surface_samples(vertices: np.ndarray, triangles: np.ndarray, count: int, seed: int = 0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points spread uniformly by area over a mesh, and their face normals."""
    rng = np.random.default_rng(seed)
    a, b, c = (vertices[triangles[:, k]].astype(np.float64) for k in range(3))
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    faces = rng.choice(len(triangles), count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    points = (1 - s)[:, None] * a[faces] + (s * (1 - r2))[:, None] * b[faces] + (s * r2)[:, None] * c[faces]
    normals = cross[faces] / np.maximum(area[faces], 1e-12)[:, None]
    return points, normals


def dropout_rate(dropped: np.ndarray) -> np.ndarray:
    """Local fraction of a depth image's pixels for which the sensor returned nothing (dark
    material, grazing angle), over ``DROPOUT_WINDOW_PX`` squares."""
    return cv2.blur(dropped.astype(np.float32), (DROPOUT_WINDOW_PX, DROPOUT_WINDOW_PX))


def observable(points: np.ndarray, normals: np.ndarray, scene: o3d.t.geometry.RaycastingScene,
               sensors: list[tuple[CameraModel, np.ndarray, CameraModel, np.ndarray, np.ndarray | None]],
               min_range: float, max_range: float, grazing_cos: float) -> np.ndarray:
    """Which points some camera measures: ``sensors`` holds per camera (depth model,
    T_world_depth, colour model, T_world_color, the depth image's ``dropout_rate`` or None)."""
    seen = np.zeros(len(points), bool)
    for depth_model, T_wd, color_model, T_wc, dropouts in sensors:
        eye = T_wd[:3, 3]
        ray = points - eye
        dist = np.linalg.norm(ray, axis=1)
        ray /= dist[:, None]
        ok = (dist >= min_range) & (dist <= max_range)
        ok &= np.abs(np.sum(normals * ray, axis=1)) >= grazing_cos     # meshes' normals may face either way
        for model, T, rates in ((depth_model, T_wd, dropouts), (color_model, T_wc, None)):
            T_local = invert(T)
            local = points @ T_local[:3, :3].T + T_local[:3, 3]
            front = local[:, 2] > 0.05
            px = np.full((len(points), 2), -1.0)
            px[front] = model.project(local[front])
            ok &= front & (px[:, 0] >= 0) & (px[:, 0] <= model.width - 1) & (px[:, 1] >= 0) \
                & (px[:, 1] <= model.height - 1)
            if rates is not None:
                u, v = (np.round(px[ok, k]).astype(np.int64) for k in (0, 1))
                ok[ok] = rates[v, u] < MAX_DROPOUT_RATE
        rays = np.concatenate([np.broadcast_to(eye, ray.shape), ray], axis=1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))['t_hit'].numpy()
        ok &= hit >= dist - 0.002
        seen |= ok
    return seen


def score_frame(model: FusedModel, truth: o3d.geometry.TriangleMesh, sensors, tof: dict, samples: int = 200_000,
                T_studio_world: np.ndarray | None = None) -> dict:
    """Accuracy and completeness of one fused frame against its ground-truth mesh (both in the
    world frame). With ``T_studio_world`` (gravity: +Z up) the lowest ``FEET_M`` of the subject
    (feet and floor contact) is also scored on its own: ``completeness_feet``."""
    gt_v, gt_t = np.asarray(truth.vertices), np.asarray(truth.triangles)
    gt_scene = raycasting_scene(gt_v, gt_t)
    if len(model.vertices) == 0:
        return {'accuracy_mm': None, 'completeness': 0.0, 'completeness_all': 0.0,
                'completeness_feet': 0.0 if T_studio_world is not None else None, 'vertices': 0}
    d_fused = gt_scene.compute_distance(o3d.core.Tensor(model.vertices.astype(np.float32))).numpy()
    points, normals = surface_samples(gt_v, gt_t, samples)
    seen = observable(points, normals, gt_scene, sensors, tof['min_range'], tof['max_range'], tof['grazing_cos'])
    d_truth = model.raycasting_scene().compute_distance(
        o3d.core.Tensor(points.astype(np.float32))).numpy()
    close = d_truth <= COMPLETENESS_MM / 1000
    feet = {}
    if T_studio_world is not None:
        height = transform_points(T_studio_world, points)[:, 2]
        low = seen & (height < transform_points(T_studio_world, gt_v)[:, 2].min() + FEET_M)
        feet = {'completeness_feet': float(close[low].mean()) if low.any() else None}
    return {'accuracy_mm': float(d_fused.mean() * 1000), 'accuracy_median_mm': float(np.median(d_fused) * 1000),
            'accuracy_p90_mm': float(np.percentile(d_fused, 90) * 1000), **feet,
            'completeness': float(close[seen].mean()) if seen.any() else 0.0,
            'completeness_all': float(close.mean()), 'observable_fraction': float(seen.mean()),
            'vertices': int(len(model.vertices))}


STAMP_TOLERANCE_NS = 20_000_000    # a fused frame and the bag's frame set it came from


def run_calibration(run_dir: str | Path) -> Calibration | None:
    """The calibration a `volcap run` used, as its ``metrics.json`` names it (None: not recorded
    or no longer there)."""
    metrics = Path(run_dir) / 'metrics.json'
    try:
        path = json.loads(metrics.read_text()).get('calibration')
    except (OSError, ValueError):
        return None
    return Calibration.load(path) if path and Path(path).exists() else None


def true_color_image(gt, camera: str, rgb: np.ndarray) -> np.ndarray:
    """What the ideal camera would have recorded where ``camera`` recorded ``rgb`` (uint8)."""
    h, w = rgb.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    true = gt.color_response(camera).true_colors(rgb.reshape(-1, 3) / 255.0, pixels, (w, h))
    return np.round(true * 255).astype(np.uint8).reshape(h, w, 3)


def frame_seams(bag: str | Path, entries: list[dict], models, gt, calibration: Calibration | None,
                progress: bool = True) -> list[dict]:
    """Per fused frame (``models`` yields them in ``entries``' order, in the world frame), the
    seam score against the bag's colour images of its frame set (module docstring)."""
    rig = gt.rig
    color_models = {c.name: calibration.cameras[c.name].color for c in rig.cameras
                    if calibration is not None and c.name in calibration.cameras}
    correct = {n: ColorModel.from_dict(d) for n, d in color_models.items() if d}
    wanted = iter(zip(entries, models))
    entry, model = next(wanted, (None, None))
    rows = []
    bar = tqdm(total=len(entries), desc='seams', unit='frame', disable=not progress)
    for fs in frame_sets(bag, phases=(CAPTURE,)):
        while entry is not None and entry['stamp_ns'] < fs.stamp_ns - STAMP_TOLERANCE_NS:
            rows.append({'index': entry['index'], 'seam_de': None})        # its frame set is not in the bag
            entry, model = next(wanted, (None, None))
        if entry is None:
            break
        if abs(entry['stamp_ns'] - fs.stamp_ns) > STAMP_TOLERANCE_NS:
            continue
        views = [SeamView(c.name, correct[c.name].apply_image(fs.cameras[c.name].color) if c.name in correct
                          else fs.cameras[c.name].color, c.color, gt.T_world_color(c.name),
                          reference=true_color_image(gt, c.name, fs.cameras[c.name].color))
                 for c in rig.cameras if c.name in fs.cameras]
        rows.append({'index': entry['index'], **seam_score(model, views)})
        bar.update()
        entry, model = next(wanted, (None, None))
    bar.close()
    return rows


def evaluate_fusion(run_dir: str | Path, bag: str | Path, progress: bool = True, max_frames: int | None = None,
                    seams: bool = True, calibration: Calibration | None = None) -> dict:
    from volcap_studio.session import GroundTruth
    gt = GroundTruth(bag)
    frames_dir = Path(run_dir) / 'frames'
    headers, entries = read_sequence(frames_dir)
    if max_frames:
        entries = entries[:max_frames]
    by_stamp = {f['stamp_ns']: f for f in gt.frames if 'T_world_subject' in f}
    stamps = np.array(sorted(by_stamp), dtype=np.int64)
    if not entries or not len(stamps):
        raise BadInput(f'nothing to score: {len(entries)} fused frames, {len(stamps)} ground-truth subject frames')
    rig = gt.rig
    tof = gt.doc['config']['tof']
    per_frame = []
    for entry in tqdm(entries, desc='scoring fused frames', unit='frame', disable=not progress):
        nearest = int(stamps[np.argmin(np.abs(stamps - entry['stamp_ns']))])
        if abs(nearest - entry['stamp_ns']) > STAMP_TOLERANCE_NS:
            raise BadInput(f'fused frame {entry["index"]} (stamp {entry["stamp_ns"]}) has no ground-truth frame')
        index = by_stamp[nearest]['index']
        truth = gt.subject_mesh(index)
        dropped = gt.arrays(index, suffix='/dropped')
        sensors = [(c.depth, gt.T_world_depth(c.name), c.color, gt.T_world_color(c.name),
                    dropout_rate(dropped[f'{c.name}/dropped'])) for c in rig.cameras]
        fused = read_ply(frames_dir / entry['ply'])
        T = T_world_frame(headers, entry['index'])       # the sequence's frame (studio) -> world
        fused.vertices = transform_points(T, fused.vertices).astype(np.float32)
        row = score_frame(fused, truth, sensors, tof, T_studio_world=np.asarray(gt.doc['T_studio_world'], float))
        per_frame.append({'index': entry['index'], 'stamp_ns': entry['stamp_ns'], **row})
    acc = [r['accuracy_mm'] for r in per_frame if r['accuracy_mm'] is not None]
    feet = [r['completeness_feet'] for r in per_frame if r.get('completeness_feet') is not None]
    seam = {}
    if seams:
        calibration = calibration if calibration is not None else run_calibration(run_dir)

        def world_models():
            for e in entries:
                model = read_ply(frames_dir / e['ply'])
                model.vertices = transform_points(T_world_frame(headers, e['index']), model.vertices).astype(np.float32)
                yield model
        rows = frame_seams(bag, entries, world_models(), gt, calibration, progress)
        scored = [r for r in rows if r['seam_de'] is not None]

        def mean(key):
            values = [r[key] for r in scored if r.get(key) is not None]
            return float(np.mean(values)) if values else None
        seam = {'seams': {'seam_de': mean('seam_de'), 'seam_de_true_colours': mean('seam_de_reference'),
                          'model_step_seam_de': mean('model_step_seam_de'),
                          'model_step_other_de': mean('model_step_other_de'), 'seam_share': mean('seam_share'),
                          'colours': 'through the calibration\'s colour models' if calibration is not None
                          else 'as recorded (no calibration: the run\'s is not recorded or gone)',
                          'frames': len(scored), 'per_frame': rows}}
    return {'accuracy_mm': float(np.mean(acc)) if acc else None,
            'completeness': float(np.mean([r['completeness'] for r in per_frame])),
            'completeness_feet': float(np.mean(feet)) if feet else None, 'feet_m': FEET_M,
            'completeness_all': float(np.mean([r['completeness_all'] for r in per_frame])),
            'completeness_threshold_mm': COMPLETENESS_MM, 'frames': len(per_frame), 'per_frame': per_frame, **seam}


def format_seams(seams: dict) -> str:
    """One line for ``evaluate_fusion``'s ``seams``."""
    if seams['seam_de'] is None:
        return 'seams: none found (no vertex where the best camera changes)'
    other = seams['model_step_other_de']
    elsewhere = f', elsewhere {other:.2f}' if other is not None else ''
    true = seams.get('seam_de_true_colours')
    floor = f' (the cameras\' true colours: {true:.2f})' if true is not None else ''
    return (f'seams: {seams["seam_de"]:.2f} CIEDE2000 between the colours two cameras give a vertex where the best '
            f'view changes{floor}, on {100 * seams["seam_share"]:.1f} % of the seen vertices (colours '
            f'{seams["colours"]}); the model\'s own colour step there {seams["model_step_seam_de"]:.2f}{elsewhere}')
