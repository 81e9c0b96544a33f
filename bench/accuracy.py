"""The calibration and colour tables of docs/benchmarks.md, measured on one synthetic studio bag
and printed with the commit they were measured on.

    python bench/accuracy.py [--out bench_out/accuracy] [--seed 5]

Renders (once) ``volcap synth --board-poses 40 --frames 6 --background-frames 3 --seed 5`` (8
cameras; the studio's per-camera exposure, white balance, crosstalk, gamma, vignetting and noise;
ToF noise; Blinn-Phong highlights under three coloured lights), then runs ``volcap calibrate``,
``volcap eval calib`` (every camera against the true poses, beside the paper's SED baseline) and
``volcap eval color --frames 6`` (fitted on capture frame sets 0, 2, 4, scored on 1, 3, 5). Writes
the reports into OUT and prints both tables as Markdown.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def volcap(*args) -> None:
    run = subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', *map(str, args)], capture_output=True, text=True)
    if run.returncode not in (0, 3):        # 3: a weak calibration is still measured
        raise SystemExit(f'volcap {" ".join(map(str, args))} exited {run.returncode}:\n{run.stderr[-3000:]}')


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--out', default=str(REPO / 'bench_out' / 'accuracy'))
    p.add_argument('--seed', type=int, default=5)
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag = out / f'studio40_seed{args.seed}'
    if not bag.exists():
        volcap('synth', '--out', bag, '--board-poses', 40, '--frames', 6, '--background-frames', 3, '--seed', args.seed,
               '--quiet')
    commit = subprocess.run(['git', '-C', str(REPO), 'rev-parse', '--short', 'HEAD'], capture_output=True,
                            text=True).stdout.strip()
    volcap('calibrate', bag, '--out', out / 'calibration.yaml', '--quiet')
    volcap('eval', 'calib', out / 'calibration.yaml', bag, '--json', out / 'calib.json', '--quiet')
    volcap('eval', 'color', bag, '--calibration', out / 'calibration.yaml', '--frames', 6, '--json',
           out / 'colour.json', '--quiet')
    calib = json.loads((out / 'calib.json').read_text())
    base = calib['baseline_gradient_descent']['cameras']
    print(f'calibration (commit {commit}, {bag.name}):\n')
    print('| camera | rot err deg | trans err mm | reproj px | paper SED baseline: rot / trans / reproj |')
    print('|---|---|---|---|---|')
    for cam, v in calib['cameras'].items():
        b = base.get(cam, {})
        print(f'| {cam} | {v["rot_err_deg"]:.3f} | {v["trans_err_mm"]:.2f} | {v["reproj_rms_px"]:.3f} | '
              f'{b.get("rot_err_deg", 0):.3f} / {b.get("trans_err_mm", 0):.2f} / {b.get("reproj_rms_px", 0):.2f} |')
    print(f'| max | **{calib["max_rot_err_deg"]:.3f}** | **{calib["max_trans_err_mm"]:.2f}** | '
          f'**{calib["max_reproj_rms_px"]:.3f}** | |')
    colour = json.loads((out / 'colour.json').read_text())
    print(f'\ncolour (commit {commit}, {bag.name}; scored pairs, std in brackets; all pairs; truth):\n')
    print('| method | CIEDE2000 | PSNR dB | all pairs: CIEDE2000 / PSNR | chroma of saturated pixels | '
          'truth CIEDE2000 (3x3) |')
    print('|---|---|---|---|---|---|')
    for name, m in colour['methods'].items():
        a = colour['methods_all_pairs'][name]

        def f(v, fmt='.2f'):
            return '-' if v is None else format(v, fmt)
        print(f'| {name} | {f(m["de2000_mean"])} ({f(m["de2000_std"])}) | {f(m["psnr_mean"])} ({f(m["psnr_std"])}) | '
              f'{f(a["de2000_mean"])} / {f(a["psnr_mean"])} | {f(m.get("chroma_before"), ".1f")} -> '
              f'{f(m.get("chroma_after"), ".1f")} | {f(m.get("truth_de2000"))} |')
    print(f'\nchart-free model chosen: {colour.get("chart_free_model", {}).get("model")}')


if __name__ == '__main__':
    main()
