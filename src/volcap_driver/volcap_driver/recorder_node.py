"""recorder: write chosen topics to a rosbag2 MCAP bag that `ros2 bag` and the mcap tools read.

    ros2 run volcap_driver recorder --ros-args -p out:=DIR -p topics:="['cam0/color/image_raw']"

Messages are stored as received (serialised, no decode) with their receive time as log time.
Topics are discovered as publishers appear; each is subscribed with the QoS its publishers
offer (reliable / transient-local when all of them are), as rosbag2 does. The bag is closed
(metadata written) on Ctrl-C, SIGTERM or after ``max_duration``.

Files (``volcap_core.bag_writer.BagWriter``): CRC-checked chunks of ``chunk_size`` bytes written
without copying the frames, so one host records 8 cameras at 30 fps (``bench/record.py``); a
new file every ``max_bagfile_size`` bytes or ``max_bagfile_duration`` seconds, as ``ros2 bag
record`` splits. After a crash or ``kill -9`` every closed file is whole and listed in
``metadata.yaml``, and the open one holds every chunk written before the kill:
``volcap bag recover`` restores it. A failed write (a full disk) stops the recording with an
ERROR naming the file and the free space; what was written stays readable.
"""
from __future__ import annotations

from dataclasses import dataclass

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from volcap_core.bag_io import COMPRESSIONS, BagError, message_class
from volcap_core.bag_writer import BagWriter, QueuedBagWriter
from volcap_core.ros import Diagnostics, declare_config, node_main
from volcap_core.settings import setting

IGNORED = ('/rosout', '/parameter_events', '/volcap/diagnostics')


def _absolute(topic: str, namespace: str) -> str:
    if topic.startswith('/'):
        return topic
    return f'{namespace.rstrip("/")}/{topic}'


@dataclass
class RecorderConfig:
    out: str = setting('', 'bag directory to create (must not exist)', read_only=True)
    compression: str = setting('none', 'MCAP chunk compression', choices=COMPRESSIONS, read_only=True)
    topics: tuple[str, ...] = setting(('',), 'topics to record (empty: every topic)', read_only=True)
    discovery_period: float = setting(0.5, 'seconds between looks for new publishers', 0.05, 10.0, read_only=True)
    max_duration: float = setting(0.0, 'stop after this many seconds (0: until stopped)', 0.0, 1e7, read_only=True)
    max_bagfile_size: int = setting(4_000_000_000, 'start a new file after this many bytes (0: never)',
                                    0, 2**62, read_only=True)
    max_bagfile_duration: float = setting(0.0, 'start a new file after this many seconds (0: never)', 0.0, 1e7,
                                          read_only=True)
    chunk_size: int = setting(8 << 20, 'MCAP chunk size in bytes: a crash loses at most the chunk being filled',
                              1, 1 << 30, read_only=True)
    max_queue_bytes: int = setting(256 << 20, 'messages waiting for the disk, in bytes (a crash loses them); '
                                   'beyond, new messages are dropped and counted', 1 << 20, 1 << 40, read_only=True)


class Recorder(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('recorder', **node_options)
        cfg = declare_config(self, RecorderConfig)
        out, compression, period, max_duration = cfg.out, cfg.compression, cfg.discovery_period, cfg.max_duration
        wanted = [t for t in cfg.topics if t]
        self.diagnostics = Diagnostics(self, 'recording')
        self.wanted = {_absolute(t, self.get_namespace()) for t in wanted}
        self.exit_code = 0
        self.failure = ''
        self.subs = {}
        self.counts = {}
        self.writer = None
        try:
            if not out:
                raise BagError('no output given: set the "out" parameter (--ros-args -p out:=DIR)')
            bag = BagWriter(out, compression, split_bytes=cfg.max_bagfile_size,
                            split_seconds=cfg.max_bagfile_duration, chunk_bytes=cfg.chunk_size)
            bag.open()
            self.writer = QueuedBagWriter(bag, cfg.max_queue_bytes)
        except (BagError, ValueError) as e:
            self.exit_code = 1
            self.diagnostics.report('error', str(e))
            self.context.try_shutdown()
            return
        self.get_logger().info(f'recorder started: writing {out} ({compression})')
        self.create_timer(period, self._discover)
        self.create_timer(2.0, self._report)
        if max_duration > 0:
            self.create_timer(max_duration, self.context.try_shutdown)
        self._discover()

    def _discover(self) -> None:
        if self.writer is None:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or topic in IGNORED or (self.wanted and topic not in self.wanted):
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
            latched = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
            profile = QoSProfile(depth=1 if latched else 100,
                                 reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            try:
                msg_class = message_class(types[0])
            except BagError as e:
                self.diagnostics.report('warn', f'not recording {topic}: {e}')
                self.subs[topic] = None
                continue
            name = topic.lstrip('/')
            self.writer.add_topic(name, types[0], latched=latched, reliable=reliable)
            self.counts[name] = 0
            self.subs[topic] = self.create_subscription(
                msg_class, topic, lambda data, name=name: self._write(name, data), profile, raw=True)
            self.get_logger().info(f'recording {topic} [{types[0]}]')

    def _write(self, topic: str, data: bytes) -> None:
        if self.writer is not None and self.writer.write(topic, data, self.get_clock().now().nanoseconds):
            self.counts[topic] += 1

    def _fail(self, why: str) -> None:
        """Stop recording; keep what is written (closed if the disk still allows)."""
        writer, self.writer = self.writer, None
        self.failure = why
        self.exit_code = 1
        try:
            writer.close()
        except OSError as e:
            self.failure += f'; the last file may lack its index ({e}): `volcap bag recover` reads it'
        self.get_logger().error(self.failure)
        self.diagnostics.report('error', self.failure, messages=sum(self.counts.values()))

    def _report(self) -> None:
        if self.writer is not None and self.writer.error is not None:
            self._fail(f'recording stopped: {self.writer.error}')
        if self.failure:
            self.diagnostics.report('error', self.failure, messages=sum(self.counts.values()))
            return
        w = self.writer
        level = 'warn' if w.dropped else 'ok'
        message = f'dropping: {w.dropped} messages found the disk queue full' if w.dropped else 'recording'
        self.diagnostics.report(level, message, messages=sum(self.counts.values()), topics=len(self.counts),
                                files=len(w.writer.files), dropped=w.dropped, queued_mb=round(w.queued_bytes / 1e6, 1))

    def destroy_node(self):
        if self.writer is not None and self.writer.error is not None:
            self._fail(f'recording stopped: {self.writer.error}')
        elif self.writer is not None:
            writer, self.writer = self.writer, None
            try:
                writer.close()
            except OSError as e:
                self.exit_code = 1
                self.get_logger().error(f'could not finish the bag: {e}')
            self.get_logger().info(f'closed bag: {sum(self.counts.values())} messages on {len(self.counts)} topics')
        return super().destroy_node()


def main(args=None):
    node_main(Recorder, args)


if __name__ == '__main__':
    main()
