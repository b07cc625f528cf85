"""The daemon's I/O interface: what every backend (simulated, Modbus TCP, ...) implements.

``connect()``, ``read() -> Measurement``, ``write(Command)``, ``close()``. Any failure to talk to
the plant raises :class:`BackendError`; the daemon then writes safe outputs and reconnects.
"""

from __future__ import annotations

from typing import Protocol

from hvac_mpc.contract import Command, Measurement


class BackendError(RuntimeError):
    """The plant could not be read or written (disconnected, timeout, protocol error)."""


class IoBackend(Protocol):
    """A connection to the box's sensors and actuators."""

    def connect(self) -> None: ...

    def read(self) -> Measurement: ...

    def write(self, command: Command) -> None: ...

    def close(self) -> None: ...
