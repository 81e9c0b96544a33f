"""Recording a rig live: seconds to write one second of 8-camera capture, and what a kill -9
mid-take leaves.

    .venv/bin/python bench/record.py [--seconds 4] [--out bench_out/record]

1. Writers, one second of an Azure Kinect rig (8 x colour 1280x720 bgra8 + depth 640x576 16UC1
   + two camera_infos, 30 fps, 1.06 GB) as CDR, each run closed and fsync'd:
   - the machine's limit: the same bytes with ``os.writev`` and one fsync (no container, no CRC);
   - volcap's ``BagWriter`` (``McapFile``: CRC-checked 8 MB chunks, no copy of the frames);
   - the ``mcap`` library's ``Writer`` (8 MB chunks, CRCs) and rosbags' ``Writer`` (no CRCs),
     the raw library calls volcap could have used.
   Target: <= 1.0 s per second of capture.
2. The recorder node in its own process, fed by a vendor-driver-like publisher process (the one
   of ``bench/rig_transport.py``) at 30 fps: messages recorded against published, the
   recorder's CPU seconds per second of capture; to the disk, and to a tmpfs (the same run
   without the disk: what the transport and the node cost).
3. ``kill -9`` of that recorder mid-take, splitting every 500 MB: the files listed in
   ``metadata.yaml``, the messages ``volcap bag recover`` restores against those the recorder
   wrote (its diagnostics count).

With ``--wire WIREBAG`` only: the recorder on 8 cameras' compact wire at 30 fps (messages
recorded against published). Writes bench_out/record.json and record.png (record_wire.json).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'bench'))
CAMERAS = [f'cam{i}' for i in range(8)]
DOMAIN = '79'
FPS = 30


def rig_messages() -> list[tuple[str, str, bytes]]:
    """(topic, type, CDR) of one frame set of the rig, as the Azure Kinect driver names them."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CameraInfo

    from volcap_core.conversions import numpy_to_image
    rng = np.random.default_rng(0)
    color = serialize_message(numpy_to_image(rng.integers(0, 255, (720, 1280, 4), dtype=np.uint8), 'bgra8'))
    depth = serialize_message(numpy_to_image(rng.integers(500, 3000, (576, 640), dtype=np.uint16), '16UC1'))
    info = serialize_message(CameraInfo(width=640, height=576))
    out = []
    for cam in CAMERAS:
        out += [(f'{cam}/rgb/image_raw', 'sensor_msgs/msg/Image', color),
                (f'{cam}/rgb/camera_info', 'sensor_msgs/msg/CameraInfo', info),
                (f'{cam}/depth/image_raw', 'sensor_msgs/msg/Image', depth),
                (f'{cam}/depth/camera_info', 'sensor_msgs/msg/CameraInfo', info)]
    return out


def time_writers(folder: Path, seconds: int, messages, rounds: int) -> list[dict]:
    """Seconds per second of capture for each writer: the median of ``rounds`` rounds, the
    writers taking turns within a round (this disk's speed wanders by 2x over a minute)."""
    times = {name: [] for name in WRITERS}
    sizes = {}
    for _ in range(rounds):
        for name, write in WRITERS.items():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            t0 = time.perf_counter()
            sizes[name] = write(folder / 'bag', seconds, messages)
            times[name].append((time.perf_counter() - t0) / seconds)
    shutil.rmtree(folder, ignore_errors=True)
    return [{'writer': name, 's_per_capture_s': float(np.median(t)), 'runs': t,
             'bytes_per_capture_s': sizes[name] / seconds} for name, t in times.items()]


