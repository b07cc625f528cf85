"""Operator modes of the daemon and what the operator may send: validated, rate-limited, logged.

Modes (switched at runtime through the authenticated API, ``PUT /mode``, or ``hvac-mpc ctl mode``):

* ``auto-mpc``  the MPC (registered controller ``mpc``), with the configured fallbacks;
* ``auto-pid``  the thesis baseline (registered controller ``baseline``);
* ``auto``      the configured controller when it is neither of these (a registered plug-in);
* ``manual``    the operator sets the actuators (``PUT /manual``, ``hvac-mpc ctl set``);
* ``safe-stop`` heater off, blower at the safe power, outlets open, until another mode is chosen.

Bumpless transfer: the controller switched in is reset with the command in force (the baseline
presets its integrators from it, the MPC starts its rate limits and warm start from it and its
estimator from the next measurement), and for ``safety.transfer_s`` after the switch every
actuator is rate-limited (``safety.rate_*``) from the command in force. The reference may have
changed while the box was in another mode, so the controller switched in does not get it at once:
its working reference starts at the readings of the switch (supply temperature, volume flow) and
ramps to the reference in force at ``safety.transfer_ramp_c_per_s`` and
``transfer_ramp_m3s_per_s`` (:class:`ReferenceRamp`; docs/real-box.md, operator modes). In manual
mode the operator's setting is approached at the same actuator rates. The interlock and every
safety bound act in every mode; a manual heater command the interlock would refuse is refused at
once with the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal, Mapping

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hvac_mpc.contract import INPUTS, REFERENCE_RANGES, Command, Measurement, Reference
from hvac_mpc.validation import describe_error

from .config import SafetyConfig
from .safety import ACTUATOR_RANGES

MODES = ("auto-mpc", "auto-pid", "auto", "manual", "safe-stop")
#: The registered controller each automatic mode runs ("auto": the configured one).
AUTO_CONTROLLERS = {"auto-mpc": "mpc", "auto-pid": "baseline"}


class ModeError(ValueError):
    """A mode request or manual command that is refused; the message says why."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


def initial_mode(controller: str) -> str:
    """The mode a configured controller runs in."""
    return next((m for m, c in AUTO_CONTROLLERS.items() if c == controller), "auto")


class ModeRequest(BaseModel):
    """Body of ``PUT /mode``."""

    model_config = ConfigDict(strict=True, extra="forbid")
    mode: Literal[MODES]  # type: ignore[valid-type]


def _actuator_field(name: str) -> Any:
    lo, hi = ACTUATOR_RANGES[name]
    return Field(None, ge=lo, le=hi, allow_inf_nan=False, description=f"{name} in [{lo}, {hi}]")


class ManualCommand(BaseModel):
    """Body of ``PUT /manual``: any subset of the actuators, each in its range (docs/model.md sec. 2)."""

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False)
    blower_power_w: float | None = _actuator_field("blower_power_w")
    heater_cmd_w: float | None = _actuator_field("heater_cmd_w")
    valve_a_pct: float | None = _actuator_field("valve_a_pct")
    valve_m_pct: float | None = _actuator_field("valve_m_pct")
    valve_f_pct: float | None = _actuator_field("valve_f_pct")
    valve_w_pct: float | None = _actuator_field("valve_w_pct")


def parse_mode(data: Any) -> str:
    try:
        return ModeRequest.model_validate(data).mode
    except ValidationError as exc:
        raise ModeError(f"invalid mode request: {describe_error(exc)}; allowed modes: {list(MODES)}") from None


def parse_manual(data: Any, heater_max_w: float) -> dict[str, float]:
    """The actuators set by a manual command (validated; the heater also against ``heater_max_w``)."""
    try:
        values = {k: v for k, v in ManualCommand.model_validate(data).model_dump().items() if v is not None}
    except ValidationError as exc:
        ranges = ", ".join(f"{k} in [{lo}, {hi}]" for k, (lo, hi) in ACTUATOR_RANGES.items())
        raise ModeError(f"invalid manual command: {describe_error(exc)}; allowed: {ranges}") from None
    if not values:
        raise ModeError(f"manual command sets nothing; fields: {list(INPUTS)}")
    if values.get("heater_cmd_w", 0.0) > heater_max_w:
        raise ModeError(f"heater_cmd_w = {values['heater_cmd_w']} is above safety.heater_max_w = {heater_max_w}")
    return values


