"""The controller I/O contract: the bottom layer every other package imports.

What crosses between a plant (simulated or real), a controller and the daemon:

* :class:`Command`     actuator commands (W, % of servo travel), one field per input;
* :class:`Measurement` one sample of the box's sensors, names and units of the measurement log;
* :class:`Reference`   what the comfort algorithm asks for, validated on construction;
* :class:`StepResult`  a controller step's command and statistics;
* :class:`Controller`  protocol: ``reset()``, ``step(measurement, reference)``;
* :class:`Plant`       protocol: ``apply(command)``, ``advance()``, ``read()``.

This module imports nothing from the rest of the project (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, Mapping, Protocol, runtime_checkable

import numpy as np

from .validation import InvalidValue, check_fields, finite_in

#: Actuator inputs in the order of every input vector (model, MPC, logs).
INPUTS = ("blower_power_w", "heater_cmd_w", "valve_a_pct", "valve_m_pct", "valve_f_pct", "valve_w_pct")


@dataclass
class Command:
    """Actuator command: blower and heater electric power (W), valve angles (% of servo travel)."""

    blower_power_w: float = 100.0
    heater_cmd_w: float = 0.0
    valve_a_pct: float = 50.0
    valve_m_pct: float = 100.0
    valve_f_pct: float = 100.0
    valve_w_pct: float = 100.0

    def vector(self) -> np.ndarray:
        """The command as an array in :data:`INPUTS` order."""
        return np.array([getattr(self, n) for n in INPUTS], float)

    @classmethod
    def from_vector(cls, v) -> "Command":
        return cls(**dict(zip(INPUTS, np.asarray(v, float).ravel().tolist())))  # tolist: the values as floats

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass
class Measurement:
    """One sample of the box's sensors (names and units of the measurement log, docs/model.md sec. 4).

    Optional signals are ``None`` when the box does not measure them.
    """

    time_s: float
    supply_temp_c: float
    volume_flow_m3s: float
    hvac_inlet_temp_c: float
    water_temp_c: float | None = None
    chiller_setpoint_c: float | None = None
    heater_power_w: float | None = None
    heater_outlet_temp_c: float | None = None
    cabin_temp_c: float | None = None
    cabin_rh_pct: float | None = None
    outlet_m_temp_c: float | None = None
    outlet_f_temp_c: float | None = None
    outlet_w_temp_c: float | None = None
    supply_rh_pct: float | None = None
    hvac_inlet_rh_pct: float | None = None

    def as_dict(self) -> dict[str, float | None]:
        return asdict(self)


#: Optional signals the thesis's box measures beyond what the controllers need (thesis sec. 2: cabin
#: temperature and humidity at the back of the cabin, a thermocouple at every outlet, humidity after the
#: box and before the blower). ``None`` when a box does not measure them.
EXTRA_SIGNALS = ("cabin_temp_c", "cabin_rh_pct", "outlet_m_temp_c", "outlet_f_temp_c", "outlet_w_temp_c",
                 "supply_rh_pct", "hvac_inlet_rh_pct")


#: Allowed ranges of each reference field (inclusive), SI units as in the names.
REFERENCE_RANGES = {
    "supply_temp_c": (5.0, 50.0),
    "volume_flow_m3s": (0.006, 0.06),
    "flow_m_m3s": (0.0, 0.06),
    "flow_f_m3s": (0.0, 0.06),
    "flow_w_m3s": (0.0, 0.06),
}
#: Largest allowed mismatch between the outlet flows' sum and the total (fraction of the total).
SPLIT_TOLERANCE = 0.1
_OUTLETS = ("flow_m_m3s", "flow_f_m3s", "flow_w_m3s")


class InvalidReference(InvalidValue):
    """A reference field is missing, malformed or out of range; the message names it."""


def _ref_field(lo: float, hi: float, optional: bool = False) -> Any:
    return field(default=None, metadata={"check": finite_in(lo, hi, optional=optional)}) if optional \
        else field(metadata={"check": finite_in(lo, hi)})


@dataclass(frozen=True)
class Reference:
    """Supply air temperature (degC), total volume flow and outlet flows m, f, w (m3/s).

    Outlet flows may be omitted (``None``): the split is then free and only the total is tracked.
    Construction validates every field and raises :class:`InvalidReference` naming the field and
    its allowed range.
    """

    supply_temp_c: float = _ref_field(*REFERENCE_RANGES["supply_temp_c"])
    volume_flow_m3s: float = _ref_field(*REFERENCE_RANGES["volume_flow_m3s"])
    flow_m_m3s: float | None = _ref_field(*REFERENCE_RANGES["flow_m_m3s"], optional=True)
    flow_f_m3s: float | None = _ref_field(*REFERENCE_RANGES["flow_f_m3s"], optional=True)
    flow_w_m3s: float | None = _ref_field(*REFERENCE_RANGES["flow_w_m3s"], optional=True)

    def __post_init__(self) -> None:
        check_fields(self, error=InvalidReference)
        split = self.split
        if split is None and any(getattr(self, n) is not None for n in _OUTLETS):
            raise InvalidReference("flow_m_m3s, flow_f_m3s, flow_w_m3s: give all three outlet flows or none")
        if split is not None:
            total = sum(split)
            if abs(total - self.volume_flow_m3s) > SPLIT_TOLERANCE * self.volume_flow_m3s:
                raise InvalidReference(
                    f"flow_m_m3s + flow_f_m3s + flow_w_m3s = {total:.5f} must be within "
                    f"{SPLIT_TOLERANCE:.0%} of volume_flow_m3s = {self.volume_flow_m3s:.5f}")

    @property
    def split(self) -> tuple[float, float, float] | None:
        """Outlet flows (m, f, w) or ``None`` when the split is free."""
        vals = (self.flow_m_m3s, self.flow_f_m3s, self.flow_w_m3s)  # _OUTLETS
        return None if vals[0] is None or vals[1] is None or vals[2] is None else vals  # type: ignore[return-value]

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> "Reference":
        """Build from a mapping (e.g. parsed JSON); unknown or missing keys raise a clear error."""
        if not isinstance(data, Mapping):
            raise InvalidReference(f"reference must be an object with fields {list(REFERENCE_RANGES)}")
        unknown = sorted(set(data) - set(REFERENCE_RANGES))
        if unknown:
            raise InvalidReference(f"unknown field(s) {unknown}; allowed: {list(REFERENCE_RANGES)}")
        for required in ("supply_temp_c", "volume_flow_m3s"):
            if required not in data:
                lo, hi = REFERENCE_RANGES[required]
                raise InvalidReference(f"{required}: required, a number in [{lo}, {hi}]")
        return cls(**dict(data))

    @classmethod
    def from_split(cls, supply_temp_c: float, volume_flow_m3s: float,
                   shares: tuple[float, float, float]) -> "Reference":
        """Reference from a total flow and outlet shares (normalised to sum to one)."""
        total = sum(shares)
        m, f, w = (volume_flow_m3s * s / total for s in shares)
        return cls(supply_temp_c, volume_flow_m3s, m, f, w)


@dataclass
class StepResult:
    """What a control step returns: the command and its statistics.

    ``stats`` keys used across controllers: ``step_time_s`` (wall time of the step),
    ``iterations`` (solver iterations, 0 for the baseline), ``status`` (solver status text),
    ``fallback`` (``None`` or the name of the fallback used), ``mode`` (e.g. "cooling").
    """

    command: Command
    stats: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Controller(Protocol):
    """Measurement and reference in, actuator command out, once per sample of ``dt_s`` seconds."""

    dt_s: float

    def step(self, measurement: Measurement, reference: Reference) -> StepResult: ...

    def reset(self) -> None: ...


@runtime_checkable
class Plant(Protocol):
    """A box, simulated or real: the interface the benchmark and the daemon's backends drive.

    ``apply`` sets the actuators (the plant clips to its ranges), ``advance`` moves one sample of
    ``dt_s`` seconds on, ``read`` returns the sensors.
    """

    dt_s: float

    def apply(self, command: Command) -> Any: ...

    def advance(self) -> None: ...

    def read(self) -> Measurement: ...


def reference_fields() -> tuple[str, ...]:
    """Names of the reference fields, in order."""
    return tuple(f.name for f in fields(Reference))
