"""The graph across hosts: a capture host and a fusion host as two network namespaces joined by a
veth link on this machine, Fast DDS over UDP between them (shared memory cannot cross hosts).

    .venv/bin/python bench/multihost.py [--seconds 10] [--rates 5,10,30]     (as root)
    .venv/bin/python bench/multihost.py --wire WIREBAG [--rates 30]          (the compact wire)

What crosses the link is what the capture host's depth filters and colour correctors send the
fusion host, 8 cameras: ``cam<i>/color/image_corrected`` (rgb8 1280x720) and
``cam<i>/depth/image_clean`` (16UC1 at the live depth scale, 640x360) with their camera_info,
26 MB per frame set, published reliably (the drivers' QoS) and received as tsdf_fusion does
(reliable keep-last 2). Per configuration, offered frame sets per second against delivered (the
worst camera stream and the median), latency (receive minus capture stamp, p50/p95):

1. the machine's limit in the same run: raw UDP, 64 KB datagrams, one sender and one receiver
   process across the link, no DDS (GB/s);
2. volcap's single-host profile and the multi-host profile (``VOLCAP_TRANSPORT=multihost``:
   32 MB socket buffers) at each offered rate;
3. the multi-host profile under 1 % packet loss on the link (iptables ``statistic``, as netem
   is not in this kernel: no added delay could be measured here);
4. a 2 s link drop (``ip link set down``, then up) mid-run: frames lost, time from link up to
   the next delivered frame, and the rate after recovery against the rate before.

The namespaces' net.core.rmem_max/wmem_max are the host's (not per namespace in this kernel):
the run raises them to 32 MB and puts them back. Writes bench_out/multihost.json and
multihost.png.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
HOSTS = {'capture': ('volcap_capture', 'vc_cap0', '10.77.0.1'), 'fusion': ('volcap_fusion', 'vc_fus0', '10.77.0.2')}
CAMERAS = [f'cam{i}' for i in range(8)]
DOMAIN = '81'


def sh(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(list(args), capture_output=True, text=True, check=check)


def make_hosts() -> None:
    remove_hosts()
    (cap_ns, cap_if, _), (fus_ns, fus_if, _) = HOSTS['capture'], HOSTS['fusion']
    sh('ip', 'netns', 'add', cap_ns)
    sh('ip', 'netns', 'add', fus_ns)
    sh('ip', 'link', 'add', cap_if, 'type', 'veth', 'peer', 'name', fus_if)
    for ns, iface, ip in HOSTS.values():
        sh('ip', 'link', 'set', iface, 'netns', ns)
        sh('ip', '-n', ns, 'addr', 'add', f'{ip}/24', 'dev', iface)
        sh('ip', '-n', ns, 'link', 'set', 'lo', 'up')
        sh('ip', '-n', ns, 'link', 'set', iface, 'up')
        sh('ip', '-n', ns, 'link', 'set', iface, 'txqueuelen', '10000')


def remove_hosts() -> None:
    for ns, _, _ in HOSTS.values():
        sh('ip', 'netns', 'del', ns, check=False)


def link(up: bool) -> None:
    ns, iface, _ = HOSTS['capture']
    sh('ip', '-n', ns, 'link', 'set', iface, 'up' if up else 'down')


def loss(probability: float) -> None:
    """Drop this share of the packets arriving at the fusion host (0: none)."""
    ns = HOSTS['fusion'][0]
    sh('ip', 'netns', 'exec', ns, 'iptables', '-F', 'INPUT')
    if probability > 0:
        sh('ip', 'netns', 'exec', ns, 'iptables', '-A', 'INPUT', '-m', 'statistic', '--mode', 'random',
           '--probability', str(probability), '-j', 'DROP')


def in_host(host: str, *command: str, env: dict | None = None, **popen) -> subprocess.Popen:
    return subprocess.Popen(['ip', 'netns', 'exec', HOSTS[host][0], *command], env=env, **popen)


def ros_env(transport: str) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=DOMAIN, ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET',
               VOLCAP_TRANSPORT=transport)
    env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    return env


# children --------------------------------------------------------------------------------------
def wire_publisher(seconds: float, fps: float, start_at: float, wire_bag: str) -> dict:
    """Child on the capture host: 8 camera pipelines' compact wire, the recorded wire bag's frame
    sets in turn with fresh stamps (CDR patched, as the bag player restamps)."""
    import rclpy
    from sensor_msgs.msg import CameraInfo, CompressedImage

    from volcap_core import qos, transport, wire
    from volcap_core.bag_reader import BagReader
    from volcap_driver.playback import restamp_cdr
    transport.configure()
    rclpy.init()
    node = rclpy.create_node('capture_host')
    kinds = {wire.WIRE_DEPTH: CompressedImage, wire.WIRE_COLOR: CompressedImage, wire.WIRE_DEPTH_INFO: CameraInfo,
             wire.WIRE_COLOR_INFO: CameraInfo}
    sets: dict[int, list] = {}
    with BagReader(wire_bag) as reader:
        for m in reader.messages([f'{c}/{t}' for c in CAMERAS for t in kinds]):
            sets.setdefault(m.stamp_ns, []).append((m.topic, m.data))
    frames = [sets[s] for s in sorted(sets)]
    pubs = {f'{c}/{t}': node.create_publisher(k, f'{c}/{t}', qos.DRIVER) for c in CAMERAS for t, k in kinds.items()}
    while time.time() < start_at:
        time.sleep(0.01)
    sent, sent_bytes, k, t0 = 0, 0, 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        delay = t0 + k / fps - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        stamp = time.time_ns()
        for topic, data in frames[k % len(frames)]:
            data = restamp_cdr(data, stamp)
            pubs[topic].publish(data)
            sent_bytes += len(data)
        sent += 1
        k += 1
    elapsed = time.monotonic() - t0
    time.sleep(2.0)
    node.destroy_node()
    rclpy.try_shutdown()
    return {'sent_sets': sent, 'sent_fps': sent / elapsed, 'payload_mbit_s': sent_bytes * 8 / elapsed / 1e6}


def publisher(seconds: float, fps: float, start_at: float) -> dict:
    """Child on the capture host: the filters' and correctors' output of 8 cameras."""
    import rclpy
    from sensor_msgs.msg import CameraInfo, Image

    from volcap_core import qos, topics, transport
    from volcap_core.conversions import ns_to_stamp, numpy_to_image
    transport.configure()
    rclpy.init()
    node = rclpy.create_node('capture_host')
    rng = np.random.default_rng(0)
    color = numpy_to_image(rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8), 'rgb8')
    depth = numpy_to_image(rng.integers(500, 3000, (360, 640), dtype=np.uint16), '16UC1')
    pubs = [(node.create_publisher(Image, f'{c}/{topics.DEPTH_CLEAN}', qos.DRIVER),
             node.create_publisher(CameraInfo, f'{c}/{topics.DEPTH_CLEAN_INFO}', qos.DRIVER),
             node.create_publisher(Image, f'{c}/{topics.COLOR_CORRECTED}', qos.DRIVER),
             node.create_publisher(CameraInfo, f'{c}/{topics.COLOR_CORRECTED_INFO}', qos.DRIVER)) for c in CAMERAS]
    while time.time() < start_at:
        time.sleep(0.01)
    sent, k, t0 = 0, 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        target = t0 + k / fps
        delay = target - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        stamp = ns_to_stamp(time.time_ns())
        for pd, pdi, pc, pci in pubs:
            info = CameraInfo(width=640, height=360)
            info.header.stamp = depth.header.stamp = color.header.stamp = stamp
            pdi.publish(info)
            pd.publish(depth)
            pci.publish(info)
            pc.publish(color)
        sent += 1
        k += 1
    elapsed = time.monotonic() - t0
    time.sleep(2.0)          # the last frames in flight, and retransmissions
    node.destroy_node()
    rclpy.try_shutdown()
    return {'sent_sets': sent, 'sent_fps': sent / elapsed}


def subscriber(seconds: float, wire_bag: str = '') -> dict:
    """Child on the fusion host: tsdf_fusion's subscriptions (its wire's with ``wire_bag``);
    (receive ns, stamp ns) per image."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CompressedImage, Image

    from volcap_core import qos, topics, transport, wire
    from volcap_core.cdr import cdr_stamp_ns
    transport.configure()
    rclpy.init()
    node = rclpy.create_node('fusion_host')
    arrivals = {f'{c}/{s}': [] for c in CAMERAS for s in ('depth', 'color')}
    streams = ((('depth', wire.WIRE_DEPTH), ('color', wire.WIRE_COLOR)) if wire_bag
               else (('depth', topics.DEPTH_CLEAN), ('color', topics.COLOR_CORRECTED)))
    kind = CompressedImage if wire_bag else Image
    for c in CAMERAS:
        for stream, topic in streams:
            node.create_subscription(kind, f'{c}/{topic}', lambda data, key=f'{c}/{stream}': arrivals[key].append(
                (time.time_ns(), cdr_stamp_ns(data))), qos.CAMERA, raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return arrivals


def udp_sink(port: int, seconds: float) -> dict:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 32 << 20)
    s.bind(('0.0.0.0', port))
    s.settimeout(0.5)
    got, first, last = 0, None, None
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            n = len(s.recv(65536))
        except socket.timeout:
            continue
        now = time.monotonic()
        first = first or now
        last = now
        got += n
    return {'bytes': got, 'seconds': (last - first) if first and last and last > first else None}


