"""Modbus TCP fieldbus backend: register map, scaling, and the client the daemon uses.

Why Modbus TCP rather than OPC UA: the box's I/O is a handful of analogue channels at 1 Hz
(7 sensors, 6 actuators). Analogue I/O couplers and small PLCs of the kind a test bench uses
speak Modbus TCP natively, a flat register map is easy to audit against wiring, and pymodbus
is pure Python without dependencies (asyncua pulls in cryptography and more, ~14 MB) with a
synchronous client that fits a fixed-rate loop. OPC UA's information model, subscriptions and
security would be unused here. Modbus has no security of its own: keep it on the lab's
isolated network (or loopback).

Register map (device id ``device_id``; addresses zero-based)::

  input registers (FC 04, read by the daemon; the I/O side's measurements)
    0-1  time_ds               uint32, high word first   0.1 s    sample time of the I/O side
    2    supply_temp_c         int16                     0.01 C
    3    volume_flow_m3s       int16                     1e-5 m3/s
    4    hvac_inlet_temp_c     int16                     0.01 C
    5    water_temp_c          int16                     0.01 C
    6    chiller_setpoint_c    int16                     0.01 C
    7    heater_power_w        int16                     0.1 W
    8    heater_outlet_temp_c  int16                     0.01 C
    9    heartbeat_echo        uint16                    last heartbeat the I/O side applied
    10   status                uint16 bits               bit 0: I/O watchdog tripped (safe outputs),
                                                     bit 1: the device takes raw signals,
                                                     bit 2: heartbeat timeout tripped (heater off)
    11-17 optional signals     int16                     cabin_temp_c 0.01 C, cabin_rh_pct 0.01 %,
                               outlet_m/f/w_temp_c 0.01 C, supply_rh_pct 0.01 %, hvac_inlet_rh_pct 0.01 %
                               (NO_VALUE when the box does not measure them)

  holding registers (FC 16, written by the daemon in one request; FC 03 reads them back)
    0    blower_power_w        uint16                    0.1 W
    1    heater_cmd_w          uint16                    0.1 W
    2-5  valve_a/m/f/w_pct     uint16                    0.01 %
    6    heartbeat             uint16                    sample counter (mod 65536) the command is for

With ``signals = "raw"`` holding registers 0-5 carry the raw device signals of the calibration
(:mod:`.calibration`) as counts of their resolution (servo duty cycle 1e-5, PWM duty 1e-4, volts
and milliamps 1e-3), and sensor registers of calibrated sensors carry raw readings (int16 counts).
The device reports its signal format in status bit 1; a daemon configured otherwise refuses it.

An int16 of 0x8000 (-32768) means "no value" (wire break, channel fault), as analogue I/O
modules report it; values beyond the int16 range saturate at +-32767 (over-range), which the
daemon's plausibility check flags. The heartbeat lets the I/O side's watchdog put the outputs
in a safe state when the daemon stops writing, and lets the plant simulator advance in lockstep.

Device-side heartbeat watchdog (docs/fieldbus.md): the daemon writes the heartbeat every tick, a
new value each time. A device that sees it unchanged for its timeout (the simulator's
``heartbeat_timeout_s``, wall time) switches the heater off and, if the heater was on lately,
keeps the blower running (at least its cool-down power, valve a open so the air passes the
heater) until the heartbeat moves again; it sets status bit 2 meanwhile.
"""

from __future__ import annotations

import logging
import math
from typing import Callable

from dataclasses import replace

from hvac_mpc.contract import Command, Measurement

from .calibration import Calibration
from .io import BackendError

NO_VALUE = -32768
#: (field, scale) of input registers 2..8 (int16).
SENSOR_REGISTERS = (("supply_temp_c", 0.01), ("volume_flow_m3s", 1e-5), ("hvac_inlet_temp_c", 0.01),
                    ("water_temp_c", 0.01), ("chiller_setpoint_c", 0.01), ("heater_power_w", 0.1),
                    ("heater_outlet_temp_c", 0.01))
#: (field, scale) of holding registers 0..5 (uint16).
COMMAND_REGISTERS = (("blower_power_w", 0.1), ("heater_cmd_w", 0.1), ("valve_a_pct", 0.01),
                     ("valve_m_pct", 0.01), ("valve_f_pct", 0.01), ("valve_w_pct", 0.01))
