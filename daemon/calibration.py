"""Actuator and sensor calibration: engineering values <-> the raw signals of the devices.

The daemon computes in engineering units (W, % of servo travel); the box's devices take raw
signals: servo PPM duty cycles (thesis table 1), a 0-5 V analogue input to the heater's power
controller (thesis sec. 4.3), a PWM duty cycle for the blower's power controller (thesis
sec. 2.2). A calibration file (TOML) maps one to the other, per signal, as a straight line or a
table (piecewise linear, strictly monotone both ways; a falling raw column is a servo mounted
the other way round). Sensors map the other way, raw reading -> unit. The format and the shipped
thesis calibration (``thesis_calibration.toml``) are described in docs/fieldbus.md::

    [actuators.valve_w_pct]
    signal = "servo_duty"      # servo_duty, pwm_duty, voltage_v, current_ma
    open = 0.06                # raw signal at 100 % (thesis table 1)
    closed = 0.1               # raw signal at 0 %

    [actuators.heater_cmd_w]
    signal = "voltage_v"
    eng = [0.0, 240.0]         # W
    raw = [0.0, 5.0]           # V

    [sensors.volume_flow_m3s]
    signal = "voltage_v"
    raw = [0.0, 10.0]          # V
    eng = [0.0, 0.1]           # m3/s

Validation (pydantic, :mod:`hvac_mpc.validation`): a table that is not strictly monotone, raw
ends outside the signal's device range, an actuator table that does not cover the actuator's
command range, an unknown signal or name: refused with the field named.

On the fieldbus a raw signal travels as an integer count of its signal's resolution
(:data:`SIGNALS`), e.g. a servo duty cycle in 1e-5 steps.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import fields
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hvac_mpc.contract import INPUTS, Command, Measurement
from hvac_mpc.validation import InvalidValue, describe_error

#: Raw signal kinds: (device range lo, hi; resolution of one fieldbus count; unit). The ranges are
#: what the output/input stage can produce: servo pulses 0.5-2.5 ms in a 20 ms frame
#: (ASSUMPTION: the usual RC-servo range, thesis table 1 lies inside it), PWM 0-100 %, the heater
#: power controller's 0-5 V input (thesis sec. 4.3) on a 0-10 V output stage, 0-20 mA current loops.
SIGNALS: dict[str, tuple[float, float, float, str]] = {
    "servo_duty": (0.025, 0.125, 1e-5, "PPM duty cycle"),
    "pwm_duty": (0.0, 1.0, 1e-4, "PWM duty cycle"),
    "voltage_v": (0.0, 10.0, 1e-3, "V"),
    "current_ma": (0.0, 20.0, 1e-3, "mA"),
}

#: Command range every actuator table must cover (docs/model.md: model input bounds).
ACTUATOR_RANGES = {"blower_power_w": (30.0, 300.0), "heater_cmd_w": (0.0, 240.0), "valve_a_pct": (0.0, 100.0),
                   "valve_m_pct": (0.0, 100.0), "valve_f_pct": (0.0, 100.0), "valve_w_pct": (0.0, 100.0)}

SENSOR_NAMES = tuple(f.name for f in fields(Measurement) if f.name != "time_s")

DEFAULT_FILE = "thesis_calibration.toml"


class CalibrationError(InvalidValue):
    """The calibration file is invalid; the message names the field."""


class SignalMap(BaseModel):
    """One signal's map: ``eng[i] <-> raw[i]``, linear between points. ``open``/``closed`` are the
    servo shorthand for ``eng = [0, 100]``, ``raw = [closed, open]``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    signal: Literal["servo_duty", "pwm_duty", "voltage_v", "current_ma"]
    eng: list[float] = Field(default_factory=list, description="engineering values, strictly increasing")
    raw: list[float] = Field(default_factory=list, description="raw signals, strictly monotone")
    open: float | None = Field(None, description="servo: raw signal at 100 % (open)")
    closed: float | None = Field(None, description="servo: raw signal at 0 % (closed)")
    device_range: tuple[float, float] | None = Field(None, description="raw range of the device; "
                                                                       "default from the signal kind")
    source: str = Field("", description="where the values come from (thesis reference or ASSUMPTION)")

    @model_validator(mode="before")
    @classmethod
    def _servo_ends(cls, data: Any) -> Any:
        if isinstance(data, dict) and ("open" in data or "closed" in data):
            if "eng" in data or "raw" in data:
                raise ValueError("give either open/closed or eng/raw, not both")
            if "open" not in data or "closed" not in data:
                raise ValueError("open and closed go together (raw signal at 100 % and at 0 %)")
            data = {**data, "eng": [0.0, 100.0], "raw": [data["closed"], data["open"]]}
        return data

    @field_validator("eng", "raw")
    @classmethod
    def _finite(cls, v: list[float]) -> list[float]:
        if len(v) < 2:
            raise ValueError(f"at least two points needed, got {len(v)}")
        if not all(math.isfinite(x) for x in v):
            raise ValueError(f"every value must be finite, got {v}")
        return v

    @field_validator("eng")
    @classmethod
    def _increasing(cls, v: list[float]) -> list[float]:
        if any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError(f"not strictly increasing: {v}")
        return v

    @field_validator("raw")
    @classmethod
    def _monotone(cls, v: list[float]) -> list[float]:
        d = np.diff(v)
        if not (np.all(d > 0) or np.all(d < 0)):
            raise ValueError(f"not strictly monotone: {v}")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> "SignalMap":
        if len(self.eng) != len(self.raw):
            raise ValueError(f"eng has {len(self.eng)} points, raw {len(self.raw)}: they must pair up")
        lo, hi = self.range
        if not lo < hi:
            raise ValueError(f"device_range: expected [lo, hi] with lo < hi, got {list(self.range)}")
        if not SIGNALS[self.signal][0] <= lo or not hi <= SIGNALS[self.signal][1]:
            raise ValueError(f"device_range {list(self.range)} exceeds the {self.signal} stage's "
                             f"[{SIGNALS[self.signal][0]}, {SIGNALS[self.signal][1]}]")
        bad = [x for x in self.raw if not lo <= x <= hi]
        if bad:
            raise ValueError(f"raw {bad} outside the device's range [{lo}, {hi}] {SIGNALS[self.signal][3]}")
        return self

    @property
    def range(self) -> tuple[float, float]:
        return self.device_range or SIGNALS[self.signal][:2]

    @property
    def count_s(self) -> float:
        """The raw value of one fieldbus count."""
        return SIGNALS[self.signal][2]

    @property
    def reversed(self) -> bool:
        """True when the raw signal falls as the engineering value rises."""
        return self.raw[-1] < self.raw[0]

    def to_raw(self, eng: float) -> float:
        """Raw signal of an engineering value (clipped to the table's ends)."""
        return float(np.interp(eng, self.eng, self.raw))

    def to_eng(self, raw: float) -> float:
        """Engineering value of a raw signal (clipped to the table's ends)."""
        r, e = (self.raw[::-1], self.eng[::-1]) if self.reversed else (self.raw, self.eng)
        return float(np.interp(raw, r, e))

    def to_count(self, eng: float) -> int:
        """Fieldbus count of an engineering value (a non-negative integer)."""
        return int(round(self.to_raw(eng) / self.count_s))

    def from_count(self, count: int) -> float:
        return self.to_eng(count * self.count_s)

    def eng_per_count(self, eng: float) -> float:
        """Engineering value of one count at ``eng`` (the local slope times the resolution)."""
        i = int(np.clip(np.searchsorted(self.eng, eng, side="right") - 1, 0, len(self.eng) - 2))
        return abs((self.eng[i + 1] - self.eng[i]) / (self.raw[i + 1] - self.raw[i])) * self.count_s


