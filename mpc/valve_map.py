"""Decision variable of the outlet valves m, f, w: a conductance-like opening instead of the angle.

The outlet flows depend on the valve angles through the measured resistance tables (thesis
tables 3-5), whose curves are flat over long stretches (valve f above 60 %, m below 30 %) and
steep over a few percent (f between 15 and 30 %). Linearised in the angle, a single
Gauss-Newton step overshoots in the steep parts and barely moves in the flat ones, and the
real-time iteration falls into a limit cycle. The MPC therefore decides an *opening*

    v(theta) = alpha * theta / 100 + (1 - alpha) * (g(theta) - g(0)) / (g(100) - g(0)),
    g = 1 / sqrt(R(theta))  (the branch conductance of the thesis's parallel network, sec. 5.2),

in [0, 1], strictly increasing, so the split g_i / sum(g) is close to linear in v; the small
``alpha`` share of the angle keeps the inverse theta(v) finite-sloped in the flat parts. The
angle sent to the servo is theta(v): a monotone piecewise-cubic (PCHIP) interpolant of the
exact inverse on a uniform grid, written as a plain CasADi expression (cheap to evaluate and
differentiate inside the model, JIT-able); tables of it serve the numeric conversions both ways.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
from scipy.interpolate import PchipInterpolator

from hvac_mpc.models import valves
from hvac_mpc.models.parameters import Parameters
from .arrays import interp

VALVE_NAMES = ("m", "f", "w")


class ValveMap:
    """Opening v in [0, 1] <-> angle theta in [0, 100] % for valves m, f, w."""

    def __init__(self, params: Parameters, alpha: float = 0.25, segments: int = 12, table_points: int = 4001):
        self.alpha = float(alpha)
        self.coeffs = valves.curves(params)
        # a shifted valve curve (Parameters.valve_*_shift_pct) is read at the effective angle, and the opening spans
        # the travel where the valve acts (models/valves.py acting_travel): near-linear in the conductance of the
        # valve as it acts, and never inside the shift, where the prediction's gradient would be zero
        self.shifts = {name: float(getattr(params, valves.SHIFT_PARAMS[name])) for name in VALVE_NAMES}
        self.travel = {name: valves.acting_travel(self.shifts[name]) for name in VALVE_NAMES}
        self.knots = np.linspace(0.0, 1.0, segments + 1)
        self._pchip: dict[str, PchipInterpolator] = {}
        self._v_tab: dict[str, np.ndarray] = {}
        self._t_tab: dict[str, np.ndarray] = {}
        v_fine = np.linspace(0.0, 1.0, table_points)
        for name in VALVE_NAMES:
            lo, hi = self.travel[name]
            theta = self._inverse_exact(name, self.knots)
            theta[0], theta[-1] = lo, hi
            pchip = PchipInterpolator(self.knots, theta)
            self._pchip[name] = pchip
            self._v_tab[name] = v_fine
            self._t_tab[name] = np.clip(np.maximum.accumulate(pchip(v_fine)), lo, hi)
        # the three tables side by side, each shifted by its own offset, so that one np.interp call
        # converts all three valves (the controller's hot path, docs/architecture.md 'One control step');
        # angles outside the acting travel map to the end openings 0 and 1
        self._offset = np.arange(len(VALVE_NAMES), dtype=float)
        # each valve's segment of the stacked tables, in angle (200 % apart) and opening (2 apart)
        self._angle_offset, self._opening_offset = 200.0 * self._offset, 2.0 * self._offset
        self._v_stack = np.concatenate([v_fine + 2.0 * i for i in range(len(VALVE_NAMES))])
        t_ends, v_ends = [], []
        for name in VALVE_NAMES:
            t, v = self._t_tab[name], v_fine
            if t[0] > 0.0:
                t, v = np.r_[0.0, t], np.r_[0.0, v]
            if t[-1] < 100.0:
                t, v = np.r_[t, 100.0], np.r_[v, 1.0]
            t_ends.append(t)
            v_ends.append(v)
        self._t_stack = np.concatenate([t + 200.0 * i for i, t in enumerate(t_ends)])
        self._v_of_t = np.concatenate(v_ends)
        self._t_of_v = np.concatenate([self._t_tab[n] for n in VALVE_NAMES])

    def theta_expr(self, name: str, v, margin: float = 0.05):
        """theta(v) in % as a CasADi expression of the opening v.

        The end segments extend ``margin`` beyond [0, 1] (clamped further out), so the derivative
        at the bounds is the curve's own slope: clamping right at 0 or 1 would give a zero
        derivative there and the Gauss-Newton step could not move a valve off a bound.
        """
        pchip = self._pchip[name]
        v = ca.fmin(ca.fmax(v, -margin), 1.0 + margin)
        c, x = pchip.c, pchip.x  # c[:, i]: cubic coefficients of segment i around x[i]
        out = 0
        last = len(x) - 2
        for i in range(last + 1):
            t = v - x[i]
            poly = ((c[0, i] * t + c[1, i]) * t + c[2, i]) * t + c[3, i]
            inside = (v >= x[i]) * (v < x[i + 1]) if i < last else (v >= x[i])
            out = out + inside * poly
        return out

    def opening_exact(self, name: str, theta_pct) -> np.ndarray:
        """v(theta) from the fitted resistance curve read at the effective angle, over the acting travel (numpy)."""
        c, s = self.coeffs[name], self.shifts[name]
        lo, hi = self.travel[name]
        g = 1.0 / np.sqrt(valves.resistance(valves.effective_angle(theta_pct, s), c))
        g0 = 1.0 / np.sqrt(valves.resistance(valves.effective_angle(lo, s), c))
        g1 = 1.0 / np.sqrt(valves.resistance(valves.effective_angle(hi, s), c))
        return self.alpha * (np.asarray(theta_pct, float) - lo) / (hi - lo) + (1.0 - self.alpha) * (g - g0) / (g1 - g0)

    def _inverse_exact(self, name: str, v: np.ndarray) -> np.ndarray:
        lo, hi = np.full_like(v, self.travel[name][0]), np.full_like(v, self.travel[name][1])
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            below = self.opening_exact(name, mid) < v
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        return 0.5 * (lo + hi)

    def angle(self, name: str, v) -> np.ndarray:
        """theta(v) in % (the B-spline, tabulated)."""
        return np.interp(np.clip(v, 0.0, 1.0), self._v_tab[name], self._t_tab[name])

    def angles(self, v) -> np.ndarray:
        """theta(v) in % of valves m, f, w at once: ``v`` (..., 3) -> (..., 3); equals :meth:`angle`."""
        x = np.minimum(np.maximum(v, 0.0), 1.0) + self._opening_offset  # np.clip: ~10 us on 3 values
        return interp(x, self._v_stack, self._t_of_v)

    def openings(self, theta_pct) -> np.ndarray:
        """v(theta) of valves m, f, w at once: ``theta_pct`` (..., 3) -> (..., 3); equals :meth:`opening`."""
        x = np.minimum(np.maximum(theta_pct, 0.0), 100.0) + self._angle_offset
        return interp(x, self._t_stack, self._v_of_t)

    def opening(self, name: str, theta_pct) -> np.ndarray:
        """v(theta), the inverse of :meth:`angle` (tabulated)."""
        return np.interp(np.clip(theta_pct, 0.0, 100.0), self._t_tab[name], self._v_tab[name])
