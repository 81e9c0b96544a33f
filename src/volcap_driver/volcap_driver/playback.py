"""Bag playback logic without ROS: topic mapping, the playback schedule, and restamping."""
from __future__ import annotations

import struct
from dataclasses import dataclass

from volcap_core.cdr import cdr_stamp_format
from volcap_core.errors import BadInput
from volcap_core.settings import setting

HEADER_FIRST_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CameraInfo', 'sensor_msgs/msg/PointCloud2',
                      'sensor_msgs/msg/CompressedImage', 'visualization_msgs/msg/Marker',
                      'geometry_msgs/msg/PoseArray', 'diagnostic_msgs/msg/DiagnosticArray')


def parse_remaps(rules: list[str]) -> dict[str, str]:
    """``['cam0/color/image_raw:=/k4a/rgb', ...]`` -> mapping (topics compared without a leading /)."""
    out = {}
    for rule in rules:
        if ':=' not in rule:
            raise BadInput(f'remap rule {rule!r} must look like FROM:=TO')
        src, dst = (part.strip().lstrip('/') for part in rule.split(':=', 1))
        if not src or not dst:
            raise BadInput(f'remap rule {rule!r} has an empty side')
        out[src] = dst
    return out


def parse_counts(rules: list[str]) -> dict[str, int]:
    """``['cam0/color/image_raw=2', ...]`` -> mapping (topics without a leading /)."""
    out = {}
    for rule in rules:
        topic, sep, count = rule.rpartition('=')
        if not sep or not topic.strip() or not count.strip().isdigit():
            raise BadInput(f'subscriber count {rule!r} must look like TOPIC=N')
        out[topic.strip().lstrip('/')] = int(count)
    return out


def output_topic(topic: str, remaps: dict[str, str], namespace: str = '') -> str:
    """Where a bag topic is published: remapped if a rule names it, else put under ``namespace``."""
    bare = topic.lstrip('/')
    if bare in remaps:
        return remaps[bare]
    ns = namespace.strip('/')
    return f'{ns}/{bare}' if ns else bare


@dataclass
class BagPlayerConfig:
    bag: str = setting('', 'rosbag2 bag directory (MCAP or sqlite3) to replay', read_only=True)
    rate: float = setting(1.0, 'playback speed relative to real time (changeable while playing)', 0.01, 100.0)
    as_fast_as_possible: bool = setting(False, 'publish without waiting between messages', read_only=True)
    loop: bool = setting(False, 'start again from the beginning when the bag ends', read_only=True)
    start_offset: float = setting(0.0, 'seconds into the bag to start from', 0.0, 1e7, read_only=True)
    loop_offset: float = setting(-1.0, 'with loop, seconds into the bag each later pass starts from, e.g. the '
                                 'capture after a clean plate (-1: start_offset)', -1.0, 1e7, read_only=True)
    topics: tuple[str, ...] = setting(('',), 'bag topics to play (empty: all)', read_only=True)
    remap: tuple[str, ...] = setting(('',), 'FROM:=TO topic remappings, e.g. cam0/color/image_raw:=/k4a/rgb/image_raw',
                                     read_only=True)
    namespace: str = setting('', 'prefix for every played topic (not remapped ones)', read_only=True)
    latched_topics: tuple[str, ...] = setting(('',), 'extra bag topics to publish transient-local (the bag\'s own '
                                              'latched topics and the volcap rig-level ones always are)',
                                              read_only=True)
    restamp: bool = setting(False, 'rewrite header stamps to the wall-clock time each message is scheduled at',
                            read_only=True)
    max_lag_ms: float = setting(0.0, 'stand in for live cameras that cannot keep up: when the sets sent start more '
                                'than a quarter of this late, send an even subset of them (one in N, N adapting); '
                                'a set later than this is sent at once and the schedule moves on (0: every set, '
                                'however late)', 0.0, 60_000.0, read_only=True)
    exit_when_done: bool = setting(True, 'shut the node down when playback ends (exit code 1 if the bag was '
                                         'unreadable)', read_only=True)
    wait_for_subscribers: float = setting(0.0, 'wait up to this many seconds for every played topic to have a '
                                               'subscriber before starting (0: start at once)', 0.0, 3600.0,
                                          read_only=True)
    subscribers: tuple[str, ...] = setting(('',), 'TOPIC=N: with wait_for_subscribers, wait for N subscribers '
                                                  'on a topic (a graph whose nodes are still being discovered '
                                                  'would miss the first frames)', read_only=True)


@dataclass
class Schedule:
    """Maps bag stamps to wall-clock times: real time scaled by ``rate``, or no waiting at all."""
    bag_start_ns: int
    wall_start_ns: int
    rate: float = 1.0
    as_fast_as_possible: bool = False

    def wall_time(self, stamp_ns: int) -> int:
        if self.as_fast_as_possible:
            return self.wall_start_ns
        return self.wall_start_ns + int((stamp_ns - self.bag_start_ns) / self.rate)

    def rebase(self, stamp_ns: int, wall_now_ns: int, rate: float) -> 'Schedule':
        """Continue from ``stamp_ns`` at ``wall_now_ns`` with a new rate (rate changed at run time)."""
        return Schedule(stamp_ns, wall_now_ns, rate, self.as_fast_as_possible)


