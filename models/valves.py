"""Outlet valves m, f, w: smooth monotone resistance curves and the parallel network (thesis 4.5.2, 5.2).

Each measured table (thesis tables 3-5) is fitted in log space by

    ln R(theta) = c0 - w1 s((theta - mu1) / h1) - w2 s((theta - mu2) / h2),   s = logistic,

with w1, w2, h1, h2 > 0, so the curve is smooth, strictly decreasing and invertible; an
optimiser can differentiate through it and :func:`angle_pct` maps a resistance back to an angle.
"""

from __future__ import annotations

import functools
import math

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

VALVES = ("m", "f", "w")
#: Parameter holding each valve's curve shift (% of travel; sign convention: :func:`effective_angle`).
SHIFT_PARAMS = {"a": "valve_a_shift_pct", "m": "valve_m_shift_pct", "f": "valve_f_shift_pct",
                "w": "valve_w_shift_pct"}


@functools.lru_cache(maxsize=32)
def fit_curve(table: tuple) -> tuple[float, ...]:
    """Fit (c0, w1, mu1, h1, w2, mu2, h2) to a table of (angle_pct, R) rows; deterministic."""
    angle = np.array([r[0] for r in table], float)
    log_r = np.log(np.array([r[1] for r in table], float))
    span = log_r.max() - log_r.min()

    def unpack(z):
        c0, lw1, mu1, lh1, lw2, mu2, lh2 = z
        return c0, math.exp(lw1), mu1, math.exp(lh1), math.exp(lw2), mu2, math.exp(lh2)

    def model(z, th):
        c0, w1, mu1, h1, w2, mu2, h2 = unpack(z)
        return c0 - w1 * _sig((th - mu1) / h1) - w2 * _sig((th - mu2) / h2)

    best = None
    for mu1, mu2 in ((20.0, 50.0), (30.0, 70.0), (15.0, 40.0), (50.0, 80.0)):
        z0 = [log_r.max(), math.log(0.6 * span), mu1, math.log(5.0), math.log(0.4 * span), mu2, math.log(10.0)]
        sol = least_squares(lambda z: model(z, angle) - log_r, z0, method="lm", max_nfev=4000)
        if best is None or sol.cost < best.cost:
            best = sol
    return tuple(float(v) for v in unpack(best.x))


def _sig(x):
    return 1.0 / (1.0 + np.exp(-x))


def resistance(angle_pct, coeffs):
    """Fitted network resistance R(theta) in kg/m^7 (CasADi or numpy input)."""
    c0, w1, mu1, h1, w2, mu2, h2 = coeffs
    if isinstance(angle_pct, (ca.SX, ca.MX, ca.DM)):
        sig = lambda x: 1.0 / (1.0 + ca.exp(-x))  # noqa: E731
        return ca.exp(c0 - w1 * sig((angle_pct - mu1) / h1) - w2 * sig((angle_pct - mu2) / h2))
    a = np.asarray(angle_pct, float)
    return np.exp(c0 - w1 * _sig((a - mu1) / h1) - w2 * _sig((a - mu2) / h2))


def _log_resistance_and_slope(a, coeffs):
    c0, w1, mu1, h1, w2, mu2, h2 = coeffs
    s1, s2 = _sig((a - mu1) / h1), _sig((a - mu2) / h2)
    value = c0 - w1 * s1 - w2 * s2
    slope = -w1 * s1 * (1 - s1) / h1 - w2 * s2 * (1 - s2) / h2
    return value, slope


@functools.lru_cache(maxsize=32)
def _inverse_table(coeffs: tuple) -> tuple[np.ndarray, np.ndarray]:
    grid = np.linspace(0.0, 100.0, 2001)
    return grid, _log_resistance_and_slope(grid, coeffs)[0]


def angle_pct(resistance_kg_m7, coeffs) -> np.ndarray:
    """Inverse of :func:`resistance`: the angle in % giving a resistance (clipped to 0..100 %).

    Interpolation on a 0.05 % grid of the strictly decreasing curve, then two Newton steps.
    """
    grid, log_r = _inverse_table(tuple(coeffs))
    target = np.clip(np.log(np.atleast_1d(np.asarray(resistance_kg_m7, float))), log_r[-1], log_r[0])
    a = np.interp(-target, -log_r, grid)
    for _ in range(2):
        value, slope = _log_resistance_and_slope(a, coeffs)
        a = np.clip(a - (value - target) / slope, 0.0, 100.0)
    return a if np.ndim(resistance_kg_m7) else float(a[0])


