"""Rig transport benchmark: a vendor-driver-like publisher of 8 cameras at 30 fps into the
subscriptions of 8 depth filters and 8 colour correctors, each camera's two consumers in their
own process (as on a rig: the drivers in one process, volcap's nodes in others).

    .venv/bin/python bench/rig_transport.py [--frames 300] [--fps 30]

The publisher sends what the Azure Kinect driver does per camera: colour 1280x720 bgra8 and
depth 640x576 16UC1 with their camera_info, reliable keep-last 1 (the driver's queue size),
each stamped at publish time. It runs on stock Fast DDS (a vendor driver started plainly) or
with volcap's Fast DDS profile (``FASTRTPS_DEFAULT_PROFILES_FILE``, as docs/driver.md tells a
studio to start its drivers). The subscribers always use the profile, with the consumers'
QoS under test: ``sensor`` (best effort, keep-last 4, the old default) or ``camera``
(reliable, keep-last 2, volcap's default).

Prints, per configuration: the publisher's achieved rate, the share of published frames
delivered per stream (worst camera and median; target >= 99 %), latency (receive minus stamp,
median and p95) and a backlog check (median latency of the last third minus the first third: a
growing queue shows as a rise). The machine's limit, measured in the same run: the publisher
alone, unpaced, with the profile and with stock Fast DDS (sets per second it can send with
nobody listening). Writes bench_out/rig_transport.json and rig_transport.png.
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

REPO = Path(__file__).resolve().parents[1]
CAMERAS = [f'cam{i}' for i in range(8)]
DOMAIN = '78'


def publisher(frames: int, fps: float, expected_subscribers: int) -> dict:
    """Child: publish ``frames`` frame sets once every subscriber has matched."""
    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    from volcap_core.conversions import ns_to_stamp, numpy_to_image

    rclpy.init()
    node = rclpy.create_node('vendor_driver')
    driver_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.VOLATILE)
    rng = np.random.default_rng(0)
    color = numpy_to_image(rng.integers(0, 255, (720, 1280, 4), dtype=np.uint8), 'bgra8')
    depth = numpy_to_image(rng.integers(500, 3000, (576, 640), dtype=np.uint16), '16UC1')
    pubs = []
    for cam in CAMERAS:
        pubs.append((cam, node.create_publisher(Image, f'{cam}/rgb/image_raw', driver_qos),
                     node.create_publisher(CameraInfo, f'{cam}/rgb/camera_info', driver_qos),
                     node.create_publisher(Image, f'{cam}/depth/image_raw', driver_qos),
                     node.create_publisher(CameraInfo, f'{cam}/depth/camera_info', driver_qos)))
    deadline = time.monotonic() + 60
    while expected_subscribers and time.monotonic() < deadline:
        matched = sum(p[1].get_subscription_count() + p[3].get_subscription_count() for p in pubs)
        if matched >= expected_subscribers:
            break
        time.sleep(0.1)
    if expected_subscribers:
        time.sleep(1.0)   # let the readers' discovery settle
    period = 1.0 / fps
    start = time.monotonic()
    late = 0
    for k in range(frames):
        target = start + k * period
        now = time.monotonic()
        if now < target:
            time.sleep(target - now)
        else:
            late += 1
        stamp = ns_to_stamp(time.time_ns())
        for cam, pc, pci, pd, pdi in pubs:
            info = CameraInfo(width=640, height=576)
            info.header.stamp = stamp
            depth.header.stamp = stamp
            depth.header.frame_id = f'{cam}_depth_camera_link'
            pd.publish(depth)
            pdi.publish(info)
            color.header.stamp = stamp
            color.header.frame_id = f'{cam}_rgb_camera_link'
            pc.publish(color)
            pci.publish(info)
    elapsed = time.monotonic() - start
    if expected_subscribers:
        time.sleep(2.0)   # the last frames still in flight
    node.destroy_node()
    rclpy.try_shutdown()
    return {'published': frames, 'publish_fps': frames / elapsed, 'late_ticks': late}


def subscriber(camera: str, qos_name: str, seconds: float) -> dict:
    """Child: one camera's depth-filter and colour-corrector subscriptions; counts and latency."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image

    from volcap_core import qos, transport
    from volcap_core.conversions import stamp_to_ns

    transport.configure()
    rclpy.init()
    profile = {'sensor': qos.SENSOR, 'camera': qos.CAMERA}[qos_name]
    arrivals = {'filter_color': [], 'filter_depth': [], 'corrector_color': []}
    executor = SingleThreadedExecutor()
    nodes = []
    for role, streams in (('filter', ('color', 'depth')), ('corrector', ('color',))):
        node = rclpy.create_node(f'{role}_{camera}')
        for stream in streams:
            topic = f'{camera}/rgb/image_raw' if stream == 'color' else f'{camera}/depth/image_raw'
            key = f'{role}_{stream}'
            node.create_subscription(Image, topic, lambda m, key=key: arrivals[key].append(
                (time.time_ns(), stamp_to_ns(m.header.stamp))), profile)
        executor.add_node(node)
        nodes.append(node)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    executor.shutdown()
    for node in nodes:
        node.destroy_node()
    rclpy.try_shutdown()
    return {k: v for k, v in arrivals.items()}


