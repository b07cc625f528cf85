"""The HTTP server of the daemon's API: uvicorn in a background thread, hardened, and the token.

Why this stack (docs in the README, daemon section): uvicorn is a maintained, widely deployed
HTTP/1.1 server (h11 parses the requests); one asyncio loop holds every connection, so idle or
slow clients cost a few kilobytes each instead of a thread, and /health is answered while
hundreds of connections trickle. What uvicorn does not bound itself is added here: a header
deadline (a connection must deliver its request headers within ``api.header_timeout_s``, also
between keep-alive requests) and a connection cap that drops the oldest connection still
sending headers, so slow clients cannot take the cap from a fresh /health request. The body
deadline and size limit are the application's (:mod:`hvac_mpc.daemon.api`).

The token every write needs is generated at first start into ``api.token_file`` (default
``<log stem>.token`` beside the log) with mode 0600, as local notebook servers do; loopback
clients need it too.
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
import stat
import threading
from pathlib import Path
from typing import Any

from .api import ApiApp, BadRequest
from .config import DaemonConfig, resolve

LOG = logging.getLogger("hvac_mpc.daemon")


# ---------------------------------------------------------------------------------------------- token
def token_path(cfg: DaemonConfig) -> Path:
    """The token file: ``api.token_file``, or ``<log stem>.token`` beside the log."""
    if cfg.api.token_file:
        return resolve(cfg, cfg.api.token_file)
    log = resolve(cfg, cfg.log.path)
    return log.with_name(log.stem + ".token")


def ensure_token(path: Path) -> str:
    """The bearer token: read from ``path``, or generated there at first start (mode 0600).

    A token file others can read is made private again (and the fact logged)."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        mode = stat.S_IMODE(path.stat().st_mode)
        if mode & 0o077:
            LOG.warning("token file %s was readable by others (mode %o): set to 0600", path, mode)
            os.chmod(path, 0o600)
        token = path.read_text().strip()
        if len(token) < 16:
            raise ValueError(f"token file {path}: the token must have at least 16 characters; delete the "
                             "file to have a new one generated")
        return token
    token = secrets.token_urlsafe(32)
    try:
        os.write(fd, (token + "\n").encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    LOG.warning("API token generated in %s (mode 0600)", path)
    return token


def load_token(cfg: DaemonConfig) -> str:
    if cfg.api.token_env:
        token = os.environ.get(cfg.api.token_env, "").strip()
        if len(token) < 16:
            raise ValueError(f"api.token_env = {cfg.api.token_env!r}: the variable is unset or shorter than "
                             "16 characters")
        return token
    return ensure_token(token_path(cfg))


# ---------------------------------------------------------------------------------------------- server
def _guarded_protocol(header_timeout_s: float, max_connections: int, stats: dict[str, int]) -> type:
    """uvicorn's h11 protocol with a header deadline and a connection cap slow clients cannot take."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class GuardedH11Protocol(H11Protocol):
        def connection_made(self, transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._opened = self.loop.time()
            self._deadline = None
            self._arm()
            if len(self.connections) > max_connections:
                waiting = sorted((c for c in self.connections if c is not self and getattr(c, "_deadline", None)),
                                 key=lambda c: c._opened)
                victim = waiting[0] if waiting else self
                stats["evicted"] += 1
                victim.transport.close()

        def _arm(self) -> None:
            self._disarm()
            self._deadline = self.loop.call_later(header_timeout_s, self._header_timeout)

        def _disarm(self) -> None:
            if getattr(self, "_deadline", None) is not None:
                self._deadline.cancel()
                self._deadline = None

        def _header_timeout(self) -> None:
            self._deadline = None
            if not self.transport.is_closing():
                stats["header_timeouts"] += 1
                self.transport.close()

        def handle_events(self) -> None:
            before = self.cycle
            super().handle_events()
            if self.cycle is not before:  # request headers complete: the app has it now
                self._disarm()

        def on_response_complete(self) -> None:
            self._arm()  # the next request's headers are due within the deadline too
            super().on_response_complete()

        def connection_lost(self, exc) -> None:
            self._disarm()
            super().connection_lost(exc)

    return GuardedH11Protocol


class ApiServer:
    """The API (uvicorn, one asyncio loop in a daemon thread). ``port`` is the bound port."""

    def __init__(self, daemon: Any, cfg: DaemonConfig):
        try:
            import uvicorn
        except ImportError as exc:
            raise RuntimeError("the HTTP API needs uvicorn: pip install 'hvac-mpc[server]' "
                               "(or set api.enabled = false)") from exc
        a = cfg.api
        self.cfg = cfg
        token = load_token(cfg)
        family = socket.AF_INET6 if ":" in a.host else socket.AF_INET
        self._sock = socket.socket(family, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._sock.bind((a.host, a.port))
        except OSError:
            self._sock.close()
            raise
        self._sock.listen(1024)
        self.port = self._sock.getsockname()[1]
        self.guard = {"evicted": 0, "header_timeouts": 0}
        self.registry = None
        self.app = ApiApp(daemon, cfg, token, lambda: self.port, self._metrics)
        self._daemon = daemon
        config = uvicorn.Config(
            self.app, http=_guarded_protocol(a.header_timeout_s, a.max_connections, self.guard), lifespan="off",
            log_config=None, access_log=False, server_header=False, date_header=False, timeout_keep_alive=5,
            h11_max_incomplete_event_size=16384, timeout_graceful_shutdown=1, ws="none", loop="asyncio")
        self._server = uvicorn.Server(config)
        self._thread: threading.Thread | None = None

    def _metrics(self) -> bytes:
        try:
            from prometheus_client import generate_latest

            from .metrics import daemon_registry
        except ImportError:
            raise BadRequest(501, "/metrics needs prometheus-client: pip install 'hvac-mpc[server]'") from None
        if self.registry is None:
            self.registry = daemon_registry(self._daemon)
        return generate_latest(self.registry)

    def stats(self) -> dict[str, int]:
        return {**self.app.counts, **self.guard}

    def start(self) -> "ApiServer":
        self._thread = threading.Thread(target=self._server.run, kwargs={"sockets": [self._sock]},
                                        name="http-api", daemon=True)
        self._thread.start()
        if self.cfg.api.port_file:
            pf = resolve(self.cfg, self.cfg.api.port_file)
            tmp = pf.with_suffix(pf.suffix + ".tmp")
            tmp.write_text(str(self.port))
            tmp.replace(pf)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(3.0)
        self._sock.close()
        if self.cfg.api.port_file:
            resolve(self.cfg, self.cfg.api.port_file).unlink(missing_ok=True)