def effective_angle(angle_pct, shift_pct):
    """Angle (%) at which a valve's curve is read when the curve is moved ``shift_pct`` % of travel.

    ASSUMPTION (sign convention, docs/model.md sec. 1): a positive shift moves the curve to the right, so
    the valve acts ``shift_pct`` less open than commanded; a valve cannot be read beyond its stops, so the
    angle is clipped to 0..100 % (numpy; the model's own reading is :func:`shifted_angles`).
    """
    return np.clip(np.asarray(angle_pct, float) - shift_pct, 0.0, 100.0)


def commanded_angle(effective_pct, shift_pct):
    """Inverse of :func:`effective_angle` within the stops: the command (%) that reads the curve at
    ``effective_pct`` (clipped to 0..100 %; numpy)."""
    return np.clip(np.asarray(effective_pct, float) + shift_pct, 0.0, 100.0)


def acting_travel(shift_pct: float) -> tuple[float, float]:
    """Commanded angles (%) over which a valve with its curve shifted by ``shift_pct`` moves at all:
    [max(0, shift), min(100, 100 + shift)]; outside it the effective angle sits at a stop."""
    return max(0.0, float(shift_pct)), min(100.0, 100.0 + float(shift_pct))


def shifted_angles(angles_pct, p) -> list:
    """Angles (%) at which the model reads the curves of valves m, f, w: the commands less the shifts of parameters
    ``p``, not clipped. ASSUMPTION: beyond the tables' range the fitted curves are read as they continue; at the
    closed end they are flat (within 0.4 % for m and f, 1.8 % for w at 10 % of travel beyond), at the open end
    valve m's keeps falling (16 % lower at 110 %), which only a negative shift reaches. Clipping like
    :func:`effective_angle` would put a kink at the stops of the unshifted model, where the MPC's openings sit
    (at a stop the derivative would halve), and the nominal solvers' iterations would change."""
    return [angles_pct[i] - getattr(p, SHIFT_PARAMS[v]) for i, v in enumerate(VALVES)]


def curves(p) -> dict[str, tuple[float, ...]]:
    """Fitted curve coefficients for valves m, f, w from the parameter tables."""
    return {"m": fit_curve(p.valve_m_table), "f": fit_curve(p.valve_f_table), "w": fit_curve(p.valve_w_table)}


def closed_leak_conductance(p) -> float:
    """Conductance 1/sqrt(R) of one closed valve (effect 'valve_leakage', ASSUMPTION).

    With all three valves closed the network conducts sqrt(1/R(0)); shared equally by three
    closed valves (mean over tables 3-5), times ``valve_closed_leak_share``.
    """
    g0 = np.mean([1.0 / math.sqrt(t[0][1]) for t in (p.valve_m_table, p.valve_f_table, p.valve_w_table)])
    return p.valve_closed_leak_share * g0 / 3.0


def branch_conductances(angles_pct, p, coeffs=None, leakage: bool = False):
    """Conductances g_i = 1/sqrt(R_i) of branches m, f, w.

    Thesis model (sec. 5.2): R_i is the table resistance at that angle, though each table row
    was measured with the other valves closed. With ``leakage`` each branch's own conductance
    is the table's minus the two closed valves' leaks measured with it (docs/model.md, 'traps').
    """
    coeffs = coeffs or curves(p)
    g = [1.0 / ca.sqrt(resistance(angles_pct[i], coeffs[v])) for i, v in enumerate(VALVES)]
    if leakage:
        g_leak = closed_leak_conductance(p)
        g = [ca.fmax(gi - 2.0 * g_leak, 0.05 * g_leak) for gi in g]
    return g


def network_resistance(conductances):
    """Parallel resistance R_tot = 1 / (sum 1/sqrt(R_i))^2 (thesis sec. 3.2 and eq. of 5.2)."""
    total = conductances[0] + conductances[1] + conductances[2]
    return 1.0 / total ** 2


def split_flows(total_m3s, conductances):
    """Outlet flows V_i = V sqrt(dp / R_i) with dp = R_tot V^2 (thesis sec. 5.2)."""
    total = conductances[0] + conductances[1] + conductances[2]
    return [total_m3s * g / total for g in conductances]
