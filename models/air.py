"""Air properties and the volume-flow sensor (thesis sections 2.4 and 4)."""

from __future__ import annotations

import casadi as ca


def density_kgm3(temp_c, p):
    """Air density rho(T) in kg/m3 at 965 mbar, 60 % RH (thesis sec. 4, fig. 16)."""
    return p.rho_slope_kgm3_per_c * temp_c + p.rho_offset_kgm3


def flow_from_pressure_m3s(dp_pa, temp_c, p):
    """Volume-flow sensor: V = C sqrt(dp) sqrt(1.2 / rho) (thesis sec. 2.4)."""
    return p.flow_sensor_c_m3s * ca.sqrt(dp_pa) * ca.sqrt(1.2 / density_kgm3(temp_c, p))


def pressure_from_flow_pa(flow_m3s, temp_c, p):
    """Inverse of :func:`flow_from_pressure_m3s`: differential pressure in Pa."""
    return (flow_m3s / p.flow_sensor_c_m3s) ** 2 * density_kgm3(temp_c, p) / 1.2


#: The least mass flow (kg/s) any division by the flow is held at, whatever the parameters (a blower's least power
#: of 0 W gives a floor of 0). ASSUMPTION: a guard only, 0.3 m3/h, far below any flow the box gives.
MIN_MASS_FLOW_KGS = 1e-4


def heat_gain_c(heat_w, mass_flow_kgs, floor_kgs, p):
    """Temperature rise (degC) of air of ``mass_flow_kgs`` (kg/s) taking ``heat_w`` (W): Q / (max(m_dot, floor) c_p).
    ``floor_kgs`` (kg/s) guards the division where the flow is below what the blower can give
    (:func:`~.blower.least_mass_flow_kgs`), itself held at :data:`MIN_MASS_FLOW_KGS` at least."""
    return heat_w / (ca.fmax(mass_flow_kgs, ca.fmax(floor_kgs, MIN_MASS_FLOW_KGS)) * p.cp_air_j_per_kgk)
