"""bag_player: replay a rosbag2 bag (MCAP or sqlite3) onto the volcap topics.

    ros2 run volcap_driver bag_player --ros-args -p bag:=DIR [-p rate:=0.5] [-p loop:=true]

Messages go out as stored (serialised CDR, original header stamps) at real time x ``rate`` or as
fast as possible; latched topics (the rig description, calibration) are transient-local so late
subscribers still get them. A missing, corrupt or truncated bag is reported on the log and on
``volcap/diagnostics``; what could be read is still played.
"""
from __future__ import annotations

import queue
import threading
import time

from rclpy.duration import Duration
from rclpy.node import Node

from volcap_core import qos, topics
from volcap_core.bag_io import BagError, message_class
from volcap_core.bag_reader import BagReader
from volcap_core.ros import Diagnostics, declare_config, node_main
from volcap_core.sync import DEFAULT_PERIOD_NS, PeriodEstimate

from .playback import (
    HEADER_FIRST_TYPES,
    BagPlayerConfig,
    Schedule,
    SetPacer,
    SetRestamper,
    output_topic,
    parse_counts,
    parse_remaps,
    restamp_cdr,
)

READ_AHEAD = 96   # messages: three 8-camera frame sets of colour, depth and their infos
# At the end, how long reliable subscribers get to acknowledge the last messages before the node
# exits: a writer destroyed with unacknowledged samples takes them with it.
DRAIN_TIMEOUT_S = 5.0


