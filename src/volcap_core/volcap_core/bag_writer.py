"""Writing rosbag2 bags (MCAP through ``McapFile``, at disk speed, split by size or time; sqlite3
through rosbags), from rclpy messages or CDR bytes as they arrive: ``BagWriter``, and
``QueuedBagWriter``, which takes the writing off the caller's thread."""
from __future__ import annotations

import threading
from collections import deque
from pathlib import Path

import yaml
from rclpy.serialization import serialize_message
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys import Stores, get_typestore

from .bag_io import COMPRESSIONS, BagError, msgtype_of, relative_name, stored_name
from .errors import BadInput
from .files import atomic_write
from .mcap_file import McapFile


def _qos(latched: bool, reliable: bool = True) -> Qos:
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 1 if latched else 10,
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


class BagWriter:
    """Write a rosbag2 MCAP bag: ``with BagWriter(path) as bag: bag.write(topic, msg, stamp_ns)``.

    Files are ``<name>_<k>.mcap`` as ``ros2 bag record`` names them, each with CRC-checked chunks
    (``McapFile``); a new file starts after ``split_bytes`` or ``split_seconds`` of log time (0: never).
    ``metadata.yaml`` is rewritten atomically as each file closes, so a recording killed
    mid-take keeps every closed file described and loses at most the open one's unwritten chunk.
    """

    def __init__(self, path: str | Path, compression: str = 'none', split_bytes: int = 0,
                 split_seconds: float = 0.0, chunk_bytes: int = 8 << 20):
        if compression not in COMPRESSIONS:
            raise BadInput(f'compression must be one of {COMPRESSIONS}, got {compression!r}')
        self.path = Path(path)
        self.compression = '' if compression == 'none' else compression
        self.split_bytes, self.split_ns = int(split_bytes), int(split_seconds * 1e9)
        self.chunk_bytes = chunk_bytes
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self._topics: dict[str, dict] = {}          # relative name -> msgtype, qos, schema text, hash
        self._closed: list[dict] = []               # files done: name, start, end, count
        self._topic_counts: dict[str, int] = {}
        self._file: McapFile | None = None
        self._channels: dict[str, int] = {}
        self.count = 0

    def __enter__(self) -> 'BagWriter':
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def files(self) -> list[Path]:
        """The bag's files so far, the open one last."""
        names = [f['path'] for f in self._closed] + ([self._file.path.name] if self._file else [])
        return [self.path / n for n in names]

    def open(self) -> None:
        try:
            self.path.mkdir(parents=True, exist_ok=False)
        except FileExistsError as e:
            raise BagError(f'cannot create bag {self.path}: it already exists') from e
        except OSError as e:
            raise BagError(f'cannot create bag {self.path}: {e}') from e
        self._start_file()

    def _start_file(self) -> None:
        name = f'{self.path.name}_{len(self._closed)}.mcap'
        self._file = McapFile(self.path / name, self.compression, self.chunk_bytes)
        self._channels = {}
        for topic in self._topics:
            self._add_channel(topic)

    def _add_channel(self, topic: str) -> None:
        t = self._topics[topic]
        schema = self._file.add_schema(t['msgtype'], 'ros2msg', t['msgdef'].encode())
        self._channels[topic] = self._file.add_channel(stored_name(topic), schema,
                                                       {'offered_qos_profiles': t['qos_text']})

    def add_topic(self, topic: str, msgtype: str, latched: bool = False, reliable: bool = True) -> None:
        topic = relative_name(topic)
        if topic in self._topics:
            return
        try:
            msgdef, _ = self._typestore.generate_msgdef(msgtype, ros_version=2)
            rihs01 = self._typestore.hash_rihs01(msgtype)
        except Exception as e:
            raise BagError(f'message type {msgtype!r} is unknown to the bag writer: {e}') from e
        qos = dump_qos_v9([_qos(latched, reliable)])
        self._topics[topic] = {'msgtype': msgtype, 'msgdef': msgdef, 'rihs01': rihs01, 'qos': qos,
                               'qos_text': yaml.safe_dump(qos, default_flow_style=False).strip()}
        self._topic_counts[topic] = 0
        self._add_channel(topic)

    def write(self, topic: str, msg, stamp_ns: int) -> None:
        """Write an rclpy message (its topic added on first use) or CDR bytes (topic added first).
        A failed write raises ``files.WriteError`` naming the file and the free space."""
        topic = relative_name(topic)
        if topic not in self._topics:
            if isinstance(msg, (bytes, bytearray, memoryview)):
                raise BagError(f'add_topic({topic!r}, type) before writing serialised data to it')
            self.add_topic(topic, msgtype_of(type(msg)))
        # Bytes are kept by reference until their chunk is written; a mutable buffer is copied.
        data = msg if isinstance(msg, bytes) else bytes(msg) if isinstance(msg, (bytearray, memoryview)) \
            else serialize_message(msg)
        stamp_ns = int(stamp_ns)
        f = self._file
        if f.messages and ((self.split_bytes and f.size >= self.split_bytes) or
                           (self.split_ns and stamp_ns - f.start_ns >= self.split_ns)):
            self._split()
        self._file.write(self._channels[topic], stamp_ns, data)
        self._topic_counts[topic] += 1
        self.count += 1

    def _split(self) -> None:
        self._close_file()
        self._write_metadata()
        self._start_file()

    def _close_file(self) -> None:
        f, self._file = self._file, None
        f.close()
        self._closed.append({'path': f.path.name, 'starting_time': {'nanoseconds_since_epoch': f.start_ns or 0},
                             'duration': {'nanoseconds': (f.end_ns or 0) - (f.start_ns or 0)},
                             'message_count': f.messages})

    def _write_metadata(self) -> None:
        starts = [f['starting_time']['nanoseconds_since_epoch'] for f in self._closed if f['message_count']]
        ends = [f['starting_time']['nanoseconds_since_epoch'] + f['duration']['nanoseconds']
                for f in self._closed if f['message_count']]
        start = min(starts, default=0)
        info = {
            'version': 9, 'storage_identifier': 'mcap',
            'relative_file_paths': [f['path'] for f in self._closed],
            'duration': {'nanoseconds': max(ends, default=0) - start},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': sum(f['message_count'] for f in self._closed),
            'topics_with_message_count': [
                {'topic_metadata': {'name': stored_name(topic), 'type': t['msgtype'], 'serialization_format': 'cdr',
                                    'offered_qos_profiles': t['qos'], 'type_description_hash': t['rihs01']},
                 'message_count': self._topic_counts[topic]} for topic, t in self._topics.items()],
            'compression_format': '', 'compression_mode': '', 'files': self._closed,
            'custom_data': None, 'ros_distro': 'jazzy'}
        text = yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False)
        atomic_write(self.path / 'metadata.yaml', lambda f: f.write(text), binary=False)

    def close(self) -> None:
        """Close the open file and write ``metadata.yaml``; after a failed write, keeps what is whole."""
        if self._file is None:
            return
        try:
            self._close_file()
        finally:
            self._write_metadata()

    def abandon(self) -> None:
        """Stop without a summary (as a crash would): the files stay recoverable."""
        if self._file is not None:
            self._file.abandon()
            self._file = None


