"""A subscriber standing in for a consumer of the camera streams: per-camera rates, frame-set
completeness (through the volcap synchroniser) and transport latency (receive time minus header
stamp, meaningful when stamps are wall-clock, e.g. a live rig or ``bag_player restamp:=true``)."""
from __future__ import annotations

import time
from collections import defaultdict

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image

from volcap_core import qos, topics
from volcap_core.conversions import stamp_to_ns
from volcap_core.sync import FrameSetSynchronizer
from volcap_driver.playback import cdr_stamp_ns

STREAMS = {'color': topics.COLOR_IMAGE, 'depth': topics.DEPTH_IMAGE}


class StreamMonitor(Node):
    def __init__(self, cameras: list[str], tolerance_ms: float = 5.0, name: str = 'volcap_monitor',
                 raw: bool = False):
        """``raw``: take serialised messages and read only the header stamp (no image decode), to
        separate transport cost from deserialisation cost."""
        super().__init__(name)
        self.cameras = cameras
        self.tolerance_ns = int(tolerance_ms * 1e6)
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
