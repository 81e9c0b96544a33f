"""``volcap bag recover``: every readable message of a damaged bag copied into a new whole one."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .bag_reader import BagReader
from .bag_writer import BagWriter


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
