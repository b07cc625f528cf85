"""Daemon configuration: a TOML file validated by pydantic into frozen models.

Sections (all optional; defaults below)::

    [loop]        period_s, speedup ("max" or inf = as fast as possible), deadline_s, max_ticks
    [log]         path, fsync, rotation (size, day), index, memory buffer while the disk fails
    [api]         enabled, host, port (0 = any free port), port_file, token file, read access,
                  timeouts, body and connection limits, allowed hosts and origins
    [controller]  name and fallback (registered entry points of group ``hvac_mpc.controllers``),
                  parameters_file, [controller.settings] (passed to the controller's settings)
    [backend]     kind ("simulated", "modbus" or "opcua"), [backend.simulated], [backend.modbus], [backend.opcua]
    [calibration] file (raw device signals, docs/fieldbus.md); [systemd] enabled, stall_s, ping_interval_s
    [safety]      interlock limits, sensor checks, rate limits, cool-down and reconnect timing,
                  ``unsafe`` (the explicit, logged override of the safety bounds)
    [monitor]     the model monitor: horizon_s, every_s, residual bounds, degraded_after
    [reference]   the initial reference (fields of :class:`hvac_mpc.contract.Reference`)
    [[faults]]    fault injection (tests, commissioning): target, kind, start_s, end_s, signal, value,
                  delay_s; see :data:`FAULT_KINDS`

A bad file (not TOML, not text, a directory), an unknown key, a wrong type or an out-of-range
value raises :class:`ConfigError` naming the key (``section.key``) and the allowed range; nothing
is started then (``hvac-mpc daemon`` exits with code 2). One mechanism validates everything:
pydantic (hvac_mpc.validation), the same as the API bodies.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hvac_mpc.contract import REFERENCE_RANGES, InvalidReference, Reference
from hvac_mpc.models.plant import PLANT_EFFECTS

from .calibration import CalibrationConfig
from .monitor import MonitorSettings
from .opcua import OpcUaConfig
from .plugins import CONTROLLER_GROUP, registered_controllers
from .watchdog import SystemdConfig

LOG = logging.getLogger("hvac_mpc.daemon")

#: A complete, commented configuration (``hvac-mpc daemon --example-config``).
EXAMPLE_TOML = """\
# hvac-mpc daemon configuration (all keys optional; the values shown are the defaults
# unless marked as an example)

[loop]
period_s = 1.0          # sample period (thesis: 1 s)
speedup = 1.0           # plant time per wall time; "max" = as fast as possible (simulated plant)
deadline_s = 0.0        # wall-time budget of a controller step; 0 = half the period
max_ticks = 0           # stop after N samples (0 = until SIGTERM/SIGINT)

[log]
path = "hvac_daemon_log.csv"   # measurement log (docs/model.md sec. 4); a restart appends
fsync = true
rotate_bytes = 0        # new segment past this size (0 = never); segments listed in <stem>.index.csv
rotate_daily = false    # new segment at each UTC midnight
buffer_rows = 86400     # rows kept in memory while the disk fails (then the oldest are dropped)
retry_s = 5.0           # between write attempts while the log is degraded

[api]
enabled = true
host = "127.0.0.1"
port = 8750
port_file = ""
token_file = ""         # bearer token of every write, generated at first start (mode 0600);
                        # "" = <log stem>.token beside the log
token_env = ""          # or: the environment variable holding the token
auth_reads = false      # true: reads need the token too (/health stays open)
allowed_hosts = []      # Host names accepted besides loopback and api.host (DNS rebinding guard)
allowed_origins = []    # Origins accepted besides the API's own
max_body_bytes = 4096
header_timeout_s = 2.0  # request headers must arrive within this time
body_timeout_s = 5.0
max_connections = 256   # beyond it the oldest connection still sending headers is dropped

[controller]
name = "mpc"            # example; "baseline" is the default
fallback = ["baseline"]
parameters_file = ""
[controller.settings]   # MpcSettings fields for "mpc", e.g. solver = "rti"

