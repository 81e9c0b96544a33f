"""Bag size and write speed per second of 8-camera capture, uncompressed and zstd (MCAP chunks).

    .venv/bin/python bench/bag_size.py

Re-writes the 30 frame sets (1 s at 30 fps) of bench/transport.py's synthetic bag through
volcap's BagWriter, and times a bare rosbags Writer on the same messages for the ratio; both
until the bag is on disk (fsync), as volcap's writer always leaves it.
"""
from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

sys.path.insert(0, str(Path(__file__).resolve().parent))
from transport import ensure_bag  # noqa: E402

from volcap_core.bag_io import BagWriter  # noqa: E402
from volcap_core.bag_reader import BagReader


def write_bare(out: Path, topics: dict, msgs: list, compression: str) -> float:
    t0 = time.perf_counter()
    w = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression == 'zstd':
        w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with w:
        store = get_typestore(Stores.ROS2_JAZZY)
        conns = {t: w.add_connection(t, ty, typestore=store) for t, ty in topics.items()}
        for m in msgs:
            w.write(conns[m.topic], m.stamp_ns, m.data)
    for f in out.glob('*.mcap'):       # on disk, as volcap's writer leaves its files (fsync)
        with open(f, 'rb') as handle:
            os.fsync(handle.fileno())
    return time.perf_counter() - t0


def main() -> int:
    bag = ensure_bag(Path(__file__).resolve().parents[1] / 'bench_out')
    with BagReader(bag) as reader:
        topics = reader.topics
        msgs = list(reader.messages())
        seconds = 30 / 30.0
    raw_mb = sum(len(m.data) for m in msgs) / 1e6
    print(f'{len(msgs)} messages, {raw_mb:.0f} MB of serialised messages = {seconds:.0f} s of 8-camera capture')
    print(f'{"writer":<28} {"compression":<12} {"MB per s of capture":>20} {"write s":>8} {"ratio to bare":>14}')
    tmp = Path(tempfile.mkdtemp())
    try:
        for compression in ('none', 'zstd'):
            # Flush dirty pages before each timed run (so one run's writeback does not land on the
            # next); three rounds, the writers taking turns to go first (this disk's speed wanders
            # by 2x within a minute), and each writer's median.
            bare, ours = [], []
            for k in range(3):
                for writer_name in (('bare', 'volcap') if k % 2 == 0 else ('volcap', 'bare')):
                    os.sync()
                    if writer_name == 'bare':
                        bare.append(write_bare(tmp / f'bare_{compression}_{k}', topics, msgs, compression))
                        shutil.rmtree(tmp / f'bare_{compression}_{k}')      # each run on the same free space
                        continue
                    out = tmp / f'volcap_{compression}_{k}'
                    t0 = time.perf_counter()
                    with BagWriter(out, compression) as writer:
                        for t, ty in topics.items():
                            writer.add_topic(t, ty)
                        for m in msgs:
                            writer.write(m.topic, m.data, m.stamp_ns)
                    ours.append(time.perf_counter() - t0)
                    size = sum(f.stat().st_size for f in out.glob('*.mcap')) / 1e6
                    shutil.rmtree(out)
            print(f'  runs (s): rosbags {[round(b, 2) for b in bare]}, volcap {[round(o, 2) for o in ours]}')
            bare_s, ours_s = float(np.median(bare)), float(np.median(ours))
            print(f'{"rosbags Writer (bare)":<28} {compression:<12} {"":>20} {bare_s:8.2f} {"":>14}')
            print(f'{"volcap BagWriter":<28} {compression:<12} {size / seconds:20.0f} {ours_s:8.2f} '
                  f'{ours_s / bare_s:14.2f}')
    finally:
        shutil.rmtree(tmp)
    return 0


if __name__ == '__main__':
    sys.exit(main())
