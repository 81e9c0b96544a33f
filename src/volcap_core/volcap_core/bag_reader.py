"""Reading rosbag2 bags (MCAP or sqlite3): ``BagReader`` yields CDR bytes in log order, reads
around damage (corrupt chunks, a cut-off file, an unfinished split) and accounts for what it
lost (``damage``, ``verify``)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterator

import yaml
from rclpy.serialization import deserialize_message
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader

from .bag_io import BagError, log, message_class, relative_name


@lru_cache(maxsize=256)
def _is_latched(offered_qos_profiles: str) -> bool:
    """Whether a channel's offered QoS (rosbag2's YAML) is transient-local. Parsed once per
    distinct text: every camera's channels carry the same few, and parsing each one took 6 ms
    (a second of every read of an 8-camera bag)."""
    profiles = yaml.safe_load(offered_qos_profiles or '[]') or []
    return any(p.get('durability') in ('transient_local', 1) for p in profiles)


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

    def _stream(self, start_ns: int | None = None) -> Iterator[tuple]:
        """(topic, msgtype, latched, log_time, data) of every readable message, in file order
        (from the first chunk that may hold ``start_ns`` where a file's summary says where)."""
        for mcap in self._mcaps:
            yield from self._stream_file(mcap, start_ns)

    @staticmethod
    def _seek_start(f, start_ns: int | None, record_of) -> bool:
        """Position ``f`` at the first chunk whose messages reach ``start_ns``, as the file's
        summary (its chunk index) tells; its schemas and channels are read from the summary, so
        a file written with them only before its first chunk still names every message. Without
        a usable summary (a cut file) the stream starts at the beginning. A looping player starts
        each pass here instead of reading the clean plate and the board again (seconds of silence
        per pass on an 8-camera bag). False: the summary says no message reaches ``start_ns``."""
        from mcap.reader import SeekingReader
        f.seek(0)
        if start_ns is None:
            return True
        try:
            summary = SeekingReader(f).get_summary()
        except Exception:
            summary = None
        f.seek(0)
        if summary is None or not summary.chunk_indexes:
            return True
        later = [c.chunk_start_offset for c in summary.chunk_indexes if c.message_end_time >= start_ns]
        if not later:
            return False
        for schema in summary.schemas.values():
            record_of(schema)
        for channel in summary.channels.values():
            record_of(channel)
        f.seek(min(later))
        return True

    def _stream_file(self, mcap: Path, start_ns: int | None = None) -> Iterator[tuple]:
        from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk
        schemas, channels = {}, {}
        n, last, bad_chunk = 0, None, None

        def record_of(record):
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                latched = _is_latched(record.metadata.get('offered_qos_profiles', ''))
                channels[record.id] = (relative_name(record.topic), schemas.get(record.schema_id, ''), latched)
        try:
            with open(mcap, 'rb') as f:
                size = mcap.stat().st_size
                if not self._seek_start(f, start_ns, record_of):
                    return
                for record in StreamReader(f, skip_magic=f.tell() > 0, emit_chunks=True,
                                           record_size_limit=size).records:
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
            for topic, msgtype, _, stamp, data in self._stream(start_ns):
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
