"""How long a rig's node processes take to end after SIGINT, once they have done their work:
`volcap run` (bag_player, camera_pipeline x8, tsdf_fusion, each its own process) on a small
studio bag, with each node's ``main`` as shipped (``volcap_core.ros.node_main``: the node shut
down, then ``os._exit``) and as it was before (``sys.exit(run_node(...))``: the interpreter's
teardown after the node's), each while ``--load`` busy processes take the cores (as a heavy test
beside the demo does in CI).

    .venv/bin/python bench/shutdown.py [--runs 2] [--load 0 2]

The graph session times each process from the signals to its exit
(``GraphSession.stop_seconds``, ``metrics.json``'s ``node_stop_s``) and kills one still running
10 s later. Writes bench_out/shutdown.json.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import tempfile
from contextlib import nullcontext
from pathlib import Path
from unittest import mock

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'bench'))
from playback import ensure_bag  # noqa: E402

# The "before" main: the same node, ended by sys.exit and so by the interpreter's teardown. Run as
# `python -c TEARDOWN_MAIN python -m <module> <args>` (the graph session's command, behind it).
TEARDOWN_MAIN = '''
import importlib, sys
from volcap_core.ros import run_node
module = importlib.import_module(sys.argv[3])
sys.argv = [sys.argv[3], *sys.argv[4:]]
module.node_main = lambda factory, args=None: sys.exit(run_node(factory, args))
module.main()
'''


IDENTITY = {'method': 'matrix_3x3', 'matrix': [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}


def _busy() -> None:
    while True:
        pass


def _calibration(bag: Path, path: Path) -> Path:
    import numpy as np

    from volcap_core.calibration import Calibration, CameraCalibration, StudioFrame
    from volcap_studio.session import GroundTruth
    gt = GroundTruth(bag)
    cameras = gt.rig.names
    calibration = Calibration(cameras[0], f'{cameras[0]}_color_optical_frame',
                              {c: CameraCalibration(gt.T_world_color(c), f'{c}_color_optical_frame', color=IDENTITY)
                               for c in cameras})
    calibration.studio = StudioFrame(np.linalg.inv(np.asarray(gt.doc['T_studio_world'], float)),
                                     details={'source': 'floor'})
    calibration.save(path)
    return path


def run_once(bag: Path, calibration: Path, main: str, load: int) -> dict:
    from volcap_bringup import session as session_module
    from volcap_bringup.graph import RunConfig
    from volcap_bringup.run_graph import run_graph
    start_node = session_module.start_node

    def teardown_start(*args, **kwargs):
        return start_node(*args, wrapper=(sys.executable, '-c', TEARDOWN_MAIN), **kwargs)
    busy = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(load)]
    with tempfile.TemporaryDirectory() as out:
        with mock.patch.object(session_module, 'start_node', teardown_start) if main == 'teardown' else nullcontext():
            for p in busy:
                p.start()
            try:
                metrics = run_graph(RunConfig(bag, calibration, out, rate=0.25, progress=False))
            finally:
                for p in busy:    # SIGKILL: a child forked after rclpy.init keeps rclpy's SIGTERM handler
                    p.kill()
                    p.join()
    stops = metrics['node_stop_s']
    return {'main': main, 'load': load, 'node_stop_s': stops, 'exit_codes': metrics['node_exit_codes'],
            'killed': sorted(n for n, c in metrics['node_exit_codes'].items() if c == -9),
            'median_s': statistics.median(stops.values()), 'max_s': max(stops.values())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--runs', type=int, default=2)
    ap.add_argument('--load', type=int, nargs='+', default=[0, 2], help='busy processes beside the graph')
    args = ap.parse_args()
    bag = ensure_bag()
    calibration = _calibration(bag, REPO / 'bench_out' / 'shutdown_calibration.yaml')
    results = []
    for load in args.load:
        for run in range(args.runs):
            for main_kind in ('node_main', 'teardown'):
                r = run_once(bag, calibration, main_kind, load)
                results.append(r)
                print(f'load {load}  run {run + 1}  {main_kind:9s}  stopped in median {r["median_s"]:.2f} s, '
                      f'max {r["max_s"]:.2f} s  killed {r["killed"] or "none"}', flush=True)
    summary = {}
    for load in args.load:
        for main_kind in ('node_main', 'teardown'):
            rs = [r for r in results if r['load'] == load and r['main'] == main_kind]
            every = [s for r in rs for s in r['node_stop_s'].values()]
            summary[f'{main_kind}_load{load}'] = {'median_s': round(statistics.median(every), 2),
                                                   'max_s': round(max(every), 2),
                                                   'killed': sum(len(r['killed']) for r in rs)}
    out = REPO / 'bench_out' / 'shutdown.json'
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({'summary': summary, 'runs': results}, indent=1))
    for k, v in summary.items():
        print(f'{k:20s} median {v["median_s"]:.2f} s  max {v["max_s"]:.2f} s  killed {v["killed"]}')
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
