"""What a telepresence client receives: the fused sequence's frames encoded for renderers (raw,
meshopt, Draco) at several triangle budgets, measured on one machine in one run.

Per encoding and budget, over the sequence's first ``--frames`` frames:

- MB per frame and Mbit/s at 30 fps;
- encode ms per frame (simplification + encoding, one core), against the bare library calls on
  the same simplified mesh (meshoptimizer's codecs, DracoPy's encoder) and against the 33.3 ms a
  frame may take at 30 fps;
- browser decode ms per frame: the player (three.js ``GLTFLoader`` with ``MeshoptDecoder`` /
  ``DRACOLoader``) in headless Chromium, every frame parsed once (``window.volcap.decodeMs``);
- geometry against the raw mesh (distance from the decoded vertices to the raw surface:
  quantisation; and from the raw vertices to the decoded surface: what the budget removes) and
  colour (CIEDE2000 of each decoded vertex to the raw mesh's colour there);
- against the ground truth (a synthetic bag's subject): accuracy and completeness as
  `volcap eval fusion` scores them, the feet (lowest 15 cm) included.

Written to ``--out`` as ``stream.json`` and ``stream.png``.

    python bench/stream.py demo_out/run/frames demo_out/studio [--frames 10] [--out bench_out/stream]
"""
import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

import DracoPy
import matplotlib
import meshoptimizer
import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from tqdm import tqdm

from volcap_core.color import delta_e2000
from volcap_core.poses import transform_points
from volcap_eval.fusion import dropout_rate, score_frame
from volcap_fusion.glb import ENCODINGS, EncodeConfig, decode_glb, encode, linear_color16, simplify
from volcap_fusion.sequence import SequenceWriter, T_world_frame, read_ply, read_sequence
from volcap_fusion.tsdf import raycasting_scene

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402

BUDGETS = (0, 60_000, 30_000, 15_000)
FRAME_MS = 1000 / 30
CHROMIUM_ARGS = ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--no-first-run',
                 '--disable-background-networking', '--disable-component-update', '--disable-sync']


def bare_library_ms(mesh, cfg: EncodeConfig) -> float:
    """The library calls alone on an already simplified mesh: meshoptimizer's vertex and index
    codecs, or DracoPy's encoder; raw: copying the arrays out."""
    t0 = time.perf_counter()
    if cfg.encoding == 'meshopt':
        n = len(mesh.vertices)
        positions = np.zeros((n, 4), np.uint16)
        positions[:, :3] = np.round((mesh.vertices - mesh.vertices.min(axis=0)) / cfg.position_step)
        meshoptimizer.encode_vertex_buffer(positions, n, 8)
        meshoptimizer.encode_vertex_buffer(linear_color16(mesh.colors, cfg.color_bits), n, 8)
        meshoptimizer.encode_index_buffer(np.ascontiguousarray(mesh.triangles, np.uint32).reshape(-1),
                                          mesh.triangles.size, n)
    elif cfg.encoding == 'draco':
        DracoPy.encode(mesh.vertices, np.ascontiguousarray(mesh.triangles, np.uint32), quantization_bits=11,
                       compression_level=7, generic_attributes={1: linear_color16(mesh.colors, cfg.color_bits)})
    else:
        mesh.vertices.tobytes() + linear_color16(mesh.colors, cfg.color_bits).tobytes() + mesh.triangles.tobytes()
    return (time.perf_counter() - t0) * 1e3


def against_raw(decoded, raw, raw_scene) -> dict:
    quant = raw_scene.compute_distance(o3d.core.Tensor(decoded.vertices)).numpy()
    loss = raycasting_scene(decoded.vertices, decoded.triangles).compute_distance(
        o3d.core.Tensor(raw.vertices)).numpy()
    nearest = cKDTree(raw.vertices).query(decoded.vertices)[1]
    de = delta_e2000(decoded.colors / 255.0, raw.colors[nearest] / 255.0)
    return {'vertex_to_raw_mm_max': float(quant.max() * 1e3), 'vertex_to_raw_mm_mean': float(quant.mean() * 1e3),
            'raw_to_decoded_mm_mean': float(loss.mean() * 1e3), 'raw_to_decoded_mm_p95': float(
                np.percentile(loss, 95) * 1e3), 'color_de2000_mean': float(de.mean()),
            'color_de2000_p99': float(np.percentile(de, 99))}


