"""``hvac-mpc ctl``: talk to a running daemon through its API (the token read from its file).

    hvac-mpc ctl --config daemon.toml status
    hvac-mpc ctl --config daemon.toml mode                  # the mode in force and the modes available
    hvac-mpc ctl --config daemon.toml mode manual
    hvac-mpc ctl --config daemon.toml set blower_power_w=150 heater_cmd_w=0
    hvac-mpc ctl --config daemon.toml reference supply_temp_c=22 volume_flow_m3s=0.03
    hvac-mpc ctl --url http://127.0.0.1:8750 --token-file hvac_daemon_log.token mode auto-pid

``--config`` finds the address (``api.host``, ``api.port`` or ``api.port_file``) and the token file
(``api.token_file``) in the daemon's own configuration. Exit codes: 0 accepted, 1 refused by the
daemon (its message printed), 2 a usage error or no daemon reachable.
"""

from __future__ import annotations

import argparse
import json
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from .config import ConfigError, load_config, resolve

USER_AGENT = "hvac-mpc-ctl"


class CtlError(RuntimeError):
    """The daemon cannot be reached or the arguments are wrong (exit code 2)."""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="the daemon's configuration (address and token file)")
    parser.add_argument("--url", help="the API's base URL, e.g. http://127.0.0.1:8750 (instead of --config)")
    parser.add_argument("--token-file", metavar="FILE", help="the token file (default: from --config)")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for an answer")
    parser.add_argument("action", choices=("status", "health", "mode", "set", "reference", "sample"),
                        help="what to do")
    parser.add_argument("values", nargs="*", help="mode name, or name=value pairs for set and reference")


def _endpoint(args: argparse.Namespace) -> tuple[str, Path | None]:
    if args.url:
        return args.url.rstrip("/"), Path(args.token_file) if args.token_file else None
    if not args.config:
        raise CtlError("give --config FILE (the daemon's configuration) or --url URL")
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        raise CtlError(f"configuration error: {exc}") from None
    from .server import token_path

    port = cfg.api.port
    if cfg.api.port_file:
        pf = resolve(cfg, cfg.api.port_file)
        try:
            port = int(pf.read_text())
        except (OSError, ValueError):
            raise CtlError(f"no daemon: port file {pf} missing or unreadable") from None
    host = cfg.api.host if cfg.api.host not in ("0.0.0.0", "::") else "127.0.0.1"
    host = f"[{host}]" if ":" in host else host
    return f"http://{host}:{port}", Path(args.token_file) if args.token_file else token_path(cfg)


def _pairs(values: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in values:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise CtlError(f"{item!r}: expected name=value")
        try:
            out[name] = float(text)
        except ValueError:
            raise CtlError(f"{item!r}: the value is not a number") from None
    return out


def request(base: str, method: str, path: str, data: bytes | None = None, headers: dict | None = None,
            timeout: float = 30.0) -> tuple[int, Any]:
    """One API call: (status, decoded JSON answer or None). Raises OSError when nothing answers."""
    req = urllib.request.Request(base + path, data=data, method=method,
                                 headers={"User-Agent": USER_AGENT, **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return resp.status, json.loads(resp.read() or b"null")
    except urllib.error.HTTPError as exc:
        try:
            return exc.code, json.loads(exc.read() or b"null")
        except ValueError:
            return exc.code, None


def _call(base: str, method: str, path: str, body: Any, token: str | None, timeout: float) -> tuple[int, Any]:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    data = None
    if body is not None:
        data, headers["Content-Type"] = json.dumps(body).encode(), "application/json"
    try:
        return request(base, method, path, data, headers, timeout)
    except OSError as exc:
        raise CtlError(f"no daemon at {base}: {getattr(exc, 'reason', exc)}") from None


def run(args: argparse.Namespace) -> int:
    try:
        base, token_file = _endpoint(args)
        token = None
        if token_file is not None and token_file.exists():
            token = token_file.read_text().strip()
        write = args.action in ("set", "reference") or (args.action == "mode" and args.values)
        if write and not token:
            raise CtlError(f"writes need the daemon's token: token file {token_file} not found")
        if args.action == "mode" and args.values:
            if len(args.values) != 1:
                raise CtlError("mode takes one name: auto-mpc, auto-pid, manual or safe-stop")
            status, answer = _call(base, "PUT", "/mode", {"mode": args.values[0]}, token, args.timeout)
        elif args.action == "set":
            status, answer = _call(base, "PUT", "/manual", _pairs(args.values), token, args.timeout)
        elif args.action == "reference":
            status, answer = _call(base, "PUT", "/reference", _pairs(args.values), token, args.timeout)
        else:
            status, answer = _call(base, "GET", f"/{args.action}", None, token, args.timeout)
    except CtlError as exc:
        print(f"hvac-mpc ctl: {exc}", file=sys.stderr)
        return 2
    if status >= 400:
        msg = answer.get("error") if isinstance(answer, dict) else answer
        print(f"hvac-mpc ctl: refused ({status}): {msg}", file=sys.stderr)
        return 1
    print(json.dumps(answer, indent=2))
    return 0