def udp_source(host: str, port: int, seconds: float) -> dict:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 32 << 20)
    payload = bytes(65000)
    sent, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        try:
            sent += s.sendto(payload, (host, port))
        except OSError:
            pass
    return {'bytes': sent, 'seconds': time.monotonic() - t0}


# runs -----------------------------------------------------------------------------------------
def child(host: str, role: str, transport: str, **kwargs) -> subprocess.Popen:
    args = [sys.executable, __file__, '--child', role] + [f'--{k.replace("_", "-")}={v}' for k, v in kwargs.items()]
    return in_host(host, *args, env=ros_env(transport), stdout=subprocess.PIPE, text=True)


def result_of(proc: subprocess.Popen, timeout: float) -> dict:
    out, _ = proc.communicate(timeout=timeout)
    return json.loads(out.strip().splitlines()[-1])


def udp_limit(seconds: float = 3.0) -> float:
    sink = child('fusion', 'udp-sink', 'single', seconds=seconds + 3)
    time.sleep(1.0)
    source = child('capture', 'udp-source', 'single', seconds=seconds)
    result_of(source, seconds + 30)
    got = result_of(sink, seconds + 30)
    return got['bytes'] / got['seconds'] / 1e9 if got['seconds'] else 0.0


def link_bytes() -> int:
    """Bytes the capture host's end of the link has sent (the kernel's counter)."""
    ns, iface, _ = HOSTS['capture']
    return int(sh('ip', 'netns', 'exec', ns, 'cat', f'/sys/class/net/{iface}/statistics/tx_bytes').stdout)


