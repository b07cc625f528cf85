"""Per-step suboptimality of the real-time iteration against the converged solution.

At every step of a closed loop the RTI answers one QP (two on a reference change) from the
shifted previous plan. :class:`FeedbackRecorder` keeps what the controller handed the solver
(estimate, last input, disturbances, reference, weights, input bounds) and the plan it got back.
:func:`suboptimality` then, outside the timed loop, compares two costs of the same problem from
the same state, both the exact cost of :class:`~hvac_mpc.mpc.ocp.TrackingProblem`:

* the RTI's plan: its inputs rolled out through the nonlinear model from the estimate, slacks
  the smallest that make the soft rows hold (so the plan is judged as it would act, not on the
  linearised prediction it was made with);
* the converged optimum: IPOPT on the full NLP (:class:`~hvac_mpc.mpc.ipopt_reference.IpoptReferenceSolver`)
  started from that rolled-out plan, so it finds the local optimum the RTI is converging to.

Two figures per step, both relative to ``J_opt``:

* ``plan``: ``(J_rti - J_opt) / J_opt``, the whole plan judged by the nonlinear model. Right
  after a cold start or a reference change the tail of a one-QP plan can be far off (its
  heater and PTC rows were linearised far from where the rollout goes), so this one has a
  long upper tail;
* ``decision``: the optimum with the first input fixed to the RTI's (the move actually applied,
  the rest of the horizon optimal again) against the free optimum: the cost of acting on the
  RTI's answer instead of the converged one.

Negative values appear only where IPOPT stops at a worse point than another start finds
(reported, not hidden).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hvac_mpc.mpc.ipopt_reference import IpoptReferenceSolver
from hvac_mpc.mpc.ocp import TrackingProblem


class FeedbackRecorder:
    """Wraps a solver with the :class:`~hvac_mpc.mpc.rti_osqp.RtiOsqpSolver` interface and keeps
    each feedback's data and answer (``records``)."""

    def __init__(self, inner):
        self.inner = inner
        self.records: list[dict[str, Any]] = []

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def feedback(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s: float = 0.0):
        res = self.inner.feedback(x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s=time_limit_s)
        self.records.append(dict(x0=np.array(x0), u_prev=np.array(u_prev), d=np.array(d), ref=np.array(ref),
                                 w_y=np.array(w_y), u_lo=np.array(u_lo), u_hi=np.array(u_hi),
                                 U=None if res.U is None else res.U.copy(), cold=bool(res.extra.get("cold_start"))))
        return res


def plan_cost(pb: TrackingProblem, cost_fn, rec: dict[str, Any]) -> tuple[float, np.ndarray]:
    """Exact cost of the recorded plan's inputs from the recorded state, and the primal point
    (states, inputs, slacks) it defines."""
    U = rec["U"]
    X = np.empty((pb.N + 1, pb.nx))
    X[0] = rec["x0"]
    for k in range(pb.N):
        X[k + 1] = np.asarray(pb.F(X[k], U[k], rec["d"], k)).ravel()
    heater = X[1:, pb.i_heater]
    S = np.maximum(0.0, pb.heater_row_coef * heater - pb.heater_row_bound)
    if pb.ptc_limit:
        S[:-1] = np.maximum(S[:-1], pb.ptc_row(heater[:-1], U[1:, pb.i_heater_cmd]))
    J = float(cost_fn(X.T, U.T, S, rec["d"], rec["ref"], rec["w_y"], rec["u_prev"]))
    return J, np.concatenate([X.ravel(), U.ravel(), S])


def suboptimality(pb: TrackingProblem, records: list[dict[str, Any]], *, jit: bool = False,
                  skip_cold: bool = True) -> dict[str, Any]:
    """Per-step suboptimality of the recorded RTI plans (see the module docstring)."""
    cost_fn = pb.cost_function()
    ipopt = IpoptReferenceSolver(pb, warm_start_init_point=False, jit=jit)
    values, decision, failed, iters, steps = [], [], 0, [], []
    for step, rec in enumerate(records):
        if rec["U"] is None or (skip_cold and rec["cold"]):
            continue
        J_rti, w0 = plan_cost(pb, cost_fn, rec)
        ipopt.w = np.clip(w0, *_bounds(ipopt, rec))
        ipopt.lam_x = np.zeros(ipopt.n)
        ipopt.lam_g = np.zeros(len(ipopt.lbg))
        res = ipopt.feedback(rec["x0"], rec["u_prev"], rec["d"], rec["ref"], rec["w_y"], rec["u_lo"], rec["u_hi"])
        if not res.ok:
            failed += 1
            continue
        J_opt = res.extra["objective"]
        w_opt = ipopt.w.copy()
        lo, hi = rec["u_lo"].copy(), rec["u_hi"].copy()
        lo[0] = hi[0] = np.clip(rec["U"][0], rec["u_lo"][0], rec["u_hi"][0])
        ipopt.w = np.clip(w_opt, *_bounds(ipopt, dict(rec, u_lo=lo, u_hi=hi)))
        fixed = ipopt.feedback(rec["x0"], rec["u_prev"], rec["d"], rec["ref"], rec["w_y"], lo, hi)
        if not fixed.ok:
            failed += 1
            continue
        values.append((J_rti - J_opt) / abs(J_opt))
        decision.append((fixed.extra["objective"] - J_opt) / abs(J_opt))
        iters.append(res.iterations)
        steps.append(step)
    out = {"steps": len(values), "ipopt_failures": failed, "converged_with": ipopt.settings}
    for name, vals in (("plan", values), ("decision", decision)):
        v = 100.0 * np.array(vals)
        if len(v):
            out[name] = dict(median_pct=float(np.median(v)), p95_pct=float(np.percentile(v, 95)),
                             max_pct=float(v.max()), min_pct=float(v.min()))
    if iters:
        out["median_ipopt_iterations"] = float(np.median(iters))
    out["per_step"] = {"step": steps, "plan_pct": [100.0 * v for v in values],
                       "decision_pct": [100.0 * v for v in decision]}
    return out


def _bounds(ipopt: IpoptReferenceSolver, rec: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    lbx = np.full(ipopt.n, -np.inf)
    ubx = np.full(ipopt.n, np.inf)
    lbx[ipopt.iu0:ipopt.is0] = rec["u_lo"].ravel()
    ubx[ipopt.iu0:ipopt.is0] = rec["u_hi"].ravel()
    lbx[ipopt.is0:] = 0.0
    return lbx, ubx
