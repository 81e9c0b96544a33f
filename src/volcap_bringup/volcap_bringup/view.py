"""`volcap view`: the browser player (``web/``: three.js from npm) served on localhost.

    volcap view run/frames              # a recorded sequence, played at its capture timing
    volcap view --live                  # the newest mesh of a running graph (volcap/mesh/glb)

The page and three.js come from the ``web/`` folder that ``make web`` fills with ``npm ci`` (or
``VOLCAP_WEB``). The sequence folder is served read-only under ``/sequence/``. Live, a ROS node
subscribes to ``volcap/mesh/glb`` and a WebSocket server (the ``websockets`` library) pushes each
GLB to every open page; a page that is still decoding gets only the newest one afterwards, so a
slow client never builds a backlog and never slows the graph.
"""
from __future__ import annotations

import functools
import http.server
import json
import os
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

WEB_ENV = 'VOLCAP_WEB'
MIME = {'.glb': 'model/gltf-binary', '.js': 'text/javascript', '.mjs': 'text/javascript', '.wasm': 'application/wasm',
        '.jsonl': 'application/jsonl', '.json': 'application/json'}


def web_root() -> Path:
    """The player's folder, with three.js installed in it (``make web``)."""
    root = Path(os.environ.get(WEB_ENV) or Path(__file__).resolve().parents[3] / 'web')
    if not (root / 'index.html').is_file():
        raise FileNotFoundError(f'no volcap player in {root} (set {WEB_ENV} to the web/ folder of a volcap checkout)')
    if not (root / 'node_modules' / 'three' / 'build' / 'three.module.js').is_file():
        raise FileNotFoundError(f'three.js is not installed in {root}: run `make web` (npm ci) first')
    return root


@dataclass
class ViewConfig:
    folder: Path | None = None          # a sequence folder (sequence.jsonl); None with live
    live: bool = False
    host: str = '127.0.0.1'
    port: int = 8080
    ws_port: int = 0                    # 0: port + 1


class PlayerHandler(http.server.SimpleHTTPRequestHandler):
    """The player's files at /, the sequence at /sequence/, the page's settings at /config.json."""

    def __init__(self, *args, web: Path, sequence: Path | None, config: dict, **kwargs):
        self.web, self.sequence, self.config = web, sequence, config
        super().__init__(*args, directory=str(web), **kwargs)

    def translate_path(self, path: str) -> str:
        path = path.split('?', 1)[0].split('#', 1)[0]
        if path.startswith('/sequence/') and self.sequence is not None:
            # SimpleHTTPRequestHandler's own translation (no '..' escapes) from the sequence folder
            self.directory = str(self.sequence)
            return super().translate_path(path[len('/sequence'):])
        self.directory = str(self.web)
        return super().translate_path(path)

    def do_GET(self):
        if self.path.split('?', 1)[0] == '/config.json':
            body = json.dumps(self.config).encode()
            self.send_response(200)
            self.send_header('Content-Type', 'application/json')
            self.send_header('Content-Length', str(len(body)))
            self.send_header('Cache-Control', 'no-store')
            self.end_headers()
            self.wfile.write(body)
            return
        super().do_GET()

    def end_headers(self):
        self.send_header('Cache-Control', 'no-store')   # a growing sequence: always the current files
        super().end_headers()

    def guess_type(self, path):
        return MIME.get(Path(path).suffix, None) or super().guess_type(path)

    def log_message(self, format, *args):   # quiet: the page reports what it does
        pass


class PlayerServer(http.server.ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):
        if not isinstance(sys.exc_info()[1], ConnectionError):   # a page closed mid-download is normal
            super().handle_error(request, client_address)


class NewestFrame:
    """The newest GLB and its sequence number; readers wait for one newer than theirs."""

    def __init__(self):
        self.data: bytes | None = None
        self.number = 0
        self.cond = threading.Condition()

    def put(self, data: bytes) -> None:
        with self.cond:
            self.data, self.number = data, self.number + 1
            self.cond.notify_all()

    def newer_than(self, number: int, timeout: float) -> tuple[int, bytes | None]:
        with self.cond:
            self.cond.wait_for(lambda: self.number > number, timeout)
            return self.number, (self.data if self.number > number else None)


def serve_live_frames(newest: NewestFrame, host: str, port: int, stop: threading.Event):
    """The WebSocket server (a thread per client) pushing the newest GLB; returns the server."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.server import serve

    def client(ws):
        seen = 0
        try:
            while not stop.is_set():
                seen, data = newest.newer_than(seen, 0.5)
                if data is not None:
                    ws.send(data)
        except ConnectionClosed:
            pass

    server = serve(client, host, port, max_size=None, compression=None)
    threading.Thread(target=server.serve_forever, name='volcap_view_ws', daemon=True).start()
    return server


def run_view(cfg: ViewConfig, ready=None) -> None:
    """Serve until interrupted. ``ready(url)`` is called once the page can be loaded."""
    web = web_root()
    sequence = None
    if not cfg.live:
        folder = Path(cfg.folder) if cfg.folder is not None else None
        if folder is not None and (folder / 'frames' / 'sequence.jsonl').is_file():
            folder = folder / 'frames'          # the --out folder of volcap run
        if folder is None or not (folder / 'sequence.jsonl').is_file():
            raise FileNotFoundError(f'{cfg.folder} holds no volumetric sequence (sequence.jsonl missing); '
                                    'give the frames folder of `volcap run --out DIR` (DIR/frames)')
        sequence = folder.resolve()
    ws_port = cfg.ws_port or cfg.port + 1
    config = {'live': f'ws://{cfg.host}:{ws_port}/' if cfg.live else None}
    handler = functools.partial(PlayerHandler, web=web, sequence=sequence, config=config)
    httpd = PlayerServer((cfg.host, cfg.port), handler)
    stop = threading.Event()
    threading.Thread(target=httpd.serve_forever, name='volcap_view_http', daemon=True).start()
    url = f'http://{cfg.host}:{httpd.server_address[1]}/'
    try:
        if cfg.live:
            _serve_live(cfg, ws_port, stop, url, ready)
        else:
            if ready:
                ready(url)
            stop.wait()
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        httpd.shutdown()
        httpd.server_close()


def _serve_live(cfg: ViewConfig, ws_port: int, stop: threading.Event, url: str, ready) -> None:
    from rclpy.executors import ExternalShutdownException
    from visualization_msgs.msg import Marker

    from volcap_core import qos, topics

    from .session import GraphSession

    newest = NewestFrame()
    server = serve_live_frames(newest, cfg.host, ws_port, stop)
    try:
        with GraphSession('volcap_view', executor='events') as session:
            session.node.create_subscription(Marker, '/' + topics.MESH_GLB,
                                             lambda m: newest.put(bytes(m.mesh_file.data)), qos.CAMERA)
            if ready:
                ready(url)
            session.spin_until(lambda: stop.is_set() or not session.ok())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        stop.set()
        server.shutdown()
