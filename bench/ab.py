"""A/B: the same commands on the same bag with an older commit and with this checkout, and how
their figures differ. Restructuring code must not change results; this says whether it did.

    python bench/ab.py BAG --old REV [--calibration CAL] [--out bench_out/ab] [--frames 3] [--run]

The old commit is checked out as a git worktree (``bench_out/ab/old``); each side runs as
``python -m volcap_bringup.cli`` with its own ``src/volcap_*`` first on ``PYTHONPATH`` (the same
.venv). Compared, each on both sides:

- ``volcap calibrate BAG --accept-weak``: every camera's ``T_world_color`` (largest element
  difference), reprojection RMS, predicted error and colour model;
- ``volcap eval depth BAG --frames N``: every method's scores;
- ``volcap eval color BAG --calibration CAL --frames 4 --no-chart``: every method's CIEDE2000 /
  PSNR / truth scores (CAL: the new side's calibration unless given);
- with ``--run``: ``volcap run BAG --calibration CAL --voxel 0.01`` (each side's default graph)
  and ``volcap eval fusion`` of its sequence: accuracy, completeness, frames fused and every
  frame's triangle count.

Writes ``OUT/ab.json`` and prints one line per figure that differs (and how many agree).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]


def tree_env(tree: Path) -> dict:
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(str(p) for p in sorted((tree / 'src').glob('volcap_*')))
    return env


def volcap(tree: Path, *args) -> float:
    """Runs the command with ``tree``'s sources; returns its wall time. Exit 3 (weak) is fine."""
    t0 = time.monotonic()
    run = subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', *map(str, args)], env=tree_env(tree),
                         capture_output=True, text=True)
    if run.returncode not in (0, 3):
        raise SystemExit(f'{tree.name}: volcap {" ".join(map(str, args))} exited {run.returncode}:\n'
                         f'{run.stderr[-3000:]}')
    return time.monotonic() - t0


def flatten(doc, prefix='') -> dict[str, float]:
    """Every number of a JSON/YAML document by its key path (lists of numbers element-wise)."""
    out = {}
    if isinstance(doc, dict):
        for k, v in doc.items():
            if k in ('created', 'seconds', 'timings_ms', 'figures', 'wall_s', 'bag', 'calibration', 'folder',
                     'ms_per_frame'):     # timings are bench/'s other scripts' to compare
                continue
            out.update(flatten(v, f'{prefix}{k}.'))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out.update(flatten(v, f'{prefix}{i}.'))
    elif isinstance(doc, (int, float)) and not isinstance(doc, bool):
        out[prefix.rstrip('.')] = float(doc)
    return out


def compare(name: str, old: dict, new: dict, tolerance: float = 1e-9) -> dict:
    a, b = flatten(old), flatten(new)
    keys = sorted(set(a) | set(b))
    differ = []
    for k in keys:
        x, y = a.get(k), b.get(k)
        if x is None or y is None:
            differ.append({'key': k, 'old': x, 'new': y})
        elif not (np.isnan(x) and np.isnan(y)) and abs(x - y) > tolerance * max(1.0, abs(x)):
            differ.append({'key': k, 'old': x, 'new': y, 'diff': y - x})
    print(f'{name}: {len(keys) - len(differ)} of {len(keys)} figures equal')
    for d in differ[:20]:
        print(f'  {d["key"]}: {d["old"]} -> {d["new"]}')
    return {'figures': len(keys), 'equal': len(keys) - len(differ), 'differ': differ}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('bag')
    p.add_argument('--old', required=True, help='the commit to compare against')
    p.add_argument('--calibration', help='calibration for eval color (default: the new side\'s)')
    p.add_argument('--out', default='bench_out/ab')
    p.add_argument('--frames', type=int, default=3, help='capture frame sets for eval depth')
    p.add_argument('--run', action='store_true', help='also compare volcap run + eval fusion')
    args = p.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    old_tree = out / 'old'
    if old_tree.exists():
        subprocess.run(['git', '-C', str(REPO), 'worktree', 'remove', '--force', str(old_tree)], check=False)
    subprocess.run(['git', '-C', str(REPO), 'worktree', 'add', '--detach', str(old_tree), args.old], check=True,
                   capture_output=True)
    new_rev = subprocess.run(['git', '-C', str(REPO), 'rev-parse', '--short', 'HEAD'], capture_output=True,
                             text=True).stdout.strip()
    result = {'bag': str(args.bag), 'old': args.old, 'new': new_rev, 'commands': {}}
    sides = {'old': old_tree, 'new': REPO}
    times: dict[str, dict[str, float]] = {side: {} for side in sides}
    for side, tree in sides.items():
        d = out / f'{side}_out'
        d.mkdir(exist_ok=True)
        print(f'{side} ({tree}): calibrate, eval depth, eval color', flush=True)
        times[side]['calibrate'] = volcap(tree, 'calibrate', args.bag, '--out', d / 'calibration.yaml', '--quiet',
                                          '--accept-weak')
        times[side]['eval depth'] = volcap(tree, 'eval', 'depth', args.bag, '--frames', args.frames, '--json',
                                           d / 'depth.json', '--quiet')
    calibration = args.calibration or out / 'new_out' / 'calibration.yaml'
    for side, tree in sides.items():
        d = out / f'{side}_out'
        times[side]['eval color'] = volcap(tree, 'eval', 'color', args.bag, '--calibration', calibration,
                                           '--frames', 4, '--no-chart', '--json', d / 'colour.json', '--quiet')
        if args.run:
            times[side]['run'] = volcap(tree, 'run', args.bag, '--calibration', calibration, '--out', d / 'run',
                                        '--voxel', 0.01, '--quiet')
            volcap(tree, 'eval', 'fusion', d / 'run', args.bag, '--json', d / 'fusion.json', '--quiet')
            metrics = json.loads((d / 'run' / 'metrics.json').read_text())
            (d / 'run_frames.json').write_text(json.dumps(
                {'frames_written': metrics['frames_written'], 'triangles': [f['triangles'] for f in metrics['frames']],
                 'missing': [len(f['missing']) for f in metrics['frames']]}))
    load = {'calibration': lambda p: yaml.safe_load(p.read_text()), 'depth': lambda p: json.loads(p.read_text()),
            'colour': lambda p: json.loads(p.read_text())}
    if args.run:
        load.update({'fusion': lambda p: json.loads(p.read_text()), 'run_frames': lambda p: json.loads(p.read_text())})
    for name, fn in load.items():
        suffix = '.yaml' if name == 'calibration' else '.json'
        result['commands'][name] = compare(name, fn(out / 'old_out' / f'{name}{suffix}'),
                                           fn(out / 'new_out' / f'{name}{suffix}'))
    result['seconds'] = times
    (out / 'ab.json').write_text(json.dumps(result, indent=1))
    print(f'wrote {out / "ab.json"}')
    subprocess.run(['git', '-C', str(REPO), 'worktree', 'remove', '--force', str(old_tree)], check=False)


if __name__ == '__main__':
    main()