#: (field, scale) of input registers 11.. (int16): the optional signals of ``Measurement``.
EXTRA_SENSOR_REGISTERS = (("cabin_temp_c", 0.01), ("cabin_rh_pct", 0.01), ("outlet_m_temp_c", 0.01),
                          ("outlet_f_temp_c", 0.01), ("outlet_w_temp_c", 0.01), ("supply_rh_pct", 0.01),
                          ("hvac_inlet_rh_pct", 0.01))
INPUT_COUNT = 11 + len(EXTRA_SENSOR_REGISTERS)
HOLDING_COUNT = 7
TIME_SCALE_S = 0.1
STATUS_WATCHDOG = 0x1
STATUS_RAW = 0x2
STATUS_HEARTBEAT = 0x4


def _int16(value: float | None, scale: float) -> int:
    """Register word (0..65535) of a scaled int16; NaN/None -> NO_VALUE, saturating at +-32767."""
    if value is None or not math.isfinite(value):
        return NO_VALUE & 0xFFFF if value is None or math.isnan(value) else (32767 if value > 0 else 32769)
    raw = int(round(value / scale))
    raw = max(-32767, min(32767, raw))
    return raw & 0xFFFF


def _from_int16(word: int, scale: float) -> float | None:
    raw = word - 0x10000 if word >= 0x8000 else word
    return None if raw == NO_VALUE else raw * scale


def encode_measurement(m: Measurement, heartbeat_echo: int = 0, status: int = 0) -> list[int]:
    """Input registers 0..INPUT_COUNT-1 for a measurement."""
    t = max(0, int(round(m.time_s / TIME_SCALE_S))) & 0xFFFFFFFF
    regs = [t >> 16, t & 0xFFFF]
    regs += [_int16(getattr(m, name), scale) for name, scale in SENSOR_REGISTERS]
    regs += [heartbeat_echo & 0xFFFF, status & 0xFFFF]
    regs += [_int16(getattr(m, name), scale) for name, scale in EXTRA_SENSOR_REGISTERS]
    return regs


def decode_measurement(regs: list[int]) -> tuple[Measurement, int, int]:
    """Measurement, heartbeat echo and status bits from input registers 0..INPUT_COUNT-1."""
    if len(regs) != INPUT_COUNT:
        raise BackendError(f"expected {INPUT_COUNT} input registers, got {len(regs)}")
    t = ((regs[0] << 16) | regs[1]) * TIME_SCALE_S
    values = {name: _from_int16(regs[2 + i], scale) for i, (name, scale) in enumerate(SENSOR_REGISTERS)}
    values.update({name: _from_int16(regs[11 + i], scale) for i, (name, scale) in enumerate(EXTRA_SENSOR_REGISTERS)})
    return Measurement(time_s=t, **values), regs[9], regs[10]


def encode_command(cmd: Command, heartbeat: int, calibration: Calibration | None = None) -> list[int]:
    """Holding registers 0..6 for a command (clipped to the register range); raw signals with a
    calibration."""
    if calibration is not None:
        return [max(0, min(65535, c)) for c in calibration.command_counts(cmd)] + [heartbeat & 0xFFFF]
    regs = []
    for name, scale in COMMAND_REGISTERS:
        v = getattr(cmd, name)
        if not math.isfinite(v):
            raise ValueError(f"{name}: command must be finite, got {v!r}")
        regs.append(max(0, min(65535, int(round(v / scale)))))
    return regs + [heartbeat & 0xFFFF]


def decode_command(regs: list[int], calibration: Calibration | None = None) -> tuple[Command, int]:
    """Command and heartbeat from holding registers 0..6 (raw signals with a calibration)."""
    if len(regs) != HOLDING_COUNT:
        raise ValueError(f"expected {HOLDING_COUNT} holding registers, got {len(regs)}")
    if calibration is not None:
        return calibration.command_from_counts(regs[:6]), regs[6]
    return Command(**{name: regs[i] * scale for i, (name, scale) in enumerate(COMMAND_REGISTERS)}), regs[6]