def publisher_ceiling(pub_profile: str, frames: int) -> float:
    """Frame sets per second the publisher sends unpaced with nobody subscribed."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=DOMAIN)
    env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    if pub_profile == 'volcap':
        from volcap_core.transport import PROFILE
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(PROFILE)
    run = subprocess.run([sys.executable, __file__, '--child', 'pub', '--frames', str(frames), '--fps', '10000',
                          '--alone'], env=env, capture_output=True, text=True, timeout=300)
    if run.returncode != 0:
        raise RuntimeError(run.stderr[-2000:])
    return json.loads(run.stdout.strip().splitlines()[-1])['publish_fps']


def run_config(pub_profile: str, qos_name: str, frames: int, fps: float) -> dict:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=DOMAIN)
    env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    seconds = frames / fps + 25
    subs = [subprocess.Popen([sys.executable, __file__, '--child', 'sub', '--camera', cam, '--qos', qos_name,
                              '--seconds', str(seconds)], env=env, stdout=subprocess.PIPE, text=True)
            for cam in CAMERAS]
    pub_env = dict(env)
    if pub_profile == 'volcap':
        from volcap_core.transport import PROFILE
        pub_env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(PROFILE)
    pub = subprocess.run([sys.executable, __file__, '--child', 'pub', '--frames', str(frames), '--fps', str(fps)],
                         env=pub_env, capture_output=True, text=True, timeout=seconds + 60)
    if pub.returncode != 0:
        raise RuntimeError(pub.stderr[-2000:])
    published = json.loads(pub.stdout.strip().splitlines()[-1])
    per_camera = {}
    latencies = []
    for cam, proc in zip(CAMERAS, subs):
        out, _ = proc.communicate(timeout=seconds + 60)
        arrivals = json.loads(out.strip().splitlines()[-1])
        per_camera[cam] = {k: len(v) / frames for k, v in arrivals.items()}
        latencies += [(recv, (recv - stamp) / 1e6) for v in arrivals.values() for recv, stamp in v]
    latencies.sort()
    lat = np.array([v for _, v in latencies])
    third = max(1, len(lat) // 3)
    delivered = np.array([share for row in per_camera.values() for share in row.values()])
    return {'publisher': 'stock Fast DDS' if pub_profile == 'stock' else 'volcap profile', 'qos': qos_name,
            'published': published, 'per_camera': per_camera,
            'delivered_worst': float(delivered.min()), 'delivered_median': float(np.median(delivered)),
            'latency_ms_median': float(np.median(lat)) if lat.size else None,
            'latency_ms_p95': float(np.percentile(lat, 95)) if lat.size else None,
            'backlog_ms': float(np.median(lat[-third:]) - np.median(lat[:third])) if lat.size else None}


def figure(results: list[dict], out: Path) -> None:
    import matplotlib.pyplot as plt

    from volcap_core.figures import save_figure
    fig, ax = plt.subplots(figsize=(8, 4))
    labels = [f'{r["publisher"]}\n{r["qos"]} QoS' for r in results]
    x = np.arange(len(results))
    ax.bar(x - 0.2, [100 * r['delivered_worst'] for r in results], 0.4, label='worst stream')
    ax.bar(x + 0.2, [100 * r['delivered_median'] for r in results], 0.4, label='median stream')
    ax.axhline(99, color='k', linestyle='--', linewidth=1, label='target 99 %')
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel('frames delivered (%)')
    ax.set_title('8 cameras x (1280x720 colour + 640x576 depth) at 30 fps into 16 consumers')
    ax.legend(loc='lower right', fontsize=8)
    save_figure(fig, out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--frames', type=int, default=300)
    ap.add_argument('--fps', type=float, default=30.0)
    ap.add_argument('--publishers', nargs='+', default=['stock', 'volcap'], choices=['stock', 'volcap'])
    ap.add_argument('--qos', nargs='+', default=['sensor', 'camera'], choices=['sensor', 'camera'])
    ap.add_argument('--out', default=str(REPO / 'bench_out'))
    ap.add_argument('--child', choices=['pub', 'sub'], help=argparse.SUPPRESS)
    ap.add_argument('--camera', help=argparse.SUPPRESS)
    ap.add_argument('--seconds', type=float, help=argparse.SUPPRESS)
    ap.add_argument('--alone', action='store_true', help=argparse.SUPPRESS)
    ap.add_argument('--image-subscribers', type=int, default=3 * len(CAMERAS), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child == 'pub':
        print(json.dumps(publisher(args.frames, args.fps, expected_subscribers=0 if args.alone else
                                   args.image_subscribers)))
        return 0
    if args.child == 'sub':
        print(json.dumps(subscriber(args.camera, args.qos[0], args.seconds)))
        return 0
    from tqdm import tqdm
    configs = [(p, q) for p in args.publishers for q in args.qos]
    results = []
    ceilings = {p: publisher_ceiling(p, 100) for p in args.publishers}
    for pub_profile, qos_name in tqdm(configs, desc='configurations', unit='run'):
        results.append(run_config(pub_profile, qos_name, args.frames, args.fps))
    print(f'\n{args.frames} frame sets at {args.fps:.0f} fps, 8 cameras, each camera\'s depth filter (colour + depth) '
          'and colour corrector (colour) subscriptions in one process per camera')
    print(f'{"publisher":<16} {"qos":<7} {"pub fps":>7} {"worst":>7} {"median":>7} {"lat med":>8} {"lat p95":>8} '
          f'{"backlog":>8}')
    for r in results:
        print(f'{r["publisher"]:<16} {r["qos"]:<7} {r["published"]["publish_fps"]:>7.1f} {r["delivered_worst"]:>7.1%} '
              f'{r["delivered_median"]:>7.1%} {r["latency_ms_median"]:>8.1f} {r["latency_ms_p95"]:>8.1f} '
              f'{r["backlog_ms"]:>+8.1f}')
    for profile, ceiling in ceilings.items():
        print(f'machine limit: the publisher alone, unpaced, {"volcap profile" if profile == "volcap" else "stock"}: '
              f'{ceiling:.1f} frame sets/s ({ceiling / args.fps:.2f}x the target rate)')
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'rig_transport.json').write_text(json.dumps({'publisher_alone_fps': ceilings, 'runs': results}, indent=2))
    figure(results, out / 'rig_transport.png')
    print(f'wrote {out / "rig_transport.json"} and rig_transport.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
