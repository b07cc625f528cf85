"""PTC electric heater (thesis sections 2.3, 4.3 and 4.4).

The air node (14.21 mg of air, 0.2 ms residence time at 0.07 kg/s) is solved algebraically
(singular perturbation of the thesis's dT_ah/dt equation), leaving the heater body as the state.
"""

from __future__ import annotations

import casadi as ca


def available_power_w(heater_c, p):
    """PTC power available at heater temperature T_h (effect 'ptc_power_fall').

    Full power below ``ptc_knee_c``, falling linearly to zero at ``ptc_zero_c`` (thesis
    sec. 2.3 and fig. 12; the shape is an ASSUMPTION).
    """
    frac = (p.ptc_zero_c - heater_c) / (p.ptc_zero_c - p.ptc_knee_c)
    return p.heater_power_max_w * ca.fmin(ca.fmax(frac, 0.0), 1.0)


def electric_power_w(heater_cmd_w, heater_c, p, ptc: bool = False):
    """Electric power drawn for a command; the nominal thesis model takes the command as is."""
    if not ptc:
        return heater_cmd_w
    return ca.fmin(heater_cmd_w, available_power_w(heater_c, p))


def air_outlet_c(heater_c, air_in_c, mass_flow_kgs, p):
    """Heater outlet air temperature from the steady air-node balance (thesis sec. 4.3).

    0 = kA (T_h - T_ah) - m cp (T_ah - T_in)  =>  T_ah = (kA T_h + m cp T_in) / (kA + m cp).
    """
    g = mass_flow_kgs * p.cp_air_j_per_kgk
    return (p.heater_ka_w_per_k * heater_c + g * air_in_c) / (p.heater_ka_w_per_k + g)


def body_rate_c_per_s(heater_c, air_c, electric_w, p):
    """dT_h/dt = (k_p P_el - kA (T_h - T_ah)) / (m_h c_h) (thesis sec. 4.3)."""
    return (p.heater_kp * electric_w - p.heater_ka_w_per_k * (heater_c - air_c)) / (
        p.heater_mass_kg * p.heater_c_j_per_kgk)


def air_node_rate_c_per_s(air_c, heater_c, air_in_c, mass_flow_kgs, p):
    """The thesis's full air-node equation dT_ah/dt (sec. 4.3), for stiff reference integration."""
    return (p.heater_ka_w_per_k * (heater_c - air_c) / (p.heater_air_mass_kg * p.cp_air_j_per_kgk)
            - mass_flow_kgs / p.heater_air_mass_kg * (air_c - air_in_c))


def steady_outlet_c(air_in_c, mass_flow_kgs, electric_w, p):
    """Steady-state heater outlet temperature, thesis eq. (5) solved for T_ah."""
    return air_in_c + p.heater_kp * electric_w / (mass_flow_kgs * p.cp_air_j_per_kgk)


def time_constant_s(mass_flow_kgs, p):
    """Heater body time constant with the algebraic air node: m_h c_h (1/kA + 1/(m cp))."""
    g = mass_flow_kgs * p.cp_air_j_per_kgk
    return p.heater_mass_kg * p.heater_c_j_per_kgk * (1.0 / p.heater_ka_w_per_k + 1.0 / g)