def raw_sensor_registers(regs: list[int], m: Measurement, calibration: Calibration) -> list[int]:
    """Device side: input registers with the calibrated sensors' raw readings (int16 counts)."""
    regs = list(regs)
    for i, (name, _) in enumerate(SENSOR_REGISTERS):
        if name in calibration.sensors:
            regs[2 + i] = _int16(calibration.sensor_to_raw(name, getattr(m, name)), calibration.sensors[name].count_s)
    return regs


def sensors_from_raw(regs: list[int], m: Measurement, calibration: Calibration) -> Measurement:
    """Daemon side: the calibrated sensors' readings in their units, from raw int16 counts."""
    values = {}
    for i, (name, _) in enumerate(SENSOR_REGISTERS):
        if name in calibration.sensors:
            values[name] = calibration.sensor_to_eng(name, _from_int16(regs[2 + i], calibration.sensors[name].count_s))
    return replace(m, **values) if values else m


def heartbeat_for(time_s: float, dt_s: float) -> int:
    """Heartbeat of the command written at daemon time ``time_s``: the next sample's index."""
    return (int(round(time_s / dt_s)) + 1) & 0xFFFF


def _pymodbus():
    try:
        import pymodbus  # noqa: F401
        from pymodbus.client import ModbusTcpClient
        from pymodbus.exceptions import ModbusException
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise RuntimeError("the Modbus backend needs pymodbus: pip install 'hvac-mpc[fieldbus]'") from exc
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    return ModbusTcpClient, ModbusException


class ModbusBackend:
    """Daemon side of the register map above (synchronous pymodbus client, one request each)."""

    def __init__(self, host: str, port: int, device_id: int = 1, timeout_s: float = 0.3, dt_s: float = 1.0,
                 clock: Callable[[], float] | None = None, calibration: Calibration | None = None):
        self.host, self.port, self.device_id = host, port, device_id
        self.calibration = calibration  # None: engineering values; else raw signals
        self.timeout_s, self.dt_s = timeout_s, dt_s
        self.clock = clock or (lambda: 0.0)
        self._client = None
        self.status_bits = 0
        self.heartbeat_echo = 0

    def connect(self) -> None:
        client_cls, _ = _pymodbus()
        self.close()
        client = client_cls(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        if not client.connect():
            client.close()
            raise BackendError(f"Modbus TCP {self.host}:{self.port}: connection refused or timed out")
        self._client = client

    def _call(self, what: str, fn, *args, **kwargs):
        if self._client is None:
            raise BackendError(f"Modbus TCP {self.host}:{self.port}: not connected")
        _, modbus_exc = _pymodbus()
        try:
            try:
                rr = fn(*args, device_id=self.device_id, **kwargs)
            except TypeError:  # pymodbus < 3.10 called the unit id 'slave'
                rr = fn(*args, slave=self.device_id, **kwargs)
        except (modbus_exc, OSError, ValueError) as exc:
            self.close()
            raise BackendError(f"Modbus TCP {self.host}:{self.port}: {what} failed ({exc})") from None
        if rr is None or rr.isError():
            raise BackendError(f"Modbus TCP {self.host}:{self.port}: {what} answered with an error ({rr})")
        return rr

    def read(self) -> Measurement:
        rr = self._call("read input registers", self._client.read_input_registers if self._client else None,
                        0, count=INPUT_COUNT)
        regs = list(rr.registers)
        m, self.heartbeat_echo, self.status_bits = decode_measurement(regs)
        if bool(self.status_bits & STATUS_RAW) != (self.calibration is not None):
            self.close()
            want, got = ("raw", "engineering") if self.calibration is not None else ("engineering", "raw")
            raise BackendError(f"Modbus TCP {self.host}:{self.port}: the device takes {got} signals, "
                               f"the daemon is set to {want} (backend.modbus.signals)")
        return m if self.calibration is None else sensors_from_raw(regs, m, self.calibration)

    def write(self, command: Command) -> None:
        regs = encode_command(command, heartbeat_for(self.clock(), self.dt_s), self.calibration)
        self._call("write holding registers", self._client.write_registers if self._client else None, 0, regs)

    def close(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            finally:
                self._client = None
