"""`volcap operator`: what the rig sees, live in a browser, without writing code.

    volcap operator [--cameras cam0,cam1] [--hz 2] [--web-port 9090]

A bridge node forwards, at ``hz`` per stream, the newest of each camera's colour image and cleaned
depth and the newest fused model (``volcap/mesh/glb``) to Rerun, whose web viewer it serves on
localhost (``rerun-sdk`` ships the viewer: nothing is fetched from the internet, which a closed
studio network would refuse). The cameras appear posed in the studio frame (+Z up) from the
calibration, with their frustums.

Why Rerun rather than the Foxglove WebSocket bridge: either adds one subscriber per stream to the
graph (this bridge takes messages serialised and decodes only the ones it forwards), so their
cost to the graph differs only in the bridge's own work; Rerun's viewer is served by the bridge
itself, where Foxglove's needs the Foxglove app or a Lichtblick install on the operator's
machine. The bridge's cost on a full rig has not been measured (docs/renderer.md).
"""
from __future__ import annotations

import urllib.parse
from dataclasses import dataclass

import cv2
import yaml
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String
from visualization_msgs.msg import Marker

from volcap_core import qos, topics
from volcap_core.calibration import Calibration
from volcap_core.cdr import cdr_stamp_ns
from volcap_core.conversions import color_message_to_rgb, image_to_numpy
from volcap_core.ros import Diagnostics


@dataclass
class OperatorConfig:
    cameras: tuple[str, ...] = tuple(topics.camera_names(8))
    hz: float = 2.0                     # forwarded per stream and second
    scale: float = 0.5                  # colour images shrunk by this before JPEG
    jpeg_quality: int = 80
    color_transport: str = 'raw'        # raw (Image) or compressed (JPEG CompressedImage)
    web_port: int = 9090
    grpc_port: int = 9876


class OperatorBridge(Node):
    """Keeps the newest serialised message per stream; a timer decodes and logs them."""

    def __init__(self, cfg: OperatorConfig, recording=None, **node_options):
        import rerun as rr
        super().__init__('volcap_operator', **node_options)
        self.cfg, self.rr = cfg, rr
        self.recording = recording
        self.newest: dict[str, tuple[type, bytes]] = {}
        self.focal: dict[str, float] = {}     # camera -> colour fx (px), for its frustum
        self.forwarded = {'color': 0, 'depth': 0, 'model': 0}
        self.superseded = 0          # messages replaced by a newer one before they were forwarded
        self.diagnostics = Diagnostics(self, 'operator view')
        color_type = CompressedImage if cfg.color_transport == 'compressed' else Image
        color_topic = topics.COLOR_IMAGE + ('/compressed' if cfg.color_transport == 'compressed' else '')
        for cam in cfg.cameras:
            self.create_subscription(CameraInfo, topics.camera_topic(cam, topics.COLOR_INFO),
                                     lambda msg, c=cam: self.focal.__setitem__(c, float(msg.k[0])), qos.SENSOR)
            for stream, kind, topic in (('color', color_type, color_topic), ('depth', Image, topics.DEPTH_CLEAN)):
                key = f'cams/{cam}/{stream}'
                self.create_subscription(kind, topics.camera_topic(cam, topic),
                                         lambda data, k=key, t=kind: self._keep(k, t, data), qos.SENSOR, raw=True)
        self.create_subscription(Marker, '/' + topics.MESH_GLB, lambda data: self._keep('model', Marker, data),
                                 qos.SENSOR, raw=True)
        self.create_subscription(String, '/' + topics.CALIBRATION, self._on_calibration, qos.LATCHED)
        rr.log('/', rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, recording=recording)
        self.create_timer(1.0 / cfg.hz, self._forward)
        self.create_timer(1.0, self._report)

    def _keep(self, key: str, kind: type, data: bytes) -> None:
        self.superseded += key in self.newest
        self.newest[key] = (kind, data)

    def _on_calibration(self, msg: String) -> None:
        rr = self.rr
        try:
            calibration = Calibration.from_yaml(msg.data)
        except (ValueError, KeyError, TypeError, yaml.YAMLError) as e:
            self.diagnostics.report('warn', f'unusable calibration: {e}')
            return
        _, T_frame_world = calibration.output_frame()
        for cam in calibration.cameras:
            T = T_frame_world @ calibration.T_world_color(cam)
            rr.log(f'cams/{cam}', rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True,
                   recording=self.recording)

    def _forward(self) -> None:
        rr = self.rr
        pending, self.newest = self.newest, {}
        for key, (kind, data) in pending.items():
            rr.set_time('capture', timestamp=cdr_stamp_ns(data) / 1e9, recording=self.recording)
            try:
                msg = deserialize_message(data, kind)
                if key == 'model':
                    self._log_model(msg)
                elif key.endswith('/color'):
                    self._log_color(key, msg)
                else:
                    self._log_depth(key, msg)
            except ValueError as e:     # a bad frame is reported, the others still go
                self.diagnostics.report('warn', f'{key}: not forwarded: {e}')

    def _log_color(self, key: str, msg) -> None:
        rr, cfg = self.rr, self.cfg
        rgb = color_message_to_rgb(msg)
        h, w = rgb.shape[:2]
        small = cv2.resize(rgb, (max(1, round(w * cfg.scale)), max(1, round(h * cfg.scale))),
                           interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode('.jpg', cv2.cvtColor(small, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY,
                                                                                  cfg.jpeg_quality])
        if ok:
            rr.log(key, rr.EncodedImage(contents=jpeg.tobytes(), media_type='image/jpeg'), recording=self.recording)
            name = key.split('/')[1]
            if self.focal.get(name):      # the frustum, once the camera_info has come
                rr.log(f'cams/{name}', rr.Pinhole(focal_length=self.focal[name] * small.shape[1] / w,
                                                  width=small.shape[1], height=small.shape[0],
                                                  camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.2),
                       static=True, recording=self.recording)
            self.forwarded['color'] += 1

    def _log_depth(self, key: str, msg: Image) -> None:
        rr = self.rr
        depth = image_to_numpy(msg)
        meter = 1000.0 if msg.encoding == '16UC1' else 1.0
        rr.log(key, rr.DepthImage(depth, meter=meter), recording=self.recording)
        self.forwarded['depth'] += 1

    def _log_model(self, msg: Marker) -> None:
        from volcap_fusion.glb import decode_glb
        rr = self.rr
        model, _ = decode_glb(bytes(msg.mesh_file.data))
        rr.log('model', rr.Mesh3D(vertex_positions=model.vertices, triangle_indices=model.triangles,
                                  vertex_colors=model.colors), recording=self.recording)
        self.forwarded['model'] += 1

    def _report(self) -> None:
        self.diagnostics.report('ok', f'forwarding to the Rerun viewer on port {self.cfg.web_port}',
                                superseded=self.superseded, **{f'forwarded_{k}': v for k, v in self.forwarded.items()})


def run_operator(cfg: OperatorConfig, ready=None) -> None:
    """Serve the viewer and bridge the graph into it until interrupted."""
    import rerun as rr
    from rclpy.executors import ExternalShutdownException

    from .session import GraphSession
    rr.init('volcap')
    uri = rr.serve_grpc(grpc_port=cfg.grpc_port)
    rr.serve_web_viewer(web_port=cfg.web_port, open_browser=False, connect_to=uri)
    try:
        with GraphSession('volcap_operator', executor='events') as session:
            session.host(OperatorBridge(cfg))
            if ready:
                ready(f'http://127.0.0.1:{cfg.web_port}/?url={urllib.parse.quote(uri, safe="")}')
            session.spin_until(lambda: not session.ok())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
