"""The safety layer applied after any controller: sensor checks, heater interlock, safe commands.

Nothing here depends on the optimiser. The interlock follows OEM practice for PTC heaters
(heater only with the blower running and its temperature in bounds, fail-safe on lost signals;
docs/real-box.md, safety):

* heater command in [0, ``heater_max_w``] (240 W, thesis sec. 2.3), never NaN;
* heater 0 when the measured volume flow is below ``min_flow_m3s`` (with hysteresis), when an
  interlock sensor is invalid (NaN, missing, out of range, stuck, stale), when the heater outlet
  air is too hot (latched until it falls below the reset temperature), when the estimated heater
  body temperature exceeds its limit, or when the backend is lost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from hvac_mpc.models import bypass
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.contract import Command, Measurement

from .config import SENSOR_FIELDS, SafetyConfig

ACTUATOR_RANGES = {"blower_power_w": (30.0, 300.0), "heater_cmd_w": (0.0, 240.0), "valve_a_pct": (0.0, 100.0),
                   "valve_m_pct": (0.0, 100.0), "valve_f_pct": (0.0, 100.0), "valve_w_pct": (0.0, 100.0)}

#: The estimated heater body temperature must fall this far below its limit to re-enable the heater.
BODY_RESET_BAND_C = 10.0


def safe_command(cfg: SafetyConfig, blower_w: float | None = None) -> Command:
    """Heater off, blower running, all outlets open, valve a at its safe position (default: all air
    through the heater so the blower carries its heat away)."""
    return Command(blower_power_w=cfg.safe_blower_w if blower_w is None else blower_w, heater_cmd_w=0.0,
                   valve_a_pct=cfg.safe_valve_a_pct, valve_m_pct=100.0, valve_f_pct=100.0, valve_w_pct=100.0)


def is_finite_command(cmd: Command) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in cmd.as_dict().values())


def clip_command(cmd: Command, heater_max_w: float) -> Command:
    """Clip every actuator to its range (docs/model.md sec. 2); the heater to ``heater_max_w``."""
    out = {}
    for name, value in cmd.as_dict().items():
        lo, hi = ACTUATOR_RANGES[name]
        if name == "heater_cmd_w":
            hi = min(hi, heater_max_w)
        out[name] = min(max(float(value), lo), hi)
    return Command(**out)


@dataclass
class SensorStatus:
    """Result of one sensor check: the fault kind of each faulty field (empty when all valid)."""

    faults: dict[str, str] = field(default_factory=dict)
    stale: bool = False

    def valid(self, name: str) -> bool:
        return not self.stale and name not in self.faults

    def all_valid(self, names) -> bool:
        return all(self.valid(n) for n in names)


class SensorMonitor:
    """Flags each reading as NaN, missing, out of range or stuck, and the sample as stale.

    ``stuck``: the same reading ``stuck_samples`` times in a row on a noisy analogue sensor.
    ``stale``: the measurement time has not advanced for ``stale_samples`` reads.
    """

    def __init__(self, cfg: SafetyConfig):
        self.cfg = cfg
        self._last: dict[str, float] = {}
        self._repeats: dict[str, int] = {}
        self._last_time: float | None = None
        self._same_time = 0

    def reset(self) -> None:
        self._last.clear()
        self._repeats.clear()
        self._last_time = None
        self._same_time = 0

    def check(self, m: Measurement) -> SensorStatus:
        status = SensorStatus()
        for name in SENSOR_FIELDS:
            value = getattr(m, name)
            kind = self._classify(name, value)
            if kind:
                status.faults[name] = kind
        t = m.time_s
        if t is None or not isinstance(t, (int, float)) or not math.isfinite(t):
            self._same_time += 1
        elif self._last_time is not None and t <= self._last_time:
            self._same_time += 1
        else:
            self._same_time = 0
            self._last_time = float(t)
        status.stale = self._same_time >= self.cfg.stale_samples
        return status

    def _classify(self, name: str, value) -> str | None:
        if value is None:
            self._repeats.pop(name, None)
            return "missing"
        if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
            self._repeats.pop(name, None)
            return "nan"
        lo, hi = self.cfg.sensor_ranges.get(name, (-math.inf, math.inf))
        if not (math.isfinite(value) and lo <= value <= hi):
            self._repeats.pop(name, None)
            return "out_of_range"
        if self.cfg.stuck_samples and name in self.cfg.stuck_sensors:
            n = self._repeats.get(name, 0) + 1 if self._last.get(name) == value else 1
            self._repeats[name] = n
            self._last[name] = value
            if n >= self.cfg.stuck_samples:
                return "stuck"
        return None


class HeaterEstimator:
    """Conservative heater body temperature (degC) from the thesis heater model (sec. 4.3).

    dT_h/dt = (k_p P - kA (T_h - T_ah)) / (m_h c_h) with the algebraic air node
    T_ah = (kA T_h + m c_pa T_in) / (kA + m c_pa). The heater's inlet air T_in is not measured;
    an upper bound stands in: max(inlet air, chiller water) + the motor heating maximum
    (the cooler core can only pull air towards the water temperature). Only the air crossing
    the core (1 - b(a) of the measured flow) cools the heater. Without a valid flow the air
    carries nothing away, so the estimate never cools then.
    """

    def __init__(self, params: Parameters, initial_c: float = 25.0):
        self.p = params
        self.temp_c = float(initial_c)
        self.air_in_bound_c = float(initial_c)

    def inlet_bound_c(self, m: Measurement, status: SensorStatus) -> float:
        cands = [getattr(m, n) for n in ("hvac_inlet_temp_c", "water_temp_c") if status.valid(n)]
        base = max(cands) if cands else self.air_in_bound_c
        return base + self.p.motor_gain_max_c

    def core_fraction(self, valve_a_pct: float, mass_flow_kgs: float) -> float:
        """Share of the air crossing core and heater: 1 - b(a), with b raised by the flow-dependent
        bypass where that makes it larger (models/bypass.py; the smaller share is the safe side)."""
        b = float(bypass.bypass_fraction(min(max(valve_a_pct, 0.0), 100.0), self.p))
        b_flow = float(bypass.flow_dependent_bypass(b, mass_flow_kgs, self.p))
        return 1.0 - max(b, b_flow)

    def update(self, dt_s: float, power_w: float, flow_m3s: float | None, air_in_c: float,
               valve_a_pct: float = 100.0) -> float:
        """Advance the estimate by ``dt_s`` with heater power ``power_w`` and measured total flow
        ``flow_m3s`` (None: unknown, nothing carried away), valve a at ``valve_a_pct``."""
        p = self.p
        self.air_in_bound_c = air_in_c
        flow = max(flow_m3s, 0.0) if flow_m3s is not None and math.isfinite(flow_m3s) else 0.0
        rho = p.rho_slope_kgm3_per_c * air_in_c + p.rho_offset_kgm3
        mass = flow * rho
        g = mass * self.core_fraction(valve_a_pct, mass) * p.cp_air_j_per_kgk
        cap = p.heater_mass_kg * p.heater_c_j_per_kgk
        ka = p.heater_ka_w_per_k
        # exact step of the linear ODE for constant inputs over dt (stable for any dt)
        k_eff = ka * g / (ka + g) if g > 0 else 0.0
        drive = p.heater_kp * max(power_w, 0.0)
        if k_eff > 0:
            t_inf = air_in_c + drive / k_eff
            self.temp_c = t_inf + (self.temp_c - t_inf) * math.exp(-k_eff * dt_s / cap)
        else:
            self.temp_c += drive * dt_s / cap
        # the PTC draws no power above ~165 C (thesis sec. 2.3): the body cannot pass it
        self.temp_c = min(max(self.temp_c, air_in_c - 50.0), max(p.ptc_zero_c, air_in_c))
        return self.temp_c

    def initialise(self, m: Measurement, status: SensorStatus, power_w: float) -> float:
        """First estimate, on the hot side: the largest of the inlet bound, the body temperature
        implied by the measured heater outlet air (all measured air through the heater), and, if
        the heater draws power, its steady state with the least air valve a lets through; capped
        at the PTC self-limit (thesis sec. 2.3: ~165 C)."""
        p = self.p
        air_in = self.inlet_bound_c(m, status)
        self.air_in_bound_c = air_in
        cands = [air_in]
        flow = m.volume_flow_m3s if status.valid("volume_flow_m3s") else None
        if flow is not None and flow > 0 and status.valid("heater_outlet_temp_c"):
            g = flow * (p.rho_slope_kgm3_per_c * air_in + p.rho_offset_kgm3) * p.cp_air_j_per_kgk
            cands.append(air_in + (m.heater_outlet_temp_c - air_in) * (p.heater_ka_w_per_k + g) / p.heater_ka_w_per_k)
        if power_w > 0:
            if flow is None or flow <= 0:
                cands.append(p.ptc_zero_c)
            else:
                self.temp_c = air_in
                self.update(1e5, power_w, flow, air_in, valve_a_pct=0.0)
                cands.append(self.temp_c)
        self.temp_c = min(max(cands), p.ptc_zero_c)
        return self.temp_c

    def cooled(self, margin_c: float) -> bool:
        return self.temp_c <= self.air_in_bound_c + margin_c


class HeaterInterlock:
    """Forces the heater command to 0 for the reasons in the module docstring; counts trips."""

    def __init__(self, cfg: SafetyConfig, params: Parameters):
        self.cfg = cfg
        self.heater_max_w = min(cfg.heater_max_w, params.heater_power_max_w)
        self.heater_temp_max_c = cfg.heater_temp_max_c or params.heater_temp_max_c
        self._flow_ok = False
        self._outlet_tripped = False
        self._body_tripped = False
        self.trips: dict[str, int] = {}

    def apply(self, cmd: Command, m: Measurement | None, status: SensorStatus | None,
              heater_est_c: float, backend_ok: bool = True) -> tuple[Command, list[str]]:
        """The command with the heater forced off where needed, and the reasons (empty if none)."""
        reasons: list[str] = []
        if not is_finite_command(cmd):
            reasons.append("command_not_finite")
            cmd = safe_command(self.cfg)
        cmd = clip_command(cmd, self.heater_max_w)
        if not backend_ok or m is None or status is None:
            reasons.append("backend_lost")
        else:
            if status.stale:
                reasons.append("sensors_stale")
            bad = [n for n in self.cfg.interlock_sensors if n in status.faults]
            if bad:
                reasons.append("sensor_invalid")
            flow = m.volume_flow_m3s if status.valid("volume_flow_m3s") else None
            if flow is None:
                self._flow_ok = False
            elif flow < self.cfg.min_flow_m3s:
                self._flow_ok = False
            elif flow >= self.cfg.min_flow_m3s + self.cfg.flow_hysteresis_m3s:
                self._flow_ok = True
            if not self._flow_ok:
                reasons.append("flow_low")
            if status.valid("heater_outlet_temp_c"):
                t_out = m.heater_outlet_temp_c
                if t_out >= self.cfg.heater_outlet_max_c:
                    self._outlet_tripped = True
                elif t_out <= self.cfg.heater_outlet_reset_c:
                    self._outlet_tripped = False
            if self._outlet_tripped:
                reasons.append("outlet_too_hot")
        if heater_est_c >= self.heater_temp_max_c:
            self._body_tripped = True
        elif heater_est_c <= self.heater_temp_max_c - BODY_RESET_BAND_C:
            self._body_tripped = False
        if self._body_tripped:
            reasons.append("heater_too_hot")
        if reasons and cmd.heater_cmd_w != 0.0:
            cmd = replace(cmd, heater_cmd_w=0.0)
        for r in reasons:
            self.trips[r] = self.trips.get(r, 0) + 1
        return cmd, reasons
