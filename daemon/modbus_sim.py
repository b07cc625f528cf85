"""The simulated plant behind a real Modbus TCP server (register map of :mod:`.modbus`).

The daemon then runs the plant through the real protocol, as it would a PLC or I/O coupler.
Two clocks:

* ``lockstep`` (tests, accelerated time): the plant advances to the sample named by the
  heartbeat register each time the daemon writes its command; after a link outage the missed
  samples are simulated with the outputs the I/O watchdog holds;
* ``realtime``: the plant advances every ``dt_s / speedup`` wall seconds on its own.

Both have the I/O side's watchdog: when no new heartbeat arrives for ``watchdog_samples``
samples the heater is switched off and the status register's bit 0 is set (a PLC's
communication-loss reaction). Run standalone::

    python -m hvac_mpc.daemon.modbus_sim --port 5020 --mode realtime
"""

from __future__ import annotations

import argparse
import asyncio
import threading
import time
from dataclasses import replace

from hvac_mpc.models.plant import SimulatedPlant

from hvac_mpc.contract import Command

from .modbus import (HOLDING_COUNT, INPUT_COUNT, STATUS_WATCHDOG, decode_command, encode_command,
                     encode_measurement)

FC_READ_INPUT = 4
WRITE_FCS = (6, 16, 23)


