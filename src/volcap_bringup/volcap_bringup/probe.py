"""The renderer stand-in: a subscriber that receives the fused output as a telepresence renderer
would, and times it. `volcap run`, `volcap live --json`, the demo and the ROS tests host it in
their graph session."""
from __future__ import annotations

import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from visualization_msgs.msg import Marker

from volcap_core import qos, topics
from volcap_core.cdr import cdr_stamp_ns
from volcap_core.sync import DEFAULT_PERIOD_NS, tolerance_for_period


class RendererProbe(Node):
    """Receives every mesh (``/volcap/mesh``) and, with ``clouds``, every fused cloud, keeping
    arrival (wall ns), capture stamp and size. With ``entry_topic`` (the first camera's colour as
    the graph receives it, Image or JPEG) it also notes when each frame set entered the graph, so
    latency counts from there (offline replay, whose stamps are the bag's); live stamps are wall
    clock, so latency counts from the stamp itself. ``reliable``: lose no mesh (offline); live
    renderers take the newest (sensor-data QoS)."""

    def __init__(self, entry_topic: str | None = None, clouds: bool = False, reliable: bool = True, **node_options):
        super().__init__('volcap_renderer_probe', **node_options)
        self.meshes: list[tuple[int, int, int]] = []       # (arrival wall ns, capture stamp ns, bytes)
        self.clouds: list[tuple[int, int, int]] = []       # (arrival wall ns, capture stamp ns, points)
        self.entered: dict[int, int] = {}                  # stamp -> wall ns its first colour image arrived here
        profile = qos.EVERY_FRAME if reliable else qos.CAMERA
        self.create_subscription(Marker, '/' + topics.MESH, self._on_mesh, profile, raw=True)
        if clouds:
            self.create_subscription(PointCloud2, '/' + topics.FUSED_POINTS, self._on_cloud, profile, raw=True)
        if entry_topic:
            kind = CompressedImage if entry_topic.endswith('/compressed') else Image
            self.create_subscription(kind, entry_topic,
                                     lambda data: self.entered.setdefault(cdr_stamp_ns(data), time.time_ns()),
                                     qos.SENSOR, raw=True)

    def _on_mesh(self, data: bytes) -> None:
        self.meshes.append((time.time_ns(), cdr_stamp_ns(data), len(data)))

    def _on_cloud(self, data: bytes) -> None:
        self.clouds.append((time.time_ns(), cdr_stamp_ns(data), len(data)))

    @property
    def mesh_count(self) -> int:
        """Distinct frame sets whose mesh arrived."""
        return len({stamp for _, stamp, _ in self.meshes})

    def latency_ms(self) -> np.ndarray:
        """Per mesh: from the frame set's entry into the graph (``entry_topic``; a set is stamped
        by whichever camera opened it, so matched within the sync tolerance) or, without an entry
        topic, from its capture stamp, to the mesh's arrival here."""
        if not self.entered:
            return np.array([(arrival - stamp) / 1e6 for arrival, stamp, _ in self.meshes])
        entered = np.array(sorted(self.entered), dtype=np.int64)
        out = []
        for arrival, stamp, _ in self.meshes:
            k = int(np.argmin(np.abs(entered - stamp)))
            if abs(int(entered[k]) - stamp) <= tolerance_for_period(DEFAULT_PERIOD_NS):
                out.append((arrival - self.entered[int(entered[k])]) / 1e6)
        return np.array(out)

    def summary(self) -> dict:
        latency = self.latency_ms()
        arrivals = sorted(t for t, _, _ in self.meshes)
        rate = (len(arrivals) - 1) / ((arrivals[-1] - arrivals[0]) / 1e9) if len(arrivals) > 2 else None
        return {'meshes_received': self.mesh_count,
                'clouds_received': len({s for _, s, _ in self.clouds}),
                'mesh_rate_hz': rate,
                'latency_ms_median': float(np.median(latency)) if latency.size else None,
                'latency_ms_p95': float(np.percentile(latency, 95)) if latency.size else None,
                'mesh_message_mb_median': float(np.median([b for _, _, b in self.meshes]) / 1e6)
                if self.meshes else None}