def restamp_cdr(data: bytes, stamp_ns: int) -> bytes:
    """Replace header.stamp in a CDR message whose first field is a std_msgs/Header, patching
    the bytes instead of decoding the (multi-MB) message; one copy."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return b''.join((data[:4], struct.pack(cdr_stamp_format(data), sec, nsec), memoryview(data)[12:]))


class SetRestamper:
    """Header stamps for a replay that restamps: each frame set moves to the wall time it is
    played at and keeps its cameras' capture offsets as recorded. (Scaling the offsets by 1/rate
    would turn a set's 1 ms of jitter into 10 ms at rate 0.1 and split it.)"""

    def __init__(self):
        self._anchor: tuple[int, int] | None = None      # (bag stamp, wall stamp) of the set's first message

    def stamp(self, stamp_ns: int, target_ns: int, half_period_ns: int) -> int:
        if self._anchor is None or abs(stamp_ns - self._anchor[0]) > half_period_ns:
            self._anchor = (stamp_ns, target_ns)
        return self._anchor[1] + stamp_ns - self._anchor[0]


class SetPacer:
    """Which frame sets a player that stands in for live cameras sends, and when: it degrades as a
    camera that cannot keep up does, sending an even subset at a steady rate instead of bursts
    and silences.

    A frame set is the messages whose scheduled times lie within half a frame period of the set's
    first; a set is sent or left out whole, never split. While the sets it sends start more than
    a quarter of ``max_lag_ns`` late (``BEHIND_SETS`` in a row: a scheduling hiccup is not a
    load), the player sends one set in ``every`` (raised by one each time, at most
    ``max_every``; evenly spaced, the phase drifting, below). While they start on time for
    about ``CALM_SETS`` sets seen (``CALM_SETS / every`` sent), ``every`` falls by one. A set
    that starts more than ``max_lag_ns`` late is sent at once and the schedule moves on from it
    (``rebase``): what a camera would send next, with no run of dropped sets behind it.
    ``max_lag_ns`` 0: every set, as scheduled.

    A strictly periodic subset meets the live graph's admission (one set in N by stamp) on a grid
    of its own: the two could miss each other for good (a suite run under load stalled so, with
    the player at up to 1 in 30), hence the drifting phase, the cap of 8 and the quick return."""

    CALM_SETS = 30
    BEHIND_SETS = 3

    def __init__(self, max_lag_ns: int, max_every: int = 8):
        self.max_lag_ns = max_lag_ns
        self.max_every = max_every
        self.every = 1
        self.sets = 0              # frame sets seen
        self.sent_sets = 0
        self.left_out = 0          # not in the subset
        self.rebased = 0           # sent late: the schedule moved on
        self._set_start: int | None = None
        self._send = True
        self._calm = 0
        self._behind = 0
        self._credit = 1.0

    def new_set(self, target_ns: int, half_period_ns: int) -> bool:
        """Whether a message scheduled at ``target_ns`` starts a new frame set."""
        return self._set_start is None or abs(target_ns - self._set_start) > half_period_ns

    def start_set(self, target_ns: int, now_ns: int) -> tuple[bool, bool]:
        """(send this set, move the schedule to now first) for a set that starts at ``target_ns``."""
        self._set_start = target_ns
        self.sets += 1
        if self.max_lag_ns <= 0:
            self._send = True
            self.sent_sets += 1
            return True, False
        if self.every == 1:
            self._send = True
        else:
            # one set in ``every + 0.1``: gaps of ``every``, now and then one more, so the subset's
            # phase drifts and meets every grid the admission may choose (a strict 1 in N can miss
            # one for good)
            self._credit += 1.0 / (self.every + 0.1)
            self._send = self._credit >= 1.0
            if self._send:
                self._credit -= 1.0
        if not self._send:
            self.left_out += 1
            return False, False
        lag = now_ns - target_ns
        if lag > self.max_lag_ns // 4:
            self._behind += 1
            self._calm = 0
            if self._behind >= self.BEHIND_SETS:    # sustained, not one scheduling hiccup
                self.every = min(self.every + 1, self.max_every)
                self._behind = 0
        else:
            self._behind = 0
            self._calm += 1
            # about a second of sets on time, whatever the subset: a player thinned to 1 in 8
            # by a burst of load is back to every set within seconds, not minutes
            if self._calm >= max(3, self.CALM_SETS // self.every) and self.every > 1:
                self.every -= 1
                self._calm = 0
        self.sent_sets += 1
        late = lag > self.max_lag_ns
        self.rebased += late
        return True, late

    def moved(self, target_ns: int) -> None:
        """The current set was rescheduled to ``target_ns`` (the schedule moved on)."""
        self._set_start = target_ns

    def send(self, target_ns: int, now_ns: int, half_period_ns: int) -> bool:
        """Whether a message of the current set goes out (starting a set when it is a new one)."""
        if self.new_set(target_ns, half_period_ns):
            return self.start_set(target_ns, now_ns)[0]
        return self._send

    def status(self) -> str:
        if self.every == 1:
            return 'playing every frame set'
        return (f'playing one frame set in {self.every} (evenly spaced: the player cannot send every set in time); '
                f'{self.left_out} of {self.sets} sets left out so far')
