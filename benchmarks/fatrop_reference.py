"""The MPC's problem solved to convergence by fatrop (benchmark only), from the stage-wise description.

fatrop (bundled with CasADi) is an interior-point NLP solver that exploits the optimal-control
structure (a Riccati recursion per iteration) but only sees it when every row lives within one
stage. The stage-wise description (:class:`~hvac_mpc.mpc.stage_ocp.StageOcp`, state augmented
with the last applied input) has that form; its ``"stagewise"`` transcription
(:class:`~hvac_mpc.mpc.stage_nlp.StageNlp`, the one that gives IPOPT its NLP in the compact
layout) orders the variables ``xa_0, v_0, xa_1, ...`` with ``xa_k = [x_k, u_{k-1}, s_k]`` and
``v_k = [u_k, s_{k+1}]`` (the slack of a soft row rides in the state: fatrop holds no soft
constraints) and the rows stage by stage, the dynamics first. CasADi's ``nlpsol`` detects the
structure (``structure_detection='auto'``) from the sparsity of the constraint Jacobian.

Settings, and why (docs/architecture.md, 'Solver comparison'):

* the objective enters times ``obj_scaling`` = 1e-3, the scaling IPOPT's reference gets as its
  ``obj_scaling_factor``: the same minimiser. Unscaled, fatrop failed on 90 of the 240 steps of the
  solve-time loop (status 1: line search failed, then its restoration phase). The failures start at
  a reference change (13 -> 20 degC at 60 s, 24 and 22 degC later): with the supply-temperature weight
  5 and a tracking error of several degC the multipliers of the initial-state and dynamics rows reach
  80..450 and those of the active input bounds 150 (0.35..0.65 and 80 on the steps it solved). fatrop
  stops on an unscaled error below ``tol`` and drives the barrier parameter to ``tol / 10``, so an
  active bound's slack has to reach about 1e-7 / 150 ~ 1e-9: there the Newton steps no longer make
  progress (the iterate was at the optimum to 4e-6 relative), the line search and the restoration
  fail, the fallback acts, the error stays large and the next step fails alike. Scaled, every step
  solves;
* ``tol`` = :data:`IPOPT_TOL_FACTOR` times IPOPT's: fatrop at 1e-7 stops as close to the optimum as
  IPOPT at 1e-6 (from the same states and starts: both 2e-5..8e-5 relative above a 1e-10 optimum,
  equal to two digits; fatrop at 1e-6 stopped ten times further off), so the times compare equal
  accuracy;
* ``jit``: the NLP's functions as generated C (:func:`hvac_mpc.mpc.codegen.compiled_nlpsol`, as
  IPOPT's ``--jit``). The solver is set up without CasADi's ``expand`` (the NLP is SX already): with
  it the solver wrapped the loaded library in an SX function and tried to differentiate it
  (``nlp_grad``), which generated code cannot, and the set-up raised in ``Function::factory``. The
  code is large (21.5 MB of C): built at -O0 it runs slower than the interpreter; the -O1 build
  did not finish within the compiler's 30-minute limit on the loaded two-core machine, where the
  solver falls back to the interpreter (the reason in ``codegen``).
"""

from __future__ import annotations

import time
from typing import Any

import casadi as ca
import numpy as np

from hvac_mpc.mpc.codegen import CodegenReport, compiled_nlpsol
from hvac_mpc.mpc.ipopt_reference import IpoptReferenceSolver, ShiftedPrimalStart
from hvac_mpc.mpc.ocp import TrackingProblem
from hvac_mpc.mpc.rti_osqp import SolveResult
from hvac_mpc.mpc.stage_nlp import StageNlp
from hvac_mpc.mpc.stage_ocp import StageOcp

from .suboptimality import FeedbackRecorder

#: fatrop's ``tol`` for the accuracy of IPOPT's (module docstring): this factor times IPOPT's ``tol``.
IPOPT_TOL_FACTOR = 0.1


