"""rosbag2 bags (MCAP or sqlite3) through rosbags, carrying rclpy-serialised (CDR) messages: the
names, types and errors the writer (``bag_writer``), the reader (``bag_reader``) and the recovery
(``bag_recovery``) share.

Messages stay serialised end to end: the writer takes rclpy messages or CDR bytes, the reader
yields CDR bytes that a player publishes as they are (no decode/encode per frame).

Topic names: the writer stores them fully qualified (``/cam0/color/image_raw``), as
``ros2 bag record`` does; the reader accepts bags with either form and hands every name out
relative to the root (``cam0/color/image_raw``), the form volcap's topic constants use.
"""
from __future__ import annotations

import importlib
import logging

from .errors import BadBag

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


