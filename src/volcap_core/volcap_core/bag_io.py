"""rosbag2 bags (MCAP or sqlite3) through rosbags, carrying rclpy-serialised (CDR) messages.

Messages stay serialised end to end: the writer takes rclpy messages or CDR bytes, the reader
yields CDR bytes that a player publishes as they are (no decode/encode per frame).

Topic names: the writer stores them fully qualified (``/cam0/color/image_raw``), as
``ros2 bag record`` does; the reader accepts bags with either form and hands every name out
relative to the root (``cam0/color/image_raw``), the form volcap's topic constants use.
"""
from __future__ import annotations

import importlib
import logging
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import yaml
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys import Stores, get_typestore

from .errors import BadBag, BadInput
from .files import atomic_write
from .mcap_file import McapFile

COMPRESSIONS = ('none', 'zstd')
log = logging.getLogger('volcap.bag')


class BagError(BadBag):
    """A bag is missing, unreadable, corrupt or truncated."""


def message_class(msgtype: str):
    """rclpy message class of a ROS type name such as ``sensor_msgs/msg/Image``."""
    try:
        pkg, kind, name = msgtype.split('/')
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ValueError, ImportError, AttributeError) as e:
        raise BagError(f'message type {msgtype!r} is not available in this ROS environment') from e


def msgtype_of(msg_class) -> str:
    module = msg_class.__module__.split('.')
    return f'{module[0]}/{module[1]}/{msg_class.__name__}'


def stored_name(topic: str) -> str:
    """The fully qualified name a bag stores for a topic."""
    return '/' + topic.lstrip('/')


def relative_name(topic: str) -> str:
    """A topic name relative to the root namespace (how the reader hands names out)."""
    return topic.lstrip('/')


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


@dataclass
class BagMessage:
    topic: str
    msgtype: str
    stamp_ns: int      # bag log time (= capture stamp for volcap bags)
    data: bytes        # CDR

    def decode(self):
        return deserialize_message(self.data, message_class(self.msgtype))


