"""The simulated I/O device behind the fieldbus simulators (:mod:`.modbus_sim`, :mod:`.opcua_sim`).

The plant side shared by both protocols: the simulated plant, its clock, the I/O watchdogs and
the decoding of raw signals, plus the thread that runs a protocol server's event loop. Two clocks:

* ``lockstep`` (tests, accelerated time): the plant advances to the sample named by the
  heartbeat each time the daemon writes its command; after a link outage the missed samples are
  simulated with the outputs the I/O watchdog holds;
* ``realtime``: the plant advances every ``dt_s / speedup`` wall seconds on its own.

Both have the I/O side's watchdog: when no new heartbeat arrives for ``watchdog_samples``
samples the heater is switched off (a PLC's communication-loss reaction). Independently of plant
time, the heartbeat watchdog runs on wall time: a heartbeat unchanged for ``heartbeat_timeout_s``
(the daemon killed, or hung) switches the heater off and, when the heater was on in the last
``cooldown_hold_s``, keeps the blower running for the cool-down (at least ``cooldown_blower_w``,
valve a and the outlets open) until the heartbeat moves again (docs/fieldbus.md).
"""

from __future__ import annotations

import argparse
import asyncio
import threading
import time
from collections import deque
from dataclasses import replace

from hvac_mpc.contract import Command, Measurement
from hvac_mpc.models.plant import SimulatedPlant

from .calibration import Calibration
from .modbus import STATUS_HEARTBEAT, STATUS_RAW, STATUS_WATCHDOG