def dds_run(transport: str, fps: float, seconds: float, events=None, wire_bag: str = '') -> dict:
    """One run: subscriber on the fusion host, publisher on the capture host; ``events``:
    [(seconds after the start, callable)] done meanwhile (link down/up). ``wire_bag``: the
    camera pipelines' compact wire (recorded by ``volcap wire``) instead of full-size images."""
    settle = 6.0               # discovery across the link before the first frame
    extra = {'wire_bag': wire_bag} if wire_bag else {}
    sub = child('fusion', 'sub', transport, seconds=seconds + settle + 6, **extra)
    start_at = time.time() + settle
    before = link_bytes()
    pub = child('capture', 'pub', transport, seconds=seconds, fps=fps, start_at=start_at, **extra)
    marks = {}
    for at, action in events or []:
        delay = start_at + at - time.time()
        if delay > 0:
            time.sleep(delay)
        marks[action.__name__] = time.time_ns()
        action()
    sent = result_of(pub, seconds + settle + 60)
    arrivals = result_of(sub, seconds + settle + 60)
    # over the whole run (discovery, the 2 s of retransmissions after): a bound on the stream's rate
    sent['link_mbit_s'] = (link_bytes() - before) * 8 / seconds / 1e6
    return summarise(sent, arrivals, marks)


