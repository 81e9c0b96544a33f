"""Shimmer: how much the fused model changes from frame to frame where the subject does not,
and what temporal filtering of the cleaned depth buys, against what it costs a moving subject.

For each seed two synthetic 8-camera studios are rendered: one whose subject holds still
(``volcap synth --motion none``) and the default turning one. Every capture frame set is cleaned
(``volcap_pipeline.replay``, the camera pipeline's own code, one cleaner per camera carrying its
temporal state) and fused with the ground-truth poses at the graph's voxel size; then

- stability (``volcap_fusion.stability``, the subject's true motion taken out): surface jitter
  (RMS mm), colour flicker (CIEDE2000), share of the surface appearing or vanishing per frame;
- the fusion against the truth (``volcap_eval.fusion.score_frame``): accuracy and completeness,
  the frames after the filter has settled (from the third).

    python bench/stability.py [--seeds 3 8] [--frames 10] [--alphas 0 0.1] [--motions none turn] [--complete-radius 4]
                              [--complete-extend 2] [--carry-decays 0 0.7] [--carry-reset-mm 1.5] [--bands]
                              [--json bench_out/stability.json]

``--bands`` also splits each sequence's jitter by height above the subject's lowest point (the
shoes, the ankles, the body): where the shimmer is.
"""
import argparse
import json
import subprocess
import time
from pathlib import Path

import numpy as np

from volcap_core.camera import depth_to_millimetres
from volcap_core.poses import invert, matrix_from_list, transform_points
from volcap_eval.fusion import dropout_rate, score_frame
from volcap_filter.pipeline import DepthFilterConfig
from volcap_fusion.config import VOXEL_SIZE
from volcap_fusion.stability import format_stability, matched_points, sequence_stability
from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion
from volcap_pipeline.replay import cleaned_frame_sets
from volcap_studio.session import GroundTruth, synthesize
from volcap_studio.studio import SynthConfig


def studio(out: Path, seed: int, frames: int, motion: str) -> Path:
    bag = out / f'studio_{motion}_{seed}_{frames}f'
    if not (bag / 'ground_truth').exists():
        synthesize(bag, SynthConfig(cameras=8, frames=frames, board_poses=0, background_frames=3, seed=seed,
                                    motion=motion), progress=False)
    return bag


def fuse_sequence(bag: Path, configs: dict[str, DepthFilterConfig], fusions: dict[str, FusionConfig]
                  ) -> tuple[dict, list[int], dict]:
    """{(filter config, fusion config): [FusedModel per capture set]} in the world frame, the
    sets' stamps, and the mean cleaning ms per camera frame of each filter config."""
    gt = GroundTruth(bag)
    T_sw = np.asarray(gt.doc['T_studio_world'], float)     # fused in the studio frame, on the floor, as the graph does
    # one fusion per pair: each carries its own last frame set
    fusion = {(c, f): TsdfFusion(cfg) for c in configs for f, cfg in fusions.items()}
    models, stamps, ms = {k: [] for k in fusion}, [], {c: [] for c in configs}
    for fs, cleaned in cleaned_frame_sets(bag, configs):
        stamps.append(fs.stamp_ns)
        for name, cams in cleaned.items():
            ms[name] += [sum(c.result.timings_ms.values()) for c in cams.values()]
            views = [CameraView(cam, depth_to_millimetres(c.result.depth), c.cleaner.output_model, c.color,
                                c.frame.color_model, T_sw @ gt.T_world_color(cam)) for cam, c in cams.items()]
            for f in fusions:
                model = fusion[name, f].fuse(views, on_floor=True)
                model.vertices = transform_points(invert(T_sw), model.vertices).astype(np.float32)
                models[name, f].append(model)
    return models, stamps, {c: float(np.mean(v)) for c, v in ms.items()}


BANDS_M = (0.0, 0.06, 0.15, 0.5, 3.0)    # height above the subject's lowest point: shoes, ankles, legs, body


def jitter_by_height(models: list, motion_of, T_studio_world: np.ndarray) -> list[dict]:
    """The sequence's surface jitter (the matched points ``sequence_stability`` scores) split by
    height in the studio frame above the models' lowest point: per band its RMS (mm), its share
    of the mean square and of the points."""
    R, t = T_studio_world[:3, :3], T_studio_world[:3, 3]
    floor = np.percentile(np.concatenate([m.vertices @ R.T + t for m in models])[:, 2], 0.1)
    matches = [matched_points(a, b, motion=motion_of(k), seed=k + 1) for k, (a, b) in enumerate(zip(models, models[1:]))
               if len(a.triangles) and len(b.triangles)]
    d2 = np.concatenate([(m.distances * 1000) ** 2 for m in matches])
    h = np.concatenate([(m.points @ R.T + t)[:, 2] - floor for m in matches])
    rows = []
    for lo, hi in zip(BANDS_M, BANDS_M[1:]):
        band = (h >= lo) & (h < hi)
        rows.append({'band_m': [lo, hi], 'jitter_rms_mm': float(np.sqrt(d2[band].mean())) if band.any() else None,
                     'share_of_mean_square': float(d2[band].sum() / d2.sum()), 'share_of_points': float(band.mean())})
    return rows


def truth_frame(gt: GroundTruth, stamp_ns: int) -> dict:
    """The ground-truth capture frame of a frame set (the sets' stamps carry the rig's jitter)."""
    return min((f for f in gt.frames if 'T_world_subject' in f), key=lambda f: abs(f['stamp_ns'] - stamp_ns))