class BagReader:
    """Read a rosbag2 bag directory (MCAP, one file or split, or sqlite3), around any damage.

    Metadata comes from rosbags where the bag is whole. Messages of MCAP bags are streamed in file
    order with the ``mcap`` stream reader (several times faster than an indexed read, which copies
    every chunk; rosbag2, rosbags and volcap write MCAP in log-time order), and every chunk's CRC
    is checked. Damage costs only what it touches, as ``mcap recover`` does: a chunk whose CRC or
    compression fails is skipped (its messages counted from its message index), a file cut off
    (no footer: a recorder killed or a disk full) is read up to the cut, and a split file that
    ``metadata.yaml`` does not list yet is read too. Each loss is logged once and listed in
    ``losses``; ``damage`` says it in one line. Only a bag with no readable message is an error.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.losses: dict[tuple, str] = {}          # (file, where) -> what was lost
        self.notes: list[str] = []                  # damage found on opening
        self._reader = None
        if not self.path.exists():
            raise BagError(f'bag {self.path} does not exist')
        self._mcaps = self._mcap_files()
        if not (self.path / 'metadata.yaml').exists():
            if not self._mcaps:
                raise BagError(f'{self.path} is not a rosbag2 bag directory (no metadata.yaml)')
            self._scan('no metadata.yaml (recording interrupted?)')
            return
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as e:
            self._reader = None
            if not self._mcaps:
                raise BagError(f'cannot open bag {self.path}: {e}') from e
            self._scan(f'unreadable index ({e})')
            return
        info = yaml.safe_load((self.path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
        listed = {Path(p).name for p in info.get('relative_file_paths') or []}
        unlisted = [m.name for m in self._mcaps if m.name not in listed]
        if unlisted:
            self._reader.close()
            self._reader = None
            self._scan(f'{", ".join(unlisted)} not in metadata.yaml (recording interrupted?)')

    def _mcap_files(self) -> list[Path]:
        """The bag's MCAP files in recording order (``name_2`` before ``name_10``)."""
        def order(p: Path):
            tail = p.stem.rsplit('_', 1)[-1]
            return (int(tail) if tail.isdigit() else -1, p.name)
        return sorted(self.path.glob('*.mcap'), key=order)

    def _scan(self, why: str) -> None:
        """Index a damaged MCAP bag by streaming it: topics, types, latching, counts, time range."""
        self._topics, self._latched, self._counts = {}, set(), {}
        self._start = self._end = None
        n = 0
        for topic, msgtype, latched, stamp, _ in self._stream():
            n += 1
            self._topics[topic] = msgtype
            if latched:
                self._latched.add(topic)
            self._counts[topic] = self._counts.get(topic, 0) + 1
            self._start = stamp if self._start is None else min(self._start, stamp)
            self._end = stamp if self._end is None else max(self._end, stamp)
        if n == 0:
            raise BagError(f'cannot open bag {self.path}: {why}; no message could be read'
                           + (f' ({self.damage})' if self.losses else ''))
        self.notes.append(f'{why}; {n} messages readable')

    @property
    def damage(self) -> str:
        """What is wrong with the bag, as far as it has been read ('' for a whole bag)."""
        return '; '.join(self.notes + list(self.losses.values()))

    def _lose(self, key: tuple, what: str) -> None:
        if key not in self.losses:
            self.losses[key] = what
            log.warning('bag %s: %s', self.path, what)

    def _stream(self) -> Iterator[tuple]:
        """(topic, msgtype, latched, log_time, data) of every readable message, in file order."""
        for mcap in self._mcaps:
            yield from self._stream_file(mcap)

    def _stream_file(self, mcap: Path) -> Iterator[tuple]:
        from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk
        schemas, channels = {}, {}
        n, last, bad_chunk = 0, None, None

        def record_of(record):
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                profiles = yaml.safe_load(record.metadata.get('offered_qos_profiles', '') or '[]') or []
                latched = any(p.get('durability') in ('transient_local', 1) for p in profiles)
                channels[record.id] = (relative_name(record.topic), schemas.get(record.schema_id, ''), latched)
        try:
            with open(mcap, 'rb') as f:
                size = mcap.stat().st_size
                for record in StreamReader(f, emit_chunks=True, record_size_limit=size).records:
                    if isinstance(record, MessageIndex):
                        if bad_chunk is not None:
                            bad_chunk[1] += len(record.records)
                        continue
                    if bad_chunk is not None:
                        self._report_chunk(mcap, *bad_chunk)
                        bad_chunk = None
                    if isinstance(record, Chunk):
                        try:
                            inner = breakup_chunk(record, validate_crc=True)
                        except Exception as e:
                            bad_chunk = [record.message_start_time, 0, f'{type(e).__name__}: {e}']
                            continue
                        for r in inner:
                            if isinstance(r, Message):
                                n, last = n + 1, r.log_time
                                yield (*channels[r.channel_id], r.log_time, r.data)
                            else:
                                record_of(r)
                    elif isinstance(record, Message):
                        n, last = n + 1, record.log_time
                        yield (*channels[record.channel_id], record.log_time, record.data)
                    else:
                        record_of(record)
            if bad_chunk is not None:
                self._report_chunk(mcap, *bad_chunk)
        except Exception as e:
            if bad_chunk is not None:
                self._report_chunk(mcap, *bad_chunk)
            where = f'after {n} messages (last stamp {last})' if n else 'before its first message'
            self._lose((mcap.name, 'end'), f'{mcap.name} is cut off or corrupt {where}: the rest of the file is '
                                           f'lost ({type(e).__name__}: {e})')

    def _report_chunk(self, mcap: Path, start_ns: int, lost: int, why: str) -> None:
        self._lose((mcap.name, start_ns), f'{mcap.name}: skipped a damaged chunk from stamp {start_ns}, '
                                          f'{lost or "an unknown number of"} messages lost ({why})')

    def __enter__(self) -> 'BagReader':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()

    @property
    def topics(self) -> dict[str, str]:
        if self._reader is None:
            return dict(self._topics)
        return {relative_name(c.topic): c.msgtype for c in self._reader.connections}

    @property
    def latched_topics(self) -> set[str]:
        if self._reader is None:
            return set(self._latched)
        out = set()
        for c in self._reader.connections:
            qos = getattr(c.ext, 'offered_qos_profiles', []) or []
            if any(q.durability == QosDurability.TRANSIENT_LOCAL for q in qos):
                out.add(relative_name(c.topic))
        return out

    @property
    def start_ns(self) -> int:
        return self._start if self._reader is None else self._reader.start_time

    @property
    def end_ns(self) -> int:
        return self._end if self._reader is None else self._reader.end_time

    @property
    def topic_counts(self) -> dict[str, int]:
        """Messages per topic, from the bag's metadata (or the scan of a damaged MCAP)."""
        if self._reader is None:
            return dict(self._counts)
        counts = {}
        for c in self._reader.connections:
            name = relative_name(c.topic)
            counts[name] = counts.get(name, 0) + c.msgcount
        return counts

    @property
    def message_count(self) -> int:
        return sum(self._counts.values()) if self._reader is None else self._reader.message_count

    def messages(self, topics: list[str] | None = None, start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[BagMessage]:
        """Messages in log-time order; ``topics`` in either form (relative or fully qualified).
        Damage ends or skips part of the iteration; ``losses`` says what was lost."""
        topics = None if topics is None else {relative_name(t) for t in topics}
        if self._mcaps:
            for topic, msgtype, _, stamp, data in self._stream():
                if (topics is None or topic in topics) and (start_ns is None or stamp >= start_ns) \
                        and (stop_ns is None or stamp < stop_ns):
                    yield BagMessage(topic, msgtype, int(stamp), data)
            return
        conns = [c for c in self._reader.connections if topics is None or relative_name(c.topic) in topics]
        n, last = 0, None
        try:
            for conn, stamp, data in self._reader.messages(connections=conns, start=start_ns, stop=stop_ns):
                n, last = n + 1, stamp
                yield BagMessage(relative_name(conn.topic), conn.msgtype, int(stamp), bytes(data))
        except Exception as e:
            where = f'after {n} messages (last stamp {last})' if n else 'before its first message'
            self._lose(('sqlite3', 'end'), f'corrupt {where}: the rest is lost ({type(e).__name__}: {e})')

    def verify(self) -> int:
        """Read every message (checking every CRC); the number readable. ``damage`` then holds all
        that is lost."""
        return sum(1 for _ in self.messages())


@dataclass
class Recovery:
    messages: int              # written to the clean copy
    damage: str                # what the damaged bag lost ('' when it was whole)


def recover(src: str | Path, dst: str | Path, compression: str = 'none') -> Recovery:
    """Copy every readable message of ``src`` (damaged or not) into a new, whole bag ``dst``."""
    with BagReader(src) as reader:
        latched = reader.latched_topics
        with BagWriter(dst, compression) as writer:
            for topic, msgtype in reader.topics.items():
                writer.add_topic(topic, msgtype, latched=topic in latched)
            for msg in reader.messages():
                writer.add_topic(msg.topic, msg.msgtype, latched=msg.topic in latched)   # no-op once added
                writer.write(msg.topic, msg.data, msg.stamp_ns)
        return Recovery(writer.count, reader.damage)
