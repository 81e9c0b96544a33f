"""rosbag2 bags (MCAP or sqlite3) through rosbags, carrying rclpy-serialised (CDR) messages.

Messages stay serialised end to end: the writer takes rclpy messages or CDR bytes, the reader
yields CDR bytes that a player publishes as they are (no decode/encode per frame).

Topic names: the writer stores them fully qualified (``/cam0/color/image_raw``), as
``ros2 bag record`` does; the reader accepts bags with either form and hands every name out
relative to the root (``cam0/color/image_raw``), the form volcap's topic constants use.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import yaml
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore

COMPRESSIONS = ('none', 'zstd')


class BagError(RuntimeError):
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
    """Write a rosbag2 MCAP bag: ``with BagWriter(path) as bag: bag.write(topic, msg, stamp_ns)``."""

    def __init__(self, path: str | Path, compression: str = 'none'):
        if compression not in COMPRESSIONS:
            raise ValueError(f'compression must be one of {COMPRESSIONS}, got {compression!r}')
        self.path = Path(path)
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        try:
            self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        except WriterError as e:
            raise BagError(f'cannot create bag {self.path}: {e}') from e
        if compression == 'zstd':
            # MCAP chunk compression: still readable by `ros2 bag` and the mcap tools.
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections = {}
        self.count = 0

    def __enter__(self) -> 'BagWriter':
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        try:
            self._writer.open()
        except Exception as e:
            raise BagError(f'cannot create bag {self.path}: {e}') from e

    def add_topic(self, topic: str, msgtype: str, latched: bool = False, reliable: bool = True) -> None:
        topic = relative_name(topic)
        if topic in self._connections:
            return
        self._connections[topic] = self._writer.add_connection(
            stored_name(topic), msgtype, typestore=self._typestore, offered_qos_profiles=[_qos(latched, reliable)])

    def write(self, topic: str, msg, stamp_ns: int) -> None:
        """Write an rclpy message (its topic added on first use) or CDR bytes (topic added first)."""
        topic = relative_name(topic)
        if topic not in self._connections:
            if isinstance(msg, (bytes, bytearray, memoryview)):
                raise BagError(f'add_topic({topic!r}, type) before writing serialised data to it')
            self.add_topic(topic, msgtype_of(type(msg)))
        data = bytes(msg) if isinstance(msg, (bytes, bytearray, memoryview)) else serialize_message(msg)
        self._writer.write(self._connections[topic], int(stamp_ns), data)
        self.count += 1

    def close(self) -> None:
        self._writer.close()


@dataclass
class BagMessage:
    topic: str
    msgtype: str
    stamp_ns: int      # bag log time (= capture stamp for volcap bags)
    data: bytes        # CDR

    def decode(self):
        return deserialize_message(self.data, message_class(self.msgtype))


class BagReader:
    """Read a rosbag2 bag directory (MCAP or sqlite3) with clear errors for bad files.

    Metadata comes from rosbags. Messages of a single-file MCAP bag are streamed in file order
    with the ``mcap`` stream reader (several times faster than an indexed read, which copies every
    chunk; rosbag2, rosbags and volcap write MCAP in log-time order). An MCAP bag whose recording
    was cut off (no footer or index, possibly no metadata.yaml) is still read up to the damage;
    ``damage`` then says what is wrong and iterating ``messages`` ends with a BagError after the
    last readable message.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.damage = ''
        self._reader = None
        if not self.path.exists():
            raise BagError(f'bag {self.path} does not exist')
        mcaps = sorted(self.path.glob('*.mcap'))
        self._mcap = mcaps[0] if len(mcaps) == 1 else None
        if not (self.path / 'metadata.yaml').exists():
            if self._mcap is None:
                raise BagError(f'{self.path} is not a rosbag2 bag directory (no metadata.yaml)')
            self._scan('no metadata.yaml (recording interrupted?)')
            return
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as e:
            self._reader = None
            if self._mcap is None:
                raise BagError(f'cannot open bag {self.path}: {e}') from e
            self._scan(f'unreadable index ({e})')

    def _scan(self, why: str) -> None:
        """Index a damaged MCAP by streaming it: topics, types, latching, counts, time range."""
        self._topics, self._latched, self._counts = {}, set(), {}
        self._start = self._end = None
        n = 0
        try:
            for topic, msgtype, latched, stamp, _ in self._stream():
                n += 1
                self._topics[topic] = msgtype
                if latched:
                    self._latched.add(topic)
                self._counts[topic] = self._counts.get(topic, 0) + 1
                self._start = stamp if self._start is None else min(self._start, stamp)
                self._end = stamp if self._end is None else max(self._end, stamp)
        except BagError as e:
            why = f'{why}; {e}'
        if n == 0:
            raise BagError(f'cannot open bag {self.path}: {why}; no message could be read')
        self.damage = f'{why}; {n} messages readable'

    def _stream(self) -> Iterator[tuple]:
        """(topic, msgtype, latched, log_time, data) of every message record, in file order, up to
        the first damaged record."""
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader
        schemas, channels = {}, {}
        n = 0
        try:
            with open(self._mcap, 'rb') as f:
                for record in StreamReader(f).records:
                    if isinstance(record, Message):
                        n += 1
                        yield (*channels[record.channel_id], record.log_time, record.data)
                    elif isinstance(record, Schema):
                        schemas[record.id] = record.name
                    elif isinstance(record, Channel):
                        profiles = yaml.safe_load(record.metadata.get('offered_qos_profiles', '') or '[]') or []
                        latched = any(p.get('durability') in ('transient_local', 1) for p in profiles)
                        channels[record.id] = (relative_name(record.topic), schemas.get(record.schema_id, ''), latched)
        except Exception as e:
            raise BagError(f'bag {self.path} is corrupt or truncated after {n} messages: '
                           f'{type(e).__name__}: {e}') from e

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
        """Messages in log-time order; ``topics`` in either form (relative or fully qualified)."""
        topics = None if topics is None else {relative_name(t) for t in topics}
        if self._mcap is not None:
            yield from self._stream_messages(topics, start_ns, stop_ns)
            return
        conns = [c for c in self._reader.connections if topics is None or relative_name(c.topic) in topics]
        n, last = 0, None
        try:
            for conn, stamp, data in self._reader.messages(connections=conns, start=start_ns, stop=stop_ns):
                n, last = n + 1, stamp
                yield BagMessage(relative_name(conn.topic), conn.msgtype, int(stamp), bytes(data))
        except Exception as e:
            where = f'after {n} messages (last stamp {last})' if n else 'before its first message'
            raise BagError(f'bag {self.path} is corrupt or truncated {where}: {type(e).__name__}: {e}') from e

    def _stream_messages(self, topics, start_ns, stop_ns) -> Iterator[BagMessage]:
        for topic, msgtype, _, stamp, data in self._stream():
            if (topics is None or topic in topics) and (start_ns is None or stamp >= start_ns) \
                    and (stop_ns is None or stamp < stop_ns):
                yield BagMessage(topic, msgtype, int(stamp), data)