class PlantModbusServer:
    """A Modbus TCP server on ``host:port`` exposing ``plant``; start/stop it any number of times
    (the plant lives on between, as a box does while its network is down)."""

    def __init__(self, plant: SimulatedPlant, host: str = "127.0.0.1", port: int = 5020, device_id: int = 1,
                 mode: str = "lockstep", speedup: float = 1.0, watchdog_samples: int = 5,
                 max_catchup_samples: int = 3600):
        if mode not in ("lockstep", "realtime"):
            raise ValueError(f"mode = {mode!r}: allowed 'lockstep', 'realtime'")
        self.plant = plant
        self.host, self.port, self.device_id = host, port, device_id
        self.mode, self.speedup = mode, speedup
        self.watchdog_samples = watchdog_samples
        self.max_catchup = max_catchup_samples
        self.lock = threading.Lock()
        self.command = plant.command
        self.heartbeat = None  # last heartbeat applied
        self.watchdog_tripped = False
        self.writes = 0
        self.samples_since_write = 0
        self.history: list[tuple[float, float, float]] = []  # (time_s, heater_cmd_w, flow true) per sample
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # ------------------------------------------------------------------ plant side
    def _sample_index(self) -> int:
        """Index of the plant's current sample, modulo the 16-bit heartbeat."""
        return int(round(self.plant.time_s / self.plant.dt_s)) & 0xFFFF

    def _advance_one(self) -> None:
        """One sample with the outputs as the I/O side holds them (watchdog applied)."""
        self.samples_since_write += 1
        if self.samples_since_write > self.watchdog_samples and not self.watchdog_tripped:
            self.watchdog_tripped = True
            self.command = replace(self.command, heater_cmd_w=0.0)
            self.plant.apply(self.command)
        self.plant.advance()
        self.history.append((self.plant.time_s, self.command.heater_cmd_w, self.plant.truth()["volume_flow_m3s"]))
        if len(self.history) > 200_000:
            del self.history[:100_000]

    def _on_command(self, cmd: Command, heartbeat: int) -> None:
        with self.lock:
            self.writes += 1
            dt = self.plant.dt_s
            if self.mode == "lockstep":
                if self.heartbeat is None and self._sample_index() == 0:
                    self.plant.time_s = ((heartbeat - 1) & 0xFFFF) * dt  # fresh plant: adopt the daemon's count
                gap = (heartbeat - self._sample_index()) & 0xFFFF
                if gap > self.max_catchup:  # far off (a restarted daemon): resynchronise without simulating
                    self.plant.time_s = ((heartbeat - 1) & 0xFFFF) * dt
                    gap = 1
                for _ in range(max(gap - 1, 0)):
                    self._advance_one()  # the missed samples: outputs as the I/O side holds them
            else:
                gap = 0
            self.command = cmd
            self.plant.apply(cmd)
            self.samples_since_write = 0
            self.watchdog_tripped = False
            if gap >= 1:
                self._advance_one()
                self.samples_since_write = 0
            self.heartbeat = heartbeat

    def input_registers(self) -> list[int]:
        with self.lock:
            return encode_measurement(self.plant.read(), self.heartbeat or 0,
                                      STATUS_WATCHDOG if self.watchdog_tripped else 0)

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        if function_code == FC_READ_INPUT:
            regs = self.input_registers()
            registers[0:INPUT_COUNT] = regs
            return None
        if function_code in WRITE_FCS and set_values is not None:
            current = list(registers[0:HOLDING_COUNT])
            off = address - start_address
            current[off:off + len(set_values)] = list(set_values)
            cmd, hb = decode_command([int(v) for v in current[:HOLDING_COUNT]])
            self._on_command(cmd, hb)
        return None

    async def _realtime_clock(self) -> None:
        period = self.plant.dt_s / self.speedup
        nxt = time.monotonic()
        while True:
            nxt += period
            await asyncio.sleep(max(0.0, nxt - time.monotonic()))
            with self.lock:
                self._advance_one()

    # ------------------------------------------------------------------ server side
    def _device(self):
        try:
            from pymodbus.simulator import DataType, SimData, SimDevice
        except ImportError as exc:  # pragma: no cover - depends on the installed version
            raise RuntimeError("the Modbus plant simulator needs pymodbus with the SimDevice API "
                               "(tested with 3.16.1): pip install -U 'hvac-mpc[fieldbus]'") from exc

        hr = [SimData(0, values=encode_command(self.command, 0), datatype=DataType.REGISTERS)]
        ir = [SimData(0, values=[0] * INPUT_COUNT, datatype=DataType.REGISTERS)]
        bits = [SimData(0, values=[False] * 16, datatype=DataType.BITS)]
        return SimDevice(self.device_id, simdata=(bits, list(bits), hr, ir), action=self._action)

    async def _serve(self) -> None:
        from pymodbus.server import ModbusTcpServer

        self._server = ModbusTcpServer(self._device(), address=(self.host, self.port))
        tasks = [asyncio.create_task(self._server.serve_forever())]
        if self.mode == "realtime":
            tasks.append(asyncio.create_task(self._realtime_clock()))
        await asyncio.sleep(0.05)
        self._ready.set()
        try:
            await asyncio.gather(*tasks)
        except asyncio.CancelledError:
            pass

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        try:
            self._main = self._loop.create_task(self._serve())
            self._loop.run_until_complete(self._main)
        except BaseException as exc:  # reported to start()
            self._error = exc
            self._ready.set()
        finally:
            self._loop.close()

    def start(self, timeout_s: float = 5.0) -> "PlantModbusServer":
        try:
            import pymodbus.server  # noqa: F401
        except ImportError as exc:  # pragma: no cover - depends on the optional extra
            raise RuntimeError("the Modbus plant simulator needs pymodbus: pip install 'hvac-mpc[fieldbus]'") from exc
        import logging
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name="modbus-plant", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s) or self._error is not None:
            raise RuntimeError(f"Modbus plant server on {self.host}:{self.port} did not start: {self._error}")
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the listener and every client connection (a network outage, for the daemon)."""
        if self._loop is None or self._thread is None:
            return

        async def _shutdown():
            if self._server is not None:
                await self._server.shutdown()
            self._main.cancel()

        try:
            asyncio.run_coroutine_threadsafe(_shutdown(), self._loop).result(timeout_s)
        except Exception:  # noqa: BLE001 - the loop may already be gone
            pass
        self._thread.join(timeout_s)
        self._thread = None
        self._loop = None
        self._server = None

    def __enter__(self) -> "PlantModbusServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="the simulated HVAC box as a Modbus TCP server")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=5020)
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="realtime")
    parser.add_argument("--speedup", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    server = PlantModbusServer(SimulatedPlant(seed=args.seed), host=args.host, port=args.port, mode=args.mode,
                               speedup=args.speedup).start()
    print(f"Modbus plant simulator on {args.host}:{args.port} ({args.mode})", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
