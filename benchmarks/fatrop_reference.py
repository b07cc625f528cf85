"""The MPC's problem written stage by stage and solved to convergence by fatrop (benchmark only).

fatrop (bundled with CasADi) is an interior-point NLP solver that exploits the optimal-control
structure (a Riccati recursion per iteration) but only sees it when every constraint lives
within one stage. :class:`~hvac_mpc.mpc.ocp.TrackingProblem` couples stages through the move
cost, the rate limits and the slacks, so here the state is augmented, acados-style:

    xa_k = [x_k, u_{k-1}, sigma_k]      (model states, last applied input, slack of node k)
    v_k  = [u_k, sigma_{k+1}]           (inputs, slack of the next node)
    xa_{k+1} = [F_k(x_k, u_k, d), u_k, sigma_{k+1}]

so the move cost ``w_du (u_k - u_{k-1})^2``, the rate limits, the heater row of node k (state
and slack in xa_k), the PTC row (x_k, u_k, sigma_k) and the terminal cost (``y(x_N, u_{N-1})``)
each use one stage's variables. The initial stage is pinned to ``[estimate, last command, 0]``.
Cost, bounds and rows are those of the tracking problem, term by term: the same optimum.

Declared through ``casadi.Opti`` in stage order (x_0, v_0, x_1, ...; per stage the dynamics
first, then the path constraints), with ``structure_detection='auto'``.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from hvac_mpc.mpc.ocp import STAGE_OUTPUTS, TrackingProblem, shift_maps, shift_nodes
from hvac_mpc.mpc.rti_osqp import SolveResult


class FatropSolver:
    """Stage-wise tracking problem in fatrop, with the solver interface of the RTI solver."""

    name = "fatrop"

    def __init__(self, problem: TrackingProblem, *, tol: float = 1e-6, max_iter: int = 300):
        self.pb = pb = problem
        N, nx, nu, nd, ny = pb.N, pb.nx, pb.nu, pb.nd, pb.ny
        opti = ca.Opti()
        na = nx + nu + 1
        XA, V = [], []
        for k in range(N + 1):
            XA.append(opti.variable(na))
            if k < N:
                V.append(opti.variable(nu + 1))
        x0 = opti.parameter(nx)
        u_prev = opti.parameter(nu)
        d = opti.parameter(nd)
        ref = opti.parameter(ny)
        w_y = opti.parameter(ny)
        u_lo = opti.parameter(nu, N)
        u_hi = opti.parameter(nu, N)
        sw = w_y / ca.DM(pb.y_scale ** 2)
        rb = pb.rate_bounds()
        i_pow = STAGE_OUTPUTS.index("heater_power_w")
        ib = pb.energy_grad_u.nonzero()[0][0]
        cost = 0
        for k in range(N + 1):
            x, ul, sig = XA[k][:nx], XA[k][nx:nx + nu], XA[k][nx + nu]
            if k == 0:
                opti.subject_to(XA[0] == ca.vertcat(x0, u_prev, 0))
            if k == N:
                e = pb.Y(x, ul, d) - ref
                cost += pb.terminal_s * ca.dot(sw, e * e)
                opti.subject_to(pb.heater_row_coef * x[pb.i_heater] - sig <= pb.heater_row_bound)
                break
            u, sig_next = V[k][:nu], V[k][nu]
            opti.subject_to(XA[k + 1] == ca.vertcat(pb.F(x, u, d, k), u, sig_next))
            y = pb.Y(x, u, d)
            e = y - ref
            blower_w = u[ib] * pb.u_sc[ib] + pb.u_off[ib]
            cost += pb.dt[k] * (ca.dot(sw, e * e)
                                + pb.energy_weight * ((blower_w + y[i_pow]) / pb.energy_scale_w) ** 2)
            du = u - ul
            cost += ca.dot(ca.DM(pb.w_du), du * du)
            cost += pb.dt[k] * (pb.slack_l1 * sig_next + pb.slack_l2 * sig_next ** 2)
            opti.subject_to(opti.bounded(u_lo[:, k], u, u_hi[:, k]))
            opti.subject_to(sig_next >= 0)
            if k >= 1:
                opti.subject_to(opti.bounded(-rb[k - 1], du, rb[k - 1]))
                opti.subject_to(pb.heater_row_coef * x[pb.i_heater] - sig <= pb.heater_row_bound)
                if pb.ptc_limit:
                    opti.subject_to(pb.ptc_row(x[pb.i_heater], u[pb.i_heater_cmd]) - sig <= 0)
        opti.minimize(cost)
        opts = {"expand": True, "structure_detection": "auto", "fatrop.tol": tol,
                "fatrop.max_iter": int(max_iter), "fatrop.print_level": 0, "print_time": False,
                "fatrop.mu_init": 1e-1}
        opti.solver("fatrop", opts)
        self.settings = {"nlp_solver": "fatrop", "tol": tol, "max_iter": int(max_iter), "hessian": "exact",
                         "structure": "stage-wise, augmented state [x, u_prev, slack]", "compiled": False}
        xa_all = ca.horzcat(*XA)
        v_all = ca.horzcat(*V)
        self._fn = opti.to_function("fatrop_reference", [x0, u_prev, d, ref, w_y, u_lo, u_hi, xa_all, v_all],
                                    [xa_all, v_all])
        self._i0, self._w1, self._j = shift_maps(pb.t_nodes, pb.dt_s)
        self.fail_next = 0
        self.reset()

    def reset(self) -> None:
        self.XA = self.V = None

    @property
    def has_trajectory(self) -> bool:
        return self.XA is not None

    def prepare(self, x_pred, u_prev, d, ref, w_y) -> float:
        """Shift the previous solution one sample (the warm start)."""
        t0 = time.perf_counter()
        if self.XA is not None:
            nx = self.pb.nx
            Xs = shift_nodes(self.XA[:, :nx], self._i0, self._w1)
            V = self.V[self._j]
            XA = np.concatenate([Xs, np.vstack([u_prev, V[:, :-1]]), np.append(0.0, V[:, -1])[:, None]], axis=1)
            XA[0, :nx] = x_pred
            self.XA, self.V = XA, V
        return time.perf_counter() - t0

    def feedback(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s: float = 0.0) -> SolveResult:
        t0 = time.perf_counter()
        pb, N, nx, nu = self.pb, self.pb.N, self.pb.nx, self.pb.nu
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure")
        if self.XA is None:
            X = pb.rollout(x0, u_prev, d)
            self.V = np.hstack([np.tile(u_prev, (N, 1)), np.zeros((N, 1))])
            self.XA = np.hstack([X, np.tile(u_prev, (N + 1, 1)), np.zeros((N + 1, 1))])
        V0 = self.V.copy()
        V0[:, :nu] = np.clip(V0[:, :nu], u_lo, u_hi)
        try:
            xa, v = self._fn(x0, u_prev, d, ref, w_y, u_lo.T, u_hi.T, self.XA.T, V0.T)
        except RuntimeError as exc:
            return SolveResult(False, f"fatrop error: {exc}", feedback_time_s=time.perf_counter() - t0)
        st = _stats(self._fn)
        iters = int(st.get("iter_count", 0))
        XA = np.asarray(xa).T
        V = np.asarray(v).T
        if not np.all(np.isfinite(XA)) or not np.all(np.isfinite(V)):
            return SolveResult(False, "non-finite solution", iterations=iters, feedback_time_s=time.perf_counter() - t0)
        self.XA, self.V = XA, V
        X = XA[:, :nx]
        U = V[:, :nu]
        S = XA[1:, nx + nu]
        if st and not st.get("success", True):
            return SolveResult(False, f"fatrop: {st.get('return_status', 'failed')}", iterations=iters,
                               feedback_time_s=time.perf_counter() - t0)
        return SolveResult(True, "solved", X=X.copy(), U=U.copy(), S=S.copy(),
                           iterations=iters, qp_solves=0, feedback_time_s=time.perf_counter() - t0)


def _stats(fn: ca.Function) -> dict:
    """fatrop's statistics of the last call (empty when CasADi does not expose them)."""
    try:
        st = fn.stats()
    except RuntimeError:
        return {}
    return st.get("solver", st) if isinstance(st, dict) else {}
