"""Subscribers that watch the camera streams. ``StreamMonitor`` stands in for a consumer in the
benchmarks: per-camera rates, frame-set completeness (through the volcap synchroniser) and
transport latency (receive time minus header stamp, meaningful when stamps are wall-clock, e.g.
a live rig or ``bag_player restamp:=true``). ``RigMonitor`` is ``volcap monitor``: the rig's
health from the stamps, on ``/volcap/diagnostics`` and as a table."""
from __future__ import annotations

import time
from collections import defaultdict

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from volcap_core import qos, topics
from volcap_core.cdr import cdr_stamp_ns
from volcap_core.conversions import stamp_to_ns
from volcap_core.diagnostics import diagnostic_array, diagnostic_status
from volcap_core.health import RigHealth
from volcap_core.sync import FrameSetSynchronizer, tolerance_ns_from_ms

from .graph import camera_remaps

STREAMS = {'color': topics.COLOR_IMAGE, 'depth': topics.DEPTH_IMAGE}


class StreamMonitor(Node):
    def __init__(self, cameras: list[str], tolerance_ms: float = 0.0, name: str = 'volcap_monitor',
                 raw: bool = False):
        """``raw``: take serialised messages and read only the header stamp (no image decode), to
        separate transport cost from deserialisation cost."""
        super().__init__(name)
        self.cameras = cameras
        self.tolerance_ns = tolerance_ns_from_ms(tolerance_ms)
        self.reset()
        self.topics = [topics.camera_topic(cam, topic) for cam in cameras for topic in STREAMS.values()]
        for cam in cameras:
            for stream, topic in STREAMS.items():
                self.create_subscription(Image, topics.camera_topic(cam, topic),
                                         lambda msg, key=(cam, stream): self._on_image(key, msg), qos.SENSOR,
                                         raw=raw)

    def reset(self) -> None:
        """Forget everything received so far (e.g. after a warm-up)."""
        self.arrivals = defaultdict(list)   # (camera, stream) -> [(receive_ns, stamp_ns)]
        self.sync = FrameSetSynchronizer(self.cameras, tuple(STREAMS), tolerance_ns=self.tolerance_ns,
                                         timeout_ns=500_000_000, max_pending=8)
        self.complete_latency_ns = []       # per complete set: last arrival - stamp
        self.sets = []

    def _on_image(self, key, msg: Image) -> None:
        now = time.time_ns()
        stamp = cdr_stamp_ns(msg) if isinstance(msg, bytes) else stamp_to_ns(msg.header.stamp)
        self.arrivals[key].append((now, stamp))
        for fs in self.sync.add(key[0], stamp, now, stream=key[1], now_ns=now):
            self._on_set(fs)

    def _on_set(self, fs) -> None:
        self.sets.append(fs)
        if fs.complete:
            self.complete_latency_ns.append(max(fs.items.values()) - fs.stamp_ns)

    def finish(self) -> None:
        for fs in self.sync.flush():
            self._on_set(fs)

    def summary(self) -> dict:
        per_camera = {}
        for cam in self.cameras:
            row = {}
            for stream in STREAMS:
                recv = np.array([a[0] for a in self.arrivals[(cam, stream)]], dtype=np.int64)
                row[f'{stream}_frames'] = int(len(recv))
                row[f'{stream}_hz'] = delivered_rate(recv)
            per_camera[cam] = row
        lat = np.array(self.complete_latency_ns, dtype=np.float64) / 1e6
        per_image = np.array([recv - stamp for arr in self.arrivals.values() for recv, stamp in arr],
                             dtype=np.float64) / 1e6
        return {'cameras': per_camera,
                'image_latency_ms_median': float(np.median(per_image)) if per_image.size else None,
                'image_latency_ms_p95': float(np.percentile(per_image, 95)) if per_image.size else None,
                'frame_sets_complete': self.sync.stats.complete,
                'frame_sets_incomplete': self.sync.stats.incomplete,
                'late_frames': self.sync.stats.late,
                'latency_ms_median': float(np.median(lat)) if lat.size else None,
                'latency_ms_p95': float(np.percentile(lat, 95)) if lat.size else None}


def delivered_rate(receive_ns: np.ndarray, pause_s: float = 0.3) -> float:
    """Mean frames per second over the stretches of continuous delivery (pauses longer than
    ``pause_s``, such as the gaps between the parts of a studio session, are left out)."""
    gaps = np.diff(receive_ns) / 1e9
    steady = gaps[gaps < pause_s]
    return float(len(steady) / steady.sum()) if steady.size and steady.sum() > 0 else 0.0