def summarise(sent: dict, arrivals: dict, marks: dict) -> dict:
    shares = [len(v) / sent['sent_sets'] for v in arrivals.values()]
    latency = np.array([(r - s) / 1e6 for v in arrivals.values() for r, s in v])
    out = {**sent, 'delivered_worst': min(shares), 'delivered_median': float(np.median(shares)),
           'latency_ms_p50': float(np.percentile(latency, 50)) if latency.size else None,
           'latency_ms_p95': float(np.percentile(latency, 95)) if latency.size else None}
    if 'down' in marks and 'up' in marks:
        down, up = marks['down'], marks['up']
        stamps = sorted({s for v in arrivals.values() for _, s in v})
        received = sorted(r for v in arrivals.values() for r, _ in v)
        before = [s for s in stamps if s < down]
        after = [r for r in received if r > up]
        period = 1e9 / sent['sent_fps']
        out['link_down_s'] = (up - down) / 1e9
        out['sets_during_drop_delivered'] = sum(1 for s in stamps if down <= s < up)
        out['first_frame_after_up_s'] = (after[0] - up) / 1e9 if after else None
        fresh = sorted(r for v in arrivals.values() for r, s in v if s >= up)
        out['first_new_frame_after_up_s'] = (fresh[0] - up) / 1e9 if fresh else None
        out['sets_lost'] = sent['sent_sets'] - len(stamps)
        out['seconds_of_sets_lost'] = out['sets_lost'] / sent['sent_fps']
        span_before = (before[-1] - before[0]) / 1e9 if len(before) > 1 else None
        late = [s for s in stamps if s >= up + 2e9]
        span_after = (late[-1] - late[0]) / 1e9 if len(late) > 1 else None
        out['sets_per_s_before'] = (len(before) - 1) / span_before if span_before else None
        out['sets_per_s_after_recovery'] = (len(late) - 1) / span_after if span_after else None
        out['offered_period_ms'] = period / 1e6
    return out


