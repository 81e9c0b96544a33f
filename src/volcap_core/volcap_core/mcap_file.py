"""One MCAP file written at disk speed, every chunk carrying its CRC.

The ``mcap`` library's writer copies each message four times on its way to disk (measured: 1.5 s
per second of 8-camera capture, 840 MB, against 0.6 s for the disk itself), and rosbags writes
chunk CRCs as 0. Here the small records (header, schemas, channels, indexes, summary, footer) are
the ``mcap`` library's own record classes; only the chunk and message headers are packed here,
so that a frame's bytes go from the subscriber's buffer to the file in one ``writev`` with no
copy. Messages are grouped into chunks of about ``chunk_bytes``, each chunk holding the schema and
channel records of the channels it uses (``add_channel``); each chunk's CRC-32 is
computed over its uncompressed records as the MCAP spec defines (by ISA-L: 18 GB/s here against
zlib's 3.6), and readers check it.

A file is readable by the ``mcap`` library, rosbags and rosbag2 once ``close`` has written its
summary; a file cut off (crash, ``kill -9``, power) holds every chunk written before the cut,
which ``volcap bag recover`` restores.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

from isal.isal_zlib import crc32
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MessageIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from .errors import BadInput
from .files import write_failure

MAGIC = b'\x89MCAP0\r\n'
_MESSAGE_HEADER = struct.Struct('<BQHIQQ')        # opcode, length, channel, sequence, log, publish time
_MESSAGE_FIELDS = 2 + 4 + 8 + 8
_CHUNK_HEAD = struct.Struct('<BQQQQI')           # opcode, length, start, end, uncompressed size, crc
_IOV_MAX = os.sysconf('SC_IOV_MAX')


def _record_bytes(*records) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return builder.end()


class McapFile:
    """``f = McapFile(path); sid = f.add_schema(...); cid = f.add_channel(...); f.write(cid, t, data);
    f.close()``. ``compression``: '' or 'zstd' (per chunk)."""

    def __init__(self, path: str | Path, compression: str = '', chunk_bytes: int = 8 << 20,
                 library: str = 'volcap'):
        if compression not in ('', 'zstd'):
            raise BadInput(f'MCAP chunk compression must be "" or "zstd", got {compression!r}')
        self.path = Path(path)
        self.compression = compression
        self.chunk_bytes = chunk_bytes
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self.size = 0                   # bytes in the file: every chunk before this offset is whole
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._counts: dict[int, int] = {}
        self._declared_schemas: set[int] = set()      # schema / channel records in the chunk being built
        self._declared_channels: set[int] = set()
        self._pending: list[tuple[int, int, bytes]] = []        # (channel, log time, data)
        self._pending_bytes = 0
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.messages = 0
        self._write([MAGIC, _record_bytes(Header(profile='ros2', library=library))])

    def _write(self, pieces: list) -> None:
        """All of ``pieces`` appended, or the file cut back to its last whole record and an error."""
        views = [memoryview(p).cast('B') for p in pieces if len(p)]
        total = sum(len(v) for v in views)
        try:
            i = 0
            while i < len(views):      # IOV_MAX pieces a call; a short write carries on where it stopped
                done = os.writev(self._fd, views[i:i + _IOV_MAX])
                while done:
                    if done >= len(views[i]):
                        done -= len(views[i])
                        i += 1
                    else:
                        views[i], done = views[i][done:], 0
        except OSError as e:
            try:
                os.ftruncate(self._fd, self.size)
                os.lseek(self._fd, self.size, os.SEEK_SET)
            except OSError:
                pass
            raise write_failure(self.path, e) from e
        self.size += total

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        """The id of the schema ``name`` (written into the chunk of its first message)."""
        for known in self._schemas:
            if known.name == name:
                return known.id
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        return schema.id

    def add_channel(self, topic: str, schema_id: int, metadata: dict[str, str],
                    message_encoding: str = 'cdr') -> int:
        """The id of a new channel. Its record (and its schema's) goes into every chunk that
        holds one of its messages, before the first: the reference writer (the C++ ``McapWriter``
        that rosbag2 uses) writes them into the chunk of the channel's first message; repeating
        them (identical records, which the spec allows) makes every chunk self-describing, so a
        reader of a cut or damaged file (``mcap recover``, ``volcap bag recover``) knows every
        channel of every whole chunk, even when the chunk that declared it first is lost. A
        channel with no message is only in the summary."""
        channel = Channel(id=len(self._channels) + 1, topic=topic, message_encoding=message_encoding,
                          metadata=metadata, schema_id=schema_id)
        self._channels.append(channel)
        self._counts[channel.id] = 0
        return channel.id

    def _declarations(self, channel_id: int) -> list[bytes]:
        """The schema and channel records due before the first message of ``channel_id`` in the
        chunk being built."""
        if channel_id in self._declared_channels:
            return []
        self._declared_channels.add(channel_id)
        channel = self._channels[channel_id - 1]
        out = []
        if channel.schema_id and channel.schema_id not in self._declared_schemas:
            self._declared_schemas.add(channel.schema_id)
            out.append(_record_bytes(self._schemas[channel.schema_id - 1]))
        return out + [_record_bytes(channel)]

    def write(self, channel_id: int, log_time: int, data: bytes) -> None:
        """Queue one message (its bytes are referenced, not copied); a full chunk is written."""
        self._pending.append((channel_id, log_time, data))
        self._pending_bytes += len(data) + _MESSAGE_HEADER.size
        self._counts[channel_id] += 1
        self.messages += 1
        self.start_ns = log_time if self.start_ns is None else min(self.start_ns, log_time)
        self.end_ns = log_time if self.end_ns is None else max(self.end_ns, log_time)
        if self._pending_bytes >= self.chunk_bytes:
            self.flush()

    def flush(self) -> None:
        """Write the queued messages as one chunk, followed by its message indexes."""
        if not self._pending:
            return
        pending, self._pending, self._pending_bytes = self._pending, [], 0
        self._declared_schemas, self._declared_channels = set(), set()     # each chunk declares its own
        records, indexes, offset, crc = [], {}, 0, 0
        for channel_id, log_time, data in pending:
            for declaration in self._declarations(channel_id):
                records.append(declaration)
                crc = crc32(declaration, crc)
                offset += len(declaration)
            head = _MESSAGE_HEADER.pack(Opcode.MESSAGE, _MESSAGE_FIELDS + len(data), channel_id, 0, log_time, log_time)
            records += (head, data)
            crc = crc32(data, crc32(head, crc))
            indexes.setdefault(channel_id, []).append((log_time, offset))
            offset += len(head) + len(data)
        start = min(t for _, t, _ in pending)
        end = max(t for _, t, _ in pending)
        if self.compression == 'zstd':
            import zstandard
            records = [zstandard.ZstdCompressor().compress(b''.join(records))]
        stored = sum(len(r) for r in records)
        compression = self.compression.encode()
        head = _CHUNK_HEAD.pack(Opcode.CHUNK, 8 * 3 + 4 + 4 + len(compression) + 8 + stored, start, end, offset, crc)
        head += struct.pack('<I', len(compression)) + compression + struct.pack('<Q', stored)
        chunk_start = self.size
        index_records = [MessageIndex(channel_id=c, records=r) for c, r in indexes.items()]
        index_bytes, index_offsets, at = [], {}, chunk_start + len(head) + stored
        for record in index_records:
            data = _record_bytes(record)
            index_offsets[record.channel_id] = at
            index_bytes.append(data)
            at += len(data)
        self._write([head, *records, *index_bytes])
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_start,
            chunk_length=len(head) + stored, message_index_offsets=index_offsets,
            message_index_length=at - chunk_start - len(head) - stored, compression=self.compression,
            compressed_size=stored, uncompressed_size=offset))

    def close(self) -> None:
        """The last chunk, the summary and the footer; then fsync. The file is whole after this."""
        if self._fd < 0:
            return
        try:
            self.flush()
            self._write([_record_bytes(DataEnd(data_section_crc=0))])
            summary_start = self.size
            groups = [(Opcode.SCHEMA, self._schemas), (Opcode.CHANNEL, self._channels),
                      (Opcode.STATISTICS, [Statistics(
                          message_count=self.messages, schema_count=len(self._schemas),
                          channel_count=len(self._channels), attachment_count=0,
                          metadata_count=0, chunk_count=len(self._chunk_indexes),
                          message_start_time=self.start_ns or 0, message_end_time=self.end_ns or 0,
                          channel_message_counts=dict(self._counts))]),
                      (Opcode.CHUNK_INDEX, self._chunk_indexes)]
            summary, offsets = b'', []
            for opcode, records in groups:
                if records:
                    data = _record_bytes(*records)
                    offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + len(summary),
                                                 group_length=len(data)))
                    summary += data
            offsets_start = summary_start + len(summary)
            summary += _record_bytes(*offsets)
            crc = crc32(struct.pack('<BQQQ', Opcode.FOOTER, 8 + 8 + 4, summary_start, offsets_start), crc32(summary))
            self._write([summary, _record_bytes(Footer(summary_start=summary_start, summary_offset_start=offsets_start,
                                                       summary_crc=crc)), MAGIC])
            os.fsync(self._fd)
        except OSError as e:
            raise write_failure(self.path, e) from e
        finally:
            os.close(self._fd)
            self._fd = -1

    def abandon(self) -> None:
        """Close without a summary (the file stays readable up to its last whole chunk)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