class Calibration(BaseModel):
    """All maps of one box: every actuator (required), sensors (optional; a sensor without a map
    is reported in its unit by the device)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    description: str = ""
    actuators: dict[str, SignalMap]
    sensors: dict[str, SignalMap] = Field(default_factory=dict)

    @field_validator("actuators")
    @classmethod
    def _all_actuators(cls, v: dict[str, SignalMap]) -> dict[str, SignalMap]:
        _only_known(v, INPUTS, "actuator")
        missing = [n for n in INPUTS if n not in v]
        if missing:
            raise ValueError(f"missing actuator(s) {missing}: every actuator needs a map")
        for name, m in v.items():
            lo, hi = ACTUATOR_RANGES[name]
            if m.eng[0] > lo or m.eng[-1] < hi:
                raise ValueError(f"{name}.eng [{m.eng[0]}, {m.eng[-1]}] does not cover the command range "
                                 f"[{lo}, {hi}]")
        return v

    @field_validator("sensors")
    @classmethod
    def _known_sensors(cls, v: dict[str, SignalMap]) -> dict[str, SignalMap]:
        _only_known(v, SENSOR_NAMES, "sensor")
        return v

    # ---------------------------------------------------------------- commands
    def command_counts(self, cmd: Command) -> list[int]:
        """Fieldbus counts of a command's raw signals, in :data:`INPUTS` order."""
        out = []
        for name in INPUTS:
            v = getattr(cmd, name)
            if not math.isfinite(v):
                raise ValueError(f"{name}: command must be finite, got {v!r}")
            out.append(self.actuators[name].to_count(v))
        return out

    def command_from_counts(self, counts: list[int]) -> Command:
        """The command the device decodes from the counts (device side)."""
        return Command(**{n: self.actuators[n].from_count(int(c)) for n, c in zip(INPUTS, counts)})

    def command_raw(self, cmd: Command) -> dict[str, float]:
        """Raw signal per actuator (OPC UA carries them as numbers)."""
        return {n: self.actuators[n].to_raw(getattr(cmd, n)) for n in INPUTS}

    def command_from_raw(self, raw: dict[str, float]) -> Command:
        return Command(**{n: self.actuators[n].to_eng(float(raw[n])) for n in INPUTS})

    # ---------------------------------------------------------------- sensors
    def sensor_to_eng(self, name: str, raw: float | None) -> float | None:
        """A sensor's reading in its unit; None and NaN pass through; beyond the table the end
        segments extend linearly, so an over-range reading stays implausible."""
        return self._sensor(name, raw, to_eng=True)

    def sensor_to_raw(self, name: str, eng: float | None) -> float | None:
        """Device side: the raw reading a sensor gives for a value in its unit."""
        return self._sensor(name, eng, to_eng=False)

    def _sensor(self, name: str, value: float | None, to_eng: bool) -> float | None:
        m = self.sensors.get(name)
        if m is None or value is None or not math.isfinite(value):
            return value
        return _extrapolated(value, m.raw, m.eng) if to_eng else _extrapolated(value, m.eng, m.raw)