def browser_decode_ms(folder: Path, frames: int) -> list[float]:
    """The player's parse time of every frame of the sequence in ``folder`` (Chromium, headless)."""
    from playwright.sync_api import sync_playwright

    from volcap_bringup.view import ViewConfig, run_view
    url, ready = [], threading.Event()
    import socket
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    threading.Thread(target=run_view, args=(ViewConfig(folder, port=port), lambda u: (url.append(u), ready.set())),
                     daemon=True).start()
    ready.wait(30)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path='/usr/bin/chromium', args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={'width': 640, 'height': 480})
        page.goto(url[0])
        page.wait_for_function(f'window.volcap && window.volcap.decodeMs.length >= {frames + 2}', timeout=300_000)
        ms = page.evaluate('window.volcap.decodeMs')
        browser.close()
    return ms[2:frames + 2]     # the first two include loading the decoders (wasm compile)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('sequence', help='a fused sequence folder (DIR/frames of volcap run)')
    ap.add_argument('bag', nargs='?', help='its synthetic bag (ground truth); omit for real captures')
    ap.add_argument('--frames', type=int, default=10)
    ap.add_argument('--out', default='bench_out/stream')
    ap.add_argument('--voxel', type=float, default=0.004, help='the voxel the sequence was fused at (m)')
    ap.add_argument('--no-browser', action='store_true')
    args = ap.parse_args()
    headers, entries = read_sequence(args.sequence)
    voxel = args.voxel
    entries = [e for e in entries if 'ply' in e][:args.frames]
    if not entries:
        raise SystemExit(f'{args.sequence}: no frames with a PLY (the full mesh) to encode')
    raws = [read_ply(Path(args.sequence) / e['ply']) for e in entries]
    scenes = [raycasting_scene(r.vertices, r.triangles) for r in raws]
    truth = None
    if args.bag:
        from volcap_studio.session import GroundTruth
        gt = GroundTruth(args.bag)
        by_stamp = {f['stamp_ns']: f for f in gt.frames if 'T_world_subject' in f}
        stamps = np.array(sorted(by_stamp), np.int64)
        truth = (gt, by_stamp, stamps)
    cases = [('raw', 0)] + [(e, b) for e in ENCODINGS if e != 'raw' for b in BUDGETS]
    results = []
    tmp = Path(tempfile.mkdtemp(prefix='volcap_stream_'))
    for encoding, budget in tqdm(cases, desc='encodings x budgets', unit='case'):
        cfg = EncodeConfig(encoding=encoding, max_triangles=budget).for_voxel(voxel)
        folder = tmp / f'{encoding}_{budget}'
        writer = SequenceWriter(folder, ('glb',), cfg)
        sizes, encode_ms, bare_ms, triangles, raw_rows, gt_rows = [], [], [], [], [], []
        for entry, raw, scene in zip(entries, raws, scenes):
            encoded = encode(raw, cfg, entry['stamp_ns'], entry['index'])
            writer.write(raw, entry['stamp_ns'], encoded=encoded)
            sizes.append(len(encoded.data))
            encode_ms.append(sum(encoded.timings_ms.values()))
            bare_ms.append(bare_library_ms(simplify(raw, budget, cfg.simplifier), cfg))
            triangles.append(encoded.triangles)
            decoded = decode_glb(encoded.data)[0]
            raw_rows.append(against_raw(decoded, raw, scene))
            if truth is not None:
                gt, by_stamp, stamps = truth
                nearest = int(stamps[np.argmin(np.abs(stamps - entry['stamp_ns']))])
                index = by_stamp[nearest]['index']
                dropped = gt.arrays(index, suffix='/dropped')
                sensors = [(c.depth, gt.T_world_depth(c.name), c.color, gt.T_world_color(c.name),
                            dropout_rate(dropped[f'{c.name}/dropped'])) for c in gt.rig.cameras]
                decoded.vertices = transform_points(T_world_frame(headers, entry['index']),
                                                    decoded.vertices).astype(np.float32)
                gt_rows.append(score_frame(decoded, gt.subject_mesh(index), sensors, gt.doc['config']['tof'],
                                           samples=100_000, T_studio_world=np.asarray(gt.doc['T_studio_world'])))
        writer.close()
        row = {'encoding': encoding, 'max_triangles': budget, 'frames': len(entries),
               'triangles_mean': float(np.mean(triangles)), 'mb_per_frame': float(np.mean(sizes) / 1e6),
               'mbit_per_s_at_30fps': float(np.mean(sizes) * 8 * 30 / 1e6),
               'encode_ms_median': float(np.median(encode_ms)), 'bare_library_ms_median': float(np.median(bare_ms)),
               'encode_vs_bare': float(np.median(encode_ms) / max(np.median(bare_ms), 1e-6)),
               'encode_share_of_30fps_frame': float(np.median(encode_ms) / FRAME_MS)}
        for key in raw_rows[0]:
            row[key] = float(np.max([r[key] for r in raw_rows]) if key.endswith('max') else
                             np.mean([r[key] for r in raw_rows]))
        if gt_rows:
            for key in ('accuracy_mm', 'completeness', 'completeness_feet'):
                values = [r[key] for r in gt_rows if r.get(key) is not None]
                row[f'truth_{key}'] = float(np.mean(values)) if values else None
        if not args.no_browser:
            ms = browser_decode_ms(folder, len(entries))
            row['browser_decode_ms_median'] = float(np.median(ms))
            row['browser_decode_ms_p95'] = float(np.percentile(ms, 95))
        results.append(row)
        tqdm.write(f'{encoding:8s} {budget or "all":>6}: {row["triangles_mean"]:8.0f} tris  '
                   f'{row["mb_per_frame"]:6.3f} MB  {row["mbit_per_s_at_30fps"]:7.1f} Mbit/s  '
                   f'encode {row["encode_ms_median"]:6.1f} ms (bare {row["bare_library_ms_median"]:5.1f})  '
                   f'browser {row.get("browser_decode_ms_median", float("nan")):6.1f} ms  '
                   f'quant max {row["vertex_to_raw_mm_max"]:.2f} mm  dE {row["color_de2000_mean"]:.2f}'
                   + (f'  truth acc {row["truth_accuracy_mm"]:.2f} mm compl {100 * row["truth_completeness"]:.1f} % '
                      f'feet {100 * (row["truth_completeness_feet"] or 0):.1f} %' if gt_rows else ''))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    doc = {'sequence': str(args.sequence), 'bag': args.bag, 'frames': len(entries), 'results': results,
           'targets': {'mbit_per_s_at_30fps': 40, 'browser_decode_ms': 15, 'encode_ms': 30,
                       'geometry_mm': 'half a voxel', 'color_de2000': 1}}
    (out / 'stream.json').write_text(json.dumps(doc, indent=2))
    figure(results, out / 'stream.png')
    print(f'wrote {out / "stream.json"} and {out / "stream.png"}')


def figure(results: list[dict], path: Path) -> None:
    labels = [f'{r["encoding"]}\n{r["max_triangles"] // 1000 or "all"}{"k" if r["max_triangles"] else ""}'
              for r in results]
    panels = [('mbit_per_s_at_30fps', 'Mbit/s at 30 fps', 40), ('encode_ms_median', 'encode ms / frame', 30),
              ('browser_decode_ms_median', 'browser decode ms / frame', 15),
              ('raw_to_decoded_mm_mean', 'raw surface to decoded (mm)', None)]
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.2))
    for ax, (key, title, target) in zip(axes, panels):
        values = [r.get(key) or 0 for r in results]
        ax.bar(range(len(values)), values, color=['#888' if r['encoding'] == 'raw' else '#3a7' if r['encoding'] ==
                                                  'meshopt' else '#37a' for r in results])
        if target:
            ax.axhline(target, color='#c33', ls='--', lw=1, label=f'target {target}')
            ax.legend()
        ax.set_xticks(range(len(values)), labels, fontsize=7)
        ax.set_title(title)
        if key == 'mbit_per_s_at_30fps':
            ax.set_yscale('log')
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == '__main__':
    main()
