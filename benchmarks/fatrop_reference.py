"""The MPC's problem solved to convergence by fatrop (benchmark only), from the stage-wise description.

fatrop (bundled with CasADi) is an interior-point NLP solver that exploits the optimal-control
structure (a Riccati recursion per iteration) but only sees it when every row lives within one
stage. The stage-wise description (:class:`~hvac_mpc.mpc.stage_ocp.StageOcp`, state augmented
with the last applied input) has that form; its ``"stagewise"`` transcription
(:class:`~hvac_mpc.mpc.stage_nlp.StageNlp`, the one that gives IPOPT its NLP in the compact
layout) orders the variables ``xa_0, v_0, xa_1, ...`` with ``xa_k = [x_k, u_{k-1}, s_k]`` and
``v_k = [u_k, s_{k+1}]`` (the slack of a soft row rides in the state: fatrop holds no soft
constraints) and the rows stage by stage, the dynamics first. CasADi's ``nlpsol`` detects the
structure (``structure_detection='auto'``) from the symbolic NLP, so fatrop runs interpreted: set
up from the generated C of the same NLP (:func:`hvac_mpc.mpc.codegen.compiled_nlpsol`, as IPOPT's
``--jit``) the structure detection fails (measured: the build succeeds after 24 min on the loaded
two-core machine, the solver's set-up then raises in ``Function::factory``).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from hvac_mpc.mpc.ocp import TrackingProblem, shift_maps, shift_nodes
from hvac_mpc.mpc.rti_osqp import SolveResult
from hvac_mpc.mpc.stage_nlp import StageNlp
from hvac_mpc.mpc.stage_ocp import StageOcp


class FatropSolver:
    """Stage-wise tracking problem in fatrop, with the solver interface of the RTI solver."""

    name = "fatrop"

    def __init__(self, problem: TrackingProblem, *, tol: float = 1e-6, max_iter: int = 300):
        self.pb = pb = problem
        self.transcription = tr = StageNlp(StageOcp(pb), "stagewise")
        opts = {"expand": True, "structure_detection": "auto", "equality": tr.equality, "fatrop.tol": tol,
                "fatrop.max_iter": int(max_iter), "fatrop.print_level": 0, "print_time": False,
                "fatrop.mu_init": 1e-1}
        self.nlp = ca.nlpsol("fatrop_reference", "fatrop", tr.nlp, opts)
        self.settings = {"nlp_solver": "fatrop", "tol": tol, "max_iter": int(max_iter), "hessian": "exact",
                         "structure": "stage-wise, augmented state [x, u_prev, slack]",
                         "compiled": False,
                         "description": "StageOcp, stagewise transcription (mpc/stage_nlp.py)"}
        self._i0, self._w1, self._j = shift_maps(pb.t_nodes, pb.dt_s)
        self.fail_next = 0
        self.reset()

    def reset(self) -> None:
        self.w = None

    @property
    def has_trajectory(self) -> bool:
        return self.w is not None

    def prepare(self, x_pred, u_prev, d, ref, w_y) -> float:
        """Shift the previous solution one sample (the warm start)."""
        t0 = time.perf_counter()
        if self.w is not None:
            tr, N = self.transcription, self.pb.N
            X, U, S = tr.unpack(self.w)
            Xs = shift_nodes(X, self._i0, self._w1)
            Xs[0] = x_pred
            self.w = tr.pack(Xs, U[self._j], S[np.minimum(self._j, N - 1)], u_prev)
        return time.perf_counter() - t0

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
            sol = self.nlp(x0=np.clip(self.w, lbx, ubx), p=tr.parameters(x0, u_prev, d, ref, w_y), lbx=lbx,
                           ubx=ubx, lbg=tr.lbg, ubg=tr.ubg)
        except RuntimeError as exc:
            return SolveResult(False, f"fatrop error: {exc}", feedback_time_s=time.perf_counter() - t0)
        st = self.nlp.stats()
        iters = int(st.get("iter_count", 0))
        w = np.asarray(sol["x"]).ravel()
        if not np.all(np.isfinite(w)):
            return SolveResult(False, "non-finite solution", iterations=iters, feedback_time_s=time.perf_counter() - t0)
        self.w = w
        if not st.get("success", True):
            return SolveResult(False, f"fatrop: {st.get('return_status', 'failed')}", iterations=iters,
                               feedback_time_s=time.perf_counter() - t0)
        X, U, S = tr.unpack(w)
        return SolveResult(True, "solved", X=X.copy(), U=U.copy(), S=S.copy(), iterations=iters, qp_solves=0,
                           feedback_time_s=time.perf_counter() - t0, extra={"objective": float(sol["f"])})
