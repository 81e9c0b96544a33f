"""Transport benchmark: an 8-camera studio bag replayed by bag_player (one process) into a
subscriber (another process), with the shipped Fast DDS profile and with stock Fast DDS.

    .venv/bin/python bench/transport.py [--seconds 10] [--rates 1 2]

Prints, per configuration: frame sets per second received complete, loss, and latency from the
scheduled publish time to the last image of a set arriving (median, p95). The bag holds colour
1280x720 rgb8 and depth 640x576 16UC1 for 8 cameras at 30 fps (28 MB per frame set).
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
FPS = 30.0


def ensure_bag(out: Path) -> Path:
    from volcap_studio.session import GroundTruth, synthesize
    from volcap_studio.studio import SynthConfig
    bag = out / 'transport_bag'
    try:
        if len(GroundTruth(bag).frames) == 30:
            return bag
    except FileNotFoundError:
        pass
    synthesize(bag, SynthConfig(cameras=8, frames=30, board_poses=0, background_frames=0, fps=FPS), overwrite=True)
    return bag


def measure(bag: Path, seconds: float, rate: float, raw: bool) -> dict:
    """Child process: subscribe, start the player, collect for ``seconds``."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from volcap_bringup.monitor import StreamMonitor
    from volcap_bringup.processes import start_node, stop
    from volcap_core import transport
    from volcap_studio.session import GroundTruth

    profile = transport.configure()
    rclpy.init()
    monitor = StreamMonitor(GroundTruth(bag).rig.names, raw=raw)
    executor = SingleThreadedExecutor()
    executor.add_node(monitor)
    player = start_node('volcap_driver', 'bag_player',
                        {'bag': str(bag), 'rate': rate, 'loop': True, 'restamp': True, 'exit_when_done': False,
                         'wait_for_subscribers': 30.0}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while not any(monitor.arrivals.values()):
            executor.spin_once(timeout_sec=0.05)
        warmup = time.monotonic() + 1.0          # let discovery and caches settle
        while time.monotonic() < warmup:
            executor.spin_once(timeout_sec=0.01)
        monitor.reset()
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            executor.spin_once(timeout_sec=0.01)
        elapsed = time.monotonic() - t0
    finally:
        stop(player)
    summary = monitor.summary()
    stamps = sorted(fs.stamp_ns for fs in monitor.sets)
    expected = round((stamps[-1] - stamps[0]) / 1e9 * FPS * rate) + 1 if len(stamps) > 1 else 0
    executor.shutdown()
    monitor.destroy_node()
    rclpy.try_shutdown()
    return {'profile': profile or 'stock Fast DDS', 'rate': rate, 'target_fps': FPS * rate,
            'sets_per_s': summary['frame_sets_complete'] / elapsed,
            'loss': max(0.0, 1 - summary['frame_sets_complete'] / expected) if expected else 1.0,
            'latency_ms_median': summary['latency_ms_median'], 'latency_ms_p95': summary['latency_ms_p95'],
            'image_latency_ms_median': summary['image_latency_ms_median'],
            'image_latency_ms_p95': summary['image_latency_ms_p95']}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--rates', type=float, nargs='+', default=[1.0, 2.0], help='playback rates (1 = 30 fps)')
    ap.add_argument('--out', default=str(REPO / 'bench_out'))
    ap.add_argument('--child', help=argparse.SUPPRESS)
    ap.add_argument('--raw', action='store_true', help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(Path(args.child), args.seconds, args.rates[0], args.raw)))
        return 0
    bag = ensure_bag(Path(args.out))
    results = []
    configs = [(False, False, rate) for rate in args.rates] + [(False, True, rate) for rate in args.rates] \
        + [(True, False, rate) for rate in args.rates]
    for stock, raw, rate in configs:
        env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID='77')
        env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
        if stock:
            env['VOLCAP_STOCK_DDS'] = '1'
        run = subprocess.run([sys.executable, __file__, '--child', str(bag), '--seconds', str(args.seconds),
                              '--rates', str(rate)] + (['--raw'] if raw else []), env=env, capture_output=True,
                             text=True, timeout=args.seconds + 120)
        if run.returncode != 0:
            print(run.stderr[-2000:], file=sys.stderr)
            return 1
        results.append(json.loads(run.stdout.strip().splitlines()[-1]))
        results[-1]['profile'] = ('stock Fast DDS' if stock else 'volcap profile') + \
            (', raw subscriber' if raw else ', decoding subscriber')
    print(f'\n8 cameras x (1280x720 rgb8 + 640x576 16UC1) = 28 MB per frame set, player and subscriber in '
          f'separate processes, {args.seconds:.0f} s per run, ms')
    print('latency: scheduled publish time to arrival, of the last image of each complete set (set) and of '
          'every image (image)')
    print(f'{"transport, subscriber":<40} {"fps":>4} {"sets/s":>7} {"loss":>6} {"set med":>8} {"set p95":>8} '
          f'{"img med":>8} {"img p95":>8}')

    def ms(v):
        return '-' if v is None else f'{v:.1f}'
    for r in results:
        print(f'{r["profile"]:<40} {r["target_fps"]:>4.0f} {r["sets_per_s"]:>7.1f} {r["loss"]:>6.1%} '
              f'{ms(r["latency_ms_median"]):>8} {ms(r["latency_ms_p95"]):>8} {ms(r["image_latency_ms_median"]):>8} '
              f'{ms(r["image_latency_ms_p95"]):>8}')
    (Path(args.out) / 'transport.json').write_text(json.dumps(results, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
