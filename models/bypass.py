"""Valve a: bypass split and mixing (thesis section 4.5.1) and the trapped-air pocket (sec. 5.4.2)."""

from __future__ import annotations

import casadi as ca


def bypass_fraction(valve_a_pct, p):
    """Fraction b(a) of air bypassing core and heater, b = 0.9 (1 - a/100)^1.3.

    a = 100 % sends all air through the core. b <= 0.9 (thesis fig. 36: at least 10 % always
    crosses the core); the exponent is an ASSUMPTION standing in for fig. 36. The curve is read at
    a - ``p.valve_a_shift_pct`` (a shifted valve curve; sign convention of models/valves.py
    ``effective_angle``: positive acts less open), clipped to the stops.
    """
    opening = ca.fmin(ca.fmax(1.0 - (valve_a_pct - p.valve_a_shift_pct) / 100.0, 0.0), 1.0)
    return p.bypass_max * (opening + 1e-9) ** p.bypass_exponent


def flow_dependent_bypass(bypass, mass_flow_kgs, p):
    """Bypass depending on total mass flow (effect 'bypass_flow', thesis sec. 4.5.1 remark).

    b_eff = b (m / m_ref)^k, kept below 0.97 (form and values are ASSUMPTIONS).
    """
    ratio = ca.fmax(mass_flow_kgs, 1e-4) / p.bypass_ref_mass_flow_kgs
    return ca.fmin(bypass * ratio ** p.bypass_flow_exponent, 0.97)


def mix_c(bypass, bypass_c, core_c):
    """Mixed air temperature, mass-weighted energy balance (thesis sec. 4.5.1)."""
    return bypass * bypass_c + (1.0 - bypass) * core_c


def trap_closed(valve_a_pct, p):
    """Smooth indicator that valve a sits in saturation and closes off the air pocket (its effective angle, the
    command less ``p.valve_a_shift_pct``, above the threshold)."""
    return 0.5 * (1.0 + ca.tanh((valve_a_pct - p.valve_a_shift_pct - p.trap_threshold_pct) / 0.5))


def trap_rate_c_per_s(trap_c, heater_c, mix_air_c, valve_a_pct, p):
    """Pocket temperature: heats towards the heater while closed, flushes into the mix when open.

    Effect 'trapped_air' (thesis sec. 5.4.2, fig. 47; dynamics are ASSUMPTIONS).
    """
    closed = trap_closed(valve_a_pct, p)
    return (closed * (heater_c - trap_c) / p.tau_trap_heat_s
            + (1.0 - closed) * (mix_air_c - trap_c) / p.tau_trap_release_s)


def trap_release_c(trap_c, mix_air_c, valve_a_pct, mass_flow_kgs, p):
    """Temperature added to the supply air by the released pocket, Q / (m cp)."""
    closed = trap_closed(valve_a_pct, p)
    q_w = (1.0 - closed) * p.trap_air_mass_kg * p.cp_air_j_per_kgk * (trap_c - mix_air_c) / p.tau_trap_release_s
    return q_w / (ca.fmax(mass_flow_kgs, 1e-4) * p.cp_air_j_per_kgk)