def figure(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    runs = result['runs']
    fig, ax = plt.subplots(figsize=(9, 4))
    labels = [f'{r["profile"]}\n{r["offered_fps"]:.0f} fps{" 1 % loss" if r.get("loss") else ""}'
              f'{" link drop" if "link_down_s" in r else ""}' for r in runs]
    x = np.arange(len(runs))
    ax.bar(x - 0.2, [100 * r['delivered_worst'] for r in runs], 0.4, label='worst stream')
    ax.bar(x + 0.2, [100 * r['delivered_median'] for r in runs], 0.4, label='median stream')
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel('frame sets delivered (%)')
    what = 'compact wire' if result.get('wire_bag') else '26 MB/set'
    ax.set_title(f'8 cameras ({what}) capture host -> fusion host over UDP; raw UDP limit '
                 f'{result["udp_limit_gb_per_s"]:.2f} GB/s', fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--rates', default='5,10,30', help='offered frame sets per second')
    ap.add_argument('--out', default=str(REPO / 'bench_out'))
    ap.add_argument('--wire', '--wire-bag', dest='wire_bag', default='',
                    help='a wire bag (volcap wire): send the camera pipelines\' compact wire instead of full-size '
                         'images (multi-host profile, each rate, delivered share and Mbit/s on the link)')
    ap.add_argument('--child', help=argparse.SUPPRESS)
    ap.add_argument('--fps', type=float, help=argparse.SUPPRESS)
    ap.add_argument('--start-at', type=float, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        result = {'pub': lambda: (wire_publisher(args.seconds, args.fps, args.start_at, args.wire_bag)
                                  if args.wire_bag else publisher(args.seconds, args.fps, args.start_at)),
                  'sub': lambda: subscriber(args.seconds, args.wire_bag),
                  'udp-sink': lambda: udp_sink(5999, args.seconds),
                  'udp-source': lambda: udp_source(HOSTS['fusion'][2], 5999, args.seconds)}[args.child]()
        print(json.dumps(result))
        return 0
    if os.geteuid() != 0:
        print('bench/multihost.py makes network namespaces: run it as root', file=sys.stderr)
        return 2
    limits = {k: Path(f'/proc/sys/net/core/{k}').read_text().strip() for k in ('rmem_max', 'wmem_max')}
    runs = []
    try:
        for k in limits:
            Path(f'/proc/sys/net/core/{k}').write_text(str(32 << 20))
        make_hosts()
        limit = udp_limit()
        print(f'machine limit: raw UDP over the link, 64 KB datagrams: {limit:.2f} GB/s '
              f'({limit * 1e3 / 26.2:.0f} frame sets/s of 26 MB)', flush=True)
        rates = [float(r) for r in args.rates.split(',')]

        def report(r):
            extra = ''
            if 'link_down_s' in r:
                extra = (f'; link down {r["link_down_s"]:.1f} s: {r["sets_lost"]} sets lost '
                         f'({r["seconds_of_sets_lost"]:.1f} s of capture), first frame {r["first_frame_after_up_s"]:.2f} s '
                         f'after up, first one captured after up {r["first_new_frame_after_up_s"]:.2f} s after up, '
                         f'{r["sets_per_s_before"] or 0:.1f} sets/s before, '
                         f'{r["sets_per_s_after_recovery"] or 0:.1f} after')
            print(f'{r["profile"]:<10} {r["offered_fps"]:>5.0f} fps offered ({r["sent_fps"]:.1f} sent)'
                  f'{" 1 % loss" if r.get("loss") else ""}: delivered worst {100 * r["delivered_worst"]:.1f} %, '
                  f'median {100 * r["delivered_median"]:.1f} %, latency p50 {r["latency_ms_p50"] or 0:.0f} ms '
                  f'p95 {r["latency_ms_p95"] or 0:.0f} ms{extra}', flush=True)
        if args.wire_bag:
            for fps in rates:
                runs.append({'profile': 'multihost', 'wire': True, 'offered_fps': fps,
                             **dds_run('multihost', fps, args.seconds, wire_bag=args.wire_bag)})
                report(runs[-1])
                print(f'  wire: {runs[-1]["payload_mbit_s"]:.0f} Mbit/s of messages, {runs[-1]["link_mbit_s"]:.0f} '
                      'Mbit/s on the link (whole run)', flush=True)
            return _write(args, {'udp_limit_gb_per_s': limit, 'wire_bag': args.wire_bag, 'runs': runs},
                          'multihost_wire')
        for profile in ('single', 'multihost'):
            for fps in rates:
                runs.append({'profile': profile, 'offered_fps': fps, **dds_run(profile, fps, args.seconds)})
                report(runs[-1])
        passing = [r['offered_fps'] for r in runs if r['profile'] == 'multihost' and r['delivered_worst'] >= 0.99]
        fps = max(passing) if passing else min(rates)
        loss(0.01)
        runs.append({'profile': 'multihost', 'offered_fps': fps, 'loss': 0.01,
                     **dds_run('multihost', fps, args.seconds)})
        report(runs[-1])
        loss(0)

        def down():
            link(False)

        def up():
            link(True)
        runs.append({'profile': 'multihost', 'offered_fps': fps,
                     **dds_run('multihost', fps, max(args.seconds, 12.0), events=[(4.0, down), (6.0, up)])})
        report(runs[-1])
    finally:
        remove_hosts()
        for k, v in limits.items():
            Path(f'/proc/sys/net/core/{k}').write_text(v)
    return _write(args, {'udp_limit_gb_per_s': limit, 'runs': runs}, 'multihost')


def _write(args, result: dict, name: str) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f'{name}.json').write_text(json.dumps(result, indent=2))
    figure(result, out / f'{name}.png')
    print(f'wrote {out / f"{name}.json"} and {name}.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
