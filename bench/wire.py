"""The deployment model's figures: one process per camera beside its driver, the compact wire, the
fusion host fed by it; each beside the previous design measured in the same run.

    .venv/bin/python bench/wire.py BAG CALIBRATION [--frames 12] [--live-seconds 45] [--out bench_out]

BAG is a synthetic studio (`volcap synth`, e.g. `make demo`'s demo_out/studio: its ground truth
scores the fusion). Measures:

1. **Per-camera pipeline on one core** (this process pinned to one CPU, one thread each for
   numba, OpenCV and OpenMP): per frame, from the driver's CDR messages to what leaves the
   camera's process. New: clean (register, mask, flying pixels), correct the foreground region,
   crop, PNG + JPEG, serialise the wire. Previous design (depth_filter + color_corrector): the
   same cleaning, the whole colour image corrected, both full-size images serialised. p50 / p95
   ms of CPU and the frames/s one core sustains.
2. **The wire**: bytes a camera sends per frame (wire vs the previous design's full-size cleaned
   depth + corrected colour vs the raw inputs), Mbit/s at 30 fps per camera and for 8.
3. **Fusion from the wire vs from the full frames** (same frame sets, same calibration, 10 mm
   and 4 mm voxels): accuracy and completeness against the ground truth, and the vertex colours'
   CIEDE2000 between the two models.
4. **The fusion host alone** (this process, both cores): per frame set from the wire messages:
   decode, integrate, extract, GLB; sets/s at 10 mm and 6 mm. The previous design's fusion of the
   same sets from full-size messages beside it.
5. **Live** (`bench/live.py`'s run, a renderer stand-in timing every mesh): `volcap live --bag
   WIREBAG` (the fusion host alone, fed the recorded wire looped at 30 fps), `volcap live --bag
   BAG` (everything on this host, one camera_pipeline per camera) and the same with
   `--split-stages` (the previous design), 10 mm.

Writes OUT/wire.json and prints the tables of docs/benchmarks.md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WARM_FRAMES = 3       # per camera and design, left out of the per-frame figures


def commit() -> str:
    return subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=REPO, capture_output=True,
                          text=True).stdout.strip()


def one_core_pipeline(bag: str, calibration: str, frames: int) -> dict:
    """Part 1 and 2, in a child process pinned to one core (run with --one-core)."""
    import numpy as np
    from rclpy.serialization import serialize_message

    from volcap_color.corrector import CameraCorrection
    from volcap_core.bag_reader import BagReader
    from volcap_core.camera import depth_to_millimetres
    from volcap_core.cdr import image_to_cdr
    from volcap_core.conversions import color_to_rgb, depth_to_metres
    from volcap_core.frames import CameraFrame, camera_topics, read_rig
    from volcap_core.topics import CAPTURE, CLEAN_PLATE, PHASE, parse_phase
    from volcap_filter.pipeline import DepthFilterConfig
    from volcap_pipeline.camera import CameraPipeline, WireConfig

    text = Path(calibration).read_text()
    with BagReader(bag) as reader:
        rig = read_rig(reader)
        layout = camera_topics(reader, rig.names)
        phases = sorted((m.stamp_ns, parse_phase(m.decode().data)) for m in reader.messages([PHASE]))
    cams = rig.names[:2]
    out = {'new_ms': [], 'old_ms': [], 'wire_bytes': [], 'old_bytes': [], 'raw_bytes': [], 'stages_ms': {}}
    for cam in cams:
        c = rig.camera(cam)
        topics_of = layout[cam]
        msgs = {}
        with BagReader(bag) as reader:
            for m in reader.messages([topics_of['color'], topics_of['depth']]):
                msgs.setdefault(m.stamp_ns, {})[
                    'depth' if m.topic == topics_of['depth'] else 'color'] = m
        # pair by nearest stamp within 20 ms (colour and depth are stamped apart on some rigs)
        colors = sorted((s, v['color']) for s, v in msgs.items() if 'color' in v)
        depths = sorted((s, v['depth']) for s, v in msgs.items() if 'depth' in v)
        pairs = []
        for s, cm in colors:
            d = min(depths, key=lambda x: abs(x[0] - s))
            if abs(d[0] - s) < 20_000_000:
                pairs.append((s, cm, d[1]))

        def phase_at(stamp):
            p = None
            for t, name in phases:
                if stamp >= t:
                    p = name
            return p
        for design in ('new', 'old'):
            pipeline = CameraPipeline(cam, DepthFilterConfig(), rig, output_scale=0.5)
            correction = CameraCorrection(cam)
            correction.set_calibration(text)
            done = 0
            for stamp, cm, dm in pairs:
                phase = phase_at(stamp)
                if phase not in (CLEAN_PLATE, CAPTURE):
                    continue
                cpu0 = time.process_time()
                color_msg, depth_msg = cm.decode(), dm.decode()
                color, depth = color_to_rgb(color_msg), depth_to_metres(depth_msg)
                frame = CameraFrame(color, depth, c.color, c.depth, depth_msg.header.frame_id,
                                    color_msg.header.frame_id)
                _, cleaned = pipeline.add(frame, stamp, phase)
                if cleaned is None:
                    continue
                if design == 'new':
                    pipeline.correction = correction
                    wf = pipeline.wire(cleaned.result.depth, cleaned.model, color, c.color, stamp, cam, WireConfig())
                    pipeline.correction = None
                    sent = sum(len(serialize_message(m)) for m in (wf.depth, wf.color, wf.depth_info, wf.color_info))
                    for k, v in {**wf.timings_ms, **cleaned.result.timings_ms}.items():
                        out['stages_ms'].setdefault(k, []).append(v)
                else:
                    corrected = correction.apply(color)
                    sent = len(image_to_cdr(depth_to_millimetres(cleaned.result.depth), '16UC1', stamp, cam)) \
                        + len(image_to_cdr(corrected, 'rgb8', stamp, cam))
                ms = (time.process_time() - cpu0) * 1e3
                if phase == CAPTURE:
                    if done >= WARM_FRAMES:    # a camera's first frames pay one-off set-up (LUTs, codecs)
                        out[f'{design}_ms'].append(ms)
                    out['wire_bytes' if design == 'new' else 'old_bytes'].append(sent)
                    if design == 'new':
                        out['raw_bytes'].append(len(cm.data) + len(dm.data))
                    done += 1
                    if done >= frames:
                        break
    summary = {}
    for design in ('new', 'old'):
        ms = np.array(out[f'{design}_ms'])
        summary[design] = {'frames': int(ms.size), 'p50_ms': float(np.median(ms)), 'p95_ms': float(np.percentile(ms, 95)),
                           'max_ms': float(ms.max()), 'fps_one_core': float(1000 / ms.mean())}
    summary['stages_ms_median'] = {k: float(np.median(v)) for k, v in out['stages_ms'].items()}
    for key in ('wire_bytes', 'old_bytes', 'raw_bytes'):
        b = float(np.mean(out[key]))
        summary['bytes_' + key.replace('_bytes', '')] = {'kbytes_per_frame': b / 1000, 'mbit_s_at_30fps': b * 8 * 30 / 1e6,
                                              'mbit_s_8_cameras': b * 8 * 30 * 8 / 1e6}
    return summary


def fusion_comparison(bag: str, calibration: str, wirebag: str, frames: int) -> dict:
    """Parts 3 and 4: the same frame sets fused from the wire and from full frames."""
    import numpy as np
    from rclpy.serialization import deserialize_message
    from scipy.spatial import cKDTree
    from sensor_msgs.msg import Image

    from volcap_color.corrector import CameraCorrection
    from volcap_core import wire
    from volcap_core.bag_reader import BagReader
    from volcap_core.calibration import Calibration
    from volcap_core.camera import depth_to_millimetres
    from volcap_core.cdr import image_to_cdr
    from volcap_core.color import delta_e2000
    from volcap_core.conversions import color_to_rgb, image_to_numpy
    from volcap_core.poses import transform_points
    from volcap_eval.fusion import dropout_rate, score_frame
    from volcap_filter.pipeline import DepthFilterConfig
    from volcap_fusion.glb import EncodeConfig
    from volcap_fusion.rig import RigFusion, wire_view
    from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion
    from volcap_pipeline.replay import cleaned_frame_sets
    from volcap_studio.session import GroundTruth

    cal = Calibration.load(calibration)
    text = Path(calibration).read_text()
    cams = list(cal.cameras)
    wire_sets: dict[int, dict] = {}
    with BagReader(wirebag) as r:
        for m in r.messages():
            if '/wire/' in m.topic:
                cam, _, stream = m.topic.partition('/')
                wire_sets.setdefault(m.stamp_ns, {})[(cam, stream)] = m.decode()
    corrections = {c: CameraCorrection(c) for c in cams}
    for c in corrections.values():
        c.set_calibration(text)
    full_sets = {}
    for fs, cleaned in cleaned_frame_sets(bag, {'v': DepthFilterConfig()}, cameras=cams, output_size='half',
                                          limit=frames):
        full_sets[fs.stamp_ns] = {n: (depth_to_millimetres(cc.result.depth), cc.model,
                                      corrections[n].apply(cc.frame.color).copy(), cc.frame.color_model)
                                  for n, cc in cleaned['v'].items()}
    stamps = [s for s in sorted(full_sets) if s in wire_sets][:frames]
    gt = GroundTruth(bag)
    by_stamp = {f['stamp_ns']: f for f in gt.frames if 'T_world_subject' in f}
    gt_stamps = np.array(sorted(by_stamp))
    tof = gt.doc['config']['tof']
    T_studio_world = np.asarray(gt.doc['T_studio_world'], float)

    def parts_wire(s):
        p = wire_sets[s]
        return {c: (p[(c, wire.WIRE_DEPTH)], p[(c, wire.WIRE_DEPTH_INFO)], p[(c, wire.WIRE_COLOR)],
                    p[(c, wire.WIRE_COLOR_INFO)]) for c in cams if (c, wire.WIRE_DEPTH) in p}

    out = {}
    for voxel in (0.01, 0.004):
        rig_w = RigFusion(TsdfFusion(FusionConfig(voxel_size=voxel)), EncodeConfig().for_voxel(voxel))
        rig_f = RigFusion(TsdfFusion(FusionConfig(voxel_size=voxel)), EncodeConfig().for_voxel(voxel))
        rows = []
        for s in stamps:
            fw = rig_w.fuse(s, cal, cams, parts_wire(s), lambda c, q, M: wire_view(c, *q, M))
            ff = rig_f.fuse(s, cal, cams, full_sets[s],
                            lambda c, q, M: CameraView(c, q[0], q[1], q[2], q[3], M))
            index = by_stamp[int(gt_stamps[np.argmin(np.abs(gt_stamps - s))])]['index']
            truth = gt.subject_mesh(index)
            dropped = gt.arrays(index, suffix='/dropped')
            sensors = [(c.depth, gt.T_world_depth(c.name), c.color, gt.T_world_color(c.name),
                        dropout_rate(dropped[f'{c.name}/dropped'])) for c in gt.rig.cameras]
            row = {}
            for name, f in (('wire', fw), ('full', ff)):
                model = f.model
                model.vertices = transform_points(np.linalg.inv(f.T_frame_world), model.vertices).astype(np.float32)
                sc = score_frame(model, truth, sensors, tof, samples=100_000, T_studio_world=T_studio_world)
                row[name] = {k: sc[k] for k in ('accuracy_mm', 'completeness', 'completeness_feet')}
            _, nearest = cKDTree(ff.model.vertices).query(fw.model.vertices)
            row['colour_de2000_mean'] = float(np.mean(delta_e2000(fw.model.colors / 255.0,
                                                                  ff.model.colors[nearest] / 255.0)))
            rows.append(row)
        mean = {d: {k: float(np.mean([r[d][k] for r in rows if r[d][k] is not None])) for k in rows[0][d]}
                for d in ('wire', 'full')}
        out[f'{voxel * 1000:.0f} mm'] = {**mean, 'colour_de2000_mean': float(np.mean([r['colour_de2000_mean']
                                                                                       for r in rows])),
                                         'frame_sets': len(rows)}
    # the fusion host's own cost, per set (both cores: Open3D integrates and meshes in parallel)
    host = {}
    for voxel in (0.01, 0.006):
        for design in ('wire', 'full'):
            rig = RigFusion(TsdfFusion(FusionConfig(voxel_size=voxel)), EncodeConfig().for_voxel(voxel))

            if design == 'full':     # as the full-size messages arrive: CDR to decode
                blobs = {s: {c: (image_to_cdr(q[0], '16UC1', s, c), q[1], image_to_cdr(q[2], 'rgb8', s, c), q[3])
                             for c, q in full_sets[s].items()} for s in stamps}

                def view(c, q, M):
                    return CameraView(c, image_to_numpy(deserialize_message(q[0], Image)), q[1],
                                      color_to_rgb(deserialize_message(q[2], Image)), q[3], M)
            times, stage = [], {}
            for k in range(3 * len(stamps)):
                s = stamps[k % len(stamps)]
                t0 = time.perf_counter()
                if design == 'wire':
                    f = rig.fuse(s, cal, cams, parts_wire(s), lambda c, q, M: wire_view(c, *q, M), glb=True)
                else:
                    f = rig.fuse(s, cal, cams, blobs[s], view, glb=True)
                times.append((time.perf_counter() - t0) * 1e3)
                for key, v in {**f.model.timings_ms, **{f'glb_{a}': b for a, b in f.encoded.timings_ms.items()}}.items():
                    stage.setdefault(key, []).append(v)
            t = np.array(times[len(stamps):])
            host[f'{design} {voxel * 1000:.0f} mm'] = {
                'ms_per_set_p50': float(np.median(t)), 'ms_per_set_p95': float(np.percentile(t, 95)),
                'sets_per_s': float(1000 / t.mean()),
                'stages_ms_median': {k: float(np.median(v[len(stamps):])) for k, v in stage.items()},
                'decode_and_other_ms': float(np.median(t) - sum(np.median(v[len(stamps):]) for v in stage.values()))}
    return {'fusion_wire_vs_full': out, 'fusion_host': host}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('bag')
    ap.add_argument('calibration')
    ap.add_argument('--frames', type=int, default=20)
    ap.add_argument('--live-seconds', type=float, default=45.0)
    ap.add_argument('--warmup', type=float, default=15.0)
    ap.add_argument('--out', default=str(REPO / 'bench_out'))
    ap.add_argument('--one-core', action='store_true', help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one_core:
        print(json.dumps(one_core_pipeline(args.bag, args.calibration, args.frames)))
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {'commit': commit(), 'bag': args.bag}
    env = {**os.environ, 'NUMBA_NUM_THREADS': '1', 'OMP_NUM_THREADS': '1', 'OPENCV_FOR_THREADS_NUM': '1'}
    print('1-2. one camera pipeline on one core ...', flush=True)
    run = subprocess.run(['taskset', '-c', '0', sys.executable, __file__, args.bag, args.calibration, '--one-core',
                          '--frames', str(args.frames)], capture_output=True, text=True, env=env)
    if run.returncode:
        raise SystemExit(run.stderr[-3000:])
    result['per_camera'] = json.loads(run.stdout.strip().splitlines()[-1])
    print(json.dumps(result['per_camera'], indent=1), flush=True)
    wirebag = out / 'wire_bag'
    if wirebag.exists():
        import shutil
        shutil.rmtree(wirebag)
    print('recording the wire (volcap wire) ...', flush=True)
    subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', 'wire', args.bag, '--calibration', args.calibration,
                    '--out', str(wirebag), '--quiet'], check=True)
    print('3-4. fusion from the wire vs full frames; the fusion host ...', flush=True)
    result.update(fusion_comparison(args.bag, args.calibration, str(wirebag), args.frames))
    print(json.dumps({k: result[k] for k in ('fusion_wire_vs_full', 'fusion_host')}, indent=1), flush=True)
    if args.live_seconds > 0:
        sys.path.insert(0, str(REPO / 'bench'))
        from live import one_run
        live = {}
        for name, bag, split in (('fusion host alone, wire bag', str(wirebag), False),
                                 ('all on one host, camera_pipeline', args.bag, False),
                                 ('all on one host, previous design (split stages)', args.bag, True)):
            print(f'5. live: {name} ...', flush=True)
            r = one_run(bag, args.calibration, 0.01, args.live_seconds + args.warmup, args.warmup, False,
                        split_stages=split)
            live[name] = {k: r[k] for k in ('delivered_meshes_per_s', 'latency_ms_p50', 'latency_ms_p95',
                                             'complete_share', 'input_sets_per_s', 'admit_every_median',
                                             'compute_bound_meshes_per_s', 'work_ms_per_set',
                                             'cpu_cores_used_by_process_group', 'node_exit_codes')}
            print(json.dumps(live[name], indent=1), flush=True)
        result['live_10mm'] = live
    (out / 'wire.json').write_text(json.dumps(result, indent=1))
    print(f'wrote {out / "wire.json"}')


if __name__ == '__main__':
    main()
