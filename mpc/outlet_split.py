"""Outlet-split feed-forward of thesis section 5.2: outlet flow references -> valve angles m, f, w.

No flow sensor sits at the outlets, so the thesis splits the measured total flow by a
feed-forward optimisation over the three valve resistances R = (R_m, R_f, R_w) in kg/m^7:

    J(R) = sum_i (V_i(R) - V_i,ref)^2 + gamma dp(R),
    dp = R_tot V_tot^2,   R_tot = 1 / (sum_i 1/sqrt(R_i))^2,   V_i = sqrt(dp / R_i)

with gamma = 1e-7, bounds R_lb <= R <= R_ub and start at R_lb (all thesis sec. 5.2). The
resistances are then mapped back to servo angles through the fitted valve curves of tables 3-5
(:func:`hvac_mpc.models.valves.angle_pct`). All functions here are pure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import minimize

from hvac_mpc.models import valves
from hvac_mpc.models.parameters import Parameters

#: Weight of the pressure loss in the cost, 1/Pa in (m3/s)^2 units (thesis sec. 5.2).
GAMMA = 1e-7
#: Lower resistance bounds R_m, R_f, R_w in kg/m^7, also the start value (thesis sec. 5.2).
R_LB = (44600.0, 56500.0, 35600.0)
#: Upper resistance bounds R_m, R_f, R_w in kg/m^7 (thesis sec. 5.2).
R_UB = (231000.0, 234500.0, 247000.0)
#: Angles (%) when the reference leaves the split free: all outlet valves fully open.
OPEN_ANGLES_PCT = (100.0, 100.0, 100.0)

# Scale of the decision variables and of the cost for the optimiser only (same minimiser):
# R ~ 1e5 kg/m^7 and J ~ V^2 ~ 1e-3 (m3/s)^2 would otherwise stall the gradient tests.
_R_SCALE = 1e5


@dataclass(frozen=True)
class SplitResult:
    """Result of the outlet-split optimisation.

    ``resistances_kg_m7`` (R_m, R_f, R_w), ``flows_m3s`` their predicted outlet flows at the
    measured total, ``pressure_loss_pa`` the network pressure loss, ``cost`` J, ``angles_pct``
    the servo angles m, f, w in [0, 100] %, ``success`` whether the optimiser converged.
    """

    resistances_kg_m7: tuple[float, float, float]
    flows_m3s: tuple[float, float, float]
    pressure_loss_pa: float
    cost: float
    angles_pct: tuple[float, float, float]
    success: bool
    iterations: int


def outlet_flows_m3s(resistances_kg_m7: Sequence[float], total_m3s: float) -> tuple[tuple[float, float, float], float]:
    """Outlet flows (m, f, w) in m3/s and pressure loss in Pa for resistances and total flow (thesis 5.2)."""
    g = [1.0 / math.sqrt(r) for r in resistances_kg_m7]
    r_tot = 1.0 / sum(g) ** 2
    dp = r_tot * total_m3s ** 2
    flows = tuple(math.sqrt(dp / r) for r in resistances_kg_m7)
    return flows, dp  # type: ignore[return-value]


def split_cost(resistances_kg_m7: Sequence[float], total_m3s: float, reference_m3s: Sequence[float],
               gamma: float = GAMMA) -> float:
    """Cost J of thesis sec. 5.2: squared outlet-flow errors (m3/s)^2 plus gamma times dp (Pa)."""
    flows, dp = outlet_flows_m3s(resistances_kg_m7, total_m3s)
    return sum((v - r) ** 2 for v, r in zip(flows, reference_m3s)) + gamma * dp


def optimise_resistances(total_m3s: float, reference_m3s: Sequence[float], gamma: float = GAMMA,
                         r_lb: Sequence[float] = R_LB, r_ub: Sequence[float] = R_UB,
                         r_start: Sequence[float] | None = None):
    """Minimise J over the resistances within bounds, starting at ``r_start`` (default R_lb, thesis 5.2).

    Returns ``(resistances_kg_m7, cost, success, iterations)``. Raises ValueError naming the
    argument for a non-finite or non-positive total flow or a negative/non-finite reference.
    """
    if not (isinstance(total_m3s, (int, float)) and math.isfinite(total_m3s) and total_m3s > 0.0):
        raise ValueError(f"total_m3s: expected a finite flow > 0 m3/s, got {total_m3s!r}")
    ref = [float(v) for v in reference_m3s]
    if len(ref) != 3 or not all(math.isfinite(v) and v >= 0.0 for v in ref):
        raise ValueError(f"reference_m3s: expected three finite flows >= 0 m3/s (m, f, w), got {reference_m3s!r}")
    lb = np.asarray(r_lb, float) / _R_SCALE
    ub = np.asarray(r_ub, float) / _R_SCALE
    z0 = np.asarray(r_lb if r_start is None else r_start, float) / _R_SCALE
    z0 = np.clip(z0, lb, ub)
    scale = 1.0 / max(total_m3s, 1e-3) ** 2  # cost scaled to O(1); same minimiser

    def fun(z):
        g = 1.0 / np.sqrt(z * _R_SCALE)
        s = g.sum()
        flows = total_m3s * g / s
        err = flows - ref
        dp = total_m3s ** 2 / s ** 2
        j = float(err @ err + gamma * dp)
        # gradient: dV_i/dg_k = V_tot (delta_ik s - g_i) / s^2, ddp/dg_k = -2 V_tot^2 / s^3,
        # dg_k/dz_k = -g_k / (2 z_k)
        dv_dg = total_m3s * (np.eye(3) * s - g[:, None]) / s ** 2
        dj_dg = 2.0 * err @ dv_dg - 2.0 * gamma * total_m3s ** 2 / s ** 3
        grad = dj_dg * (-g / (2.0 * z))
        return j * scale, grad * scale

    sol = minimize(fun, z0, jac=True, method="L-BFGS-B", bounds=list(zip(lb, ub)),
                   options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 200})
    r = np.clip(sol.x, lb, ub) * _R_SCALE
    return tuple(float(v) for v in r), float(sol.fun / scale), bool(sol.success), int(sol.nit)


def resistances_to_angles(resistances_kg_m7: Sequence[float], coeffs: dict,
                          shifts_pct: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple[float, float, float]:
    """Servo angles m, f, w in % (0..100) for resistances, through the fitted curves of tables 3-5, each
    moved by its curve shift ``shifts_pct`` (Parameters.valve_*_shift_pct; models/valves.py)."""
    return tuple(float(valves.commanded_angle(valves.angle_pct(r, coeffs[v]), s))  # type: ignore[return-value]
                 for r, v, s in zip(resistances_kg_m7, valves.VALVES, shifts_pct))


def outlet_split(total_m3s: float, reference_m3s: Sequence[float] | None, params: Parameters | None = None,
                 coeffs: dict | None = None, gamma: float = GAMMA) -> SplitResult:
    """Feed-forward of thesis sec. 5.2: valve angles m, f, w for outlet flow references (m3/s).

    ``total_m3s`` is the measured total volume flow. ``reference_m3s`` is (m, f, w) or ``None``
    (free split): then the valves stay fully open (:data:`OPEN_ANGLES_PCT`) with the flows the
    open network gives. ``coeffs`` are the fitted valve curves (default from ``params``).
    """
    params = params or Parameters()
    coeffs = coeffs or valves.curves(params)
    if reference_m3s is None:
        r_open = tuple(float(valves.resistance(100.0, coeffs[v])) for v in valves.VALVES)
        total = total_m3s if math.isfinite(total_m3s) and total_m3s > 0 else 0.0
        flows, dp = outlet_flows_m3s(r_open, total) if total > 0 else ((0.0, 0.0, 0.0), 0.0)
        return SplitResult(r_open, flows, dp, 0.0, OPEN_ANGLES_PCT, True, 0)  # type: ignore[arg-type]
    r, cost, success, nit = optimise_resistances(total_m3s, reference_m3s, gamma)
    flows, dp = outlet_flows_m3s(r, total_m3s)
    shifts = tuple(getattr(params, valves.SHIFT_PARAMS[v]) for v in valves.VALVES)
    return SplitResult(r, flows, dp, cost, resistances_to_angles(r, coeffs, shifts), success,  # type: ignore[arg-type]
                       nit)
