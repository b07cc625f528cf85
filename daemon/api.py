"""The daemon's HTTP API as a plain ASGI application (served by :mod:`hvac_mpc.daemon.server`).

Endpoints (the route table in :func:`routes`, one line each)::

    GET  /health      200 {"ok": true, "status": "ok" | "degraded", ...} while the loop ticks, else 503
    GET  /status      counters, mode, log state, interlock trips, mode history
    GET  /sample      the latest logged sample (log schema names)
    GET  /reference   the reference in force
    GET  /mode        the operator mode, the modes available, the manual setting, recent changes
    GET  /metrics     Prometheus text format (needs the ``server`` extra)
    PUT  /reference   set it (POST too); body: Reference fields as JSON
    PUT  /mode        {"mode": "auto-mpc" | "auto-pid" | "manual" | "safe-stop"}
    PUT  /manual      actuators in manual mode, e.g. {"blower_power_w": 150}
    PUT  /model       {"path": "model.toml"}: validate a model file and swap it in between two samples
    POST /model/rollback  back to the model in force before the last swap

Every request: the Host header must name this server (loopback names, ``api.host``,
``api.allowed_hosts``; 403 otherwise, against DNS rebinding), an ``Origin`` must be the API's own
or in ``api.allowed_origins`` (403, against cross-site requests from a browser). Writes need
``Authorization: Bearer <token>`` (401, compared in constant time) and
``Content-Type: application/json`` (415); their bodies are validated by pydantic (400 naming the
field and its range; integers over 30 digits are refused before conversion, NaN and Infinity
too). Reads need the token with ``api.auth_reads``. Bodies above ``api.max_body_bytes`` get 413,
bodies slower than ``api.body_timeout_s`` 408. Nothing is changed by a refused request.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
from dataclasses import dataclass
from typing import Any, Awaitable, Callable

from hvac_mpc.contract import InvalidReference, Reference

from .config import LOOPBACK_HOSTS, DaemonConfig
from .modes import ModeError, parse_manual, parse_mode

LOG = logging.getLogger("hvac_mpc.daemon")
JSON = "application/json"
MAX_INT_DIGITS = 30
MAX_PATH_CHARS = 2048
MAX_HEADER_BYTES = 8192


class BadRequest(ValueError):
    """A request refused with ``status`` and a message for the client."""

    def __init__(self, status: int, message: str, headers: list[tuple[bytes, bytes]] | None = None):
        super().__init__(message)
        self.status = status
        self.headers = headers or []


# ---------------------------------------------------------------------------------------------- JSON
def _parse_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise ValueError(f"number with {len(text.lstrip('-'))} digits (at most {MAX_INT_DIGITS})")
    return int(text)


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number")


def parse_json(raw: bytes) -> Any:
    """JSON with every number range-checkable: no NaN/Infinity, no integer over 30 digits."""
    try:
        return json.loads(raw.decode("utf-8"), parse_int=_parse_int, parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise BadRequest(400, f"body is not valid JSON: {exc}") from None


# ---------------------------------------------------------------------------------------------- routes
@dataclass(frozen=True)
class Route:
    """One endpoint: method, path, access ('open', 'read' or 'write') and the handler.

    A handler gets ``(body, client)`` (body None for reads) and returns ``(status, payload)``;
    write handlers run in a worker thread (they may take a while, e.g. building the MPC)."""

    method: str
    path: str
    access: str
    handler: Callable[[Any, str], tuple[int, Any]]


def routes(d: Any, metrics: Callable[[], bytes]) -> list[Route]:
    """The route table: one line per endpoint (extend here)."""
    return [
        Route("GET", "/health", "open", lambda _b, _c: _health(d)),
        Route("GET", "/status", "read", lambda _b, _c: (200, d.status())),
        Route("GET", "/sample", "read", lambda _b, _c: (200, s) if (s := d.latest_sample()) is not None
              else (503, {"error": "no sample yet"})),
        Route("GET", "/reference", "read", lambda _b, _c: (200, d.get_reference().as_dict())),
        Route("GET", "/mode", "read", lambda _b, _c: (200, d.get_mode())),
        Route("GET", "/metrics", "read", lambda _b, _c: (200, metrics())),
        Route("PUT", "/reference", "write", lambda b, c: _put_reference(d, b, c)),
        Route("POST", "/reference", "write", lambda b, c: _put_reference(d, b, c)),
        Route("PUT", "/mode", "write", lambda b, c: (200, d.set_mode(parse_mode(b), c))),
        Route("PUT", "/manual", "write", lambda b, c: (200, d.set_manual(
            parse_manual(b, d.cfg.safety.heater_max_w), c))),
        Route("PUT", "/model", "write", lambda b, c: _put_model(d, b, c)),
        Route("POST", "/model/rollback", "write", lambda b, c: _model_call(lambda: d.rollback_model(c))),
    ]


def _health(d: Any) -> tuple[int, Any]:
    ok, info = d.health()
    return (200 if ok else 503), {"ok": ok, **info}


def _put_reference(d: Any, body: Any, client: str) -> tuple[int, Any]:
    try:
        ref = Reference.from_mapping(body)
    except (InvalidReference, TypeError) as exc:
        raise BadRequest(400, f"invalid reference: {exc}") from None
    d.set_reference(ref, client)
    return 200, {"accepted": ref.as_dict()}


def _put_model(d: Any, body: Any, client: str) -> tuple[int, Any]:
    if not isinstance(body, dict) or set(body) != {"path"} or not isinstance(body["path"], str) or not body["path"]:
        raise BadRequest(400, 'invalid model request: expected {"path": "<model file>"}')
    return _model_call(lambda: d.load_model(body["path"], client))


def _model_call(call: Callable[[], dict]) -> tuple[int, Any]:
    """Run a model load or rollback; a refused one is a 409 naming why (nothing changed)."""
    from .monitor import ModelLoadError

    try:
        return 200, call()
    except ModelLoadError as exc:
        raise BadRequest(409, str(exc)) from None


# ---------------------------------------------------------------------------------------------- ASGI app
class ApiApp:
    """The ASGI application (HTTP only; lifespan is not used)."""

    def __init__(self, daemon: Any, cfg: DaemonConfig, token: str, port_getter: Callable[[], int],
                 metrics: Callable[[], bytes]):
        self.cfg = cfg
        self.token = token.encode()
        self.port = port_getter
        self.routes = {(r.method, r.path): r for r in routes(daemon, metrics)}
        self.paths = {r.path for r in self.routes.values()}
        self.counts = {"ok": 0, "rejected": 0, "timeouts": 0}
        a = cfg.api
        self.hosts = {h.lower() for h in (*LOOPBACK_HOSTS, a.host, *a.allowed_hosts)}

    async def __call__(self, scope: dict, receive: Callable[[], Awaitable[dict]], send: Callable) -> None:
        if scope["type"] != "http":
            return
        try:
            status, payload, extra = await self._handle(scope, receive)
        except BadRequest as exc:
            status, payload, extra = exc.status, {"error": str(exc)}, exc.headers
        except ModeError as exc:
            status, payload, extra = exc.status, {"error": str(exc)}, []
        except Exception as exc:  # noqa: BLE001 - never an unanswered request
            LOG.exception("API handler failed")
            status, payload, extra = 500, {"error": f"internal error: {type(exc).__name__}"}, []
        self.counts["ok" if status < 400 else "rejected"] += 1
        if isinstance(payload, bytes):
            body, ctype = payload, b"text/plain; version=0.0.4; charset=utf-8"
        else:
            body, ctype = json.dumps(payload, allow_nan=False, default=str).encode(), JSON.encode()
        headers = [(b"content-type", ctype), (b"content-length", str(len(body)).encode()),
                   (b"cache-control", b"no-store"), (b"x-content-type-options", b"nosniff"), *extra]
        if status >= 400 and status not in (404, 405):
            headers.append((b"connection", b"close"))
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})

    async def _handle(self, scope: dict, receive: Callable) -> tuple[int, Any, list]:
        if sum(len(k) + len(v) + 4 for k, v in scope["headers"]) > MAX_HEADER_BYTES:
            raise BadRequest(431, f"request headers larger than {MAX_HEADER_BYTES} bytes")
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        self._check_host_and_origin(headers)
        method, path = scope["method"], scope["path"].rstrip("/") or "/"
        if len(scope.get("raw_path", b"")) > MAX_PATH_CHARS:
            raise BadRequest(414, f"path longer than {MAX_PATH_CHARS} characters")
        route = self.routes.get((method, path))
        if route is None:
            if path in self.paths:
                allowed = sorted(m for m, p in self.routes if p == path)
                raise BadRequest(405, f"method {method} not allowed on {path}; allowed: {allowed}")
            raise BadRequest(404, f"unknown path {path!r}; paths: {sorted(self.paths)}")
        if route.access == "write" or (route.access == "read" and self.cfg.api.auth_reads):
            self._check_token(headers)
        client = self._client(scope, headers)
        if route.access != "write":
            status, payload = route.handler(None, client)
            return status, payload, []
        ctype = headers.get("content-type", "").split(";", 1)[0].strip().lower()
        if ctype != JSON:
            raise BadRequest(415, f"Content-Type {ctype or '(none)'!r} not accepted; use {JSON}")
        body = parse_json(await self._body(headers, receive))
        loop = asyncio.get_running_loop()
        status, payload = await loop.run_in_executor(None, route.handler, body, client)
        return status, payload, []

    def _check_host_and_origin(self, headers: dict[str, str]) -> None:
        host = headers.get("host", "")
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        name = name.strip("[]").lower()
        if name not in self.hosts:
            raise BadRequest(403, f"Host {host!r} not allowed (allowed: {sorted(self.hosts)} or api.allowed_hosts)")
        origin = headers.get("origin")
        if origin is not None:
            own = {f"http://{h if ':' not in h else '[' + h + ']'}:{self.port()}" for h in self.hosts}
            if origin not in own and origin not in self.cfg.api.allowed_origins:
                raise BadRequest(403, f"Origin {origin!r} not allowed (cross-site request; api.allowed_origins)")
        if headers.get("sec-fetch-site") == "cross-site":
            raise BadRequest(403, "cross-site request refused")

    def _check_token(self, headers: dict[str, str]) -> None:
        given = headers.get("authorization", "")
        if not (given.startswith("Bearer ") and hmac.compare_digest(given[7:].strip().encode(), self.token)):
            raise BadRequest(401, "missing or wrong bearer token (the token file is named in the daemon's "
                                  "configuration, api.token_file)", [(b"www-authenticate", b"Bearer")])

    @staticmethod
    def _client(scope: dict, headers: dict[str, str]) -> str:
        host, port = scope.get("client") or ("?", 0)
        agent = headers.get("user-agent", "")[:60]
        return f"{host}:{port}" + (f" ({agent})" if agent else "")

    async def _body(self, headers: dict[str, str], receive: Callable) -> bytes:
        limit = self.cfg.api.max_body_bytes
        length = headers.get("content-length")
        if length is not None:
            if not length.isdigit():
                raise BadRequest(400, "Content-Length is not a number")
            if int(length) > limit:
                raise BadRequest(413, f"body of {length} bytes exceeds the limit of {limit} bytes")
        chunks: list[bytes] = []
        size = 0

        async def read() -> None:
            nonlocal size
            while True:
                msg = await receive()
                if msg["type"] == "http.disconnect":
                    raise BadRequest(400, "client disconnected")
                chunk = msg.get("body", b"")
                size += len(chunk)
                if size > limit:
                    raise BadRequest(413, f"body exceeds the limit of {limit} bytes")
                chunks.append(chunk)
                if not msg.get("more_body", False):
                    return

        try:
            await asyncio.wait_for(read(), self.cfg.api.body_timeout_s)
        except TimeoutError:
            self.counts["timeouts"] += 1
            raise BadRequest(408, f"body not received within {self.cfg.api.body_timeout_s} s") from None
        return b"".join(chunks)