class BagPlayer(Node):
    def __init__(self, **node_options):
        """``node_options`` (namespace, parameter_overrides, context) let a composed process host it."""
        super().__init__('bag_player', **node_options)
        self.cfg = declare_config(self, BagPlayerConfig, self._on_config)
        c = self.cfg
        self.bag, self.fast, self.loop, self.start_offset = c.bag, c.as_fast_as_possible, c.loop, c.start_offset
        self.topic_filter, self.remaps = c.topics, parse_remaps([r for r in c.remap if r])
        self.expected_subscribers = parse_counts([r for r in c.subscribers if r])
        self.namespace_prefix, self.extra_latched, self.restamp = c.namespace, c.latched_topics, c.restamp
        self.exit_when_done, self.wait_for_subscribers = c.exit_when_done, c.wait_for_subscribers
        self.diagnostics = Diagnostics(self, 'playback')
        self.exit_code = 0
        self.published = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='bag_playback', daemon=True)
        self.get_logger().info(f'bag_player started: {self.bag or "(no bag given)"}')
        self._thread.start()

    def _on_config(self, cfg: BagPlayerConfig) -> None:
        self.cfg = cfg     # the rate is read afresh while playing; the rest applies at start

    @property
    def playing(self) -> bool:
        """False once playback has ended (or failed)."""
        return self._thread.is_alive()

    def destroy_node(self):
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        return super().destroy_node()

    def _run(self) -> None:
        try:
            if not self.bag:
                raise BagError('no bag given: set the "bag" parameter (--ros-args -p bag:=DIR)')
            with BagReader(self.bag) as reader:
                if reader.damage:
                    self.diagnostics.report('warn', f'damaged bag {self.bag}: {reader.damage}; playing what is readable')
                self._play(reader)
        except BagError as e:
            self.exit_code = 1
            self.diagnostics.report('error', str(e), published=self.published)
        except Exception as e:  # a bug must not leave the node silently idle
            if not self.context.ok():
                return      # shutting down (Ctrl-C): publishing stopped working, nothing failed
            self.exit_code = 1
            self.diagnostics.report('error', f'playback failed: {type(e).__name__}: {e}', published=self.published)
        if self.exit_when_done and not self._stop.is_set():
            self.context.try_shutdown()

    def _play(self, reader: BagReader) -> None:
        wanted = [t for t in self.topic_filter if t]
        bag_topics = {t: ty for t, ty in reader.topics.items() if not wanted or t in wanted}
        missing = set(wanted) - set(bag_topics)
        if missing:
            self.diagnostics.report('warn', f'topics not in {self.bag}: {sorted(missing)}')
        latched = reader.latched_topics | set(topics.LATCHED) | {t for t in self.extra_latched if t}
        pubs = {}
        for topic, msgtype in bag_topics.items():
            profile = qos.LATCHED if topic in latched else qos.DRIVER
            pubs[topic] = self.create_publisher(message_class(msgtype), output_topic(topic, self.remaps,
                                                                                     self.namespace_prefix), profile)
        self._await_subscribers(pubs)
        start = reader.start_ns + int(self.start_offset * 1e9)
        self.get_logger().info(f'playing {len(pubs)} of {len(reader.topics)} topics of a {reader.message_count}-'
                               f'message bag, {(reader.end_ns - reader.start_ns) / 1e9:.2f} s of bag time')
        rate = self.cfg.rate
        last_report = time.monotonic()
        period = PeriodEstimate()
        next_pass_ns = target = time.time_ns()
        pacer = SetPacer(int(self.cfg.max_lag_ms * 1e6))
        restamper = SetRestamper()
        while not self._stop.is_set():
            # A pass that starts late keeps to the frame grid of the last (whole periods later).
            frame_ns = int((period.period_ns or DEFAULT_PERIOD_NS) / rate)
            late_by = time.time_ns() - next_pass_ns
            if late_by > 0:
                next_pass_ns += -(-late_by // frame_ns) * frame_ns
            schedule = Schedule(start, next_pass_ns, rate, self.fast)
            for msg in self._read_ahead(reader, list(pubs), start):
                period.add(msg.topic, msg.stamp_ns)
                new_rate = self.cfg.rate
                if new_rate != rate:
                    rate, schedule = new_rate, schedule.rebase(msg.stamp_ns, time.time_ns(), new_rate)
                target = schedule.wall_time(msg.stamp_ns)
                half_period = int((period.period_ns or DEFAULT_PERIOD_NS) / rate) // 2
                if msg.msgtype in HEADER_FIRST_TYPES:
                    if pacer.new_set(target, half_period):
                        send, late = pacer.start_set(target, time.time_ns())
                        if late:         # sent now; the schedule goes on from here, no run of drops
                            schedule = schedule.rebase(msg.stamp_ns, time.time_ns(), rate)
                            target = schedule.wall_time(msg.stamp_ns)
                            pacer.moved(target)
                    if not pacer.send(target, time.time_ns(), half_period):
                        continue          # left out of the subset: not waited for either
                delay = (target - time.time_ns()) / 1e9
                if delay > 0 and self._stop.wait(delay):
                    return
                data = msg.data
                if self.restamp and msg.msgtype in HEADER_FIRST_TYPES:
                    data = restamp_cdr(data, restamper.stamp(msg.stamp_ns, target,
                                                             (period.period_ns or DEFAULT_PERIOD_NS) // 2))
                pubs[msg.topic].publish(data)
                self.published += 1
                if time.monotonic() - last_report > 1.0:
                    last_report = time.monotonic()
                    self.diagnostics.report('ok' if pacer.every == 1 else 'warn', pacer.status(),
                                            published=self.published, sets=pacer.sets, sets_sent=pacer.sent_sets,
                                            sets_left_out=pacer.left_out, send_every=pacer.every,
                                            sets_rebased=pacer.rebased, lag_ms=f'{(time.time_ns() - target) / 1e6:.1f}',
                                            bag_time=f'{(msg.stamp_ns - reader.start_ns) / 1e9:.3f}')
            if not self.loop:
                break
            # The next pass one frame period after this one's last set, as a camera would send it
            # (sooner, and its first set would share stamps with this pass's last).
            next_pass_ns = target + int((period.period_ns or DEFAULT_PERIOD_NS) / rate)
            if self.cfg.loop_offset >= 0:
                start = reader.start_ns + int(self.cfg.loop_offset * 1e9)
        if self._stop.is_set() or not self.context.ok():
            return
        deadline = time.monotonic() + DRAIN_TIMEOUT_S      # one budget for all topics, not one each
        unacknowledged = [t for t, p in pubs.items()
                          if not p.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic())))]
        if unacknowledged:
            self.diagnostics.report('warn', f'{len(unacknowledged)} topics not acknowledged by every reliable '
                                            f'subscriber at the end, e.g. {unacknowledged[0]}')
        if reader.losses:
            self.diagnostics.report('warn', f'finished: {self.published} messages published; damaged bag '
                                            f'{self.bag}: {reader.damage}', published=self.published,
                                    damaged_parts=len(reader.losses))
            self.get_logger().warning(f'damaged bag, played what was readable: {reader.damage}')
        else:
            self.diagnostics.report('ok', f'finished: {self.published} messages published', published=self.published)
        self.get_logger().info(f'finished: {self.published} messages published')


    def _read_ahead(self, reader: BagReader, topic_list: list[str], start: int):
        """Messages from a reader thread that stays up to READ_AHEAD messages (a few frame sets)
        ahead, so a set is in memory when its time comes and goes out in one burst, as a rig's
        cameras publish it. Reader errors surface here, after the messages read before them."""
        q = queue.Queue(maxsize=READ_AHEAD)
        done = object()

        def produce():
            try:
                for msg in reader.messages(topic_list, start_ns=start):
                    while not self._stop.is_set():
                        try:
                            q.put(msg, timeout=0.1)
                            break
                        except queue.Full:
                            continue
                    if self._stop.is_set():
                        return
                q.put(done)
            except Exception as e:   # handed to the playback thread
                q.put(e)

        threading.Thread(target=produce, name='bag_read_ahead', daemon=True).start()
        while not self._stop.is_set():
            try:
                item = q.get(timeout=0.1)
            except queue.Empty:
                continue
            if item is done:
                return
            if isinstance(item, Exception):
                raise item
            yield item

    def _await_subscribers(self, pubs: dict) -> None:
        """Until every topic has matched its expected subscribers (``subscribers``, else one) and
        every subscription the graph shows on it: a subscriber still being discovered (a colour
        corrector that started a moment after the depth filter on the same topic) would miss the
        first frames, which are volatile."""
        def waiting():
            return [t for t, p in pubs.items()
                    if p.get_subscription_count() < max(self.expected_subscribers.get(t, 1),
                                                         self.count_subscribers(p.topic_name))]
        deadline = time.monotonic() + self.wait_for_subscribers
        while time.monotonic() < deadline and not self._stop.is_set():
            if not waiting():
                return
            self._stop.wait(0.05)
        if self.wait_for_subscribers > 0 and waiting():
            late = waiting()
            self.diagnostics.report('warn', f'starting with too few subscribers on {len(late)} topics, e.g. {late[0]} '
                                            f'({pubs[late[0]].get_subscription_count()})')


def main(args=None):
    node_main(BagPlayer, args)


if __name__ == '__main__':
    main()
