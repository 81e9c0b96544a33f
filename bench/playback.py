"""Playback speed of bag_player: wall-clock time over bag time between the parts of a studio
session, at several rates (moved here from the test suite: a timing is not a test).

    .venv/bin/python bench/playback.py [BAG]

Without BAG a small studio session is rendered into bench_out/playback_bag. Prints, per setting,
the measured ratio and the expected one (1/rate; 0 for as_fast_as_possible).
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SETTINGS = [({'rate': 1.0}, 1.0), ({'rate': 2.0}, 0.5), ({'as_fast_as_possible': True}, 0.0)]
TOPIC = 'cam2/color/camera_info'


def ensure_bag() -> Path:
    from volcap_studio.session import synthesize
    from volcap_studio.studio import SynthConfig
    bag = REPO / 'bench_out' / 'playback_bag'
    if not (bag / 'metadata.yaml').exists():
        synthesize(bag, SynthConfig(cameras=8, frames=2, board_poses=2, background_frames=1, seed=7), overwrite=True)
    return bag


def measure(bag: Path, params: dict) -> float:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo

    from volcap_bringup.processes import start_node, stop
    from volcap_core import qos
    from volcap_core.conversions import stamp_to_ns
    got = []
    node = rclpy.create_node('playback_probe')
    node.create_subscription(CameraInfo, TOPIC, lambda m: got.append((time.monotonic(), stamp_to_ns(m.header.stamp))),
                             qos.EVERY_FRAME)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    player = start_node('volcap_driver', 'bag_player', {'bag': str(bag), 'wait_for_subscribers': 20.0,
                                                        'topics': [TOPIC], **params})
    try:
        deadline = time.monotonic() + 120
        while player.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
    finally:
        stop(player)
        executor.shutdown()
        node.destroy_node()
    arrivals = np.array([a for a, _ in got])
    stamps = np.array([s for _, s in got]) / 1e9
    wall, bag_s = np.diff(arrivals), np.diff(stamps)
    long = bag_s > 0.5          # the ~1 s gaps between session parts: delivery jitter hardly matters there
    return float(wall[long].sum() / bag_s[long].sum())


def main() -> int:
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    import rclpy

    from volcap_core import transport
    bag = Path(sys.argv[1]) if len(sys.argv) > 1 else ensure_bag()
    transport.configure()
    rclpy.init()
    try:
        print('| setting | wall / bag time | expected |\n|---|---|---|')
        for params, expected in SETTINGS:
            print(f'| {params} | {measure(bag, params):.3f} | {expected:.3f} |', flush=True)
    finally:
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