def write_raw(path: Path, seconds: int, messages) -> int:
    """The disk alone: the same bytes in 8 MB writes (the chunk size; one 35 MB write per frame
    set measured 1.2-3x slower here), one fsync at the end."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    frame_set = memoryview(b''.join(data for _, _, data in messages))
    size = 0
    for _ in range(seconds * FPS):
        for at in range(0, len(frame_set), 8 << 20):
            view = frame_set[at:at + (8 << 20)]
            while view:
                done = os.write(fd, view)
                view = view[done:]
                size += done
    os.fsync(fd)
    os.close(fd)
    return size


def write_volcap(path: Path, seconds: int, messages) -> int:
    from volcap_core.bag_writer import BagWriter
    with BagWriter(path) as bag:
        for topic, msgtype, _ in messages:
            bag.add_topic(topic, msgtype)
        for k in range(seconds * FPS):
            for topic, _, data in messages:
                bag.write(topic, data, k * 33_333_333)
    return sum(p.stat().st_size for p in path.glob('*.mcap'))


def write_mcap_library(path: Path, seconds: int, messages) -> int:
    from mcap.writer import CompressionType, Writer
    path.mkdir()
    with open(path / 'bag.mcap', 'wb') as f:
        w = Writer(f, chunk_size=8 << 20, compression=CompressionType.NONE, enable_crcs=True)
        w.start('ros2', 'bench')
        schemas = {t: w.register_schema(t, 'ros2msg', b'') for t in {m for _, m, _ in messages}}
        channels = [w.register_channel('/' + topic, 'cdr', schemas[m]) for topic, m, _ in messages]
        for k in range(seconds * FPS):
            for channel, (_, _, data) in zip(channels, messages):
                w.add_message(channel, k * 33_333_333, data, k * 33_333_333)
        w.finish()
        f.flush()
        os.fsync(f.fileno())
    return (path / 'bag.mcap').stat().st_size


def write_rosbags(path: Path, seconds: int, messages) -> int:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        connections = [w.add_connection('/' + topic, m, typestore=store) for topic, m, _ in messages]
        for k in range(seconds * FPS):
            for conn, (_, _, data) in zip(connections, messages):
                w.write(conn, k * 33_333_333, data)
    (mcap,) = path.glob('*.mcap')
    with open(mcap, 'rb') as f:
        os.fsync(f.fileno())
    return mcap.stat().st_size


WRITERS = {'disk limit (8 MB writes + fsync)': write_raw, 'volcap BagWriter (CRC chunks)': write_volcap,
           'mcap library Writer (CRC chunks)': write_mcap_library, 'rosbags Writer (no CRC)': write_rosbags}


def cpu_seconds(pid: int) -> float:
    import psutil
    times = psutil.Process(pid).cpu_times()
    return times.user + times.system


def stop_recorder(recorder) -> None:
    """SIGINT (the recorder closes its bag), or kill it when it does not exit."""
    if recorder.poll() is None:
        recorder.send_signal(signal.SIGINT)
        try:
            recorder.wait(60)
        except subprocess.TimeoutExpired:
            recorder.kill()
            recorder.wait()


def recorded(out: Path, published_sets: int, topics: list[str]) -> dict:
    """What the recorder wrote against what was published on ``topics``, every CRC checked."""
    from volcap_core.bag_reader import BagReader
    with BagReader(out) as bag:
        counts = bag.topic_counts
        readable = bag.verify()
    expected = published_sets * len(topics)
    return {'recorded': sum(counts.values()), 'expected': expected, 'readable': readable,
            'recorded_share': sum(counts.values()) / expected}


def record_live(out: Path, frames: int, kill_after: float | None = None, split_bytes: int = 4_000_000_000) -> dict:
    """The recorder node fed by the rig publisher; optionally killed -9 ``kill_after`` s into the take."""
    from volcap_bringup.processes import start_node
    from volcap_core.transport import PROFILE
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=DOMAIN,
               FASTRTPS_DEFAULT_PROFILES_FILE=str(PROFILE))
    shutil.rmtree(out, ignore_errors=True)
    topics = [f'/{cam}/{s}' for cam in CAMERAS for s in ('rgb/image_raw', 'rgb/camera_info', 'depth/image_raw',
                                                        'depth/camera_info')]
    recorder = start_node('volcap_driver', 'recorder', {'out': str(out), 'topics': topics,
                                                        'max_bagfile_size': split_bytes, 'discovery_period': 0.1},
                          env=env)
    cpu0 = None
    try:
        pub = subprocess.Popen([sys.executable, str(REPO / 'bench' / 'rig_transport.py'), '--child', 'pub',
                                '--frames', str(frames), '--fps', str(FPS), '--image-subscribers',
                                str(2 * len(CAMERAS))], env=env, stdout=subprocess.PIPE, text=True)
        # The publisher waits for 16 image subscriptions; the recorder's CPU is counted from then.
        time.sleep(1.0)
        cpu0 = cpu_seconds(recorder.pid)
        if kill_after is not None:
            deadline = time.monotonic() + 60
            while sum(f.stat().st_size for f in out.glob('*.mcap')) < 50e6 and time.monotonic() < deadline:
                time.sleep(0.05)              # recording has begun
            time.sleep(kill_after)
            recorder.send_signal(signal.SIGKILL)
            recorder.wait(10)
            pub.kill()
            pub.wait()
            return {'killed_after_s': kill_after}
        published = json.loads(pub.communicate(timeout=frames / FPS + 120)[0].strip().splitlines()[-1])
        cpu = cpu_seconds(recorder.pid) - cpu0
    finally:
        stop_recorder(recorder)
    return {'published_sets': published['published'], 'publish_fps': published['publish_fps'],
            **recorded(out, published['published'], topics),
            'recorder_cpu_s_per_capture_s': cpu / (published['published'] / FPS),
            'files': len(list(out.glob('*.mcap')))}


def record_wire(out: Path, wire_bag: str, seconds: float) -> dict:
    """The recorder node recording 8 camera pipelines' compact wire at 30 fps (the recorded wire
    bag's sets with fresh stamps, sent by bench/multihost.py's capture-host publisher on this
    host): messages recorded against published."""
    from volcap_bringup.processes import start_node
    from volcap_core import wire
    from volcap_core.transport import PROFILE
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=DOMAIN,
               FASTRTPS_DEFAULT_PROFILES_FILE=str(PROFILE))
    shutil.rmtree(out, ignore_errors=True)
    topics = [f'/{cam}/{t}' for cam in CAMERAS for t in (wire.WIRE_DEPTH, wire.WIRE_COLOR, wire.WIRE_DEPTH_INFO,
                                                          wire.WIRE_COLOR_INFO)]
    recorder = start_node('volcap_driver', 'recorder', {'out': str(out), 'topics': topics, 'discovery_period': 0.1},
                          env=env)
    try:
        time.sleep(3.0)           # the recorder subscribed before the first set (volatile topics)
        cpu0 = cpu_seconds(recorder.pid)
        pub = subprocess.run([sys.executable, str(REPO / 'bench' / 'multihost.py'), '--child', 'pub',
                              f'--wire-bag={wire_bag}', f'--seconds={seconds}', f'--fps={FPS}',
                              f'--start-at={time.time() + 2.0}'], env=env, capture_output=True, text=True,
                             timeout=seconds + 120)
        published = json.loads(pub.stdout.strip().splitlines()[-1])
        cpu = cpu_seconds(recorder.pid) - cpu0
    finally:
        stop_recorder(recorder)
    return {'published_sets': published['sent_sets'], 'publish_fps': published['sent_fps'],
            'payload_mbit_s': published['payload_mbit_s'], **recorded(out, published['sent_sets'], topics),
            'recorder_cpu_s_per_capture_s': cpu / (published['sent_sets'] / FPS)}


def kill_and_recover(out: Path, frames: int, kill_after: float) -> dict:
    import yaml

    from volcap_core.bag_reader import BagReader
    from volcap_core.bag_recovery import recover
    record_live(out, frames, kill_after=kill_after, split_bytes=500_000_000)
    files = sorted(out.glob('*.mcap'))
    meta = out / 'metadata.yaml'
    listed = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']['relative_file_paths'] \
        if meta.exists() else []
    with BagReader(out) as bag:
        damage = bag.damage
    recovered_dir = out.with_name(out.name + '_recovered')
    shutil.rmtree(recovered_dir, ignore_errors=True)
    t0 = time.perf_counter()
    result = recover(out, recovered_dir)
    recover_s = time.perf_counter() - t0
    on_disk = sum(f.stat().st_size for f in files)
    shutil.rmtree(recovered_dir, ignore_errors=True)
    return {'files': len(files), 'listed_in_metadata': len(listed), 'damage': damage,
            'recovered_messages': result.messages, 'recovered_seconds_of_capture': result.messages / (32 * FPS),
            'bytes_on_disk': on_disk, 'recover_s': recover_s}


def figure(writers: list[dict], out: Path) -> None:
    import matplotlib.pyplot as plt

    from volcap_core.figures import save_figure
    fig, ax = plt.subplots(figsize=(8, 3.5))
    names = [w['writer'] for w in writers]
    ax.barh(names, [w['s_per_capture_s'] for w in writers], color=['grey', 'tab:green', 'tab:blue', 'tab:orange'])
    ax.axvline(1.0, color='k', linestyle='--', linewidth=1, label='real time (target)')
    ax.set_xlabel('seconds to write one second of 8-camera capture (1.06 GB)')
    ax.invert_yaxis()
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--seconds', type=int, default=4, help='seconds of capture per writer run')
    ap.add_argument('--rounds', type=int, default=3, help='runs of each writer (the median is reported)')
    ap.add_argument('--out', default=str(REPO / 'bench_out' / 'record'))
    ap.add_argument('--wire', default='', help='only: the recorder on 8 cameras\' compact wire (a volcap wire bag '
                                               'replayed at 30 fps), --seconds of it')
    args = ap.parse_args()
    os.environ.setdefault('MALLOC_MMAP_THRESHOLD_', '67108864')
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.wire:
        r = record_wire(out / 'wire', args.wire, args.seconds)
        print(f'recorder node, the compact wire of 8 cameras at {r["publish_fps"]:.1f} fps '
              f'({r["payload_mbit_s"]:.0f} Mbit/s): {r["recorded"]} of {r["expected"]} messages recorded '
              f'({100 * r["recorded_share"]:.2f} %), {r["readable"]} readable, recorder CPU '
              f'{r["recorder_cpu_s_per_capture_s"]:.2f} s per second of capture')
        (out / 'record_wire.json').write_text(json.dumps(r, indent=1))
        return 0 if r['recorded'] == r['expected'] else 1
    messages = rig_messages()
    writers = time_writers(out / 'writer', args.seconds, messages, args.rounds)
    for w in writers:
        print(f'{w["writer"]:<36} {w["s_per_capture_s"]:.2f} s per second of capture, median of '
              f'{", ".join(f"{t:.2f}" for t in w["runs"])} ({w["bytes_per_capture_s"] / 1e9:.2f} GB per second of '
              'capture)', flush=True)
    limit = writers[0]['s_per_capture_s']
    for w in writers[1:]:
        w['vs_disk_limit'] = w['s_per_capture_s'] / limit
    print('ratios to the disk limit: ' + ', '.join(f'{w["writer"]} {w["vs_disk_limit"]:.2f}x' for w in writers[1:]))
    live = {}
    for where, folder in (('disk', out / 'live'), ('tmpfs (no disk)', Path('/dev/shm') / 'volcap_record_bench')):
        live[where] = record_live(folder, frames=args.seconds * FPS)
        r = live[where]
        print(f'recorder node to {where}: {r["recorded"]} of {r["expected"]} messages recorded '
              f'({100 * r["recorded_share"]:.1f} %), publisher {r["publish_fps"]:.1f} fps, recorder CPU '
              f'{r["recorder_cpu_s_per_capture_s"]:.2f} s per second of capture, {r["files"]} file(s)', flush=True)
        shutil.rmtree(folder, ignore_errors=True)
    killed = kill_and_recover(out / 'killed', frames=10 * FPS, kill_after=2.0)
    print(f'kill -9 2 s into the take (500 MB splits): {killed["files"]} files, {killed["listed_in_metadata"]} listed in '
          f'metadata.yaml; recover restored {killed["recovered_messages"]} messages '
          f'({killed["recovered_seconds_of_capture"]:.2f} s of capture) in {killed["recover_s"]:.1f} s')
    shutil.rmtree(out / 'killed', ignore_errors=True)
    result = {'writers': writers, 'recorder_node': live, 'kill_and_recover': killed}
    (REPO / 'bench_out').mkdir(exist_ok=True)
    (REPO / 'bench_out' / 'record.json').write_text(json.dumps(result, indent=2))
    figure(writers, REPO / 'bench_out' / 'record.png')
    print(f'wrote {REPO / "bench_out" / "record.json"} and record.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
