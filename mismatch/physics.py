"""Pure physics of the independent box: scalar functions of floats, SI units as in the names.

Written from the thesis (sections 2, 3.2, 4, 5) and docs/model.md only; nothing here comes from
``hvac_mpc.models``. Each update of a state is an exact solution over a sub-step with its inputs
frozen (first-order lags, ramps) or a linearised-implicit one (heater body with the PTC fall), so
any step length is stable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.interpolate import PchipInterpolator

from . import constants as k

# ================================================================= air, blower motor


def air_density(temp_c: float) -> float:
    """Air density (kg/m3) at ``temp_c`` (thesis 4: linear fit at 965 mbar, 60 % RH)."""
    return k.RHO_SLOPE * temp_c + k.RHO_OFFSET


def motor_gain_c(blower_w: float) -> float:
    """Steady temperature rise of the air by the blower motor (degC) at electric power ``blower_w``."""
    return k.MOTOR_GAIN_FULL_C * (blower_w / k.BLOWER_MAX_W) ** k.MOTOR_GAIN_EXPONENT


def relax(value: float, target: float, factor: float) -> float:
    """Exact step of a first-order lag towards a constant ``target``; ``factor`` = exp(-h / tau)."""
    return target + (value - target) * factor


# ================================================================= valves and flows (thesis 3.2, 4.5)


def effective_angle(angle_pct: float, shift_pct: float) -> float:
    """Angle at which the valve's curve is read: the curve moved ``shift_pct`` % of travel to the right.

    A positive shift makes a valve act ``shift_pct`` less open than commanded (clipped to 0-100 %).
    """
    return min(k.VALVE_MAX_PCT, max(k.VALVE_MIN_PCT, angle_pct - shift_pct))


def bypass_fraction(a_pct: float) -> float:
    """Share of the air bypassing core and heater at valve a angle ``a_pct`` (100 % = all through the core).

    ASSUMPTION (docs/model.md sec. 1, fig. 36 has no data): b = 0.9 (1 - a/100)^1.3; b <= 0.9 from thesis 4.5.1.
    """
    return k.BYPASS_MAX * (1.0 - a_pct / 100.0) ** k.BYPASS_EXPONENT


def flow_dependent_bypass(bypass: float, mass_flow_kgs: float, exponent: float) -> float:
    """Bypass share when the split also depends on the total mass flow (thesis 4.5.1 remark; the form
    and its reference flow are ASSUMPTIONS): b (m / m_ref)^exponent, at most 0.97; ``exponent`` 0 is b."""
    if exponent == 0.0:
        return bypass
    return min(bypass * (max(mass_flow_kgs, 1e-4) / k.BYPASS_FLOW_REF_KGS) ** exponent, 0.97)


def isotonic_decreasing(values: np.ndarray) -> np.ndarray:
    """Closest non-increasing sequence in the least-squares sense (pool adjacent violators)."""
    blocks: list[list[float]] = []  # [mean, weight]
    for v in np.asarray(values, float):
        blocks.append([float(v), 1.0])
        while len(blocks) > 1 and blocks[-2][0] < blocks[-1][0]:
            m2, w2 = blocks.pop()
            m1, w1 = blocks.pop()
            blocks.append([(m1 * w1 + m2 * w2) / (w1 + w2), w1 + w2])
    return np.concatenate([np.full(int(w), m) for m, w in blocks])


def log_resistance_curve(table: tuple[tuple[float, float], ...]) -> PchipInterpolator:
    """Monotone (non-increasing) interpolant of ln R over the angle, from a thesis resistance table.

    The table's few non-monotone points (measurement scatter, e.g. table 4 at 60/70 %) are pooled
    first; PCHIP then keeps the curve monotone between the points.
    """
    angles = np.array([row[0] for row in table], float)
    log_r = isotonic_decreasing(np.log([row[1] for row in table]))
    return PchipInterpolator(angles, log_r, extrapolate=False)


def blower_stiffness(resistances: np.ndarray, flows: np.ndarray) -> float:
    """Internal resistance R_int of the blower (kg/m7) from flows measured at one blower setting.

    Model: a pressure source p with internal resistance R_int, so 1/V^2 = (R_int + R)/p; a straight
    line through (R, 1/V^2) gives R_int = intercept / slope (thesis tables 3-5, sec. 4.5.2).
    """
    slope, intercept = np.polyfit(np.asarray(resistances, float), 1.0 / np.asarray(flows, float) ** 2, 1)
    return float(intercept / slope)


def own_conductances(r_m: float, r_f: float, r_w: float, leak: float) -> tuple[float, float, float]:
    """Conductances 1/sqrt(R) of valves m, f, w alone (sqrt(m7/kg)).

    Tables 3-5 hold the whole network with the other two valves closed (docs/model.md, "traps"), so a
    valve's own conductance is the table's minus the two closed valves' leak ``leak`` each
    (parallel paths add conductances, thesis 3.2).
    """
    floor = 1e-6
    return tuple(max(floor, r ** -0.5 - 2.0 * leak) for r in (r_m, r_f, r_w))  # type: ignore[return-value]


def core_resistance(stiff_plus_open: float) -> float:
    """Resistance of the core path (cooler + heater, kg/m7) giving thesis 4.5.1's ~10 % flow loss.

    With the bypass and core in parallel, the box resistance is R_core (1 - b)^2 (see
    :func:`box_resistance`); the flow ratio between b = 0 and b = 0.9 is set to ``CORE_FLOW_RATIO``.
    ``stiff_plus_open`` is R_int + R of the open outlet network.
    """
    r2 = k.CORE_FLOW_RATIO ** 2
    open_share = (1.0 - k.BYPASS_MAX) ** 2
    return stiff_plus_open * (1.0 - r2) / (r2 - open_share)


def box_resistance(bypass: float, r_core: float) -> float:
    """Resistance (kg/m7) of the bypass and core paths in parallel, bypass share ``bypass``.

    Bypass conductance g_b = g_c b / (1 - b), so R = 1 / (g_b + g_c)^2 = R_core (1 - b)^2.
    """
    return r_core * (1.0 - bypass) ** 2


def blower_flow_m3s(blower_w: float, gain: float, r_int: float, r_ref: float, r_load: float) -> float:
    """Volume flow (m3/s) at the inlet: linear in blower power at a fixed load, falling with the load.

    V = gain P sqrt((R_int + R_ref) / (R_int + R_load)); ``gain`` (m3/s per W) is the flow per watt at
    the reference load ``r_ref`` (all valves open, full bypass; docs/model.md sec. 1).
    """
    return gain * blower_w * math.sqrt((r_int + r_ref) / (r_int + r_load))


@dataclass(frozen=True)
class ValveNetwork:
    """The valve curves and the resistances derived from the thesis tables (built once, immutable)."""

    curve_m: PchipInterpolator
    curve_f: PchipInterpolator
    curve_w: PchipInterpolator
    leak: float          # conductance of one closed outlet valve, sqrt(m7/kg)
    r_int: float         # blower internal resistance, kg/m7
    r_open: float        # outlet network with m, f, w at 100 %
    r_core: float        # core path (cooler + heater)
    r_ref: float         # load at which BLOWER_FLOW_PER_W holds: r_open + box at full bypass

    def resistances(self, m_pct: float, f_pct: float, w_pct: float) -> tuple[float, float, float]:
        """Table resistances (kg/m7) of the network with only that valve at its angle."""
        return (math.exp(float(self.curve_m(m_pct))), math.exp(float(self.curve_f(f_pct))),
                math.exp(float(self.curve_w(w_pct))))

    def conductances(self, m_pct: float, f_pct: float, w_pct: float) -> tuple[float, float, float]:
        """Own conductances of valves m, f, w (sqrt(m7/kg))."""
        return own_conductances(*self.resistances(m_pct, f_pct, w_pct), self.leak)


@lru_cache(maxsize=1)
def valve_network() -> ValveNetwork:
    """Build the valve network from tables 3-5 (cached: a constant of the thesis data)."""
    tables = (k.TABLE3_RM, k.TABLE4_RF, k.TABLE5_RW)
    curves = [log_resistance_curve(t) for t in tables]
    leak = float(np.mean([r0 ** -0.5 for r0 in (math.exp(float(c(0.0))) for c in curves)])) / 3.0
    r_tab = np.concatenate([[row[1] for row in t] for t in tables])
    flows = np.concatenate([k.TABLE3_FLOW, k.TABLE4_FLOW, k.TABLE5_FLOW])
    r_int = blower_stiffness(r_tab, flows)
    g_open = own_conductances(*(math.exp(float(c(100.0))) for c in curves), leak)
    r_open = 1.0 / sum(g_open) ** 2
    r_core = core_resistance(r_int + r_open)
    r_ref = r_open + box_resistance(k.BYPASS_MAX, r_core)
    return ValveNetwork(*curves, leak=leak, r_int=r_int, r_open=r_open, r_core=r_core, r_ref=r_ref)


# ================================================================= cooler, heater, mixing, duct


def cooler_outlet_c(air_in_c: float, water_c: float, literal_fit: bool = False,
                    effectiveness: float = k.COOLER_SLOPE) -> float:
    """Air temperature after the cooler core (degC).

    Nominal: effectiveness form T_in + 0.7564 (T_w - T_in), equal to the thesis 4.2 fit at 25.9 C inlet
    (``effectiveness``: another one, e.g. :func:`cooler_effectiveness_ntu`).
    ``literal_fit``: the thesis 4.2 fit 0.7564 T_w + 6.312 as it stands, whatever the inlet air.
    """
    if literal_fit:
        return k.COOLER_SLOPE * water_c + k.COOLER_OFFSET_C
    return air_in_c + effectiveness * (water_c - air_in_c)


def cooler_effectiveness_ntu(core_mass_flow_kgs: float, ntu_ref: float) -> float:
    """Effectiveness of a core whose number of transfer units is ``ntu_ref`` at the reference core mass flow and
    falls as (core mass flow)^-0.4 (air-side film coefficient ~ m^0.6; ASSUMPTION): 1 - exp(-NTU), the water side
    taken as isothermal (its capacity flow far above the air's)."""
    ntu = ntu_ref * (max(core_mass_flow_kgs, 1e-6) / k.COOLER_NTU_REF_KGS) ** -k.COOLER_NTU_EXPONENT
    return 1.0 - math.exp(-ntu)


def entering_air_c(inlet_c: float, cabin_c: float, recirculation_share: float) -> float:
    """Air entering the box (degC): the inlet air with a share of cabin air drawn in behind the inlet sensor."""
    return inlet_c + recirculation_share * (cabin_c - inlet_c)


def heater_effective_ua(ka_w_per_k: float, capacity_flow_w_per_k: float) -> float:
    """Heat conductance (W/K) from heater body to the incoming air with the air node at rest.

    The 14 mg air node (thesis 4.4) settles in ~0.2 ms, so it is algebraic; series of k_A,h and the
    air's capacity flow W = m_dot c_pa: UA = k_A W / (k_A + W).
    """
    return ka_w_per_k * capacity_flow_w_per_k / (ka_w_per_k + capacity_flow_w_per_k)


def heater_air_outlet_c(body_c: float, air_in_c: float, ka_w_per_k: float, capacity_flow_w_per_k: float) -> float:
    """Air temperature leaving the heater (degC): the thesis 4.3 air node solved at rest (closed form)."""
    return (ka_w_per_k * body_c + capacity_flow_w_per_k * air_in_c) / (ka_w_per_k + capacity_flow_w_per_k)


def ptc_available_w(body_c: float, power_fall: bool = True) -> float:
    """Electric power (W) the PTC heater can draw at body temperature ``body_c``.

    240 W up to ~60 C, falling linearly to 0 at 165 C (thesis 2.3, ASSUMPTION on the shape and the
    knee, docs/model.md sec. 1); constant 240 W when ``power_fall`` is off (the thesis model).
    """
    if not power_fall:
        return k.HEATER_MAX_W
    share = (k.PTC_ZERO_C - body_c) / (k.PTC_ZERO_C - k.PTC_KNEE_C)
    return k.HEATER_MAX_W * min(1.0, max(0.0, share))


def heater_electric_w(cmd_w: float, body_c: float, scale: float = 1.0, power_fall: bool = True) -> float:
    """Electric power (W) drawn: the command, capped by the PTC, times the heater's ``scale``."""
    return scale * min(cmd_w, ptc_available_w(body_c, power_fall))


def _heater_power_line(cmd_w: float, body_c: float, scale: float, power_fall: bool) -> tuple[float, float]:
    """Electric power as p0 - p1 T around ``body_c`` (the active branch of min(cmd, PTC curve))."""
    span = k.PTC_ZERO_C - k.PTC_KNEE_C
    on_fall = power_fall and k.PTC_KNEE_C < body_c < k.PTC_ZERO_C and ptc_available_w(body_c) < cmd_w
    if on_fall:
        p1 = scale * k.HEATER_MAX_W / span
        return p1 * k.PTC_ZERO_C, p1
    return heater_electric_w(cmd_w, body_c, scale, power_fall), 0.0


def heater_body_step(body_c: float, air_in_c: float, cmd_w: float, ua_w_per_k: float, dt_s: float,
                     scale: float = 1.0, power_fall: bool = True, wall_ua_w_per_k: float = 0.0,
                     wall_c: float = 0.0) -> float:
    """Heater body temperature (degC) after ``dt_s``: m_h c_h dT/dt = k_p P(T) - UA (T - T_in) (thesis 4.3),
    less a loss ``wall_ua_w_per_k`` (T - T_wall) to the box walls at ``wall_c``.

    P(T) is linearised on its active branch and the linear equation solved exactly: stable for any step.
    """
    p0, p1 = _heater_power_line(cmd_w, body_c, scale, power_fall)
    capacity = k.HEATER_MASS_KG * k.HEATER_CP
    gain = k.HEATER_KP * p1 + ua_w_per_k + wall_ua_w_per_k
    target = (k.HEATER_KP * p0 + ua_w_per_k * air_in_c + wall_ua_w_per_k * wall_c) / gain
    return relax(body_c, target, math.exp(-gain * dt_s / capacity))


def heater_steady_c(air_in_c: float, cmd_w: float, ua_w_per_k: float, scale: float = 1.0,
                    power_fall: bool = True, wall_ua_w_per_k: float = 0.0, wall_c: float = 0.0) -> float:
    """Heater body temperature (degC) at rest: k_p P(T) = UA (T - T_in) + UA_wall (T - T_wall), in closed form.

    The right side minus the left rises strictly with T, so the root is on the command branch if the
    PTC can deliver the command there, else on the PTC's falling line.
    """
    ua, g = ua_w_per_k, wall_ua_w_per_k
    on_command = air_in_c + (k.HEATER_KP * scale * cmd_w - g * (air_in_c - wall_c)) / (ua + g)
    if ptc_available_w(on_command, power_fall) >= cmd_w:
        return on_command
    p1 = k.HEATER_KP * scale * k.HEATER_MAX_W / (k.PTC_ZERO_C - k.PTC_KNEE_C)
    return (p1 * k.PTC_ZERO_C + ua * air_in_c + g * wall_c) / (p1 + ua + g)


def mix_c(bypass: float, bypass_air_c: float, core_air_c: float) -> float:
    """Mixed air temperature (degC) of the two streams, energy balance by mass share (thesis 4.5.1)."""
    return bypass * bypass_air_c + (1.0 - bypass) * core_air_c


def duct_outlet_c(air_c: float, cabin_c: float, ua_w_per_k: float, mass_flow_kgs: float) -> float:
    """Air temperature (degC) after a duct losing heat to the cabin: plug flow, T_cab + dT exp(-UA / m_dot c_p).

    ASSUMPTION: the duct wall has no heat capacity and the cabin air is at ``cabin_c``.
    """
    if ua_w_per_k <= 0.0:
        return air_c
    return cabin_c + (air_c - cabin_c) * math.exp(-ua_w_per_k / (mass_flow_kgs * k.CP_AIR))


def thermocouple_target_c(air_c: float, body_c: float, radiation_share: float) -> float:
    """Temperature (degC) the thermocouple settles at in air at ``air_c`` seeing the heater body at ``body_c``:
    the air plus ``radiation_share`` of the body's excess (radiation; 0 = the air)."""
    return air_c + radiation_share * (body_c - air_c)


# ================================================================= chiller (thesis 2.2, 4.2)


def chiller_relay(water_c: float, setpoint_c: float, cooling: bool, band_c: float = k.CHILLER_BAND_C) -> bool:
    """Two-point control: compressor on above set point + band, off below set point - band, else as it was."""
    if water_c >= setpoint_c + band_c:
        return True
    if water_c <= setpoint_c - band_c:
        return False
    return cooling


def chiller_ramp(water_c: float, setpoint_c: float, cooling: bool, dt_s: float, rate_scale: float = 1.0,
                 band_c: float = k.CHILLER_BAND_C) -> float:
    """Water temperature (degC) after ``dt_s``: a ramp towards the two-point control's target.

    Compressor on: falls at 0.00682 C/s towards set point - band; off: rises at 0.00702 C/s towards
    set point + band (thesis 4.2 slopes, their mean is the model's 0.00692); stops at the target.
    """
    target = setpoint_c - band_c if cooling else setpoint_c + band_c
    fall = rate_scale * k.CHILLER_FALL_C_PER_S * dt_s
    rise = rate_scale * k.CHILLER_RISE_C_PER_S * dt_s
    return water_c + min(rise, max(-fall, target - water_c))


# ================================================================= sensors (thesis 2.4)


def flow_sensor_m3s(volume_flow_m3s: float, air_c: float, calibration_c: float | None = None) -> float:
    """Volume-flow sensor reading (m3/s): dp of the pipe, read back through V = C sqrt(dp) sqrt(1.2/rho).

    The pipe's dp is rho/1.2 (V/C)^2 at the true air temperature; the reading uses the density at
    ``calibration_c`` (default: the air temperature, which makes the reading exact).
    """
    rho = air_density(air_c)
    dp = rho / k.FLOW_SENSOR_RHO_REF * (volume_flow_m3s / k.FLOW_SENSOR_C) ** 2
    rho_read = rho if calibration_c is None else air_density(calibration_c)
    return k.FLOW_SENSOR_C * math.sqrt(dp) * math.sqrt(k.FLOW_SENSOR_RHO_REF / rho_read)
