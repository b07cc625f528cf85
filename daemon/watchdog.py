"""systemd ``Type=notify`` support: READY, watchdog pings while the loop is healthy, STOPPING.

The notification protocol (sd_notify(3)) is one datagram per message to the AF_UNIX socket named
by ``$NOTIFY_SOCKET``: a path, or ``@name`` for the abstract namespace. It is written here with the
standard library's socket module, no dependency. ``$WATCHDOG_USEC`` (set by ``WatchdogSec=``)
gives the watchdog timeout; ``$WATCHDOG_PID``, when set, names the process expected to ping.

:class:`SystemdWatchdog` runs in its own thread beside the control loop:

* ``READY=1`` once the first sample has been controlled and logged (start-up done);
* ``WATCHDOG=1`` every ``ping_interval_s`` (default half the watchdog timeout) *only while the
  loop is healthy*: the last tick finished less than ``stall_s`` ago. A hung loop (a fieldbus call
  that never returns, a dead lock) or stalled ticks stop the pings, and systemd kills and restarts
  the service; the device-side heartbeat watchdog (docs/fieldbus.md) switches the heater off
  meanwhile;
* ``STOPPING=1`` when the shutdown sequence (heater off, cool-down) starts; pings go on during
  the cool-down, which is a healthy loop too.

The unit file ``packaging/hvac-mpc-daemon.service`` shows the matching systemd settings.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from typing import Callable

from pydantic import BaseModel, ConfigDict, Field

LOG = logging.getLogger("hvac_mpc.daemon.watchdog")


class SystemdConfig(BaseModel):
    """``[systemd]``: notification and watchdog settings (used only when ``$NOTIFY_SOCKET`` is set)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(True, description="send READY/WATCHDOG/STOPPING when started by systemd")
    stall_s: float = Field(0.0, ge=0.0, le=3600.0, allow_inf_nan=False,
                           description="the loop counts as hung when no tick finished for this long (wall s); "
                                       "0 = 3 wall periods, at least 2 s")
    ping_interval_s: float = Field(0.0, ge=0.0, le=3600.0, allow_inf_nan=False,
                                   description="time between pings (wall s); 0 = half of $WATCHDOG_USEC")


def socket_address(path: str) -> str | None:
    """The ``AF_UNIX`` address of a ``$NOTIFY_SOCKET`` value: ``@name`` is the abstract namespace."""
    if not path:
        return None
    if path.startswith("@"):
        return "\0" + path[1:]
    if path.startswith("/"):
        return path
    return None  # vsock and other address families are not supported


class Notifier:
    """Sends sd_notify messages to ``$NOTIFY_SOCKET`` (or ``path``); a no-op without a socket."""

    def __init__(self, path: str | None = None):
        raw = os.environ.get("NOTIFY_SOCKET", "") if path is None else path
        self.address = socket_address(raw)
        if raw and self.address is None:
            LOG.warning("NOTIFY_SOCKET=%r: unsupported address, notifications off", raw)
        self._sock: socket.socket | None = None
        self.sent: list[str] = []  # messages sent, for status and tests
        self.errors = 0

    @property
    def active(self) -> bool:
        return self.address is not None

    def notify(self, message: str) -> bool:
        """Send one message (e.g. ``"READY=1"``); False when there is no socket or it failed."""
        if self.address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.connect(self.address)
            self._sock.sendall(message.encode("utf-8"))
        except OSError as exc:
            self.errors += 1
            (LOG.warning if self.errors <= 3 else LOG.debug)("sd_notify %r failed: %s", message, exc)
            self.close()
            return False
        self.sent.append(message.split("=", 1)[0])
        if len(self.sent) > 1000:
            del self.sent[:500]
        return True

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def watchdog_timeout_s(environ: dict | None = None) -> float | None:
    """``$WATCHDOG_USEC`` in seconds, or None when not set, not for this process, or malformed."""
    env = os.environ if environ is None else environ
    pid = env.get("WATCHDOG_PID", "")
    if pid and pid != str(os.getpid()):
        return None
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    return usec / 1e6 if usec > 0 else None


class SystemdWatchdog:
    """The notification thread. ``state()`` returns the loop state ("starting", "running",
    "shutdown", "stopped"), ``tick_age_s()`` the wall time since the last finished tick and
    ``ticks()`` the number of ticks done."""

    def __init__(self, notifier: Notifier, cfg: SystemdConfig, wall_period_s: float,
                 state: Callable[[], str], tick_age_s: Callable[[], float], ticks: Callable[[], int]):
        self.notifier = notifier
        self.state, self.tick_age_s, self.ticks = state, tick_age_s, ticks
        self.stall_s = cfg.stall_s if cfg.stall_s > 0 else max(3.0 * wall_period_s, 2.0)
        timeout = watchdog_timeout_s()
        if cfg.ping_interval_s > 0:
            self.interval_s = cfg.ping_interval_s
        else:
            self.interval_s = timeout / 2.0 if timeout else math.inf
        self.pings = 0
        self.withheld = 0  # pings not sent because the loop was not healthy
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def healthy(self) -> bool:
        """The loop is running (or cooling down) and its last tick is recent."""
        return self.state() in ("running", "shutdown") and self.tick_age_s() < self.stall_s

    def start(self) -> "SystemdWatchdog":
        self._thread = threading.Thread(target=self._run, name="systemd-watchdog", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        ready = stopping = False
        next_ping = time.monotonic()
        while not self._stop.is_set():
            state = self.state()
            if not ready and state in ("running", "shutdown") and self.ticks() > 0:
                ready = self.notifier.notify("READY=1")
            if not stopping and state in ("shutdown", "stopped") and ready:
                stopping = self.notifier.notify("STOPPING=1")
            if state == "stopped":
                break
            now = time.monotonic()
            if ready and now >= next_ping:
                next_ping = now + self.interval_s
                if self.healthy():
                    self.pings += self.notifier.notify("WATCHDOG=1")
                else:
                    self.withheld += 1
            self._stop.wait(min(0.05, self.interval_s))

    def stop(self) -> None:
        """Send STOPPING=1 (if not yet sent) and end the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if "STOPPING" not in self.notifier.sent and "READY" in self.notifier.sent:
            self.notifier.notify("STOPPING=1")
        self.notifier.close()


def start_watchdog(cfg: SystemdConfig, wall_period_s: float, state: Callable[[], str],
                   tick_age_s: Callable[[], float], ticks: Callable[[], int]) -> SystemdWatchdog | None:
    """The notification thread when enabled and started under systemd (``$NOTIFY_SOCKET``), else None."""
    if not cfg.enabled:
        return None
    notifier = Notifier()
    if not notifier.active:
        return None
    return SystemdWatchdog(notifier, cfg, wall_period_s, state, tick_age_s, ticks).start()