def heater_refusal(heater_w: float, sample: Mapping[str, Any] | None, safety: SafetyConfig) -> str | None:
    """Why a manual heater command of ``heater_w`` must be refused now (None: accepted).

    The interlock's own conditions on the latest sample: a valid measured flow at least
    ``min_flow_m3s + flow_hysteresis_m3s``, no interlock reason in force, the backend connected."""
    if heater_w <= 0.0:
        return None
    if sample is None or not sample.get("connected", False):
        return "heater refused: no measurement (backend not connected)"
    flow = sample.get("volume_flow_m3s")
    need = safety.min_flow_m3s + safety.flow_hysteresis_m3s
    if flow is None or "volume_flow_m3s" in (sample.get("sensor_faults") or {}):
        return "heater refused: the volume flow is not measured validly"
    if flow < need:
        return (f"heater refused: measured volume flow {flow:.4f} m3/s is below safety.min_flow_m3s + "
                f"flow_hysteresis_m3s = {need:.4f} m3/s (raise the blower or open the outlets first)")
    reasons = [r for r in (sample.get("interlock") or []) if r != "flow_low"]
    if reasons:
        return f"heater refused: interlock active ({', '.join(reasons)})"
    return None


def rate_limited(target: Command, previous: Command, safety: SafetyConfig, dt_s: float) -> Command:
    """``target`` with each actuator moved at most its rate limit over ``dt_s`` from ``previous``."""
    rates = {"blower_power_w": safety.rate_blower_w_per_s, "heater_cmd_w": safety.rate_heater_w_per_s}
    out = {}
    for name in INPUTS:
        step = rates.get(name, safety.rate_valve_pct_per_s) * dt_s
        prev, want = getattr(previous, name), getattr(target, name)
        out[name] = min(max(want, prev - step), prev + step)
    return Command(**out)


@dataclass(frozen=True)
class ModeChange:
    """One entry of the mode history: when (UTC and daemon time), from, to, and which client asked."""

    utc: str
    time_s: float
    old: str
    new: str
    client: str

    def as_dict(self) -> dict[str, Any]:
        return {"utc": self.utc, "time_s": self.time_s, "from": self.old, "to": self.new, "client": self.client}


def _toward(value: float, target: float, step: float) -> float:
    return min(max(target, value - step), value + step)


class ReferenceRamp:
    """The working reference of a controller switched in (setpoint tracking with a ramp).

    ``arm()`` at a switch into an automatic mode; the next ``working()`` starts the ramp at that
    sample's readings (supply temperature and volume flow, clipped to the reference ranges) and
    each call moves it towards the reference in force by at most ``rate * dt_s``, the outlet
    flows in the target's shares of the working total. When it has reached the target the ramp
    ends and the target passes through unchanged. A rate of 0 switches the ramp off (the
    reference in force at once)."""

    def __init__(self, rate_c_per_s: float, rate_m3s_per_s: float):
        self.rate_c_per_s = float(rate_c_per_s)
        self.rate_m3s_per_s = float(rate_m3s_per_s)
        self._armed = False
        self._temp_c: float | None = None
        self._flow_m3s: float | None = None

    @property
    def active(self) -> bool:
        return self._temp_c is not None

    def arm(self) -> None:
        """A switch into an automatic mode: the next working reference starts at the readings."""
        self._armed = self.rate_c_per_s > 0.0 or self.rate_m3s_per_s > 0.0
        self._temp_c = self._flow_m3s = None

    def cancel(self) -> None:
        """Leave the ramp (a switch to manual or safe-stop)."""
        self._armed = False
        self._temp_c = self._flow_m3s = None

    def working(self, m: Measurement, target: Reference, dt_s: float) -> Reference:
        """The reference the controller gets this sample (``target`` once the ramp has ended)."""
        if self._armed:
            self._armed = False
            self._temp_c = _start(m.supply_temp_c, target.supply_temp_c, "supply_temp_c", self.rate_c_per_s)
            self._flow_m3s = _start(m.volume_flow_m3s, target.volume_flow_m3s, "volume_flow_m3s",
                                    self.rate_m3s_per_s)
            step_c = step_f = 0.0  # the first sample holds the readings of the switch
        else:
            step_c, step_f = self.rate_c_per_s * dt_s, self.rate_m3s_per_s * dt_s
        if self._temp_c is None or self._flow_m3s is None:
            return target
        self._temp_c = _toward(self._temp_c, target.supply_temp_c, step_c)
        self._flow_m3s = _toward(self._flow_m3s, target.volume_flow_m3s, step_f)
        if self._temp_c == target.supply_temp_c and self._flow_m3s == target.volume_flow_m3s:
            self._temp_c = self._flow_m3s = None
            return target
        split = target.split
        if split is None:
            return replace(target, supply_temp_c=self._temp_c, volume_flow_m3s=self._flow_m3s)
        return Reference.from_split(self._temp_c, self._flow_m3s, split)

    def status(self) -> dict[str, Any] | None:
        """The working values while the ramp runs (None otherwise)."""
        if self._temp_c is None:
            return None
        return {"supply_temp_c": self._temp_c, "volume_flow_m3s": self._flow_m3s}


def _start(reading: float | None, target: float, name: str, rate: float) -> float:
    """Where a ramp starts: the reading (in the reference's range), or the target without a ramp."""
    if rate <= 0.0 or reading is None or not math.isfinite(reading):
        return target
    lo, hi = REFERENCE_RANGES[name]
    return min(max(float(reading), lo), hi)