class SimulatedDevice:
    """The plant behind a protocol server; subclasses implement ``_start_server`` and
    ``_stop_server`` (coroutines run in the device's event-loop thread). Start and stop it any
    number of times (the plant lives on between, as a box does while its network is down)."""

    name = "device"

    def __init__(self, plant: SimulatedPlant, mode: str = "lockstep", speedup: float = 1.0,
                 watchdog_samples: int = 5, max_catchup_samples: int = 3600, heartbeat_timeout_s: float = 3.0,
                 cooldown_blower_w: float = 120.0, calibration: Calibration | None = None):
        if mode not in ("lockstep", "realtime"):
            raise ValueError(f"mode = {mode!r}: allowed 'lockstep', 'realtime'")
        self.plant = plant
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
        self.heartbeat_timeout_s = heartbeat_timeout_s  # wall s; 0 = no heartbeat watchdog
        self.cooldown_blower_w = cooldown_blower_w  # ASSUMPTION: the daemon's safe blower power
        self.calibration = calibration  # None: engineering values; else the device takes raw signals
        self.heartbeat_tripped = False
        self.heartbeat_trips: list[float] = []  # wall time (time.monotonic) of each trip
        #: per trip: (writes received before it, the command held when it tripped)
        self.heartbeat_trip_held: list[tuple[int, Command]] = []
        self._heartbeat_wall: float | None = None  # wall time the heartbeat last changed
        self._heater_on_wall: float | None = None  # wall time a command last had the heater on
        #: ASSUMPTION: a heater on within this many wall seconds before a heartbeat trip may still be
        #: hot (body time constant ~90 s, docs/model.md): the blower cools it; otherwise outputs hold
        self.cooldown_hold_s = 300.0
        self.received: deque = deque(maxlen=20000)  # (heartbeat, raw signals as written, decoded command)
        self._snapshot: tuple[tuple, Measurement] | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
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
            if heartbeat != self.heartbeat:
                self._heartbeat_wall = time.monotonic()
                self.heartbeat_tripped = False
            elif self.heartbeat_tripped:
                cmd = self.command  # an unchanged heartbeat does not release the heartbeat watchdog
            self.command = cmd
            if cmd.heater_cmd_w > 0:
                self._heater_on_wall = time.monotonic()
            self.plant.apply(cmd)
            self.samples_since_write = 0
            self.watchdog_tripped = False
            if gap >= 1:
                self._advance_one()
                self.samples_since_write = 0
            self.heartbeat = heartbeat

    def measurement(self) -> Measurement:
        """The plant's reading of the current sample (one noise draw per sample and command)."""
        with self.lock:
            key = (self.plant.time_s, self.writes, self.heartbeat_tripped)
            if self._snapshot is None or self._snapshot[0] != key:
                self._snapshot = (key, self.plant.read())
            return self._snapshot[1]

    def status_bits(self) -> int:
        """Status word: bit 0 I/O watchdog tripped, bit 1 raw signals, bit 2 heartbeat watchdog tripped."""
        return ((STATUS_WATCHDOG if self.watchdog_tripped else 0) | (STATUS_RAW if self.calibration else 0)
                | (STATUS_HEARTBEAT if self.heartbeat_tripped else 0))

    def check_heartbeat(self) -> bool:
        """The heartbeat watchdog (wall time): heater off, blower on for the cool-down when the
        heartbeat has not changed for ``heartbeat_timeout_s``. True when it trips now."""
        with self.lock:
            if (self.heartbeat_timeout_s <= 0 or self._heartbeat_wall is None or self.heartbeat_tripped
                    or time.monotonic() - self._heartbeat_wall < self.heartbeat_timeout_s):
                return False
            self.heartbeat_tripped = True
            now = time.monotonic()
            self.heartbeat_trips.append(now)
            self.heartbeat_trip_held.append((self.writes, self.command))
            if self._heater_on_wall is not None and now - self._heater_on_wall <= self.cooldown_hold_s:
                self.command = replace(self.command, heater_cmd_w=0.0,
                                       blower_power_w=max(self.command.blower_power_w, self.cooldown_blower_w),
                                       valve_a_pct=100.0, valve_m_pct=100.0, valve_f_pct=100.0, valve_w_pct=100.0)
            else:  # the heater has been off long enough (e.g. after the daemon's own cool-down): hold
                self.command = replace(self.command, heater_cmd_w=0.0)
            self.plant.apply(self.command)
            return True

    async def _heartbeat_watch(self) -> None:
        while True:
            await asyncio.sleep(min(0.05, self.heartbeat_timeout_s / 4))
            self.check_heartbeat()

    async def _realtime_clock(self) -> None:
        period = self.plant.dt_s / self.speedup
        nxt = time.monotonic()
        while True:
            nxt += period
            await asyncio.sleep(max(0.0, nxt - time.monotonic()))
            with self.lock:
                self._advance_one()

    # ------------------------------------------------------------------ event-loop thread
    async def _start_server(self) -> None:  # pragma: no cover - protocol specific
        raise NotImplementedError

    async def _stop_server(self) -> None:  # pragma: no cover - protocol specific
        raise NotImplementedError

    async def _serve(self) -> None:
        await self._start_server()
        tasks = []
        if self.mode == "realtime":
            tasks.append(asyncio.create_task(self._realtime_clock()))
        if self.heartbeat_timeout_s > 0:
            tasks.append(asyncio.create_task(self._heartbeat_watch()))
        self._ready.set()
        try:
            await asyncio.gather(*tasks, asyncio.Event().wait())
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

    def start(self, timeout_s: float = 10.0):
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-plant", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s) or self._error is not None:
            raise RuntimeError(f"{self.name} plant server did not start: {self._error}")
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the listener and every client connection (a network outage, for the daemon)."""
        if self._loop is None or self._thread is None:
            return

        async def _shutdown():
            try:
                await self._stop_server()
            finally:
                self._main.cancel()

        try:
            asyncio.run_coroutine_threadsafe(_shutdown(), self._loop).result(timeout_s)
        except Exception:  # noqa: BLE001 - the loop may already be gone
            pass
        self._thread.join(timeout_s)
        self._thread = None
        self._loop = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def run_standalone(argv: list[str] | None, server_cls: type, protocol: str, port: int) -> int:
    """Command line of a simulator module: serve the simulated box until Ctrl-C."""
    parser = argparse.ArgumentParser(description=f"the simulated HVAC box as a {protocol} server")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=port)
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="realtime")
    parser.add_argument("--speedup", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--heartbeat-timeout", type=float, default=3.0,
                        help="heater off when the heartbeat is unchanged this long (wall s; 0 = off)")
    parser.add_argument("--raw", nargs="?", const="", metavar="CALIBRATION",
                        help="take raw signals, decoded with this calibration file (default: the thesis's)")
    args = parser.parse_args(argv)
    calibration = None
    if args.raw is not None:
        from .calibration import load_calibration

        calibration = load_calibration(args.raw)
    server = server_cls(SimulatedPlant(seed=args.seed), host=args.host, port=args.port, mode=args.mode,
                        speedup=args.speedup, heartbeat_timeout_s=args.heartbeat_timeout,
                        calibration=calibration).start()
    print(f"{protocol} plant simulator on {args.host}:{args.port} ({args.mode})", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()
    return 0
