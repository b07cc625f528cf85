"""Daemon configuration: a TOML file read into frozen dataclasses, every key validated.

Sections (all optional; defaults below)::

    [loop]        period_s, speedup ("max" or inf = as fast as possible), deadline_s, max_ticks
    [log]         path, fsync
    [api]         enabled, host, port (0 = any free port), port_file, token, token_env, max_body_bytes
    [controller]  name ("mpc", "baseline" or "package.module:Class"), fallback (list), parameters_file,
                  [controller.settings] (passed to the controller's settings)
    [backend]     kind ("simulated" or "modbus"), [backend.simulated], [backend.modbus]
    [safety]      interlock limits, sensor checks, cool-down and reconnect timing
    [reference]   the initial reference (fields of :class:`hvac_mpc.mpc.reference.Reference`)
    [[faults]]    fault injection (tests, commissioning): target, kind, start_s, end_s, signal, value,
                  delay_s; see :data:`FAULT_KINDS`

An unknown key, a wrong type or an out-of-range value raises :class:`ConfigError` naming the
key (``section.key``) and the allowed range; nothing is started then.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

from hvac_mpc.contract import InvalidReference, Reference


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

[api]
enabled = true
host = "127.0.0.1"      # anything else needs a token
port = 8750
port_file = ""
token_env = ""          # e.g. "HVAC_MPC_TOKEN": the bearer token is read from this variable
max_body_bytes = 4096

[controller]
name = "mpc"            # example; "baseline" is the default
fallback = ["baseline"]
parameters_file = ""
[controller.settings]   # MpcSettings fields for "mpc", e.g. solver = "rti"

[backend]
kind = "simulated"      # or "modbus"
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

[safety]
heater_max_w = 240.0
min_flow_m3s = 0.004
heater_outlet_max_c = 85.0
heater_outlet_reset_c = 75.0
safe_blower_w = 120.0
stuck_samples = 30
stale_samples = 3
cooldown_max_s = 900.0

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


def _f(default: Any, doc: str, lo: float | None = None, hi: float | None = None,
       choices: tuple | None = None) -> Any:
    meta = {"doc": doc, "range": (lo, hi), "choices": choices}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


#: Sensor fields a Measurement carries (hvac_mpc.models.plant.Measurement, without time_s).
SENSOR_FIELDS = ("supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c", "water_temp_c",
                 "chiller_setpoint_c", "heater_power_w", "heater_outlet_temp_c")

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


@dataclass(frozen=True)
class LoopConfig:
    period_s: float = _f(1.0, "sample period (thesis: sampling 1 s)", 0.01, 60.0)
    speedup: float = _f(1.0, "plant time per wall time; inf ('max') runs as fast as possible", 0.01, math.inf)
    deadline_s: float = _f(0.0, "wall-time budget of one controller step; 0 = half the real period", 0.0, 60.0)
    max_ticks: int = _f(0, "stop (with the shutdown sequence) after this many samples; 0 = run until stopped",
                        0, 10**9)

    @property
    def wall_period_s(self) -> float:
        return 0.0 if math.isinf(self.speedup) else self.period_s / self.speedup

    @property
    def step_deadline_s(self) -> float:
        return self.deadline_s if self.deadline_s > 0 else 0.5 * self.period_s


@dataclass(frozen=True)
class LogConfig:
    path: str = _f("hvac_daemon_log.csv", "measurement log (CSV, docs/model.md sec. 4); appended on restart")
    fsync: bool = _f(True, "fsync every row (a crash loses at most the row in flight)")


@dataclass(frozen=True)
class ApiConfig:
    enabled: bool = _f(True, "serve the reference API")
    host: str = _f("127.0.0.1", "bind address; anything but loopback needs a token")
    port: int = _f(8750, "TCP port; 0 = any free port (written to port_file)", 0, 65535)
    port_file: str = _f("", "file to write the bound port to (for scripts and tests)")
    token: str = _f("", "bearer token (prefer token_env)")
    token_env: str = _f("", "environment variable holding the bearer token")
    max_body_bytes: int = _f(4096, "largest accepted request body", 64, 1_000_000)
    request_timeout_s: float = _f(5.0, "socket timeout per request (slow clients are dropped)", 0.1, 120.0)


@dataclass(frozen=True)
class ControllerConfig:
    name: str = _f("baseline", "'mpc', 'baseline' or 'package.module:Class'")
    fallback: list = _f(["baseline"], "controllers tried in order when the primary fails or misses its "
                                      "deadline; the safe command always comes last")
    parameters_file: str = _f("", "model parameters (TOML/JSON, hvac_mpc.models.parameters); '' = defaults")
    model_file: str = _f("", "refined model file (hvac-mpc identify: parameters, effects, discovered terms) for "
                             "'mpc'; its parameters replace parameters_file; '' = none")
    settings: dict = _f({}, "keyword arguments of the controller's settings (MpcSettings for 'mpc')")


@dataclass(frozen=True)
class SimulatedBackendConfig:
    seed: int = _f(0, "noise seed", 0, 2**31)
    effects: list = _f(["all"], "plant effects (hvac_mpc.models.plant.PLANT_EFFECTS) or ['all']")
    inlet_temp_c: float = _f(25.0, "inlet air temperature", -20.0, 50.0)
    chiller_setpoint_c: float = _f(5.0, "chiller set point (docs/model.md sec. 1: 5 C cooling)", -5.0, 30.0)


@dataclass(frozen=True)
class ModbusBackendConfig:
    host: str = _f("127.0.0.1", "Modbus TCP server (PLC, I/O coupler or the plant simulator)")
    port: int = _f(5020, "Modbus TCP port (502 on a real coupler)", 1, 65535)
    device_id: int = _f(1, "Modbus unit/device id", 0, 255)
    timeout_s: float = _f(0.3, "request timeout", 0.01, 10.0)


@dataclass(frozen=True)
class BackendConfig:
    kind: str = _f("simulated", "I/O backend", choices=("simulated", "modbus"))
    simulated: SimulatedBackendConfig = field(default_factory=SimulatedBackendConfig)
    modbus: ModbusBackendConfig = field(default_factory=ModbusBackendConfig)


@dataclass(frozen=True)
class SafetyConfig:
    heater_max_w: float = _f(240.0, "heater command limit (thesis sec. 2.3: ~240 W maximum)", 0.0, 240.0)
    min_flow_m3s: float = _f(
        0.004, "ASSUMPTION heater off below this volume flow: under the 0.0057 m3/s of the blower at 30 W "
               "with all valves open (docs/model.md sec. 1); at 0.004 m3/s and 240 W the heater body settles "
               "near 95 C above inlet, below heater_temp_max_c", 0.0, 0.05)
    flow_hysteresis_m3s: float = _f(0.001, "flow above min_flow + this re-enables the heater", 0.0, 0.02)
    heater_outlet_max_c: float = _f(85.0, "ASSUMPTION heater outlet air trip temperature", 30.0, 165.0)
    heater_outlet_reset_c: float = _f(75.0, "heater re-enabled below this outlet temperature", 20.0, 160.0)
    heater_temp_max_c: float = _f(0.0, "estimated heater body trip temperature; 0 = Parameters.heater_temp_max_c",
                                  0.0, 165.0)
    sensor_ranges: dict = _f(DEFAULT_SENSOR_RANGES, "plausible range per sensor [lo, hi]")
    interlock_sensors: list = _f(["volume_flow_m3s", "heater_outlet_temp_c"],
                                 "sensors the heater interlock needs valid (else heater off)")
    control_sensors: list = _f(["supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c"],
                               "sensors the controller needs; invalid -> safe command")
    hold_sensors: list = _f(["hvac_inlet_temp_c", "water_temp_c", "chiller_setpoint_c"],
                            "slow sensors whose last good value may stand in for hold_last_good_s")
    hold_last_good_s: float = _f(10.0, "how long a held last good value may stand in", 0.0, 600.0)
    stuck_sensors: list = _f(["supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c", "heater_outlet_temp_c"],
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


FAULT_KINDS = {
    "sensor": ("nan", "stuck", "out_of_range", "missing", "stale", "value"),
    "controller": ("fail", "nan", "delay", "solver"),
    "backend": ("disconnect",),
    "daemon": ("fatal", "fatal_repeated"),
}


@dataclass(frozen=True)
class FaultSpec:
    """One injected fault, active for daemon time in [start_s, end_s)."""

    target: str = _f("sensor", "what the fault hits", choices=tuple(FAULT_KINDS))
    kind: str = _f("nan", "fault kind; sensor: nan/stuck/out_of_range/missing/stale/value (reading "
                          "replaced by value), controller: fail/nan/delay/solver (the controller's own "
                          "solver fails, if it supports that), backend: disconnect, "
                          "daemon: fatal (an unexpected error inside the loop, once) or "
                          "fatal_repeated (on every sample of the window)")
    start_s: float = _f(0.0, "start (daemon time)", 0.0, math.inf)
    end_s: float = _f(0.0, "end (daemon time)", 0.0, math.inf)
    signal: str = _f("", "sensor field for sensor faults")
    value: float = _f(1e4, "reading used by out_of_range and value", -math.inf, math.inf)
    delay_s: float = _f(0.0, "wall-time delay of a controller step for kind 'delay'", 0.0, 60.0)

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.end_s


@dataclass(frozen=True)
class DaemonConfig:
    loop: LoopConfig = field(default_factory=LoopConfig)
    log: LogConfig = field(default_factory=LogConfig)
    api: ApiConfig = field(default_factory=ApiConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    reference: dict = field(default_factory=lambda: {"supply_temp_c": 20.0, "volume_flow_m3s": 0.03})
    faults: list = field(default_factory=list)
    base_dir: str = "."

    @property
    def initial_reference(self) -> Reference:
        return Reference.from_mapping(self.reference)


_SECTIONS = {"loop": LoopConfig, "log": LogConfig, "api": ApiConfig, "controller": ControllerConfig,
             "backend": BackendConfig, "safety": SafetyConfig}


def _check_value(cls: type, name: str, value: Any, where: str) -> Any:
    f = next(f for f in fields(cls) if f.name == name)
    expect = type(getattr(cls(), name))
    meta = f.metadata
    if expect is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if expect in (int, float):
        if expect is float and name == "speedup" and isinstance(value, str) and value.lower() in ("max", "inf"):
            value = math.inf
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number in [{meta['range'][0]}, {meta['range'][1]}], "
                              f"got {value!r}")
        if expect is int and (isinstance(value, float) and not value.is_integer()):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        value = expect(value)
        lo, hi = meta["range"]
        if math.isnan(value) or (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ConfigError(f"{where} = {value} is outside the allowed range [{lo}, {hi}]")
        return value
    if expect is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        if meta.get("choices") and value not in meta["choices"]:
            raise ConfigError(f"{where} = {value!r}: allowed values {list(meta['choices'])}")
        return value
    if expect is list:
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        return list(value)
    if expect is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table, got {value!r}")
        return dict(value)
    return value


def _build(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"[{where}]: expected a table, got {data!r}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"[{where}]: unknown key(s) {unknown}; allowed: {sorted(known)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        sub = {"simulated": SimulatedBackendConfig, "modbus": ModbusBackendConfig}.get(name) \
            if cls is BackendConfig else None
        if sub is not None:
            kwargs[name] = _build(sub, value, f"{where}.{name}")
        else:
            kwargs[name] = _check_value(cls, name, value, f"{where}.{name}")
    return cls(**kwargs)


def _check_safety(s: SafetyConfig) -> None:
    for key in ("interlock_sensors", "control_sensors", "hold_sensors", "stuck_sensors"):
        bad = sorted(set(getattr(s, key)) - set(SENSOR_FIELDS))
        if bad:
            raise ConfigError(f"safety.{key}: unknown sensor(s) {bad}; allowed: {list(SENSOR_FIELDS)}")
    bad = sorted(set(s.sensor_ranges) - set(SENSOR_FIELDS))
    if bad:
        raise ConfigError(f"safety.sensor_ranges: unknown sensor(s) {bad}; allowed: {list(SENSOR_FIELDS)}")
    for name, rng in s.sensor_ranges.items():
        if (not isinstance(rng, (list, tuple)) or len(rng) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rng)
                or not rng[0] < rng[1]):
            raise ConfigError(f"safety.sensor_ranges.{name}: expected [lo, hi] with lo < hi, got {rng!r}")
    if s.heater_outlet_reset_c >= s.heater_outlet_max_c:
        raise ConfigError(f"safety.heater_outlet_reset_c = {s.heater_outlet_reset_c} must be below "
                          f"safety.heater_outlet_max_c = {s.heater_outlet_max_c}")
    if s.reconnect_max_s < s.reconnect_initial_s:
        raise ConfigError("safety.reconnect_max_s must be at least safety.reconnect_initial_s")
    if s.cooldown_max_s < s.cooldown_min_s:
        raise ConfigError("safety.cooldown_max_s must be at least safety.cooldown_min_s")


def _build_fault(data: Any, i: int) -> FaultSpec:
    where = f"faults[{i}]"
    spec = _build(FaultSpec, data, where)
    if spec.kind not in FAULT_KINDS[spec.target]:
        raise ConfigError(f"{where}.kind = {spec.kind!r}: allowed for target {spec.target!r}: "
                          f"{list(FAULT_KINDS[spec.target])}")
    if spec.end_s <= spec.start_s:
        raise ConfigError(f"{where}.end_s = {spec.end_s} must be after start_s = {spec.start_s}")
    if spec.target == "sensor" and spec.signal not in SENSOR_FIELDS:
        raise ConfigError(f"{where}.signal = {spec.signal!r}: allowed {list(SENSOR_FIELDS)}")
    return spec


def config_from_mapping(data: Mapping[str, Any], base_dir: str | Path = ".") -> DaemonConfig:
    """Validated :class:`DaemonConfig` from a parsed TOML mapping."""
    allowed = set(_SECTIONS) | {"reference", "faults"}
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise ConfigError(f"unknown section(s) {unknown}; allowed: {sorted(allowed)}")
    kwargs: dict[str, Any] = {name: _build(cls, data.get(name, {}), name) for name, cls in _SECTIONS.items()}
    _check_safety(kwargs["safety"])
    if not kwargs["controller"].name:
        raise ConfigError("controller.name: required ('mpc', 'baseline' or 'package.module:Class')")
    reference = dict(data.get("reference", {"supply_temp_c": 20.0, "volume_flow_m3s": 0.03}))
    try:
        Reference.from_mapping(reference)
    except InvalidReference as exc:
        raise ConfigError(f"[reference]: {exc}") from None
    faults = data.get("faults", [])
    if not isinstance(faults, list):
        raise ConfigError("faults: expected an array of tables [[faults]]")
    api = kwargs["api"]
    if api.enabled and api.host not in ("127.0.0.1", "localhost", "::1") and not (api.token or api.token_env):
        raise ConfigError(f"api.host = {api.host!r} is not loopback: set api.token_env (or api.token) so "
                          "requests need a bearer token")
    return DaemonConfig(reference=reference, faults=[_build_fault(f, i) for i, f in enumerate(faults)],
                        base_dir=str(base_dir), **kwargs)


def load_config(path: str | Path) -> DaemonConfig:
    """Read and validate a TOML configuration file; relative paths in it are relative to the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return config_from_mapping(data, base_dir=path.parent)


def resolve(config: DaemonConfig, p: str) -> Path:
    """A path from the configuration, relative to the configuration file's directory."""
    q = Path(p)
    return q if q.is_absolute() else Path(config.base_dir) / q