def format_rates(summary: dict) -> str:
    lines = ['camera   colour Hz  frames   depth Hz  frames']
    for cam, row in summary['cameras'].items():
        lines.append(f'{cam:<8} {row["color_hz"]:9.1f} {row["color_frames"]:7d} {row["depth_hz"]:10.1f} '
                     f'{row["depth_frames"]:7d}')
    lines.append(f'frame sets: {summary["frame_sets_complete"]} complete, {summary["frame_sets_incomplete"]} '
                 f'incomplete, {summary["late_frames"]} late frames')
    return '\n'.join(lines)


class RigMonitor(Node):
    """``volcap monitor``: per camera rate, drops, colour-depth offset and drift from the rig
    (``volcap_core.health``), on ``/volcap/diagnostics`` every second. Reads only the header
    stamps of the serialised images (no decode), on the topics of the given driver."""

    def __init__(self, cameras: list[str], driver: str = 'volcap', registered: bool = False,
                 color_transport: str = 'raw', window_s: float = 10.0, **node_options):
        super().__init__('volcap_monitor', **node_options)
        self.health = RigHealth(cameras, window_s)
        self.report = self.health.report()
        remaps = camera_remaps(driver, registered)
        color = topics.COLOR_COMPRESSED if color_transport == 'compressed' else topics.COLOR_IMAGE
        color_type = CompressedImage if color_transport == 'compressed' else Image
        self.topics = []
        for cam in cameras:
            for stream, rel, kind in (('color', color, color_type), ('depth', topics.DEPTH_IMAGE, Image)):
                topic = topics.camera_topic(cam, remaps.get(rel, rel))
                self.topics.append(topic)
                self.create_subscription(kind, topic, lambda data, c=cam, s=stream: self.health.add(
                    c, s, cdr_stamp_ns(data), time.time_ns()), qos.CAMERA, raw=True)
        self.pub = self.create_publisher(DiagnosticArray, '/' + topics.DIAGNOSTICS, qos.EVENTS)
        self.create_timer(1.0, self._publish)

    def _publish(self) -> None:
        self.report = self.health.report(time.time_ns())
        statuses = []
        for cam, h in self.report.cameras.items():
            message = '; '.join(h.warnings) or f'{h.rate_hz:.1f} Hz'
            values = {k: v for k, v in h.to_dict().items() if k not in ('camera', 'warnings', 'level')}
            statuses.append(diagnostic_status(f'volcap monitor {cam}', h.level, message, values, hardware_id=cam))
        spread = self.report.spread_ms_max
        silent = [c for c, h in self.report.cameras.items() if h.silent_s is not None]
        statuses.append(diagnostic_status('volcap monitor rig', 'error' if silent else
                                          'warn' if self.report.warnings else 'ok',
                                          f'silent: {", ".join(silent)}' if silent else
                                          f'frame-set stamp spread up to {spread:.1f} ms' if spread is not None
                                          else 'waiting for frames',
                                          {'period_ms': round(self.report.period_ms, 3),
                                           'tolerance_ms': round(self.report.tolerance_ms, 3)}))
        self.pub.publish(diagnostic_array(statuses, time.time_ns()))


def health_table(report):
    """A rich Table of a RigHealthReport."""
    from rich.table import Table

    def ms(v, fmt='{:+.1f}'):
        return '-' if v is None else fmt.format(v)
    table = Table(title=f'volcap rig monitor: {1000 / report.period_ms:.1f} fps, pairing tolerance '
                        f'{report.tolerance_ms:.1f} ms, frame-set spread median {ms(report.spread_ms_median, "{:.1f}")}'
                        f' / max {ms(report.spread_ms_max, "{:.1f}")} ms')
    for column in ('camera', 'Hz', 'dropped', 'colour-depth ms', 'offset ms', 'drift ms/s', 'status'):
        table.add_column(column, justify='left' if column in ('camera', 'status') else 'right')
    for cam, h in report.cameras.items():
        table.add_row(cam, f'{h.rate_hz:.1f}', str(h.dropped), ms(h.color_depth_offset_ms), ms(h.rig_offset_ms),
                      ms(h.drift_ms_per_s, '{:+.2f}'),
                      ('[red]' if h.silent_s is not None else '[yellow]') + '; '.join(h.warnings) if h.warnings
                      else '[green]ok')
    return table