class QueuedBagWriter:
    """A ``BagWriter`` on its own thread, fed through a queue of at most ``max_bytes``: a
    subscriber's callback never waits for the disk (writeback stalls cost queue, not frames).
    With the queue full, the message offered is refused and counted in ``dropped``. A write
    error stops the thread and is kept in ``error``; ``close`` writes what was queued first."""

    def __init__(self, writer: BagWriter, max_bytes: int = 1 << 30):
        self.writer = writer
        self.max_bytes = max_bytes
        self.queued_bytes = 0
        self.dropped = 0
        self.error: Exception | None = None
        self._queue: deque = deque()         # (bytes, work)
        self._cond = threading.Condition()
        self._closing = False
        self._thread = threading.Thread(target=self._run, name='bag_writer', daemon=True)
        self._thread.start()

    def add_topic(self, topic: str, msgtype: str, latched: bool = False, reliable: bool = True) -> None:
        """As ``BagWriter.add_topic``, in order with the writes (on the writer's thread)."""
        with self._cond:
            self._queue.append((0, lambda: self.writer.add_topic(topic, msgtype, latched, reliable)))
            self._cond.notify()

    def write(self, topic: str, data: bytes, stamp_ns: int) -> bool:
        with self._cond:
            if self.error is not None or self.queued_bytes + len(data) > self.max_bytes:
                self.dropped += 1
                return False
            self._queue.append((len(data), lambda: self.writer.write(topic, data, stamp_ns)))
            self.queued_bytes += len(data)
            self._cond.notify()
        return True

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    return
                size, work = self._queue.popleft()
            try:
                work()              # the disk, outside the lock
            except (OSError, BagError) as e:
                with self._cond:
                    self.error = e
                    self.dropped += len(self._queue) + 1
                    self._queue.clear()
                    self.queued_bytes = 0
                return
            with self._cond:
                self.queued_bytes -= size

    def close(self) -> None:
        """Write what is queued, then close the bag (an OSError if that fails; a write error that
        stopped the thread earlier stays in ``error``)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()
        self.writer.close()
