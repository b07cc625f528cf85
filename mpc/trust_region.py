"""A trust region for the real-time iteration's QP: where the QP's plan raises the nonlinear cost, the QP is
solved again with its inputs held near the linearisation point.

The real-time iteration takes the QP's plan as one Gauss-Newton step from the linearisation point. Where the
box's response is bilinear in two inputs' effects (the core flow valve a sets, times the heater body's
excess over the air the core passes on), the QP's linear model is right for small moves and wrong for the whole
stroke: linearised at valve a shut, it sees opening as better than it is; linearised at valve a open, shutting
it (and lowering the blower with it) as better than it is. Where the entering air is nearly as warm as the body
can make the core's air, the two errors change the sign of the plan, and the iteration alternates between the
two ends (docs/identification.md, 'Why the right model tracks worse: the recirculation term in the QP').

:func:`region_bounds` is the QP's input box for one trust radius: each stage's input within ``radius`` times
that input's range of its value in the linearisation point's plan, inside the problem's own bounds. The
solver (:meth:`.rti_osqp.RtiOsqpSolver`, ``trust_radii``) checks each QP's plan on the problem's nonlinear
cost (:class:`.plan_merit.PlanMerit`); where it is worse than the linearisation point's, it solves the same
QP again within each radius in turn and takes the first plan no worse than the linearisation point (else the
least cost among those solved). Unlike the damped step (``step_fractions``), the inputs the region leaves
free move to their best within it, so the blower is re-planned for the valve a the region allows.

Not on a cold start (the first step after a reset): its linearisation point is the starting command held over the
horizon, a guess and not a plan, so a QP plan costing more than it says nothing of a linearisation error, and the
start's SQP iterations (``cold_start_qps``) move on from it anyway. With the region there, each iteration stayed
within a radius of the last and the first command came from near the guess: on the independent box whose heater
body loses heat to its walls the heater held at 3 W instead of 10 W through the warm-up, the body leaner at the
step up (docs/identification.md, "The trust region at the cold start").
"""

from __future__ import annotations

import numpy as np

#: Largest number of radii a solver tries on one QP (each one more QP solve with the same matrices).
MAX_RADII = 4


def check_radii(radii) -> tuple[float, ...]:
    """``radii`` as a tuple of floats, each in (0, 1), strictly decreasing, at most :data:`MAX_RADII`;
    ValueError naming the rule otherwise."""
    if not isinstance(radii, (tuple, list)) or len(radii) > MAX_RADII:
        raise ValueError(f"trust radii {radii!r} must be a sequence of at most {MAX_RADII} numbers in (0, 1)")
    out = []
    for r in radii:
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not np.isfinite(r) or not 0.0 < r < 1.0:
            raise ValueError(f"trust radius {r!r} must be a number in (0, 1)")
        if out and r >= out[-1]:
            raise ValueError(f"trust radii {tuple(radii)!r} must decrease")
        out.append(float(r))
    return tuple(out)


def region_bounds(u_lin: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray, span: np.ndarray,
                  radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The QP's input bounds (N x nu, scaled) within ``radius`` x ``span`` (per input, the input's scaled
    range) of the linearisation point's plan ``u_lin`` and inside ``u_lo`` .. ``u_hi``. Where the plan lies
    outside the problem's bounds (the first stage's rate limits moved on), the region is the nearest point
    of those bounds, so the box is never empty."""
    lo = np.maximum(u_lo, u_lin - radius * span)
    hi = np.minimum(u_hi, u_lin + radius * span)
    lo = np.minimum(lo, u_hi)
    hi = np.maximum(hi, lo)
    return lo, hi
