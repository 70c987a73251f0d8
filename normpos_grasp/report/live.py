"""Live view of a running cell: a small HTTP server on 127.0.0.1 serving the WebGL page and the current state.

The cell loop calls `LiveView.publish(scene, state)` after each frame; browsers poll `/scene.json`.
`LiveView.follow(read_state)` streams the arm's state (a JSON-ready dict) from a background thread, also while the
arm moves.

Hardening: the Host header must name a loopback host (127.0.0.0/8, ::1, localhost, with an optional port; 403
otherwise), so a page on another site cannot read the scene through DNS rebinding; a request must arrive complete
within `request_timeout_s` (slow or half-open clients are dropped) and at most `max_connections` are served at once
(503 beyond that).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import socket
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs

from normpos_grasp.errors import InputError
from normpos_grasp.hosts import host_header_is_loopback, is_loopback
from normpos_grasp.report.html import live_page
from normpos_grasp.report.scene3d import TwinScene

log = logging.getLogger(__name__)


class _DeadlineReader(io.RawIOBase):
    """Socket reader that fails with TimeoutError once `deadline` (time.monotonic seconds) has passed, so a client
    sending its request one byte at a time cannot hold a connection longer than the request timeout."""

    def __init__(self, sock: socket.socket, deadline: float) -> None:
        self._sock = sock
        self.deadline = deadline

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("request not complete within the request timeout")
        self._sock.settimeout(left)
        return self._sock.recv_into(buffer)


class _CappedServer(ThreadingHTTPServer):
    """ThreadingHTTPServer serving at most `max_connections` connections at once; 503 beyond that."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], handler: Any, max_connections: int) -> None:
        self._slots = threading.BoundedSemaphore(max_connections)
        super().__init__(address, handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            with contextlib.suppress(OSError):
                request.settimeout(1.0)
                request.sendall(
                    b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: 5\r\n"
                    b"Connection: close\r\n\r\nbusy\n"
                )
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


class LiveView:
    """Serves the live page on `host:port` (127.0.0.1 by default; port 0 picks a free one) in a daemon thread.

    request_timeout_s: seconds a client has to send a complete request (and per socket write); max_connections:
    connections served at once. Requests whose Host header is not a loopback name or address get 403.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8765,
        title: str = "normpos-grasp live view",
        *,
        request_timeout_s: float = 5.0,
        max_connections: int = 32,
    ) -> None:
        if not 0 < request_timeout_s <= 300:
            raise InputError(f"request_timeout_s must lie in (0, 300] seconds, got {request_timeout_s}")
        if not 1 <= max_connections <= 1024:
            raise InputError(f"max_connections must lie in 1..1024, got {max_connections}")
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise InputError(f"live view port must be an integer in 0..65535 (0 picks a free one), got {port!r}")
        if not is_loopback(host):
            raise InputError(
                f"the live view serves loopback addresses only (127.0.0.1, ::1, localhost), got {host!r}; "
                "reach it from another machine through an SSH tunnel"
            )
        self._lock = threading.Lock()
        # the scene payload is serialised once per publish; state updates (several a second) only touch their part
        self._scene_bytes = b"null"
        self._state_bytes = b"null"
        self._version = 0
        self._page = live_page(title).encode("utf-8")
        view = self

        class Handler(BaseHTTPRequestHandler):
            timeout = request_timeout_s  # per socket operation (StreamRequestHandler.setup applies it)

            def setup(self) -> None:
                super().setup()
                self.rfile.close()  # the plain socket file: replaced by one that enforces the request deadline
                self.rfile = io.BufferedReader(_DeadlineReader(self.connection, time.monotonic() + request_timeout_s))

            def do_GET(self) -> None:
                self.connection.settimeout(request_timeout_s)  # the request is read: writes get their own timeout
                if not host_header_is_loopback(self.headers.get("Host")):
                    log.warning("live view: refused a request for Host %r", self.headers.get("Host"))
                    self._send(403, "text/plain", b"forbidden: the live view answers loopback host names only\n")
                    return
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
            self._server = _CappedServer((host, port), Handler, max_connections)
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


def add_watch_overlay(scene: TwinScene, zones: Any, intrusions: Any = ()) -> None:
    """Draw the zone watch into a twin: each watched zone (`name`, corners `lo`, `hi` in the world, m) as a
    translucent amber box, each intrusion (`label`, world sample `points` (N, 3)) as red points (docs/watch.md)."""
    import numpy as np

    for zone in zones:
        lo, hi = np.asarray(zone.lo, dtype=np.float64), np.asarray(zone.hi, dtype=np.float64)
        pose = np.eye(4)
        pose[:3, 3] = (lo + hi) / 2.0
        scene.add_box(f"watch/zone/{zone.name}", pose, hi - lo, (255, 176, 0), 0.18)
    for k, intrusion in enumerate(intrusions):
        scene.add_points(f"watch/intrusion/{k}/{intrusion.label}", intrusion.points, (230, 20, 20))