class FatropSolver(ShiftedPrimalStart):
    """Stage-wise tracking problem in fatrop, with the solver interface of the RTI solver."""

    name = "fatrop"

    def __init__(self, problem: TrackingProblem, *, tol: float = 1e-7, max_iter: int = 300,
                 obj_scaling: float = 1e-3, jit: bool = False):
        if not (np.isfinite(obj_scaling) and obj_scaling > 0.0):
            raise ValueError(f"obj_scaling = {obj_scaling!r} must be a finite number > 0")
        self.pb = pb = problem
        self.transcription = tr = StageNlp(StageOcp(pb), "stagewise")
        self.obj_scaling = float(obj_scaling)
        # the objective times obj_scaling: the same minimiser, IPOPT's obj_scaling_factor (module docstring)
        nlp = {**tr.nlp, "f": self.obj_scaling * tr.nlp["f"]}
        opts = {"structure_detection": "auto", "equality": tr.equality, "fatrop.tol": tol,
                "fatrop.max_iter": int(max_iter), "fatrop.print_level": 0, "print_time": False,
                "fatrop.mu_init": 1e-1}
        self.codegen = CodegenReport()
        if jit:
            self.nlp = compiled_nlpsol("fatrop_reference", "fatrop", nlp, opts, self.codegen)
        else:
            self.nlp = ca.nlpsol("fatrop_reference", "fatrop", nlp, opts)
        self.settings = {"nlp_solver": "fatrop", "tol": tol, "max_iter": int(max_iter), "obj_scaling": self.obj_scaling,
                         "hessian": "exact",
                         "structure": "stage-wise, augmented state [x, u_prev, slack]",
                         "compiled": self.codegen.active,
                         "description": "StageOcp, stagewise transcription (mpc/stage_nlp.py)"}
        self._init_shift(pb)

    def feedback(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s: float = 0.0) -> SolveResult:
        t0 = time.perf_counter()
        pb, tr = self.pb, self.transcription
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure")
        if self.w is None:
            self.w = tr.pack(pb.rollout(x0, u_prev, d), np.tile(u_prev, (pb.N, 1)), np.zeros(pb.N), u_prev)
        lbx, ubx = tr.bounds(u_lo, u_hi)
        try:
            sol = self.nlp(x0=np.clip(self.w, lbx, ubx), p=tr.parameters(x0, u_prev, d, ref, w_y, self.p_model),
                           lbx=lbx, ubx=ubx, lbg=tr.lbg, ubg=tr.ubg)
        except RuntimeError as exc:
            return SolveResult(False, f"fatrop error: {exc}", feedback_time_s=time.perf_counter() - t0)
        st = self.nlp.stats()
        iters = int(st.get("iter_count", 0))
        w = np.asarray(sol["x"]).ravel()
        if not np.all(np.isfinite(w)):
            return SolveResult(False, "non-finite solution", iterations=iters, feedback_time_s=time.perf_counter() - t0)
        if not st.get("success", True):  # the warm start stays the shifted previous solution (as IPOPT's)
            return SolveResult(False, f"fatrop: {st.get('return_status', 'failed')}", iterations=iters,
                               feedback_time_s=time.perf_counter() - t0)
        self.w = w
        X, U, S = tr.unpack(w)
        return SolveResult(True, "solved", X=X.copy(), U=U.copy(), S=S.copy(), iterations=iters, qp_solves=0,
                           feedback_time_s=time.perf_counter() - t0,
                           extra={"objective": float(sol["f"]) / self.obj_scaling})


class StartRecorder(FeedbackRecorder):
    """:class:`~hvac_mpc.benchmarks.suboptimality.FeedbackRecorder` of a :class:`FatropSolver` that also
    keeps, per feedback, the point fatrop started from (``start``: states, inputs, slacks; None on a
    cold start) and its answer (``ok``, ``objective``), for :func:`agreement`. What it adds to a step
    is a few copies of small arrays (microseconds against fatrop's tens of milliseconds)."""

    def feedback(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s: float = 0.0):
        inner = self.inner
        start = None if inner.w is None else inner.transcription.unpack(inner.w)
        res = super().feedback(x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s=time_limit_s)
        self.records[-1].update(start=start, ok=bool(res.ok), objective=res.extra.get("objective"),
                                p_model=inner.p_model.copy())
        return res


def agreement(pb: TrackingProblem, records: list[dict[str, Any]], **ipopt_settings) -> dict[str, Any]:
    """Per step, fatrop's objective against IPOPT's on the same problem from the same state and the
    same starting point (:class:`~hvac_mpc.mpc.ipopt_reference.IpoptReferenceSolver`, its default
    settings or ``ipopt_settings``; no multipliers carried over): ``rel_diff`` = (J_fatrop -
    J_ipopt) / J_ipopt over the steps both solved. Failures of either are counted, not compared."""
    ipopt = IpoptReferenceSolver(pb, **{"warm_start_init_point": False, **ipopt_settings})
    diffs, steps, failed = [], [], 0
    for step, rec in enumerate(records):
        ipopt.reset()
        ipopt.set_parameters(rec["p_model"])
        if rec["start"] is not None:
            ipopt.w = ipopt.transcription.pack(*rec["start"], rec["u_prev"])
            ipopt.lam_x, ipopt.lam_g = np.zeros(ipopt.n), np.zeros(len(ipopt.lbg))
        res = ipopt.feedback(rec["x0"], rec["u_prev"], rec["d"], rec["ref"], rec["w_y"], rec["u_lo"], rec["u_hi"])
        failed += not res.ok
        if res.ok and rec["ok"]:
            j = res.extra["objective"]
            diffs.append((rec["objective"] - j) / abs(j))
            steps.append(step)
    v = np.array(diffs)
    out: dict[str, Any] = {"steps": len(records), "compared": len(diffs),
                           "fatrop_failures": sum(not r["ok"] for r in records), "ipopt_failures": failed,
                           "ipopt_settings": ipopt.settings}
    if len(v):
        out.update(rel_diff_median=float(np.median(v)), rel_diff_abs_p95=float(np.percentile(np.abs(v), 95)),
                   rel_diff_max=float(v.max()), rel_diff_min=float(v.min()))
    out["per_step"] = {"step": steps, "rel_diff": diffs}
    return out


def agreement_line(ag: dict[str, Any]) -> str:
    """One printed line of :func:`agreement`'s result."""
    line = (f"fatrop against IPOPT, same state and start, {ag['compared']} of {ag['steps']} steps (failures: "
            f"fatrop {ag['fatrop_failures']}, IPOPT {ag['ipopt_failures']})")
    if not ag["compared"]:
        return line
    return (line + f": cost (fatrop / IPOPT - 1) median {ag['rel_diff_median']:+.1e}, |.| p95 "
            f"{ag['rel_diff_abs_p95']:.1e}, range {ag['rel_diff_min']:+.1e} .. {ag['rel_diff_max']:+.1e}")
