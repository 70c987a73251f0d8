"""Live view of a running cell: a small HTTP server on 127.0.0.1 serving the WebGL page and the current state.

The cell loop calls `LiveView.publish(scene, state)` after each frame; browsers poll `/scene.json`.
"""

from __future__ import annotations

import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from normpos_grasp.errors import InputError
from normpos_grasp.report.html import live_page
from normpos_grasp.report.scene3d import TwinScene

log = logging.getLogger(__name__)


class LiveView:
    """Serves the live page on `host:port` (127.0.0.1 by default; port 0 picks a free one) in a daemon thread."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, title: str = "normpos-grasp live view") -> None:
        self._lock = threading.Lock()
        self._scene_json = b'{"version": null, "scene": null, "state": null}'
        self._version = 0
        self._page = live_page(title).encode("utf-8")
        view = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                if path in ("/", "/index.html"):
                    self._send(200, "text/html; charset=utf-8", view._page)
                elif path == "/scene.json":
                    with view._lock:
                        body = view._scene_json
                    self._send(200, "application/json", body)
                else:
                    self._send(404, "text/plain", b"not found")

            def _send(self, code: int, ctype: str, body: bytes) -> None:
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: Any) -> None:
                log.debug("live view: " + format, *args)

        try:
            self._server = ThreadingHTTPServer((host, port), Handler)
        except OSError as exc:
            raise InputError(f"cannot serve the live view on {host}:{port}: {exc}") from exc
        self._thread = threading.Thread(target=self._server.serve_forever, name="normpos-live-view", daemon=True)

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        name = host.decode() if isinstance(host, bytes) else str(host)
        return f"http://{name}:{port}/"

    def start(self) -> LiveView:
        self._thread.start()
        log.info("live view at %s", self.url)
        return self

    def publish(self, scene: TwinScene | None, state: dict[str, Any] | None = None) -> None:
        """Replace the served frame (scene may be None to keep the last one) and arm state."""
        with self._lock:
            current = json.loads(self._scene_json)
            if scene is not None:
                self._version += 1
                current["scene"] = scene.to_payload()
                current["version"] = str(self._version)
            if state is not None:
                current["state"] = state
            self._scene_json = json.dumps(current).encode("utf-8")

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()

    def __enter__(self) -> LiveView:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
