"""The thesis baseline (thesis section 5): PI/PID loops, mode switching and the outlet-split feed-forward.

Loops, with the gains of thesis section 5 (docs/model.md sec. 3), discrete at the 1 s sample:

- total volume flow: PI on the blower, error in m3/h, output the power controller's 0-5 V
  input spanning 0-300 W (thesis sec. 5.1; the units are the ones under which the thesis gains
  make sense, docs/model.md 'traps').
- cooling (thesis sec. 5.4.1, thermocouple): PID with anti-windup on valve a (0-100 %),
  error = measured - reference, so more valve a = more air through the cooler = colder.
- heating (thesis sec. 5.4.2): PI with anti-windup on valve a, capped at 80 % (trapped hot air,
  fig. 47), and PI with anti-windup on the heater, 0-5 V spanning 0-240 W; error = reference -
  measured, so more valve a = more air through the heater = warmer.
- outlet split: the feed-forward optimisation of thesis sec. 5.2 (:mod:`.outlet_split`).

Anti-windup is the back-calculation of thesis sec. 5.4.1, u(k+1) = kp e(k) + sum_i [ki e(i) +
kaw (u_sat(i) - u(i))]. The thesis prints the correction as kaw (u(i) - u_sat(i)); with that
sign it would feed the excess back and wind up further, so it is read as the usual
back-calculation (the difference is written the other way round).

ASSUMPTIONS where the thesis is silent (each stated where it is used):
- mode switching rule (:func:`choose_mode`);
- derivative of the cooling PID on the measurement, not the error (no kick on reference steps);
- the volume-flow integral is clamped to the 0-5 V span (the thesis uses no anti-windup because
  its references stay reachable; here a reference may not be, and the controller is also the
  MPC's last-resort fallback);
- bumpless start and mode change (:meth:`BaselineController.track`, integrators preset);
- valve a in heating is a PI: the text calls it a PID but gives kp, ki and kaw only;
- the heater is off in cooling mode; the chiller set point is not an actuator of the baseline
  (in heating the water is expected near the inlet temperature, as in the thesis's tests);
- the loop errors are limited (``max_temp_error_c``, ``max_flow_error_m3h``) so that absurd but
  finite readings cannot overflow an integrator; a non-finite reading holds its loops' commands.
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass, field, replace

from hvac_mpc.models import valves
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.contract import Command, Measurement

from hvac_mpc.contract import StepResult
from .outlet_split import outlet_split
from hvac_mpc.contract import Reference

COOLING = "cooling"
HEATING = "heating"
M3S_TO_M3H = 3600.0


def _g(default, source: str):
    return field(default=default, metadata={"source": source})


@dataclass(frozen=True)
class BaselineGains:
    """Gains and limits of the thesis baseline; every field says where it comes from."""

    flow_kp_v_per_m3h: float = _g(0.006, "thesis sec. 5.1 (k_p,v, error in m3/h: docs/model.md 'traps')")
    flow_ki_v_per_m3h: float = _g(0.005, "thesis sec. 5.1 (k_i,v per 1 s sample)")
    blower_w_per_v: float = _g(60.0, "thesis sec. 2.1 and 5.1: 0-5 V input spans 0-300 W (docs/model.md 'traps')")
    cool_kp_pct_per_c: float = _g(7.0, "thesis sec. 5.4.1 (thermocouple PID)")
    cool_ki_pct_per_c: float = _g(1.0, "thesis sec. 5.4.1 (per 1 s sample)")
    cool_kd_pct_per_c: float = _g(2.0, "thesis sec. 5.4.1 (per 1 s sample)")
    cool_kaw: float = _g(1.0, "thesis sec. 5.4.1")
    heat_valve_kp_pct_per_c: float = _g(7.0, "thesis sec. 5.4.2 (valve a)")
    heat_valve_ki_pct_per_c: float = _g(0.5, "thesis sec. 5.4.2 (valve a, per 1 s sample)")
    heat_valve_kaw: float = _g(1.0, "thesis sec. 5.4.2 (valve a)")
    heat_valve_a_max_pct: float = _g(80.0, "thesis sec. 5.4.2 (cap against the trapped-air release)")
    heater_kp_v_per_c: float = _g(1.5, "thesis sec. 5.4.2 (k_p,h)")
    heater_ki_v_per_c: float = _g(0.05, "thesis sec. 5.4.2 (k_i,h per 1 s sample)")
    heater_kaw: float = _g(0.5, "thesis sec. 5.4.2")
    heater_w_per_v: float = _g(48.0, "thesis sec. 2.3 and 5.4.2: 0-5 V input spans 0-240 W (docs/model.md 'traps')")
    control_v_max: float = _g(5.0, "thesis sec. 5.1 and 5.4.2 (0-5 V analogue input of the power controllers)")
    mode_hysteresis_c: float = _g(0.5, "ASSUMPTION half-width of the mode switching band (thesis silent)")
    max_temp_error_c: float = _g(
        100.0, "ASSUMPTION limit on the temperature error fed to the loops (absurd finite readings)")
    max_flow_error_m3h: float = _g(
        720.0, "ASSUMPTION limit on the flow error fed to the PI (absurd finite readings)")

    @classmethod
    def slow_sensor(cls, **changes) -> "BaselineGains":
        """Cooling gains for the old slow sensor (tau_s = 100.4 s): PI with anti-windup, kp 3 %/C,
        ki 0.09 %/C, kaw 0.1 (thesis sec. 5.4.1, before the thermocouple); other gains as default."""
        return replace(cls(cool_kp_pct_per_c=3.0, cool_ki_pct_per_c=0.09, cool_kd_pct_per_c=0.0, cool_kaw=0.1),
                       **changes)

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"gain {name}: expected a finite number >= 0, got {value!r}")
        if not 0.0 < self.heat_valve_a_max_pct <= 100.0:
            raise ValueError(f"gain heat_valve_a_max_pct = {self.heat_valve_a_max_pct} is outside (0, 100] %")


class DiscretePid:
    """Discrete PI(D) with back-calculation anti-windup, gains per sample of ``dt_s`` = 1 s.

    u(k) = kp e(k) + I(k) + kd D(k),  I(k) = I(k-1) + ki e(k) dt + kaw (u_sat(k-1) - u(k-1)),
    D(k) = -(y(k) - y(k-1)) / dt (derivative on the measurement y). Gains keep their thesis
    meaning per second when ``dt_s`` differs from 1 s. With ``clamp_integral`` the integrator is
    also kept within [lo, hi] (for a loop without back-calculation). State is per instance.
    """

    def __init__(self, kp: float, ki: float, kaw: float, lo: float, hi: float, kd: float = 0.0,
                 dt_s: float = 1.0, clamp_integral: bool = False):
        self.kp, self.ki, self.kd, self.kaw = kp, ki, kd, kaw
        self.lo, self.hi = lo, hi
        self.dt_s = dt_s
        self.clamp_integral = clamp_integral
        self.reset()

    def reset(self, output: float | None = None) -> None:
        """Clear the state; with ``output`` the integrator is preset so the next output starts there."""
        self.integral = 0.0 if output is None else min(max(output, self.lo), self.hi)
        self._u = self._u_sat = self.integral
        self._y_prev: float | None = None

    def update(self, error: float, measurement: float | None = None) -> float:
        """One sample: the saturated output for an error (and, for the D-term, the measurement)."""
        integral = self.integral + self.ki * error * self.dt_s + self.kaw * (self._u_sat - self._u)
        if self.clamp_integral:
            integral = min(max(integral, self.lo), self.hi)
        d = 0.0
        if self.kd and measurement is not None and self._y_prev is not None:
            d = -(measurement - self._y_prev) / self.dt_s
        u = self.kp * error + integral + self.kd * d
        if not math.isfinite(u):  # cannot happen for bounded errors; never emit a non-finite command
            return self._u_sat
        self.integral = integral
        if self.kd and measurement is not None:
            self._y_prev = measurement
        self._u, self._u_sat = u, min(max(u, self.lo), self.hi)
        return self._u_sat


def warmest_cooling_supply_c(inlet_c: float, water_c: float, params: Parameters) -> float:
    """Warmest supply temperature the cooling mode can give (valve a closed, degC).

    Maximum bypass b_max; the rest crosses the cooler core (effectiveness form of the thesis
    sec. 4.2 fit). Motor heating is left out (a margin of up to ~2 C at full blower power).
    """
    cooled = inlet_c + params.cooler_slope * (water_c - inlet_c)
    return params.bypass_max * inlet_c + (1.0 - params.bypass_max) * cooled


def choose_mode(current: str | None, reference_c: float, inlet_c: float, water_c: float,
                params: Parameters, hysteresis_c: float) -> str:
    """Cooling or heating mode (ASSUMPTION: the thesis gives no switching rule).

    Heating when the reference lies above what the cooling path can deliver with valve a closed
    (:func:`warmest_cooling_supply_c`) by more than ``hysteresis_c``; back to cooling when it
    lies below that by more than ``hysteresis_c``; in between the mode is kept. Without a
    current mode the nearer side is taken.
    """
    warmest = warmest_cooling_supply_c(inlet_c, water_c, params)
    if current is None:
        return HEATING if reference_c > warmest else COOLING
    if current == COOLING and reference_c > warmest + hysteresis_c:
        return HEATING
    if current == HEATING and reference_c < warmest - hysteresis_c:
        return COOLING
    return current


def _finite(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _limit(value: float, bound: float) -> float:
    return min(max(value, -bound), bound)


class BaselineController:
    """The thesis controllers behind the project's step interface (:class:`~.controller.Controller`).

    ``step(measurement, reference)`` returns the command for the next sample. It does not raise
    on a finite measurement; a non-finite or missing reading holds the commands of the loops
    that need it (listed in ``stats['held']``, ``stats['status'] == 'held'``).
    """

    def __init__(self, params: Parameters | None = None, dt_s: float = 1.0, gains: BaselineGains | None = None):
        if not _finite(dt_s) or dt_s <= 0:
            raise ValueError(f"dt_s: expected a finite sample time > 0 s, got {dt_s!r}")
        self.params = params or Parameters()
        self.dt_s = float(dt_s)
        self.gains = gains or BaselineGains()
        self._coeffs = valves.curves(self.params)
        g = self.gains
        p_min_v = self.params.blower_power_min_w / g.blower_w_per_v
        p_max_v = self.params.blower_power_max_w / g.blower_w_per_v
        self._flow = DiscretePid(g.flow_kp_v_per_m3h, g.flow_ki_v_per_m3h, 0.0, max(p_min_v, 0.0),
                                 min(p_max_v, g.control_v_max), dt_s=self.dt_s, clamp_integral=True)
        self._cool = DiscretePid(g.cool_kp_pct_per_c, g.cool_ki_pct_per_c, g.cool_kaw, 0.0, 100.0,
                                 kd=g.cool_kd_pct_per_c, dt_s=self.dt_s)
        self._heat_valve = DiscretePid(g.heat_valve_kp_pct_per_c, g.heat_valve_ki_pct_per_c, g.heat_valve_kaw,
                                       0.0, g.heat_valve_a_max_pct, dt_s=self.dt_s)
        h_max_v = min(self.params.heater_power_max_w / g.heater_w_per_v, g.control_v_max)
        self._heater = DiscretePid(g.heater_kp_v_per_c, g.heater_ki_v_per_c, g.heater_kaw, 0.0, h_max_v,
                                   dt_s=self.dt_s)
        self.reset()

    # ------------------------------------------------------------------ interface
    def reset(self) -> None:
        """Forget all loop state: integrators, mode, last command."""
        for loop in (self._flow, self._cool, self._heat_valve, self._heater):
            loop.reset()
        self.mode: str | None = None
        self._last = Command()
        self._started = False

    def track(self, command: Command, mode: str | None = None) -> None:
        """Bumpless hand-over: preset the integrators so the loops continue from ``command``.

        For taking over from another controller (e.g. as the MPC's fallback). ASSUMPTION: the
        thesis starts its loops from rest.
        """
        for name, value in command.as_dict().items():
            if not _finite(value):
                raise ValueError(f"command.{name}: expected a finite number, got {value!r}")
        self._last = Command(**command.as_dict())
        self._flow.reset(command.blower_power_w / self.gains.blower_w_per_v)
        self._cool.reset(command.valve_a_pct)
        self._heat_valve.reset(command.valve_a_pct)
        self._heater.reset(command.heater_cmd_w / self.gains.heater_w_per_v)
        if mode is not None:
            if mode not in (COOLING, HEATING):
                raise ValueError(f"mode: expected {COOLING!r} or {HEATING!r}, got {mode!r}")
            self.mode = mode
        self._started = True

    def step(self, measurement: Measurement, reference: Reference) -> StepResult:
        """One sample: measurement and reference in, actuator command out (see module docstring)."""
        t0 = time.perf_counter()
        m, g = measurement, self.gains
        held: list[str] = []
        cmd = Command(**self._last.as_dict())
        flow_ok = _finite(getattr(m, "volume_flow_m3s", None))
        temp_ok = _finite(getattr(m, "supply_temp_c", None))
        inlet_ok = _finite(getattr(m, "hvac_inlet_temp_c", None))

        if not self._started:
            self._start(m, flow_ok)

        # --- mode (held when the inlet temperature is unknown)
        if inlet_ok:
            water = self._water_c(m)
            self._switch_mode(choose_mode(self.mode, reference.supply_temp_c, m.hvac_inlet_temp_c, water,
                                          self.params, self.gains.mode_hysteresis_c))
        else:
            held.append("hvac_inlet_temp_c")
            if self.mode is None:
                self.mode = COOLING

        # --- total volume flow PI (thesis sec. 5.1), error in m3/h, output 0-5 V -> 0-300 W
        if flow_ok:
            e_m3h = _limit((reference.volume_flow_m3s - m.volume_flow_m3s) * M3S_TO_M3H, g.max_flow_error_m3h)
            cmd.blower_power_w = self._flow.update(e_m3h) * self.gains.blower_w_per_v
        else:
            held.append("volume_flow_m3s")

        # --- temperature (thesis sec. 5.4)
        if temp_ok:
            # error limited to +-max_temp_error_c (absurd but finite readings cannot overflow a loop)
            y = reference.supply_temp_c + _limit(float(m.supply_temp_c) - reference.supply_temp_c,
                                                 g.max_temp_error_c)
            if self.mode == COOLING:
                cmd.valve_a_pct = self._cool.update(y - reference.supply_temp_c, measurement=-y)
                cmd.heater_cmd_w = 0.0
            else:
                e = reference.supply_temp_c - y
                cmd.valve_a_pct = self._heat_valve.update(e)
                cmd.heater_cmd_w = self._heater.update(e) * self.gains.heater_w_per_v
        else:
            held.append("supply_temp_c")

        # --- outlet split feed-forward (thesis sec. 5.2) on the measured total flow
        # (the reference total stands in for a missing or implausible reading)
        plausible = flow_ok and 1e-4 < m.volume_flow_m3s < 1.0
        total = float(m.volume_flow_m3s) if plausible else reference.volume_flow_m3s
        split_status = None
        try:
            split = outlet_split(total, reference.split, self.params, self._coeffs)
            cmd.valve_m_pct, cmd.valve_f_pct, cmd.valve_w_pct = split.angles_pct
            if not split.success:
                split_status = "outlet split optimisation did not converge; its best point is used"
        except (ValueError, ArithmeticError) as exc:  # last-resort controller: keep the last angles
            split_status = f"outlet split failed ({exc}); last valve angles held"

        self._last = cmd
        stats = {"step_time_s": time.perf_counter() - t0, "iterations": 0,
                 "status": "held" if held else "ok", "fallback": None, "mode": self.mode}
        if held:
            stats["held"] = held
        if split_status:
            stats["split_status"] = split_status
        return StepResult(Command(**cmd.as_dict()), stats)

    # ------------------------------------------------------------------ internals
    def _water_c(self, m: Measurement) -> float:
        """Water temperature for the mode rule: measured, else the chiller set point, else the inlet."""
        for value in (getattr(m, "water_temp_c", None), getattr(m, "chiller_setpoint_c", None)):
            if _finite(value):
                return float(value)
        return float(m.hvac_inlet_temp_c)

    def _start(self, m: Measurement, flow_ok: bool) -> None:
        """First sample: preset the flow integrator to the power the nominal blower curve gives for
        the measured flow (bumpless start; ASSUMPTION, docs/model.md sec. 1, blower curve)."""
        if flow_ok and m.volume_flow_m3s > 0:
            power_w = m.volume_flow_m3s / self.params.flow_per_watt_m3s_per_w
            self._flow.reset(power_w / self.gains.blower_w_per_v)
            self._last.blower_power_w = min(max(power_w, self.params.blower_power_min_w),
                                            self.params.blower_power_max_w)
        self._started = True

    def _switch_mode(self, new: str) -> None:
        """Change mode bumplessly: the new valve-a loop starts at the present valve a (ASSUMPTION)."""
        if new == self.mode:
            return
        if self.mode is not None:
            a = self._last.valve_a_pct
            if new == HEATING:
                self._heat_valve.reset(min(a, self.gains.heat_valve_a_max_pct))
                self._heater.reset(0.0)
            else:
                self._cool.reset(a)
        self.mode = new
