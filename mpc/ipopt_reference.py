"""The same discrete problem as :mod:`hvac_mpc.mpc.rti_osqp`, solved to convergence by IPOPT.

A reference for comparison (solve time, closed-loop cost), not for real-time use. The NLP is
built once with CasADi (SX, exact Hessian): the compact transcription
(:class:`~hvac_mpc.mpc.stage_nlp.StageNlp`) of the stage-wise description
(:class:`~hvac_mpc.mpc.stage_ocp.StageOcp`) that fatrop and do-mpc are built from too: the
variables ``[x_0..x_N, u_0..u_N-1, s_1..s_N]`` (scaled) of the real-time iteration's QP, the
same stage functions, cost, bounds, rate limits and soft heater and PTC rows. Per-step data
enter as NLP parameters; every solve is warm-started from the shifted previous primal solution
and the previous multipliers. ``obj_scaling`` only scales the
objective inside IPOPT (an option, the problem is unchanged). With ``jit`` the NLP's functions
(objective, constraints, gradient, Jacobian, Hessian of the Lagrangian) run as generated C,
compiled once and cached on disk (:func:`hvac_mpc.mpc.codegen.compiled_nlpsol`).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from .codegen import CodegenReport, compiled_nlpsol
from .ocp import TrackingProblem, shift_maps, shift_nodes
from .rti_osqp import SolveResult
from .stage_nlp import StageNlp
from .stage_ocp import StageOcp



def shifted_start(transcription, w: np.ndarray, maps: tuple, x_pred: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
    """The solution ``w`` of a stage-wise transcription shifted one sample, the warm start of the next
    solve: states by ``maps`` (:func:`~hvac_mpc.mpc.ocp.shift_maps`) with ``x_pred`` first, inputs and
    slacks by node, ``u_prev`` the command in force."""
    i0, w1, j = maps
    X, U, S = transcription.unpack(w)
    Xs = shift_nodes(X, i0, w1)
    Xs[0] = x_pred
    return transcription.pack(Xs, U[j], S[np.minimum(j, len(S) - 1)], u_prev)


class ShiftedPrimalStart:
    """The warm start the converged references share: the last primal solution ``w`` of the
    stage-wise transcription shifted one sample (:func:`shifted_start`); what a subclass keeps
    besides (multipliers) it resets in its own ``reset``."""

    def _init_shift(self, pb: TrackingProblem) -> None:
        self._i0, self._w1, self._j = shift_maps(pb.t_nodes, pb.dt_s)
        self.fail_next = 0
        self.p_model = np.array(pb.model.p_default, float)
        self.reset()

    def set_parameters(self, p: np.ndarray) -> None:
        """Model parameters (``HvacModel.p_default`` order) of the next solves, e.g. the filter's with its heat flow
        into the mixed air (:class:`~.estimator.DisturbanceEkf`, ``adapts_parameters``): an NLP parameter, no
        rebuild. Without it a controller whose filter adapts them fell back at every step."""
        self.p_model = np.array(p, float)

    def reset(self) -> None:
        self.w = None

    @property
    def has_trajectory(self) -> bool:
        return self.w is not None

    def prepare(self, x_pred, u_prev, d, ref, w_y) -> float:
        """Shift the previous primal solution one sample (the warm start; multipliers kept)."""
        t0 = time.perf_counter()
        if self.w is not None:
            self.w = shifted_start(self.transcription, self.w, (self._i0, self._w1, self._j), x_pred, u_prev)
        return time.perf_counter() - t0


class IpoptReferenceSolver(ShiftedPrimalStart):
    """Full-NLP reference with the solver interface of :class:`RtiOsqpSolver`."""

    name = "ipopt"

    def __init__(self, problem: TrackingProblem, *, tol: float = 1e-6, max_iter: int = 300,
                 warm_start_init_point: bool = True, obj_scaling: float = 1e-3, jit: bool = False):
        self.pb = pb = problem
        # the NLP is the compact transcription of the stage-wise description (variables
        # [x_0..x_N, u_0..u_N-1, s_1..s_N], rows x0, dynamics, rate, heater, PTC)
        self.transcription = StageNlp(StageOcp(pb), "compact")
        tr = self.transcription
        self.n = tr.n
        self.n_eq = len(tr.rows["x0"]) + tr.rows["dyn"].size
        # the cost sums tracking errors over ~100 s of horizon (values of 1e2..1e4); without the extra
        # objective scaling IPOPT cycles near the optimum on the flat directions left by the
        # redundant actuators (measured on the simulated plant)
        opts = {"ipopt.tol": tol, "ipopt.max_iter": int(max_iter), "ipopt.print_level": 0, "print_time": False,
                "ipopt.sb": "yes", "ipopt.acceptable_iter": 0, "ipopt.obj_scaling_factor": obj_scaling}
        if warm_start_init_point:
            opts.update({"ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-8,
                         "ipopt.warm_start_mult_bound_push": 1e-8, "ipopt.warm_start_slack_bound_push": 1e-8,
                         "ipopt.mu_init": 1e-4})
        nlp = tr.nlp
        self.codegen = CodegenReport()
        if jit:
            self.nlp = compiled_nlpsol("ipopt_reference", "ipopt", nlp, opts, self.codegen)
        else:
            self.nlp = ca.nlpsol("ipopt_reference", "ipopt", nlp, opts)
        self.settings = {"tol": tol, "max_iter": int(max_iter), "warm_start_init_point": warm_start_init_point,
                         "obj_scaling": obj_scaling, "compiled": self.codegen.active,
                         "linear_solver": "mumps", "hessian": "exact",
                         "description": "StageOcp, compact transcription (mpc/stage_nlp.py)"}
        self.lbg, self.ubg = tr.lbg, tr.ubg
        self.iu0 = int(tr.iu[0, 0])
        self.is0 = int(tr.i_slack[0])
        self._init_shift(pb)

    def reset(self) -> None:
        super().reset()
        self.lam_x = None
        self.lam_g = None

    def feedback(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s: float = 0.0) -> SolveResult:
        t0 = time.perf_counter()
        pb, N = self.pb, self.pb.N
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure")
        if self.w is None:
            tr = self.transcription
            self.w = tr.pack(pb.rollout(x0, u_prev, d), np.tile(u_prev, (N, 1)), np.zeros(N), u_prev)
            self.lam_x = np.zeros(self.n)
            self.lam_g = np.zeros(len(self.lbg))
        lbx, ubx = self.transcription.bounds(u_lo, u_hi)
        w0 = np.clip(self.w, lbx, ubx)
        p = self.transcription.parameters(x0, u_prev, d, ref, w_y, self.p_model)
        try:
            sol = self.nlp(x0=w0, p=p, lbx=lbx, ubx=ubx, lbg=self.lbg, ubg=self.ubg, lam_x0=self.lam_x,
                           lam_g0=self.lam_g)
        except RuntimeError as exc:
            return SolveResult(False, f"ipopt error: {exc}", feedback_time_s=time.perf_counter() - t0)
        st = self.nlp.stats()
        status = str(st.get("return_status", "unknown"))
        iters = int(st.get("iter_count", 0))
        wsol = np.asarray(sol["x"]).ravel()
        if not st.get("success", False) or not np.all(np.isfinite(wsol)):
            return SolveResult(False, status, iterations=iters, qp_solves=0,
                               feedback_time_s=time.perf_counter() - t0)
        self.w = wsol
        self.lam_x = np.asarray(sol["lam_x"]).ravel()
        self.lam_g = np.asarray(sol["lam_g"]).ravel()
        X, U, S = self.transcription.unpack(wsol)
        return SolveResult(True, status, X=X.copy(), U=U.copy(), S=S.copy(), iterations=iters, qp_solves=0,
                           feedback_time_s=time.perf_counter() - t0, extra={"objective": float(sol["f"])})
