"""Live view of a running cell: a small HTTP server on 127.0.0.1 serving the WebGL page and the current state.

The cell loop calls `LiveView.publish(scene, state)` after each frame; browsers poll `/scene.json`.
`LiveView.follow(read_state)` streams the arm's state (a JSON-ready dict) from a background thread, also while the
arm moves.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs

from normpos_grasp.errors import InputError
from normpos_grasp.report.html import live_page
from normpos_grasp.report.scene3d import TwinScene

log = logging.getLogger(__name__)


class LiveView:
    """Serves the live page on `host:port` (127.0.0.1 by default; port 0 picks a free one) in a daemon thread."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, title: str = "normpos-grasp live view") -> None:
        self._lock = threading.Lock()
        # the scene payload is serialised once per publish; state updates (several a second) only touch their part
        self._scene_bytes = b"null"
        self._state_bytes = b"null"
        self._version = 0
        self._page = live_page(title).encode("utf-8")
        view = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                path, _, query = self.path.partition("?")
                if path in ("/", "/index.html"):
                    self._send(200, "text/html; charset=utf-8", view._page)
                elif path == "/scene.json":
                    since = parse_qs(query).get("since", [""])[0]
                    body = view._document(since)
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
        self._follow_stop = threading.Event()
        self._follower: threading.Thread | None = None

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
        scene_bytes = json.dumps(scene.to_payload()).encode("utf-8") if scene is not None else None
        state_bytes = json.dumps(state).encode("utf-8") if state is not None else None
        with self._lock:
            if scene_bytes is not None:
                self._version += 1
                self._scene_bytes = scene_bytes
            if state_bytes is not None:
                self._state_bytes = state_bytes

    def _document(self, since: str = "") -> bytes:
        """The /scene.json body: {"version": "N" or null, "scene": payload, "state": state}; the scene is null when
        the client already holds version `since` (state-only polls stay small)."""
        with self._lock:
            current = str(self._version) if self._version else None
            version = json.dumps(current).encode("ascii")
            scene = b"null" if (current is not None and since == current) else self._scene_bytes
            state = self._state_bytes
        return b'{"version": ' + version + b', "scene": ' + scene + b', "state": ' + state + b"}"

    def follow(self, read_state: Callable[[], dict[str, Any]], period_s: float = 0.2) -> None:
        """Publish `read_state()` every `period_s` seconds from a daemon thread until `close()`.

        A failing read is published as {'error': message} (the page shows it) and retried next period.
        """
        if self._follower is not None:
            raise InputError("this live view already follows a state source")

        def loop() -> None:
            while not self._follow_stop.is_set():
                try:
                    state = read_state()
                except Exception as exc:  # any failure of the source is shown, never fatal here
                    state = {"error": f"{type(exc).__name__}: {exc}"}
                self.publish(None, state)
                self._follow_stop.wait(period_s)

        self._follower = threading.Thread(target=loop, name="normpos-live-state", daemon=True)
        self._follower.start()

    @property
    def version(self) -> int:
        """Number of scenes published so far."""
        with self._lock:
            return self._version

    def close(self) -> None:
        self._follow_stop.set()
        if self._follower is not None:
            self._follower.join(timeout=2.0)
        self._server.shutdown()
        self._server.server_close()

    def __enter__(self) -> LiveView:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
