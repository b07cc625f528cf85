"""Blower: volume flow and motor heating (thesis section 4.1)."""

from __future__ import annotations

import casadi as ca

from . import air


def open_flow_m3s(blower_power_w, p):
    """Volume flow with all valves open and full bypass, V = k P_b (ASSUMPTION, fig. 20 stand-in)."""
    return p.flow_per_watt_m3s_per_w * blower_power_w


def least_mass_flow_kgs(inlet_temp_c, p):
    """The least mass flow the blower gives (kg/s): its least power, all air across the core (the core's flow loss in
    full), at the inlet air's density. ASSUMPTION: the valves open (a closed outlet lowers it further; the model's
    flow offset can too), so it is a floor for a division by the flow, not a bound on the model's flow."""
    return (air.density_kgm3(inlet_temp_c, p) * open_flow_m3s(p.blower_power_min_w, p)
            * (1.0 - p.core_flow_loss))


def core_flow_factor(bypass, p):
    """Flow reduction when air crosses the core: 1 - 0.1 (1 - b / b_max) (thesis sec. 4.5.1, fig. 33)."""
    return 1.0 - p.core_flow_loss * (1.0 - bypass / p.bypass_max)


def fan_curve_factor(r_network_kg_m7, r_open_kg_m7, p):
    """Flow ratio at fixed blower power when the network resistance changes (effect 'fan_curve').

    Fan curve dp = p0 - k V^2 meeting the network dp = R V^2 gives V ~ 1 / sqrt(k + R);
    normalised to 1 with all valves open, where the flow curve V(P_b) was measured (ASSUMPTION,
    k fitted to the closed and open rows of thesis tables 3-5).
    """
    return ca.sqrt((p.fan_k_kg_m7 + r_open_kg_m7) / (p.fan_k_kg_m7 + r_network_kg_m7))


def motor_gain_c(blower_power_w, p):
    """Steady-state air heating by the motor, K_m(P_b) in C (ASSUMPTION, fig. 18 stand-in)."""
    ratio = ca.fmax(blower_power_w, 0.0) / p.blower_power_max_w
    return p.motor_gain_max_c * ratio ** p.motor_gain_exponent


def motor_rise_rate_c_per_s(rise_c, blower_power_w, p, asymmetric: bool = False):
    """d(rise)/dt of the first-order motor-heating lag G_m = K_m / (tau_m s + 1) (thesis sec. 4.1.1).

    With ``asymmetric`` the lag heats with ``tau_motor_heating_s`` and cools with
    ``tau_motor_cooling_s`` (effect 'motor_asymmetry', thesis sec. 4.1.1 text).
    """
    error = motor_gain_c(blower_power_w, p) - rise_c
    if not asymmetric:
        return error / p.tau_motor_s
    heating = 0.5 * (1.0 + ca.tanh(error / 0.02))
    tau = heating * p.tau_motor_heating_s + (1.0 - heating) * p.tau_motor_cooling_s
    return error / tau
