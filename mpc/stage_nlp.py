"""One transcription of the stage-wise description (:class:`~hvac_mpc.mpc.stage_ocp.StageOcp`) into
the NLP that CasADi's ``nlpsol`` solvers take (IPOPT, fatrop), and its Gauss-Newton QP.

docs/architecture.md, 'The stage-wise description'. Both layouts walk the same stages and call the
same stage functions (dynamics, least-squares cost, rows); they differ only in where the
variables sit:

* ``"compact"`` (IPOPT, a general sparse solver): ``w = [x_0..x_N, u_0..u_N-1, s_1..s_N]``; the
  copy part of the augmented state is substituted (``xa_k = [x_k, u_{k-1}]``, ``u_{-1}`` the
  parameter ``u_prev``), the slacks of the soft rows are variables ``s_k >= 0``. Rows grouped by
  kind: initial state, dynamics, rate, heater, PTC, flow floor. These are the variables and rows of the real-time
  iteration's QP (:mod:`hvac_mpc.mpc.rti_osqp`).
* ``"stagewise"`` (fatrop, which needs every row within one stage): ``w = [xa_0, v_0, xa_1, ...,
  xa_N]`` with ``xa_k = [x_k, u_{k-1}, s_k]`` and ``v_k = [u_k, s_{k+1}]``: the slack, which fatrop
  cannot hold as such, rides in the state to the stage whose rows it relaxes. Rows in stage order,
  each stage its dynamics then its path rows (the initial state is a path row of stage 0).

The parameters are ``[x0, u_prev, d, ref, w_y]`` (scaled estimate, last command, disturbances,
output reference, output weights); the model parameters are those the problem was built with.
Input bounds and ``s >= 0`` are variable bounds (:meth:`StageNlp.bounds`).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .ocp import STAGE_OUTPUTS
from .stage_ocp import StageOcp

LAYOUTS = ("compact", "stagewise")
#: Row groups in the order of the compact layout.
ROW_GROUPS = ("x0", "dyn", "rate", "heater", "ptc", "floor")


class StageNlp:
    """The NLP of a :class:`StageOcp` in one of :data:`LAYOUTS`.

    Attributes: ``nlp`` (``x``, ``p``, ``f``, ``g`` for ``nlpsol``), ``lbg``, ``ubg``, ``equality``
    (per row), ``n`` (variables), ``rows`` (group -> row indices of ``g``, per stage for ``dyn``),
    ``ix`` (N+1, nx), ``iu`` (N, nu), ``i_slack`` (N: where ``s_1..s_N`` are read),
    ``i_slack_bound`` (where ``s >= 0`` is imposed); ``residual``, ``weights``, ``target`` (stacked
    least-squares terms), ``l1``, ``l2`` (slack costs per variable) for :meth:`gauss_newton_qp`.
    """

    def __init__(self, ocp: StageOcp, layout: str = "compact"):
        if layout not in LAYOUTS:
            raise ValueError(f"layout = {layout!r} must be one of {LAYOUTS}")
        self.ocp, self.layout = ocp, layout
        N, nx, nu = ocp.N, ocp.nx, ocp.nu
        self.x0, self.u_prev = ca.SX.sym("x0", nx), ca.SX.sym("u_prev", nu)
        self.d, self.ref, self.w_y = ca.SX.sym("d", ocp.nd), ca.SX.sym("ref", ocp.ny), ca.SX.sym("w_y", ocp.ny)
        # the model parameters (HvacModel.p_default order) enter as parameters too: a filter that adapts them (the
        # heat flow into the mixed air, a learned bypass-flow exponent) hands them over per step (set_parameters)
        self.p_model = ca.SX.sym("p_model", ocp.p_model.size)
        p = ca.vertcat(self.x0, self.u_prev, self.d, self.ref, self.w_y, self.p_model)
        if layout == "compact":
            xa, u, s = self._compact_variables()
        else:
            xa, u, s = self._stagewise_variables()
        self._build(xa, u, s, p)

    # ------------------------------------------------------------------ variables
    def _compact_variables(self):
        ocp = self.ocp
        N, nx, nu = ocp.N, ocp.nx, ocp.nu
        n_x, n_u = (N + 1) * nx, N * nu
        self.n = n_x + n_u + N
        self.w = w = ca.SX.sym("w", self.n)
        self.ix = np.arange(n_x).reshape(N + 1, nx)
        self.iu = n_x + np.arange(n_u).reshape(N, nu)
        self.i_slack = self.i_slack_bound = n_x + n_u + np.arange(N)
        self._copies = None
        xa = [ca.vertcat(w[self.ix[k]], w[self.iu[k - 1]] if k else self.u_prev) for k in range(N + 1)]
        u = [w[self.iu[k]] for k in range(N)]
        s = [0.0] + [w[i] for i in self.i_slack]
        return xa, u, s

    def _stagewise_variables(self):
        ocp = self.ocp
        N, nx, nu = ocp.N, ocp.nx, ocp.nu
        na, nv = nx + nu + 1, nu + 1
        self.n = (N + 1) * na + N * nv
        self.w = w = ca.SX.sym("w", self.n)
        start = np.arange(N + 1) * (na + nv)
        self.ix = start[:, None] + np.arange(nx)
        i_copy = start[:, None] + nx + np.arange(nu)  # u_{k-1} in xa_k
        i_sig = start + nx + nu  # s_k in xa_k
        self.iu = start[:N, None] + na + np.arange(nu)
        self.i_slack = i_sig[1:]
        self.i_slack_bound = start[:N] + na + nu  # s_{k+1} in v_k
        self._copies = (i_copy, i_sig)
        self._xa_idx = [np.concatenate([self.ix[k], i_copy[k], [i_sig[k]]]) for k in range(N + 1)]
        xa = [w[i] for i in self._xa_idx]
        u = [w[self.iu[k]] for k in range(N)]
        s = [w[i] for i in i_sig]
        return xa, u, s

    # ------------------------------------------------------------------ rows and cost
    def _build(self, xa, u, s, p) -> None:
        """Walk the stages: rows (by group and stage), cost and least-squares terms; then order the rows."""
        ocp, pm = self.ocp, self.p_model
        groups: dict[str, list] = {g: [] for g in ROW_GROUPS}  # (stage, expr, lb, ub)
        order: list[tuple[str, int]] = []  # stage order: (group, stage)
        cost, res, wts, tgt = 0, [], [], []
        self.l1, self.l2 = np.zeros(self.n), np.zeros(self.n)
        # the flaps' target: fixed, or from the reference's split (OcpSpec.flap_target_from_split), a function of p
        flap_target = ocp.problem.flap_target_for(self.ref, self.w_y[STAGE_OUTPUTS.index("flow_m_m3s")] > 0.0)
        self._flap_target = (ca.Function("stage_nlp_flap_target", [p], [ca.vertcat(*flap_target)])
                             if ocp.problem.flap_split_target is not None else None)
        for k, st in enumerate(ocp.stages):
            xk, uk = xa[k][:ocp.nxa], None if st.terminal else u[k]
            for group, expr, lb, ub in self._stage_rows(k, xa, uk, s[k], pm):
                groups[group].append((k, expr, lb, ub))
                order.append((group, k))
            res.append(ocp.terminal_residual(xk, self.d, pm) if st.terminal else ocp.residual(xk, uk, self.d, pm))
            wts.append(ocp.weights(k, self.w_y))
            tgt.append(ocp.target(k, self.ref))
            cost += ocp.stage_cost(k, xk, uk, s[k], self.d, self.ref, self.w_y, pm)
            if not st.terminal:  # the flaps' flat direction priced (Weights.flap_closure_per_pct2), 0 when off
                cost += ocp.problem.flap_closure_cost(uk, k, flap_target)
            if st.has_slack:
                i = self.i_slack[k - 1]
                self.l1[i], self.l2[i] = st.slack_l1, st.slack_l2
        # the value of the heat stored in the heater body over the horizon (Weights.body_heat_power_w), linear
        cost += ocp.problem.body_heat_cost(xa[0][:ocp.nx], xa[-1][:ocp.nx], self.u_prev)
        if self.layout == "compact":  # grouped by kind, stages in order within a group
            order = [(g, item[0]) for g in ROW_GROUPS for item in groups[g]]
        self._order_rows(groups, order)
        self.p, self.f = p, cost
        self.residual, self.weights, self.target = ca.vertcat(*res), ca.vertcat(*wts), ca.vertcat(*tgt)
        self.nlp = {"x": self.w, "p": p, "f": cost, "g": self.g}

    def _stage_rows(self, k: int, xa: list, uk, sk, pm) -> list:
        """(group, expr, lb, ub) of stage k: initial state (k = 0), gap-closing rows, path rows."""
        ocp, nx, st = self.ocp, self.ocp.nx, self.ocp.stages[k]
        stagewise = self.layout == "stagewise"
        xk = xa[k][:ocp.nxa]
        out = []
        if k == 0:
            init = xa[0] - ca.vertcat(self.x0, self.u_prev, 0) if stagewise else xa[0][:nx] - self.x0
            out.append(("x0", init, np.zeros(init.numel()), np.zeros(init.numel())))
        if not st.terminal:
            f = ocp.dynamics[st.substeps](xk, uk, self.d, st.dt_s, pm)
            # gap-closing rows: fatrop requires x_{k+1} - F, the compact layout keeps the IPOPT
            # reference's F - x_{k+1} (the same rows, negated)
            gap = (xa[k + 1] - ca.vertcat(f, self.w[self.i_slack_bound[k]]) if stagewise
                   else f[:nx] - xa[k + 1][:nx])
            out.append(("dyn", gap, np.zeros(gap.numel()), np.zeros(gap.numel())))
        h = ocp.rows(k, xk, uk, sk, self.d, pm)
        out += [(kind, h[sl], st.lh[sl], st.uh[sl]) for kind, sl in st.row_slices(ocp.nu).items()]
        return out

    def _order_rows(self, groups: dict, order: list) -> None:
        """``g``, its bounds and the row indices of each group, rows in ``order``."""
        by_key = {(g, item[0]): item for g in ROW_GROUPS for item in groups[g]}
        parts, lbg, ubg, rows, o = [], [], [], {g: [] for g in ROW_GROUPS}, 0
        for group, k in order:
            _, expr, lb, ub = by_key[(group, k)]
            parts.append(expr)
            lbg.append(lb), ubg.append(ub)
            rows[group].append(np.arange(o, o + expr.numel()))
            o += expr.numel()
        self.rows = {g: np.array(v) if g == "dyn" else (np.concatenate(v) if v else np.zeros(0, int))
                     for g, v in rows.items()}
        self.g = ca.vertcat(*parts)
        self.lbg, self.ubg = np.concatenate(lbg), np.concatenate(ubg)
        self.equality = [bool(a == b) for a, b in zip(self.lbg, self.ubg)]

    # ------------------------------------------------------------------ values
    def parameters(self, x0, u_prev, d, ref, w_y, p_model=None) -> np.ndarray:
        """The NLP's parameter vector; ``p_model``: the model parameters (None: those the problem was built with)."""
        return np.concatenate([x0, u_prev, d, ref, w_y, self.ocp.p_model if p_model is None else p_model])

    def bounds(self, u_lo: np.ndarray, u_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Variable bounds: the inputs (N, nu) per stage, ``s >= 0``, the rest free."""
        lbx, ubx = np.full(self.n, -np.inf), np.full(self.n, np.inf)
        lbx[self.iu] = u_lo
        ubx[self.iu] = u_hi
        lbx[self.i_slack_bound] = 0.0
        return lbx, ubx

    def pack(self, X: np.ndarray, U: np.ndarray, S: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Variables from states (N+1, nx), inputs (N, nu), slacks s_1..s_N and the last command."""
        w = np.zeros(self.n)
        w[self.ix] = X
        w[self.iu] = U
        w[self.i_slack] = S
        if self._copies is not None:
            i_copy, i_sig = self._copies
            w[i_copy] = np.vstack([u_prev, U])
            w[i_sig[0]] = 0.0
            w[self.i_slack_bound] = S
        return w

    def unpack(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """States (N+1, nx), inputs (N, nu) and slacks s_1..s_N of a variable vector."""
        w = np.asarray(w, float).ravel()
        return w[self.ix], w[self.iu], w[self.i_slack]

    def cost_function(self) -> ca.Function:
        """The objective ``(w, p) -> f``."""
        return ca.Function("stage_nlp_cost", [self.w, self.p], [self.f], ["w", "p"], ["f"])

    def gauss_newton_qp(self, w_lin: np.ndarray, p: np.ndarray) -> dict[str, np.ndarray]:
        """The Gauss-Newton QP at ``w_lin`` in absolute variables (dense):
        ``min 1/2 z'Pz + q'z  s.t.  lg <= A z <= ug`` (plus :meth:`bounds`), with P from the
        least-squares residuals' Jacobian (``2 J'WJ``) and the slacks' quadratic cost, A the
        Jacobian of the rows, the rows' bounds moved by their value at ``w_lin``."""
        if not hasattr(self, "_gn"):
            J, Jg = ca.jacobian(self.residual, self.w), ca.jacobian(self.g, self.w)
            self._gn = ca.Function("stage_nlp_gn", [self.w, self.p],
                                   [self.residual, J, self.weights, self.target, self.g, Jg])
        r, J, W, T, g, Jg = (np.asarray(ca.densify(v)) for v in self._gn(w_lin, p))
        r, W, T, g = r.ravel(), W.ravel(), T.ravel(), g.ravel()
        P = 2.0 * J.T @ (W[:, None] * J) + np.diag(2.0 * self.l2)
        q = 2.0 * J.T @ (W * (r - J @ w_lin - T)) + self.l1
        pb = self.ocp.problem  # the value of the body's heat, linear in the terminal state, while heating
        q[self.ix[-1][pb.i_heater]] += pb.body_heat_on(np.asarray(p, float).ravel()[pb.nx:pb.nx + pb.nu]) * pb.body_heat_coef
        # the flaps' flat direction priced (zero when off): constant, or with its target from the reference's split
        target = None if self._flap_target is None else np.asarray(self._flap_target(p), float).ravel()
        flap_h, flap_g = pb.flap_closure_hessian(target)
        iu = np.asarray(self.iu).ravel()
        P[iu, iu] += flap_h.ravel()
        q[iu] += flap_g.ravel()
        shift = g - Jg @ w_lin
        return {"P": P, "q": q, "A": Jg, "lg": self.lbg - shift, "ug": self.ubg - shift}