[backend]
kind = "simulated"      # or "modbus", "opcua"
[backend.simulated]
seed = 0
effects = ["all"]
inlet_temp_c = 25.0
chiller_setpoint_c = 5.0
[backend.modbus]
host = "127.0.0.1"
port = 5020
device_id = 1
timeout_s = 0.3
signals = "engineering" # or "raw": device signals through [calibration] (docs/fieldbus.md)
[backend.opcua]
endpoint = "opc.tcp://127.0.0.1:4840/hvac-mpc/"
namespace = "urn:hvac-mpc:box"
timeout_s = 0.5
signals = "engineering"

[calibration]
file = ""               # raw-signal calibration; "" = the thesis's (daemon/thesis_calibration.toml)

[systemd]
enabled = true          # READY/WATCHDOG/STOPPING when started by systemd (Type=notify)
stall_s = 0.0           # no tick for this long = hung, pings stop; 0 = 3 periods, at least 2 s
ping_interval_s = 0.0   # 0 = half of WatchdogSec

[safety]
heater_max_w = 240.0
min_flow_m3s = 0.004
heater_outlet_max_c = 85.0
heater_outlet_reset_c = 75.0
safe_blower_w = 120.0
stuck_samples = 30
stale_samples = 3
cooldown_max_s = 900.0
rate_blower_w_per_s = 60.0    # manual mode and the transfer after a mode switch
rate_heater_w_per_s = 60.0
rate_valve_pct_per_s = 20.0
transfer_s = 30.0
transfer_ramp_c_per_s = 0.025     # after a switch: reference ramps from the reading (0 = at once)
transfer_ramp_m3s_per_s = 0.0005
unsafe = false                # true allows min_flow_m3s = 0 and no interlock sensor (logged)

[monitor]               # model monitor (docs/real-box.md, model monitoring)
horizon_s = 60.0        # free-run window of the horizon residual
every_s = 10.0          # one horizon evaluation this often
bound_supply_temp_c = 4.6           # horizon RMS bounds (measured: 1.25 x healthy maximum)
bound_volume_flow_m3s = 0.016
bound_heater_outlet_temp_c = 26.0
bound_one_step_supply_temp_c = 0.8  # one-step RMS bounds over the window (the same way)
bound_one_step_volume_flow_m3s = 0.016
bound_one_step_heater_outlet_temp_c = 26.0
degraded_after = 3      # evaluations in a row beyond a bound -> "degraded"

[reference]
supply_temp_c = 20.0
volume_flow_m3s = 0.03

