"""The simulated plant behind a real Modbus TCP server (register map of :mod:`.modbus`).

The daemon then runs the plant through the real protocol, as it would a PLC or I/O coupler.
Two clocks:

* ``lockstep`` (tests, accelerated time): the plant advances to the sample named by the
  heartbeat register each time the daemon writes its command; after a link outage the missed
  samples are simulated with the outputs the I/O watchdog holds;
* ``realtime``: the plant advances every ``dt_s / speedup`` wall seconds on its own.

Both have the I/O side's watchdog: when no new heartbeat arrives for ``watchdog_samples``
samples the heater is switched off and the status register's bit 0 is set (a PLC's
communication-loss reaction). Independently of plant time, the heartbeat watchdog runs on wall
time: a heartbeat unchanged for ``heartbeat_timeout_s`` (e.g. the daemon killed, or hung) switches
the heater off and keeps the blower running for the cool-down (at least ``cooldown_blower_w``,
valve a and the outlets open) and sets status bit 2, until the heartbeat moves again.

With a ``calibration`` the device takes raw signals (servo duty cycles, volts, PWM duty) and
decodes them with it, and reports calibrated sensors as raw readings. Run standalone::

    python -m hvac_mpc.daemon.modbus_sim --port 5020 --mode realtime
"""

from __future__ import annotations

import asyncio

from hvac_mpc.models.plant import SimulatedPlant

from .calibration import Calibration
from .device_sim import SimulatedDevice, run_standalone
from .modbus import (HOLDING_COUNT, INPUT_COUNT, decode_command, encode_command, encode_measurement,
                     raw_sensor_registers)

FC_READ_INPUT = 4
WRITE_FCS = (6, 16, 23)


class PlantModbusServer(SimulatedDevice):
    """A Modbus TCP server on ``host:port`` exposing ``plant`` (plant side: :class:`.device_sim.SimulatedDevice`);
    start/stop it any number of times (the plant lives on between, as a box does while its network is down)."""

    name = "Modbus"

    def __init__(self, plant: SimulatedPlant, host: str = "127.0.0.1", port: int = 5020, device_id: int = 1,
                 mode: str = "lockstep", speedup: float = 1.0, watchdog_samples: int = 5,
                 max_catchup_samples: int = 3600, heartbeat_timeout_s: float = 3.0,
                 cooldown_blower_w: float = 120.0, calibration: Calibration | None = None):
        super().__init__(plant, mode=mode, speedup=speedup, watchdog_samples=watchdog_samples,
                         max_catchup_samples=max_catchup_samples, heartbeat_timeout_s=heartbeat_timeout_s,
                         cooldown_blower_w=cooldown_blower_w, calibration=calibration)
        self.host, self.port, self.device_id = host, port, device_id
        self._server = None

    def input_registers(self) -> list[int]:
        m = self.measurement()
        with self.lock:
            regs = encode_measurement(m, self.heartbeat or 0, self.status_bits())
            return regs if self.calibration is None else raw_sensor_registers(regs, m, self.calibration)

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        if function_code == FC_READ_INPUT:
            regs = self.input_registers()
            registers[0:INPUT_COUNT] = regs
            return None
        if function_code in WRITE_FCS and set_values is not None:
            current = list(registers[0:HOLDING_COUNT])
            off = address - start_address
            current[off:off + len(set_values)] = list(set_values)
            regs = [int(v) for v in current[:HOLDING_COUNT]]
            cmd, hb = decode_command(regs, self.calibration)
            self.received.append((hb, regs, cmd))
            self._on_command(cmd, hb)
        return None

    # ------------------------------------------------------------------ server side
    def _device(self):
        try:
            from pymodbus.simulator import DataType, SimData, SimDevice
        except ImportError as exc:  # pragma: no cover - depends on the installed version
            raise RuntimeError("the Modbus plant simulator needs pymodbus with the SimDevice API "
                               "(tested with 3.16.1): pip install -U 'hvac-mpc[fieldbus]'") from exc

        hr = [SimData(0, values=encode_command(self.command, 0, self.calibration), datatype=DataType.REGISTERS)]
        ir = [SimData(0, values=[0] * INPUT_COUNT, datatype=DataType.REGISTERS)]
        bits = [SimData(0, values=[False] * 16, datatype=DataType.BITS)]
        return SimDevice(self.device_id, simdata=(bits, list(bits), hr, ir), action=self._action)

    async def _start_server(self) -> None:
        from pymodbus.server import ModbusTcpServer

        self._server = ModbusTcpServer(self._device(), address=(self.host, self.port))
        self._serving = asyncio.create_task(self._server.serve_forever())
        await asyncio.sleep(0.05)
        if self._serving.done():
            self._serving.result()  # raises the bind error

    async def _stop_server(self) -> None:
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    def start(self, timeout_s: float = 5.0) -> "PlantModbusServer":
        try:
            import pymodbus.server  # noqa: F401
        except ImportError as exc:  # pragma: no cover - depends on the optional extra
            raise RuntimeError("the Modbus plant simulator needs pymodbus: pip install 'hvac-mpc[fieldbus]'") from exc
        import logging
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        super().start(timeout_s)
        return self


def main(argv: list[str] | None = None) -> int:
    return run_standalone(argv, PlantModbusServer, "Modbus TCP", 5020)


if __name__ == "__main__":
    raise SystemExit(main())
