"""The same discrete problem as :mod:`hvac_mpc.mpc.rti_osqp`, solved to convergence by IPOPT.

A reference for comparison (solve time, closed-loop cost), not for real-time use. The NLP is
built once with CasADi (SX, exact Hessian) from :class:`TrackingProblem`: identical variables
``[x_0..x_N, u_0..u_N-1, s_1..s_N]`` (scaled), stage functions, cost, bounds, rate limits and
soft heater limit. Per-step data enter as NLP parameters; every solve is warm-started from the
shifted previous primal solution and the previous multipliers. ``obj_scaling`` only scales the
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


class IpoptReferenceSolver:
    """Full-NLP reference with the solver interface of :class:`RtiOsqpSolver`."""

    name = "ipopt"

    def __init__(self, problem: TrackingProblem, *, tol: float = 1e-6, max_iter: int = 300,
                 warm_start_init_point: bool = True, obj_scaling: float = 1e-3, jit: bool = False):
        self.pb = pb = problem
        N, nx, nu = pb.N, pb.nx, pb.nu
        self.n = (N + 1) * nx + N * nu + N
        w = ca.SX.sym("w", self.n)
        X = ca.reshape(w[:(N + 1) * nx], nx, N + 1)
        U = ca.reshape(w[(N + 1) * nx:(N + 1) * nx + N * nu], nu, N)
        S = w[(N + 1) * nx + N * nu:]
        x0 = ca.SX.sym("x0", nx)
        u_prev = ca.SX.sym("u_prev", nu)
        d = ca.SX.sym("d", pb.nd)
        ref = ca.SX.sym("ref", pb.ny)
        w_y = ca.SX.sym("w_y", pb.ny)
        p = ca.vertcat(x0, u_prev, d, ref, w_y)
        cost = pb.symbolic_cost(X, U, S, d, ref, w_y, u_prev)
        g = [X[:, 0] - x0]
        for k in range(N):
            g.append(pb.F(X[:, k], U[:, k], d, k) - X[:, k + 1])
        self.n_eq = (N + 1) * nx
        for k in range(1, N):
            g.append(U[:, k] - U[:, k - 1])
        g.append(pb.heater_row_coef * X[pb.i_heater, 1:].T - S)
        n_ptc = N - 1 if pb.ptc_limit else 0
        if n_ptc:
            g.append(pb.ptc_row(X[pb.i_heater, 1:N], U[pb.i_heater_cmd, 1:N]).T - S[:N - 1])
        g = ca.vertcat(*g)
        # the cost sums tracking errors over ~100 s of horizon (values of 1e2..1e4); without the extra
        # objective scaling IPOPT cycles near the optimum on the flat directions left by the
        # redundant actuators (measured on the simulated plant)
        opts = {"ipopt.tol": tol, "ipopt.max_iter": int(max_iter), "ipopt.print_level": 0, "print_time": False,
                "ipopt.sb": "yes", "ipopt.acceptable_iter": 0, "ipopt.obj_scaling_factor": obj_scaling}
        if warm_start_init_point:
            opts.update({"ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-8,
                         "ipopt.warm_start_mult_bound_push": 1e-8, "ipopt.warm_start_slack_bound_push": 1e-8,
                         "ipopt.mu_init": 1e-4})
        nlp = {"x": w, "p": p, "f": cost, "g": g}
        self.codegen = CodegenReport()
        if jit:
            self.nlp = compiled_nlpsol("ipopt_reference", "ipopt", nlp, opts, self.codegen)
        else:
            self.nlp = ca.nlpsol("ipopt_reference", "ipopt", nlp, opts)
        self.settings = {"tol": tol, "max_iter": int(max_iter), "warm_start_init_point": warm_start_init_point,
                         "obj_scaling": obj_scaling, "compiled": self.codegen.active,
                         "linear_solver": "mumps", "hessian": "exact"}
        rb = pb.rate_bounds()
        self.lbg = np.concatenate([np.zeros(self.n_eq), -rb.ravel(), np.full(N + n_ptc, -np.inf)])
        self.ubg = np.concatenate([np.zeros(self.n_eq), rb.ravel(), np.full(N, pb.heater_row_bound),
                                   np.zeros(n_ptc)])
        self.iu0 = (N + 1) * nx
        self.is0 = self.iu0 + N * nu
        self._i0, self._w1, self._j = shift_maps(pb.t_nodes, pb.dt_s)
        self.fail_next = 0
        self.reset()

    def reset(self) -> None:
        self.w = None
        self.lam_x = None
        self.lam_g = None

    @property
    def has_trajectory(self) -> bool:
        return self.w is not None

    def prepare(self, x_pred, u_prev, d, ref, w_y) -> float:
        """Shift the previous primal solution one sample (the warm start; multipliers kept)."""
        t0 = time.perf_counter()
        if self.w is not None:
            pb, N, nx, nu = self.pb, self.pb.N, self.pb.nx, self.pb.nu
            X = self.w[:self.iu0].reshape(N + 1, nx)
            U = self.w[self.iu0:self.is0].reshape(N, nu)
            S = self.w[self.is0:]
            Xs = shift_nodes(X, self._i0, self._w1)
            Xs[0] = x_pred
            self.w = np.concatenate([Xs.ravel(), U[self._j].ravel(), S[np.minimum(self._j, N - 1)]])
        return time.perf_counter() - t0

    def feedback(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s: float = 0.0) -> SolveResult:
        t0 = time.perf_counter()
        pb, N, nx, nu = self.pb, self.pb.N, self.pb.nx, self.pb.nu
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure")
        if self.w is None:
            X = pb.rollout(x0, u_prev, d)
            self.w = np.concatenate([X.ravel(), np.tile(u_prev, N), np.zeros(N)])
            self.lam_x = np.zeros(self.n)
            self.lam_g = np.zeros(len(self.lbg))
        lbx = np.full(self.n, -np.inf)
        ubx = np.full(self.n, np.inf)
        lbx[self.iu0:self.is0] = u_lo.ravel()
        ubx[self.iu0:self.is0] = u_hi.ravel()
        lbx[self.is0:] = 0.0
        w0 = np.clip(self.w, lbx, ubx)
        p = np.concatenate([x0, u_prev, d, ref, w_y])
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
        X = wsol[:self.iu0].reshape(N + 1, nx)
        U = wsol[self.iu0:self.is0].reshape(N, nu)
        S = wsol[self.is0:]
        return SolveResult(True, status, X=X.copy(), U=U.copy(), S=S.copy(), iterations=iters, qp_solves=0,
                           feedback_time_s=time.perf_counter() - t0, extra={"objective": float(sol["f"])})