# fault injection (tests, commissioning), example:
# [[faults]]
# target = "sensor"
# kind = "nan"
# signal = "volume_flow_m3s"
# start_s = 120.0
# end_s = 180.0
"""


class ConfigError(ValueError):
    """The configuration is invalid; the message names the key and the allowed values."""


#: Sensor fields a Measurement carries (hvac_mpc.contract.Measurement, without time_s).
SENSOR_FIELDS = ("supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c", "water_temp_c",
                 "chiller_setpoint_c", "heater_power_w", "heater_outlet_temp_c")
SensorName = Literal[SENSOR_FIELDS]  # type: ignore[valid-type]

#: Plausible ranges of each sensor; a reading outside is a sensor fault (ASSUMPTION: wide bounds
#: around the box's physical operating range, thesis sec. 2; a lab replaces them for its sensors).
DEFAULT_SENSOR_RANGES = {
    "supply_temp_c": [-20.0, 90.0],
    "volume_flow_m3s": [-0.002, 0.1],
    "hvac_inlet_temp_c": [-20.0, 50.0],
    "water_temp_c": [-5.0, 50.0],
    "chiller_setpoint_c": [-5.0, 30.0],
    "heater_power_w": [-5.0, 260.0],
    "heater_outlet_temp_c": [-20.0, 170.0],
}

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


def _f(default: Any, doc: str, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
       inf: bool = False) -> Any:
    """A field with its description and allowed range (``lo_open``: lo excluded; ``inf``: inf allowed)."""
    bounds: dict[str, Any] = {}
    if lo is not None:
        bounds["gt" if lo_open else "ge"] = lo
    if hi is not None:
        bounds["le"] = hi
    if inf:
        bounds["allow_inf_nan"] = True
    if isinstance(default, (list, dict)):
        return Field(default_factory=lambda: type(default)(default), description=doc, **bounds)
    return Field(default, description=doc, **bounds)


class _Section(BaseModel):
    """A configuration table: strict types, unknown keys refused, immutable, no NaN."""

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True, allow_inf_nan=False)

    def replace(self, **changes: Any) -> Any:
        """A validated copy with ``changes`` (the dataclasses.replace of these models)."""
        return type(self).model_validate({**self.model_dump(), **changes})


class LoopConfig(_Section):
    period_s: float = _f(1.0, "sample period (thesis: sampling 1 s)", 0.01, 60.0)
    speedup: float = _f(1.0, "plant time per wall time; inf ('max') runs as fast as possible", 0.01, math.inf,
                        inf=True)
    deadline_s: float = _f(0.0, "wall-time budget of one controller step; 0 = half the real period", 0.0, 60.0)
    max_ticks: int = _f(0, "stop (with the shutdown sequence) after this many samples; 0 = run until stopped",
                        0, 10**9)

    @field_validator("speedup", mode="before")
    @classmethod
    def _max_is_inf(cls, v: Any) -> Any:
        return math.inf if isinstance(v, str) and v.lower() in ("max", "inf") else v

    @property
    def wall_period_s(self) -> float:
        return 0.0 if math.isinf(self.speedup) else self.period_s / self.speedup

    @property
    def step_deadline_s(self) -> float:
        return self.deadline_s if self.deadline_s > 0 else 0.5 * self.period_s


class LogConfig(_Section):
    path: str = _f("hvac_daemon_log.csv", "measurement log (CSV, docs/model.md sec. 4); appended on restart")
    fsync: bool = _f(True, "fsync every row (a crash loses at most the row in flight)")
    rotate_bytes: int = _f(0, "start a new segment when the active file passes this size; 0 = never",
                           0, 2**50)
    rotate_daily: bool = _f(False, "start a new segment at each UTC midnight")
    buffer_rows: int = _f(86400, "rows held in memory while the disk fails (a day at 1 s); beyond it the "
                                 "oldest buffered rows are dropped and counted", 1, 10**7)
    retry_s: float = _f(5.0, "wall time between write attempts while the log is degraded", 0.0, 3600.0)


class ApiConfig(_Section):
    enabled: bool = _f(True, "serve the HTTP API")
    host: str = _f("127.0.0.1", "bind address")
    port: int = _f(8750, "TCP port; 0 = any free port (written to port_file)", 0, 65535)
    port_file: str = _f("", "file to write the bound port to (for scripts and tests)")
    token_file: str = _f("", "file of the bearer token every write needs; generated at first start with mode "
                             "0600 (like a notebook server's token); '' = <log stem>.token beside the log")
    token_env: str = _f("", "environment variable holding the token instead of the file")
    auth_reads: bool = _f(False, "require the token for reads too (/health stays open)")
    allowed_hosts: list[str] = _f([], "Host header names accepted besides the loopback names and api.host "
                                      "(DNS rebinding guard)")
    allowed_origins: list[str] = _f([], "Origin values accepted on writes besides the API's own")
    max_body_bytes: int = _f(4096, "largest accepted request body", 64, 1_000_000)
    header_timeout_s: float = _f(2.0, "a connection must deliver its request headers within this time",
                                 0.1, 60.0)
    body_timeout_s: float = _f(5.0, "a request must deliver its body within this time", 0.1, 120.0)
    max_connections: int = _f(256, "open connections; beyond it the oldest one still sending headers is "
                                   "dropped (slow clients cannot exhaust it)", 8, 100000)

    @model_validator(mode="after")
    def _reads_off_loopback(self) -> "ApiConfig":
        if self.enabled and self.host not in LOOPBACK_HOSTS and not self.auth_reads:
            raise ValueError(f"host = {self.host!r} is not loopback: set api.auth_reads = true so reads need the "
                             "token too (writes always do)")
        return self


class ControllerConfig(_Section):
    name: str = _f("baseline", f"a registered controller (entry point group {CONTROLLER_GROUP}): "
                               "'mpc', 'baseline' or a plug-in's name")
    fallback: list[str] = _f(["baseline"], "controllers tried in order when the primary fails or misses its "
                                           "deadline; the safe command always comes last")
    parameters_file: str = _f("", "model parameters (TOML/JSON, hvac_mpc.models.parameters); '' = defaults")
    model_file: str = _f("", "refined model file (hvac-mpc identify: parameters, effects, discovered terms) for "
                             "'mpc'; its parameters replace parameters_file; '' = none")
    settings: dict[str, Any] = _f({}, "keyword arguments of the controller's settings (MpcSettings for 'mpc')")

    @field_validator("name", "fallback")
    @classmethod
    def _registered(cls, v: Any) -> Any:
        names = [v] if isinstance(v, str) else v
        known = registered_controllers()
        for n in names:
            if n not in known:
                hint = (" (controllers are loaded only through a registered entry point, never from a "
                        "'module:name')") if ":" in n or "." in n else ""
                raise ValueError(f"{n!r} is not a registered controller{hint}; registered: {sorted(known)}")
        return v

    @field_validator("fallback", mode="before")
    @classmethod
    def _one_name(cls, v: Any) -> Any:
        return [v] if isinstance(v, str) else v


class SimulatedBackendConfig(_Section):
    seed: int = _f(0, "noise seed", 0, 2**31)
    effects: list[Literal[PLANT_EFFECTS + ("all",)]] = _f(  # type: ignore[valid-type]
        ["all"], "plant effects (hvac_mpc.models.plant.PLANT_EFFECTS) or ['all']")
    inlet_temp_c: float = _f(25.0, "inlet air temperature", -20.0, 50.0)
    chiller_setpoint_c: float = _f(5.0, "chiller set point (docs/model.md sec. 1: 5 C cooling)", -5.0, 30.0)

    @field_validator("effects", mode="before")
    @classmethod
    def _one_effect(cls, v: Any) -> Any:
        return [v] if isinstance(v, str) else v


class ModbusBackendConfig(_Section):
    host: str = _f("127.0.0.1", "Modbus TCP server (PLC, I/O coupler or the plant simulator)")
    port: int = _f(5020, "Modbus TCP port (502 on a real coupler)", 1, 65535)
    device_id: int = _f(1, "Modbus unit/device id", 0, 255)
    timeout_s: float = _f(0.3, "request timeout", 0.01, 10.0)
    signals: Literal["engineering", "raw"] = _f(
        "engineering", "holding registers 0-5 carry engineering values or raw device signals (calibration file)")


class BackendConfig(_Section):
    kind: Literal["simulated", "modbus", "opcua"] = _f("simulated", "I/O backend")
    simulated: SimulatedBackendConfig = Field(default_factory=SimulatedBackendConfig)
    modbus: ModbusBackendConfig = Field(default_factory=ModbusBackendConfig)
    opcua: OpcUaConfig = Field(default_factory=OpcUaConfig)


SensorRange = Annotated[list[float], Field(min_length=2, max_length=2, description="[lo, hi] with lo < hi")]


class SafetyConfig(_Section):
    heater_max_w: float = _f(240.0, "heater command limit (thesis sec. 2.3: ~240 W maximum)", 0.0, 240.0)
    min_flow_m3s: float = _f(
        0.004, "ASSUMPTION heater off below this volume flow: under the 0.0057 m3/s of the blower at 30 W "
               "with all valves open (docs/model.md sec. 1); at 0.004 m3/s and 240 W the heater body settles "
               "near 95 C above inlet, below heater_temp_max_c; above 0 unless unsafe", 0.0, 0.05)
    flow_hysteresis_m3s: float = _f(0.001, "flow above min_flow + this re-enables the heater", 0.0, 0.02)
    heater_outlet_max_c: float = _f(85.0, "ASSUMPTION heater outlet air trip temperature", 30.0, 165.0)
    heater_outlet_reset_c: float = _f(75.0, "heater re-enabled below this outlet temperature", 20.0, 160.0)
    heater_temp_max_c: float = _f(0.0, "estimated heater body trip temperature; 0 = Parameters.heater_temp_max_c",
                                  0.0, 165.0)
    sensor_ranges: dict[SensorName, SensorRange] = _f(  # type: ignore[valid-type]
        DEFAULT_SENSOR_RANGES, "plausible range per sensor [lo, hi]")
    interlock_sensors: list[SensorName] = _f(  # type: ignore[valid-type]
        ["volume_flow_m3s", "heater_outlet_temp_c"],
        "sensors the heater interlock needs valid (else heater off); at least one unless unsafe")
    control_sensors: list[SensorName] = _f(  # type: ignore[valid-type]
        ["supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c"],
        "sensors the controller needs; invalid -> safe command")
    hold_sensors: list[SensorName] = _f(  # type: ignore[valid-type]
        ["hvac_inlet_temp_c", "water_temp_c", "chiller_setpoint_c"],
        "slow sensors whose last good value may stand in for hold_last_good_s")
    hold_last_good_s: float = _f(10.0, "how long a held last good value may stand in", 0.0, 600.0)
    stuck_sensors: list[SensorName] = _f(  # type: ignore[valid-type]
        ["supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c", "heater_outlet_temp_c"],
        "noisy analogue sensors checked for a frozen reading")
    stuck_samples: int = _f(30, "identical readings in a row that mean 'stuck'; 0 = no check", 0, 100000)
    stale_samples: int = _f(3, "reads without a new measurement time that mean 'stale'", 1, 1000)
    safe_blower_w: float = _f(120.0, "ASSUMPTION blower power of the safe command and the cool-down", 30.0, 300.0)
    safe_valve_a_pct: float = _f(100.0, "valve a in the safe command: 100 % sends all air through the heater "
                                        "(thesis table 1), carrying its heat away", 0.0, 100.0)
    cooldown_margin_c: float = _f(5.0, "cool-down ends when the heater estimate is this close to its "
                                       "inlet air bound", 0.5, 100.0)
    cooldown_min_s: float = _f(5.0, "shortest cool-down", 0.0, 3600.0)
    cooldown_max_s: float = _f(900.0, "longest cool-down (also used when flow is unknown)", 1.0, 7200.0)
    reconnect_initial_s: float = _f(1.0, "first reconnect delay (plant time)", 0.01, 600.0)
    reconnect_max_s: float = _f(30.0, "largest reconnect delay (doubling backoff)", 0.01, 3600.0)
    rate_blower_w_per_s: float = _f(60.0, "ASSUMPTION blower rate limit in manual mode and at a mode switch "
                                          "(the MPC's default, mpc/ocp.py)", 1.0, 1000.0)
    rate_heater_w_per_s: float = _f(60.0, "heater rate limit in manual mode and at a mode switch (rising; "
                                          "the interlock switches it off at once)", 1.0, 1000.0)
    rate_valve_pct_per_s: float = _f(20.0, "valve rate limit in manual mode and at a mode switch", 0.5, 100.0)
    transfer_s: float = _f(30.0, "after a switch to an automatic mode the command is rate-limited this long",
                           0.0, 600.0)
    transfer_ramp_c_per_s: float = _f(
        0.025, "ASSUMPTION after a switch to an automatic mode the controller's supply temperature reference "
              "starts at the reading and ramps to the reference in force at this rate (1.5 C/min: 0.25 C in "
              "the 10 s after a switch); 0 = the reference at once", 0.0, 10.0)
    transfer_ramp_m3s_per_s: float = _f(
        0.0005, "ASSUMPTION the same ramp for the volume flow reference (0.03 m3/s per min); 0 = at once",
        0.0, 1.0)
    unsafe: bool = _f(False, "allow min_flow_m3s = 0 and an empty interlock_sensors (logged at every start)")

    @field_validator("sensor_ranges")
    @classmethod
    def _ordered(cls, v: dict) -> dict:
        for name, (lo, hi) in v.items():
            if not lo < hi:
                raise ValueError(f"{name}: expected [lo, hi] with lo < hi, got [{lo}, {hi}]")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> "SafetyConfig":
        if self.heater_outlet_reset_c >= self.heater_outlet_max_c:
            raise ValueError(f"heater_outlet_reset_c = {self.heater_outlet_reset_c} must be below "
                             f"heater_outlet_max_c = {self.heater_outlet_max_c}")
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError("reconnect_max_s must be at least reconnect_initial_s")
        if self.cooldown_max_s < self.cooldown_min_s:
            raise ValueError("cooldown_max_s must be at least cooldown_min_s")
        if not self.unsafe:
            if self.min_flow_m3s <= 0.0:
                raise ValueError(f"min_flow_m3s = {self.min_flow_m3s} must be above 0 (allowed (0, 0.05]); "
                                 "set safety.unsafe = true to override")
            if not self.interlock_sensors:
                raise ValueError(f"interlock_sensors: at least one of {list(SENSOR_FIELDS)}; "
                                 "set safety.unsafe = true to override")
        return self

    def unsafe_overrides(self) -> list[str]:
        """The safety bounds this configuration overrides (empty unless ``unsafe``)."""
        out = []
        if self.min_flow_m3s <= 0.0:
            out.append(f"min_flow_m3s = {self.min_flow_m3s}")
        if not self.interlock_sensors:
            out.append("interlock_sensors = []")
        return out


def _like_monitor(name: str, doc: str) -> Any:
    """A ``[monitor]`` field with the default and allowed range of :class:`.monitor.MonitorSettings`' field
    ``name`` (one place for both)."""
    f = next(f for f in dataclasses.fields(MonitorSettings) if f.name == name)
    check = f.metadata["check"]
    return _f(f.default, doc, check.lo, check.hi)


class MonitorConfig(_Section):
    """``[monitor]``: the model monitor's window, cadence and residual bounds (:class:`.monitor.MonitorSettings`;
    docs/real-box.md, model monitoring). The default bounds are 1.25 times the largest residual a healthy
    simulated box gave (:data:`.monitor.DEFAULT_BOUNDS`); a lab sets them from a run of its box."""

    horizon_s: float = _like_monitor("horizon_s", "free-run window of the horizon residual")
    every_s: float = _like_monitor("every_s", "time between two horizon evaluations")
    bound_supply_temp_c: float = _like_monitor("bound_supply_temp_c",
                                               "bound on the supply temperature's horizon RMS residual")
    bound_volume_flow_m3s: float = _like_monitor("bound_volume_flow_m3s",
                                                 "bound on the volume flow's horizon RMS residual")
    bound_heater_outlet_temp_c: float = _like_monitor("bound_heater_outlet_temp_c",
                                                      "bound on the heater outlet temperature's horizon RMS residual")
    bound_one_step_supply_temp_c: float = _like_monitor(
        "bound_one_step_supply_temp_c", "bound on the supply temperature's one-step RMS residual over the window")
    bound_one_step_volume_flow_m3s: float = _like_monitor(
        "bound_one_step_volume_flow_m3s", "bound on the volume flow's one-step RMS residual over the window")
    bound_one_step_heater_outlet_temp_c: float = _like_monitor(
        "bound_one_step_heater_outlet_temp_c",
        "bound on the heater outlet temperature's one-step RMS residual over the window")
    degraded_after: int = _like_monitor(
        "degraded_after", "evaluations in a row beyond a bound before 'degraded' (and within before 'ok')")

    def settings(self) -> MonitorSettings:
        """The :class:`hvac_mpc.daemon.monitor.MonitorSettings` of this section."""
        return MonitorSettings(**self.model_dump())


FAULT_KINDS = {
    "sensor": ("nan", "stuck", "out_of_range", "missing", "stale", "value"),
    "controller": ("fail", "nan", "delay", "solver"),
    "backend": ("disconnect",),
    "daemon": ("fatal", "fatal_repeated"),
    "log": ("enospc", "eio"),
}


class FaultSpec(_Section):
    """One injected fault, active for daemon time in [start_s, end_s)."""

    target: Literal[tuple(FAULT_KINDS)] = _f("sensor", "what the fault hits")  # type: ignore[valid-type]
    kind: str = _f("nan", "fault kind; sensor: nan/stuck/out_of_range/missing/stale/value (reading "
                          "replaced by value), controller: fail/nan/delay/solver (the controller's own "
                          "solver fails, if it supports that), backend: disconnect, "
                          "daemon: fatal (an unexpected error inside the loop, once) or "
                          "fatal_repeated (on every sample of the window), log: enospc/eio (every "
                          "log write fails: disk full, I/O error)")
    start_s: float = _f(0.0, "start (daemon time)", 0.0, math.inf, inf=True)
    end_s: float = _f(0.0, "end (daemon time)", 0.0, math.inf, inf=True)
    signal: str = _f("", "sensor field for sensor faults")
    value: float = _f(1e4, "reading used by out_of_range and value", -math.inf, math.inf, inf=True)
    delay_s: float = _f(0.0, "wall-time delay of a controller step for kind 'delay'", 0.0, 60.0)

    @model_validator(mode="after")
    def _consistent(self) -> "FaultSpec":
        if self.kind not in FAULT_KINDS[self.target]:
            raise ValueError(f"kind = {self.kind!r}: allowed for target {self.target!r}: "
                             f"{list(FAULT_KINDS[self.target])}")
        if not self.end_s > self.start_s:
            raise ValueError(f"end_s = {self.end_s} must be after start_s = {self.start_s}")
        if self.target == "sensor" and self.signal not in SENSOR_FIELDS:
            raise ValueError(f"signal = {self.signal!r}: allowed {list(SENSOR_FIELDS)}")
        return self

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.end_s


class DaemonConfig(_Section):
    loop: LoopConfig = Field(default_factory=LoopConfig)
    log: LogConfig = Field(default_factory=LogConfig)
    api: ApiConfig = Field(default_factory=ApiConfig)
    controller: ControllerConfig = Field(default_factory=ControllerConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)
    safety: SafetyConfig = Field(default_factory=SafetyConfig)
    reference: dict[str, Any] = Field(default_factory=lambda: {"supply_temp_c": 20.0, "volume_flow_m3s": 0.03},
                                      description="the initial reference (Reference fields)")
    faults: list[FaultSpec] = Field(default_factory=list)
    base_dir: str = "."
    systemd: SystemdConfig = Field(default_factory=SystemdConfig)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    monitor: MonitorConfig = Field(default_factory=MonitorConfig)

    @field_validator("reference", mode="before")
    @classmethod
    def _reference_table(cls, v: Any) -> Any:
        if not isinstance(v, Mapping):
            ranges = ", ".join(f"{k} in [{lo}, {hi}]" for k, (lo, hi) in REFERENCE_RANGES.items())
            raise ValueError(f"expected a table [reference] with {ranges} (outlet flows optional), got {v!r:.60}")
        return v

    @field_validator("reference")
    @classmethod
    def _reference(cls, v: dict) -> dict:
        try:
            Reference.from_mapping(v)
        except (InvalidReference, TypeError) as exc:
            raise ValueError(str(exc)) from None
        return v

    @property
    def initial_reference(self) -> Reference:
        return Reference.from_mapping(self.reference)


def _field_info(loc: tuple, model: type[BaseModel] = DaemonConfig):
    """The pydantic FieldInfo at ``loc`` (None where the path leaves the models)."""
    info = None
    for part in loc:
        if isinstance(model, type) and issubclass(model, BaseModel) and part in model.model_fields:
            info = model.model_fields[part]
            model = info.annotation  # type: ignore[assignment]
        elif isinstance(part, int):
            args = getattr(model, "__args__", ())
            model = args[0] if args else None  # type: ignore[assignment]
        else:
            return None
    return info


def _allowed(info) -> str:
    """The allowed range or choices of a field, from its constraints."""
    if info is None:
        return ""
    lo = hi = None
    left = "["
    for m in info.metadata:
        if getattr(m, "ge", None) is not None:
            lo = m.ge
        if getattr(m, "gt", None) is not None:
            lo, left = m.gt, "("
        if getattr(m, "le", None) is not None:
            hi = m.le
    if lo is not None or hi is not None:
        return f"{left}{lo}, {hi}]"
    args = getattr(info.annotation, "__args__", ())
    if getattr(info.annotation, "__origin__", None) is Literal:
        return f"one of {list(args)}"
    return ""


def _short(value: Any) -> str:
    """repr, cut to 60 characters (a 10**400 in a file is named, not printed whole)."""
    r = repr(value)
    return r if len(r) <= 60 else r[:57] + "..."


def describe_config_error(err: ValidationError, prefix: str = "") -> str:
    """One line per problem: the key (``section.key``), what is wrong, the value and the allowed range."""
    lines = []
    for e in err.errors():
        loc = tuple(e["loc"])
        key = prefix + ".".join(str(p) if not isinstance(p, int) else f"[{p}]" for p in loc).replace(".[", "[")
        got = e.get("input")
        info = _field_info(loc) if loc else None
        allowed = _allowed(info)
        if e["type"] in ("greater_than_equal", "less_than_equal", "greater_than", "less_than") and allowed:
            lines.append(f"{key} = {_short(got)} is outside the allowed range {allowed}")
        elif e["type"] == "extra_forbidden":
            parent = _field_info(loc[:-1]) if len(loc) > 1 else None
            model = parent.annotation if parent is not None else DaemonConfig
            known = sorted(set(getattr(model, "model_fields", {})) - {"base_dir"})
            lines.append(f"{key}: unknown key; allowed: {known}")
        else:
            msg = e["msg"].removeprefix("Value error, ")
            shown = "" if isinstance(got, dict) or e["type"] == "value_error" else f" (got {_short(got)})"
            lines.append(f"{key or '(top level)'}: {msg}{shown}" + (f"; allowed: {allowed}" if allowed else ""))
    return "; ".join(lines)


def config_from_mapping(data: Mapping[str, Any], base_dir: str | Path = ".") -> DaemonConfig:
    """Validated :class:`DaemonConfig` from a parsed TOML mapping."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"expected a table of sections, got {type(data).__name__}")
    try:
        cfg = DaemonConfig.model_validate({**dict(data), "base_dir": str(base_dir)})
    except ValidationError as exc:
        raise ConfigError(describe_config_error(exc)) from None
    if "raw" in (cfg.backend.modbus.signals, cfg.backend.opcua.signals):
        cfg.calibration.check(Path(base_dir), ConfigError)  # a bad calibration file: nothing starts
    if cfg.safety.unsafe and cfg.safety.unsafe_overrides():
        LOG.warning("safety.unsafe = true: safety bounds overridden: %s", ", ".join(cfg.safety.unsafe_overrides()))
    return cfg


def load_config(path: str | Path) -> DaemonConfig:
    """Read and validate a TOML configuration file; relative paths in it are relative to the file."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
        data = tomllib.loads(text)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, expected a TOML configuration file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a UTF-8 text file (byte {exc.start}); expected TOML") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return config_from_mapping(data, base_dir=path.parent)


def resolve(config: DaemonConfig, p: str) -> Path:
    """A path from the configuration, relative to the configuration file's directory."""
    q = Path(p)
    return q if q.is_absolute() else Path(config.base_dir) / q
