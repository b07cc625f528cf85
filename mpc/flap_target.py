"""The flaps' rest mix for a reference's split: the openings of least blower power that give its outlet shares.

The outlet flows of flaps m, f, w split the total flow as their branch conductances ``g_i`` (models/valves.py,
thesis sec. 5.2): ``Q_i / Q = g_i / sum(g)``. For given shares ``s_i`` the network conducts most, and the blower
needs least power for the total flow (the fan curve, models/blower.py), with ``g_i = s_i G`` and ``G`` as large as
the flaps allow: ``G = min_i g_i,top / s_i``, the flap that limits it fully open, the others at the conductance their
share asks. This module gives those openings (the decision ``v`` of :mod:`~.valve_map`) from the reference's outlet
flows, numpy or CasADi, so the flap-closure term (``Weights.flap_closure_per_pct2`` with
``OcpSpec.flap_target_from_split``) pulls the flaps to where the energy term already holds them at rest on that
split, and adds only the flat direction's curvature (docs/architecture.md 'The flat direction priced, winter traced').
Where the split is not tracked (its outlet weights zero) the target is every flap fully open (the least resistance).

ASSUMPTION: the model's nominal valve curves and leakage (the controller's own parameters); the conductance fraction
to opening is tabulated on ``TABLE_POINTS`` angles over each flap's acting travel and read linearly.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hvac_mpc.models import valves
from .valve_map import VALVE_NAMES, ValveMap

#: Angles over each flap's acting travel at which conductance and opening are tabulated.
TABLE_POINTS = 201
#: Shares below this count as zero (a flap the split closes): it limits nothing.
SHARE_FLOOR = 1e-9


def _conductance(i: int, theta_pct: float, params, coeffs, leakage: bool) -> float:
    """Branch conductance of flap ``i`` (0 m, 1 f, 2 w) at the commanded angle ``theta_pct`` as the model has it
    (its shift and, with ``leakage``, the closed flaps' leaks taken off; the other two flaps' angles do not enter)."""
    angles = [100.0] * len(VALVE_NAMES)
    angles[i] = float(theta_pct)
    return float(valves.branch_conductances(valves.shifted_angles(angles, params), params, coeffs, leakage)[i])


class SplitTarget:
    """The rest-mix openings of flaps m, f, w for a reference's outlet flows (:meth:`openings`, numpy or CasADi)."""

    def __init__(self, params, valve_map: ValveMap, leakage: bool):
        self.ratio_tables, self.opening_tables, self.g_top = [], [], []
        coeffs = valves.curves(params)
        for i, name in enumerate(VALVE_NAMES):
            lo, hi = valve_map.travel[name]
            theta = np.linspace(lo, hi, TABLE_POINTS)
            g = np.array([_conductance(i, t, params, coeffs, leakage) for t in theta])
            g = np.maximum.accumulate(g)
            ratio = g / g[-1]
            keep = np.r_[True, np.diff(ratio) > 1e-12]  # strictly increasing for the linear reading
            self.ratio_tables.append(ratio[keep])
            self.opening_tables.append(np.asarray(valve_map.opening(name, theta), float)[keep])
            self.g_top.append(float(g[-1]))

    def openings(self, flows, tracked):
        """Openings (fractions, flaps m, f, w) for the outlet flows ``flows`` (any unit, three entries) where
        ``tracked`` (bool or CasADi expression: the split's weights are on); all 1 where not tracked or the flows sum
        to zero. numpy in, numpy array out; CasADi in, a list of three expressions out."""
        if isinstance(flows, (ca.SX, ca.MX)) or isinstance(tracked, (ca.SX, ca.MX)):
            return self._openings_casadi(flows, tracked)
        q = np.maximum(np.asarray(flows, float).ravel()[:3], 0.0)
        total = float(q.sum())
        if not tracked or not total > 0.0:
            return np.ones(3)
        s = q / total
        G = min(g / max(si, SHARE_FLOOR) for g, si in zip(self.g_top, s))
        return np.array([np.interp(min(si * G / g, 1.0), r, v)
                         for si, g, r, v in zip(s, self.g_top, self.ratio_tables, self.opening_tables)])

    def _openings_casadi(self, flows, tracked) -> list:
        q = [ca.fmax(flows[i], 0.0) for i in range(3)]
        total = q[0] + q[1] + q[2]
        safe = ca.fmax(total, SHARE_FLOOR)
        s = [qi / safe for qi in q]
        G = ca.fmin(ca.fmin(*[g / ca.fmax(si, SHARE_FLOOR) for g, si in zip(self.g_top[:2], s[:2])]),
                    self.g_top[2] / ca.fmax(s[2], SHARE_FLOOR))
        out = []
        for si, g, r, v in zip(s, self.g_top, self.ratio_tables, self.opening_tables):
            ratio = ca.fmin(ca.fmax(si * G / g, float(r[0])), 1.0)
            split = ca.pw_lin(ratio, ca.DM(r), ca.DM(v))
            out.append(ca.if_else(ca.logic_and(tracked, total > 0.0), split, 1.0))
        return out
