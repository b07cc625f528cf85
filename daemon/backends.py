"""I/O backends: where the daemon reads sensors and writes actuators.

One small interface (:class:`IoBackend`): ``connect()``, ``read() -> Measurement``,
``write(Command)``, ``close()``. Any failure to talk to the plant raises :class:`BackendError`;
the daemon then writes safe outputs and reconnects with backoff.

* :class:`SimulatedBackend`: the built-in simulated plant (hvac_mpc.models.plant), advanced in
  lockstep with the daemon clock (one sample per tick, however fast the loop runs).
* :class:`hvac_mpc.daemon.modbus.ModbusBackend`: Modbus TCP to a PLC, an I/O coupler or the
  plant simulator server (:mod:`hvac_mpc.daemon.modbus_sim`).
* :class:`hvac_mpc.daemon.opcua.OpcUaBackend`: OPC UA to a PLC or the plant simulator server
  (:mod:`hvac_mpc.daemon.opcua_sim`).
* :class:`FaultInjectingBackend`: wraps any backend and injects the ``[[faults]]`` of the
  configuration (sensor NaN, stuck, out of range, missing, stale, a wrong value; backend disconnect).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

from hvac_mpc.models.parameters import Parameters
from hvac_mpc.models.plant import PLANT_EFFECTS, Environment, SimulatedPlant
from hvac_mpc.contract import Command, Measurement

from .calibration import Calibration
from .config import DaemonConfig, FaultSpec, SimulatedBackendConfig
from .io import BackendError, IoBackend

#: Largest gap (samples) the simulated plant integrates to catch up; beyond it the plant is
#: settled at the new time instead (a restart after a long pause).
MAX_CATCHUP_SAMPLES = 3600


class SimulatedBackend:
    """The simulated plant as an I/O backend.

    ``clock()`` returns the daemon time (s) of the current sample; ``write`` applies the command
    and advances the plant to the next sample, so plant time follows daemon time exactly.
    """

    def __init__(self, params: Parameters, cfg: SimulatedBackendConfig, dt_s: float,
                 clock: Callable[[], float], initial_command: Command | None = None):
        effects = PLANT_EFFECTS if list(cfg.effects) == ["all"] else tuple(cfg.effects)
        self._make = lambda: SimulatedPlant(
            params, effects=effects, seed=cfg.seed, dt_s=dt_s,
            environment=Environment(cfg.inlet_temp_c, cfg.chiller_setpoint_c), initial_command=initial_command)
        self.dt_s = dt_s
        self.clock = clock
        self.plant: SimulatedPlant | None = None

    def connect(self) -> None:
        if self.plant is None:
            self.plant = self._make()
            self.plant.time_s = float(self.clock())

    def read(self) -> Measurement:
        if self.plant is None:
            raise BackendError("simulated plant: not connected")
        return self.plant.read()

    def write(self, command: Command) -> None:
        if self.plant is None:
            raise BackendError("simulated plant: not connected")
        self.plant.apply(command)
        target = float(self.clock()) + self.dt_s
        n = int(round((target - self.plant.time_s) / self.dt_s))
        if n > MAX_CATCHUP_SAMPLES:
            self.plant.settle()
            self.plant.time_s = target
        elif n > 0:
            self.plant.advance(n)

    def close(self) -> None:
        """The simulated plant lives on (as a real box does while the link is down)."""


class FaultInjectingBackend:
    """Wraps a backend and injects the configured sensor and backend faults by daemon time."""

    def __init__(self, inner: IoBackend, faults: Sequence[FaultSpec], clock: Callable[[], float]):
        self.inner = inner
        self.faults = [f for f in faults if f.target in ("sensor", "backend")]
        self.clock = clock
        self._frozen: dict[int, object] = {}
        self._last_command: Command | None = None
        self.injected: dict[str, int] = {}

    def _active(self, target: str) -> list[tuple[int, FaultSpec]]:
        t = self.clock()
        return [(i, f) for i, f in enumerate(self.faults) if f.target == target and f.active(t)]

    def _count(self, f: FaultSpec) -> None:
        key = f"{f.target}:{f.kind}"
        self.injected[key] = self.injected.get(key, 0) + 1

    def _disconnected(self) -> FaultSpec | None:
        active = self._active("backend")
        for _, f in active:
            self._count(f)
        return active[0][1] if active else None

    def connect(self) -> None:
        if (f := self._disconnected()) is not None:
            raise BackendError(f"injected disconnect until t = {f.end_s} s")
        self.inner.connect()

    def read(self) -> Measurement:
        if (f := self._disconnected()) is not None:
            raise BackendError(f"injected disconnect until t = {f.end_s} s")
        m = self.inner.read()
        active = self._active("sensor")
        live = {i for i, _ in active}
        for i in list(self._frozen):
            if i not in live:
                del self._frozen[i]
        for i, f in active:
            self._count(f)
            if f.kind == "nan":
                m = replace(m, **{f.signal: math.nan})
            elif f.kind == "missing":
                m = replace(m, **{f.signal: None})
            elif f.kind in ("out_of_range", "value"):
                m = replace(m, **{f.signal: f.value})
            elif f.kind == "stuck":
                m = replace(m, **{f.signal: self._frozen.setdefault(i, getattr(m, f.signal))})
            elif f.kind == "stale":
                m = self._frozen.setdefault(i, m)  # the whole sample repeats, time included
        return m

    def write(self, command: Command) -> None:
        if (f := self._disconnected()) is not None:
            # the I/O side's watchdog: outputs held, heater off, while the link is down
            held = replace(self._last_command or command, heater_cmd_w=0.0)
            self.inner.write(held)
            raise BackendError(f"injected disconnect until t = {f.end_s} s")
        self.inner.write(command)
        self._last_command = command

    def close(self) -> None:
        self.inner.close()


def _calibration(config: DaemonConfig) -> Calibration:
    """The configured calibration file (relative to the configuration), or the thesis's."""
    return config.calibration.load(Path(config.base_dir))


def make_backend(config: DaemonConfig, params: Parameters, clock: Callable[[], float]) -> IoBackend:
    """The configured backend, wrapped for fault injection when ``[[faults]]`` name any."""
    kind = config.backend.kind
    if kind == "simulated":
        from .safety import safe_command
        backend: IoBackend = SimulatedBackend(params, config.backend.simulated, config.loop.period_s, clock,
                                              initial_command=safe_command(config.safety))
    elif kind == "modbus":
        from .modbus import ModbusBackend
        c = config.backend.modbus
        backend = ModbusBackend(c.host, c.port, device_id=c.device_id, timeout_s=c.timeout_s,
                                dt_s=config.loop.period_s, clock=clock,
                                calibration=_calibration(config) if c.signals == "raw" else None)
    elif kind == "opcua":
        from .opcua import OpcUaBackend
        c = config.backend.opcua
        backend = OpcUaBackend(c, dt_s=config.loop.period_s, clock=clock,
                               calibration=_calibration(config) if c.signals == "raw" else None)
    else:  # pragma: no cover - the configuration rejects other kinds
        raise ValueError(f"backend.kind = {kind!r}: allowed 'simulated', 'modbus', 'opcua'")
    if any(f.target in ("sensor", "backend") for f in config.faults):
        backend = FaultInjectingBackend(backend, config.faults, clock)
    return backend
