"""How fast a restarted node rejoins: a depth filter is killed (SIGKILL, as a crash) while a
camera streams, then started again; seconds from the restart to its first cleaned frame, and
how long the fusion host would name the camera silent.

    .venv/bin/python bench/rejoin.py [--runs 3]

The camera is bag_player looping a small studio bag at real time (one camera's colour, depth and
camera_info; the rig on /volcap/rig); the filter runs without a foreground mask (``mask_mode:
none``: a restarted filter with a saved clean plate loads it, one without learns a new one
first). Writes bench_out/rejoin.json.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'bench'))
from playback import ensure_bag  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--runs', type=int, default=3)
    args = ap.parse_args()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image

    from volcap_bringup.processes import start_node, stop
    from volcap_core import qos, topics, transport
    bag = ensure_bag()
    transport.configure()
    rclpy.init()
    node = rclpy.create_node('rejoin_probe')
    got = []
    node.create_subscription(Image, f'/cam0/{topics.DEPTH_CLEAN}', lambda m: got.append(time.monotonic()), qos.CAMERA)
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    def spin(seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
    played = [f'cam0/{t}' for t in (topics.COLOR_IMAGE, topics.COLOR_INFO, topics.DEPTH_IMAGE, topics.DEPTH_INFO)]
    player = start_node('volcap_driver', 'bag_player', {'bag': str(bag), 'topics': played + [topics.RIG], 'loop': True,
                                                        'restamp': True, 'exit_when_done': False})
    rejoin = []
    try:
        filt = start_node('volcap_filter', 'depth_filter', {'mask_mode': 'none'}, namespace='cam0')
        spin(20)
        for _ in range(args.runs):
            filt.send_signal(signal.SIGKILL)
            filt.wait()
            spin(2)
            got.clear()
            restarted = time.monotonic()
            filt = start_node('volcap_filter', 'depth_filter', {'mask_mode': 'none'}, namespace='cam0')
            end = restarted + 60
            while not got and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.02)
            rejoin.append(got[0] - restarted if got else None)
            print(f'restart to first cleaned frame: {rejoin[-1]:.2f} s' if got else 'no frame within 60 s', flush=True)
            spin(3)
        stop(filt)
    finally:
        stop(player)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    done = [r for r in rejoin if r is not None]
    result = {'rejoin_s': rejoin, 'median_s': float(np.median(done)) if done else None}
    (REPO / 'bench_out').mkdir(exist_ok=True)
    (REPO / 'bench_out' / 'rejoin.json').write_text(json.dumps(result, indent=2))
    print(f'median {result["median_s"]:.2f} s from restart to the first cleaned frame (process start, imports, '
          'discovery, first frame pair)' if done else 'never rejoined')
    return 0


if __name__ == '__main__':
    sys.exit(main())
