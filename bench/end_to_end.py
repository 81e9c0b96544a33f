"""Calibrate, then run, scored: the whole path a studio takes, on synthetic studios nobody tuned on.

For each seed an 8-camera studio is rendered (16 board poses held between neighbouring stands,
as the calibration's advice guides; a clean plate; a turning subject), then exactly what a user
types:

    volcap calibrate BAG --out calibration.yaml         # exit 0 (within the target) or 3 (weak)
    volcap run BAG --calibration calibration.yaml --out run
    volcap eval fusion run BAG --json fusion.json       # accuracy, completeness, feet, seams
    volcap eval stability run BAG --json stability.json

and the figures are printed as a Markdown table with the commit, and written to ``--json``.

    python bench/end_to_end.py [--seeds 11 12] [--frames 10] [--work bench_out/end_to_end]
"""
import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def volcap(*args, ok=(0,)) -> tuple[int, float]:
    """Runs the CLI; (exit code, seconds). An exit code outside ``ok`` stops the bench."""
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', *map(str, args)], capture_output=True, text=True)
    if run.returncode not in ok:
        raise SystemExit(f'volcap {" ".join(map(str, args))} exited {run.returncode}:\n{run.stdout[-2000:]}'
                         f'\n{run.stderr[-3000:]}')
    return run.returncode, time.perf_counter() - t0


def commit() -> str:
    return subprocess.run(['git', '-C', str(REPO), 'rev-parse', '--short', 'HEAD'], capture_output=True,
                          text=True).stdout.strip() or 'unknown'


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[11, 12])
    ap.add_argument('--frames', type=int, default=10)
    ap.add_argument('--board-poses', type=int, default=16)
    ap.add_argument('--work', default=str(REPO / 'bench_out' / 'end_to_end'))
    ap.add_argument('--json', default=str(REPO / 'bench_out' / 'end_to_end.json'))
    args = ap.parse_args()
    work = Path(args.work)
    rows = []
    for seed in args.seeds:
        base = work / f'seed{seed}'
        bag = base / 'studio'
        seconds = {}
        if not (bag / 'ground_truth').exists():
            _, seconds['synth'] = volcap('synth', '--out', bag, '--frames', args.frames, '--board-poses',
                                         args.board_poses, '--board-layout', 'pairs', '--background-frames', 3,
                                         '--seed', seed, '--quiet', '--overwrite')
        code, seconds['calibrate'] = volcap('calibrate', bag, '--out', base / 'calibration.yaml', '--quiet',
                                            ok=(0, 3))
        run = base / 'run'
        if run.exists():
            subprocess.run(['rm', '-rf', str(run)], check=True)
        _, seconds['run'] = volcap('run', bag, '--calibration', base / 'calibration.yaml', '--out', run, '--quiet')
        _, seconds['eval_fusion'] = volcap('eval', 'fusion', run, bag, '--json', base / 'fusion.json', '--quiet')
        _, seconds['eval_stability'] = volcap('eval', 'stability', run, bag, '--json', base / 'stability.json',
                                              '--quiet')
        fusion = json.loads((base / 'fusion.json').read_text())
        stability = json.loads((base / 'stability.json').read_text())
        metrics = json.loads((run / 'metrics.json').read_text())
        row = {'seed': seed, 'calibration_exit': code, 'frames_fused': metrics['frames_written'],
               'capture_frame_sets': metrics['capture_frame_sets_in_bag'],
               'accuracy_mm': fusion['accuracy_mm'], 'completeness': fusion['completeness'],
               'completeness_feet': fusion['completeness_feet'], 'seams': {k: v for k, v in fusion['seams'].items()
                                                                          if k != 'per_frame'},
               'jitter_rms_mm': stability['jitter_rms_mm'], 'flicker_de': stability['flicker_de'],
               'appear_vanish': stability['appear_vanish'], 'seconds': seconds}
        rows.append(row)
        print(f'seed {seed}: calibrate exit {code}, {row["frames_fused"]}/{row["capture_frame_sets"]} fused, '
              f'accuracy {row["accuracy_mm"]:.2f} mm, completeness {100 * row["completeness"]:.1f} %, feet '
              f'{100 * row["completeness_feet"]:.1f} %, seams {row["seams"]["seam_de"]:.2f}; '
              + ', '.join(f'{k} {v:.0f} s' for k, v in seconds.items()), flush=True)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'commit': commit(), 'frames': args.frames, 'board_poses': args.board_poses,
                               'rows': rows}, indent=2))
    print(f'\ncalibrate, then run, scored (commit {commit()}, {args.frames} frames, {args.board_poses} poses in '
          'pairs):\n')
    print('| seed | calibration | accuracy mm | completeness | feet (lowest 15 cm) | seam CIEDE2000 (true colours) | '
          'model step at seams / elsewhere | jitter mm | flicker | appear/vanish |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    for r in rows:
        s = r['seams']
        print(f'| {r["seed"]} | {"within the target" if r["calibration_exit"] == 0 else "weak"} | '
              f'{r["accuracy_mm"]:.2f} | {100 * r["completeness"]:.1f} % | {100 * r["completeness_feet"]:.1f} % | '
              f'{s["seam_de"]:.2f} ({s["seam_de_true_colours"]:.2f}) | '
              f'{s["model_step_seam_de"]:.2f} / {s["model_step_other_de"]:.2f} | '
              f'{r["jitter_rms_mm"]:.2f} | {r["flicker_de"]:.2f} | {100 * r["appear_vanish"]:.2f} % |')
    print(f'\nwrote {out}')


if __name__ == '__main__':
    main()
