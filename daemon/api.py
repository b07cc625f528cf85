"""Reference API for the comfort algorithm: HTTP with JSON (stdlib server in a thread).

Endpoints::

    GET  /health             200 {"ok": true, ...} while the loop ticks, else 503
    GET  /reference          the reference in force
    PUT  /reference          set it (POST too); body: Reference fields as JSON
    GET  /status             counters: ticks, deadline misses, fallbacks, interlock trips, faults, ...
    GET  /sample             the latest logged sample (log schema names)

A reference is validated with :meth:`Reference.from_mapping`; a malformed or out-of-range one
is answered with 400 and a message naming the field and its range, and changes nothing.
Bodies above ``max_body_bytes`` get 413 unread; a body that is not JSON, 400; a content type
other than application/json, 415. At most 16 connections are served at once (more get
503), each dropped after ``request_timeout_s`` without progress. With a token configured,
every request needs ``Authorization: Bearer <token>`` (401 otherwise, compared in constant time).
"""

from __future__ import annotations

import hmac
import json
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Callable, Protocol

from hvac_mpc.contract import InvalidReference, Reference


class ApiBackend(Protocol):
    """What the API needs from the daemon (all methods thread-safe)."""

    def get_reference(self) -> Reference: ...

    def set_reference(self, ref: Reference) -> None: ...

    def status(self) -> dict[str, Any]: ...

    def latest_sample(self) -> dict[str, Any] | None: ...

    def health(self) -> tuple[bool, dict[str, Any]]: ...


class _Server(ThreadingHTTPServer):
    """Threaded HTTP server with a cap on concurrent connections (beyond it: 503 and close)."""

    daemon_threads = True
    allow_reuse_address = True
    max_connections = 16
    request_queue_size = 64  # listen backlog: excess connections get a quick 503, not a SYN retry

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.dropped = 0
        self.refused = 0
        self._active = threading.BoundedSemaphore(self.max_connections)

    def process_request(self, request, client_address) -> None:
        if not self._active.acquire(blocking=False):
            self.refused += 1
            try:
                request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
            except OSError:
                pass
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._active.release()

    def handle_error(self, request, client_address) -> None:
        """A client that vanished or timed out mid-request: drop it quietly and count it."""
        self.dropped += 1


def _handler(backend: ApiBackend, token: str, max_body: int, timeout_s: float,
             count: Callable[[str], None]) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "hvac-mpc-daemon"
        sys_version = ""
        timeout = timeout_s
        protocol_version = "HTTP/1.1"

        def log_message(self, fmt, *args):  # quiet; the daemon counts requests instead
            pass

        def _send(self, status: int, payload: Any, close: bool = False) -> None:
            body = json.dumps(payload, allow_nan=False, default=str).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            if close:
                self.send_header("Connection", "close")
                self.close_connection = True
            self.end_headers()
            self.wfile.write(body)
            count("ok" if status < 400 else "rejected")

        def _error(self, status: int, message: str, close: bool = False) -> None:
            self._send(status, {"error": message}, close)

        def _authorised(self) -> bool:
            if not token:
                return True
            given = self.headers.get("Authorization", "")
            ok = given.startswith("Bearer ") and hmac.compare_digest(given[7:].strip().encode(), token.encode())
            if not ok:
                self.send_response(HTTPStatus.UNAUTHORIZED)
                body = b'{"error": "missing or wrong bearer token"}'
                self.send_header("WWW-Authenticate", "Bearer")
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Connection", "close")
                self.close_connection = True
                self.end_headers()
                self.wfile.write(body)
                count("rejected")
            return ok

        def _path(self) -> str:
            return self.path.split("?", 1)[0].rstrip("/") or "/"

        def do_GET(self) -> None:  # noqa: N802 - http.server naming
            if not self._authorised():
                return
            path = self._path()
            if path == "/health":
                ok, info = backend.health()
                self._send(200 if ok else 503, {"ok": ok, **info})
            elif path == "/reference":
                self._send(200, backend.get_reference().as_dict())
            elif path == "/status":
                self._send(200, backend.status())
            elif path == "/sample":
                sample = backend.latest_sample()
                self._send(200 if sample is not None else 503,
                           sample if sample is not None else {"error": "no sample yet"})
            else:
                self._error(404, f"unknown path {path!r}; paths: /health /reference /status /sample")

        def _set_reference(self) -> None:
            if not self._authorised():
                return
            if self._path() != "/reference":
                self._error(404 if self._path() not in ("/health", "/status", "/sample") else 405,
                            "only /reference accepts PUT or POST")
                return
            length = self.headers.get("Content-Length")
            if self.headers.get("Transfer-Encoding"):
                self._error(411, "chunked bodies are not accepted; send Content-Length", close=True)
                return
            try:
                n = int(length) if length is not None else -1
            except ValueError:
                n = -1
            if n < 0:
                self._error(411, "Content-Length required", close=True)
                return
            if n > max_body:
                self._error(413, f"body of {n} bytes exceeds the limit of {max_body} bytes", close=True)
                return
            try:
                raw = self.rfile.read(n)
            except TimeoutError:
                self.close_connection = True
                count("rejected")
                return
            if len(raw) != n:
                self._error(400, f"body shorter than its Content-Length ({len(raw)} of {n} bytes)", close=True)
                return
            ctype = self.headers.get("Content-Type", "application/json").split(";", 1)[0].strip().lower()
            if ctype != "application/json":
                self._error(415, f"Content-Type {ctype!r} not accepted; use application/json")
                return
            try:
                data = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant)
            except (UnicodeDecodeError, ValueError, RecursionError) as exc:
                self._error(400, f"body is not valid JSON: {exc}")
                return
            try:
                ref = Reference.from_mapping(data)
            except InvalidReference as exc:
                self._error(400, f"invalid reference: {exc}")
                return
            except TypeError as exc:  # e.g. a JSON array or nested object where a number belongs
                self._error(400, f"invalid reference: {exc}")
                return
            backend.set_reference(ref)
            self._send(200, {"accepted": ref.as_dict()})

        do_PUT = _set_reference  # noqa: N815
        do_POST = _set_reference  # noqa: N815

        def _not_allowed(self) -> None:
            if self._authorised():
                self._error(405, "method not allowed")

        do_DELETE = _not_allowed  # noqa: N815
        do_PATCH = _not_allowed  # noqa: N815

    return Handler


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number")


class ReferenceApi:
    """The HTTP server in a background thread. ``port`` is the bound port after :meth:`start`."""

    def __init__(self, backend: ApiBackend, host: str = "127.0.0.1", port: int = 8750, token: str = "",
                 max_body_bytes: int = 4096, request_timeout_s: float = 5.0):
        if host not in ("127.0.0.1", "localhost", "::1") and not token:
            raise ValueError(f"api host {host!r} is not loopback: a bearer token is required")
        self.counts = {"ok": 0, "rejected": 0}
        self._lock = threading.Lock()
        handler = _handler(backend, token, max_body_bytes, request_timeout_s, self._count)
        self._server = _Server((host, port), handler)
        self.host = host
        self.port = self._server.server_address[1]
        self._thread: threading.Thread | None = None

    @property
    def dropped(self) -> int:
        """Connections dropped mid-request (client gone or too slow)."""
        return self._server.dropped

    @property
    def refused(self) -> int:
        """Connections refused because ``max_connections`` were open."""
        return self._server.refused

    def _count(self, what: str) -> None:
        with self._lock:
            self.counts[what] += 1

    def start(self) -> "ReferenceApi":
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="reference-api", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        if self._thread is not None:
            self._thread.join(2.0)