def truth_scores(gt: GroundTruth, models: list, stamps: list[int], skip: int) -> dict:
    tof = gt.doc['config']['tof']
    T_sw = np.asarray(gt.doc['T_studio_world'], float)
    rows = []
    for model, stamp in list(zip(models, stamps))[skip:]:
        index = truth_frame(gt, stamp)['index']
        dropped = gt.arrays(index, suffix='/dropped')
        sensors = [(c.depth, gt.T_world_depth(c.name), c.color, gt.T_world_color(c.name),
                    dropout_rate(dropped[f'{c.name}/dropped'])) for c in gt.rig.cameras]
        rows.append(score_frame(model, gt.subject_mesh(index), sensors, tof, T_studio_world=T_sw))
    return {k: float(np.mean([r[k] for r in rows if r.get(k) is not None]))
            for k in ('accuracy_mm', 'completeness', 'completeness_feet')}


def commit() -> str:
    try:
        return subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return 'unknown'


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[3, 8])
    ap.add_argument('--frames', type=int, default=10)
    ap.add_argument('--alphas', type=float, nargs='+', default=[0.0, 0.1],
                    help='temporal_alpha values of the depth filter (0 = off)')
    ap.add_argument('--motions', nargs='+', default=['none', 'turn'], choices=['none', 'turn'])
    ap.add_argument('--complete-radius', type=int, default=DepthFilterConfig().complete_radius,
                    help='the depth filter\'s complete_radius (0: holes inside the mask not completed)')
    ap.add_argument('--complete-extend', type=int, default=DepthFilterConfig().complete_extend,
                    help='the depth filter\'s complete_extend (0: completion only between depth on three sides)')
    ap.add_argument('--voxel', type=float, default=VOXEL_SIZE)
    ap.add_argument('--carry-decays', type=float, nargs='+', default=[FusionConfig().carry_decay],
                    help='the fusion\'s carry_decay values (0: each frame set fused alone)')
    ap.add_argument('--carry-reset-mm', type=float, default=FusionConfig().carry_reset_mm,
                    help='the fusion\'s carry_reset_mm')
    ap.add_argument('--bands', action='store_true', help='split the jitter by height above the lowest point')
    ap.add_argument('--work', default='bench_out/stability')
    ap.add_argument('--json', default='bench_out/stability.json')
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    configs = {f'alpha {a:g}': DepthFilterConfig(temporal_alpha=a, complete_radius=args.complete_radius,
                                                     complete_extend=args.complete_extend)
               for a in args.alphas}
    fusions = {f'carry {d:g}': FusionConfig(voxel_size=args.voxel, carry_decay=d, carry_reset_mm=args.carry_reset_mm)
               for d in args.carry_decays}
    results = []
    for seed in args.seeds:
        for motion in args.motions:
            t0 = time.perf_counter()
            bag = studio(work, seed, args.frames, motion)
            gt = GroundTruth(bag)
            models, stamps, ms = fuse_sequence(bag, configs, fusions)
            poses = {s: matrix_from_list(truth_frame(gt, s)['T_world_subject']) for s in stamps}
            for (filter_name, fusion_name), seq in models.items():
                name = f'{filter_name}, {fusion_name}'
                # the first two frames are the filter settling; pairs and truth from the third
                settled, settled_stamps = seq[2:], stamps[2:]
                motion_of = (lambda k, s=settled_stamps: poses[s[k + 1]] @ invert(poses[s[k]]))
                stability = sequence_stability(settled, motion=motion_of)
                scores = truth_scores(gt, seq, stamps, 2)
                carry_ms = [m.timings_ms.get('carry', 0.0) for m in seq]
                fuse_ms = [sum(m.timings_ms.values()) for m in seq]
                row = {'seed': seed, 'motion': motion, 'config': name, 'clean_ms_per_camera_frame': ms[filter_name],
                       'fuse_ms': float(np.median(fuse_ms)), 'carry_ms': float(np.median(carry_ms)),
                       **{k: stability[k] for k in ('frame_pairs', 'jitter_rms_mm', 'flicker_de', 'appear_vanish')},
                       # per pair: how the change falls as the average fills (the steady state is the tail)
                       'jitter_per_pair_mm': [p['jitter_rms_mm'] for p in stability['pairs']],
                       'flicker_per_pair': [p['flicker_de'] for p in stability['pairs']],
                       **scores}
                if args.bands:
                    row['jitter_by_height'] = jitter_by_height(settled, motion_of, np.asarray(gt.doc['T_studio_world'], float))
                results.append(row)
                print(f'seed {seed} motion {motion:4s} {name} {format_stability(stability)}; accuracy '
                      f'{scores["accuracy_mm"]:.2f} mm, completeness {100 * scores["completeness"]:.1f} %, feet '
                      f'{100 * scores["completeness_feet"]:.1f} %; cleaning {ms[filter_name]:.0f} ms/camera frame; fusion '
                      f'{row["fuse_ms"]:.0f} ms/set, of it carry {row["carry_ms"]:.0f} ms', flush=True)
                for band in row.get('jitter_by_height', []):
                    lo, hi = (100 * x for x in band['band_m'])
                    print(f'    {lo:.0f}-{hi:.0f} cm above the lowest point: jitter {band["jitter_rms_mm"] or 0:.2f} mm RMS, '
                          f'{100 * band["share_of_mean_square"]:.0f} % of the mean square on '
                          f'{100 * band["share_of_points"]:.1f} % of the surface', flush=True)
            print(f'  ({time.perf_counter() - t0:.0f} s)', flush=True)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'commit': commit(), 'frames': args.frames, 'voxel': args.voxel, 'results': results}, indent=2))
    print(f'wrote {out}')


if __name__ == '__main__':
    main()