def _only_known(names, allowed: tuple[str, ...], what: str) -> None:
    unknown = sorted(set(names) - set(allowed))
    if unknown:
        raise ValueError(f"unknown {what}(s) {unknown}; allowed: {list(allowed)}")


def _extrapolated(x: float, xs: list[float], ys: list[float]) -> float:
    if xs[-1] < xs[0]:
        xs, ys = xs[::-1], ys[::-1]
    if x < xs[0]:
        return ys[0] + (x - xs[0]) * (ys[1] - ys[0]) / (xs[1] - xs[0])
    if x > xs[-1]:
        return ys[-1] + (x - xs[-1]) * (ys[-1] - ys[-2]) / (xs[-1] - xs[-2])
    return float(np.interp(x, xs, ys))


def calibration_from_mapping(data: Any, where: str = "calibration") -> Calibration:
    """A validated :class:`Calibration`; :class:`CalibrationError` names the field otherwise."""
    try:
        return Calibration.model_validate(data)
    except ValidationError as exc:
        raise CalibrationError(f"{where}: {describe_error(exc)}") from None


def load_calibration(path: str | Path | None = None) -> Calibration:
    """Read a calibration file (TOML); None or "" = the shipped thesis calibration."""
    if not path:
        text = resources.files("hvac_mpc.daemon").joinpath(DEFAULT_FILE).read_text()
        return calibration_from_mapping(tomllib.loads(text), DEFAULT_FILE)
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{p}: no such calibration file") from None
    except (IsADirectoryError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{p}: not a readable text file ({exc.__class__.__name__})") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{p}: not valid TOML ({exc})") from None
    return calibration_from_mapping(data, str(p))


class CalibrationConfig(BaseModel):
    """``[calibration]``: the file used when a fieldbus backend is set to raw signals."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    file: str = Field("", description="calibration file (TOML, relative to the configuration); "
                                      "'' = the shipped thesis calibration (thesis table 1)")

    def load(self, base_dir: Path) -> Calibration:
        """The calibration in force: the file (relative to ``base_dir``) or the thesis's."""
        return load_calibration(base_dir / self.file if self.file else None)

    def check(self, base_dir: Path, error: type[Exception] = CalibrationError) -> None:
        """Raise ``error`` naming the file and field when the calibration is invalid."""
        try:
            self.load(base_dir)
        except CalibrationError as exc:
            raise error(f"calibration.file: {exc}") from None
