"""do-mpc given the MPC's stage-wise description, as a solver for :class:`MpcController` (benchmark only).

do-mpc (optional extra ``compare``) is the controller a user would otherwise pick. It gets the
functions of the stage-wise description (:class:`~hvac_mpc.mpc.stage_ocp.StageOcp`, the one IPOPT
and fatrop are built from): its state augmented with the last input (do-mpc's ``x`` and ``ul``),
its dynamics, its least-squares stage cost (tracking, energy and move), its terminal cost and its
rows (rate, heater, PTC); the same horizon, bounds and weights. It solves the full NLP with IPOPT
at do-mpc's defaults (output suppressed, iteration cap as the IPOPT reference; no extra
objective scaling, as a user would run it). Differences forced by do-mpc's API:

* one right-hand side for all stages: the non-uniform stages (move blocking) enter as
  time-varying parameters (stage duration and a one-hot choice of the RK4 substep count), so
  every stage evaluates each substep variant and keeps one;
* one set of rows for all stages: an inner stage's, the rate bounds per stage and the per-stage
  input bounds fed by parameters (stage 0's rate rows inactive, its limits in its input bounds);
* its soft constraints are linear-penalty only, each row with its own slack: the heater and PTC
  slacks cost ``slack_l1 * mean stage duration`` per degC (the quadratic part is left out).
"""

from __future__ import annotations

import time
import warnings

import casadi as ca
import numpy as np

from hvac_mpc.mpc.ocp import TrackingProblem
from hvac_mpc.mpc.rti_osqp import SolveResult
from hvac_mpc.mpc.stage_ocp import StageOcp


def _import_do_mpc():
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import do_mpc  # noqa: F401
            import do_mpc.controller  # noqa: F401
            import do_mpc.model  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("do-mpc is not installed; install the optional extra: pip install 'hvac-mpc[compare]'") \
            from exc
    return do_mpc


class DoMpcSolver:
    """The tracking problem in do-mpc, with the solver interface of :class:`RtiOsqpSolver`."""

    name = "do-mpc"

    def __init__(self, problem: TrackingProblem, *, max_iter: int = 300):
        for weight, field in ((problem.body_heat_coef, "body_heat_power_w"),
                              (problem.flap_closure_weight, "flap_closure_per_pct2")):
            if weight:
                raise ValueError(f"DoMpcSolver: weights.{field} must be 0 (range [0, 0]); the term is in the OSQP, "
                                 "IPOPT and fatrop solvers only, and do-mpc would solve another problem")
        do_mpc = _import_do_mpc()
        self.pb = pb = problem
        N, nx, nu, nd, ny = pb.N, pb.nx, pb.nu, pb.nd, pb.ny
        ocp = StageOcp(pb)
        self.p_model = np.array(ocp.p_model, float)
        substeps = sorted(ocp.dynamics)
        self._substeps = substeps
        model = do_mpc.model.Model("discrete", "SX")
        x = model.set_variable("_x", "x", (nx, 1))
        ul = model.set_variable("_x", "ul", (nu, 1))
        u = model.set_variable("_u", "u", (nu, 1))
        dt = model.set_variable("_tvp", "dt", (1, 1))
        sel = model.set_variable("_tvp", "sel", (len(substeps), 1))
        d = model.set_variable("_tvp", "d", (nd, 1))
        ref = model.set_variable("_tvp", "ref", (ny, 1))
        wy = model.set_variable("_tvp", "wy", (ny, 1))
        lo = model.set_variable("_tvp", "lo", (nu, 1))
        hi = model.set_variable("_tvp", "hi", (nu, 1))
        rb = model.set_variable("_tvp", "rb", (nu, 1))
        pm = model.set_variable("_tvp", "pm", (self.p_model.size, 1))  # the model parameters (set_parameters)
        xa = ca.vertcat(x, ul)
        x_next = 0
        for i, n in enumerate(substeps):
            x_next = x_next + sel[i] * ocp.dynamics[n](xa, u, d, dt, pm)[:nx]
        model.set_rhs("x", x_next)
        model.set_rhs("ul", u)  # the copy part of the description's dynamics
        # the description's least-squares stage cost (tracking, energy, move) and terminal cost
        e = ocp.residual(xa, u, d, pm) - ocp.target(0, ref)
        model.set_expression("lterm", ca.dot(ocp.path_weights(dt, wy), e * e))
        model.set_expression("mterm", ocp.stage_cost(N, xa, None, 0.0, d, ref, wy, pm))
        model.setup()

        mpc = do_mpc.controller.MPC(model)
        mpc.settings.n_horizon = N
        mpc.settings.t_step = pb.dt_s
        mpc.settings.state_discretization = "discrete"
        mpc.settings.store_full_solution = False
        mpc.settings.store_solver_stats = []
        mpc.settings.supress_ipopt_output()
        mpc.settings.nlpsol_opts.update({"ipopt.max_iter": int(max_iter)})
        mpc.set_objective(lterm=model.aux["lterm"], mterm=model.aux["mterm"])
        mpc.bounds["lower", "_u", "u"] = pb.u_lo
        mpc.bounds["upper", "_u", "u"] = pb.u_hi
        mpc.set_nl_cons("u_hi", u - hi, ub=0.0)
        mpc.set_nl_cons("u_lo", lo - u, ub=0.0)
        # the rows of an inner stage (rate, heater, PTC, flow floor); the rate bounds per stage as parameters
        inner = ocp.stages[1]
        h, rows = inner.h(ca.vertcat(model.x["x"], model.x["ul"]), model.u["u"], d, pm), inner.row_slices(nu)
        mpc.set_nl_cons("rate_hi", h[rows["rate"]] - rb, ub=0.0)
        mpc.set_nl_cons("rate_lo", -rb - h[rows["rate"]], ub=0.0)
        for kind in ("heater", "ptc"):
            if kind in rows:
                mpc.set_nl_cons(kind, h[rows[kind]] - inner.uh[rows[kind]], ub=0.0, soft_constraint=True,
                                penalty_term_cons=float(pb.slack_l1 * pb.dt.mean()))
        if "floor" in rows:
            mpc.set_nl_cons("floor", inner.lh[rows["floor"]] - h[rows["floor"]], ub=0.0)
        self._tvp_template = mpc.get_tvp_template()
        self._dt = np.append(pb.dt, pb.dt[-1])
        self._sel = np.zeros((N + 1, len(substeps)))
        for k, n in enumerate(pb.stage_substeps):
            self._sel[k, substeps.index(int(n))] = 1.0
        rate = pb.rate_bounds()
        self._rb = np.vstack([np.full((1, nu), 1e3), rate, rate[-1:]])  # stage 0: folded into lo/hi
        self._data = dict(d=np.zeros(nd), ref=np.zeros(ny), w_y=np.zeros(ny), u_lo=np.tile(pb.u_lo, (N, 1)),
                          u_hi=np.tile(pb.u_hi, (N, 1)))
        mpc.set_tvp_fun(self._tvp_fun)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mpc.setup()
        self.mpc = mpc
        self.settings = {"nlp_solver": "ipopt (do-mpc defaults)", "max_iter": int(max_iter), "compiled": False,
                         "description": "StageOcp functions (dynamics, least-squares cost, rows) through do-mpc"}
        self.fail_next = 0
        self._initialised = False

    def _tvp_fun(self, t_now):
        tpl, dd = self._tvp_template, self._data
        for k in range(self.pb.N + 1):
            kk = min(k, self.pb.N - 1)
            tpl["_tvp", k, "dt"] = self._dt[k]
            tpl["_tvp", k, "sel"] = self._sel[k]
            tpl["_tvp", k, "d"] = dd["d"]
            tpl["_tvp", k, "ref"] = dd["ref"]
            tpl["_tvp", k, "wy"] = dd["w_y"]
            tpl["_tvp", k, "lo"] = dd["u_lo"][kk]
            tpl["_tvp", k, "hi"] = dd["u_hi"][kk]
            tpl["_tvp", k, "rb"] = self._rb[k]
            tpl["_tvp", k, "pm"] = self.p_model
        return tpl

    def reset(self) -> None:
        self._initialised = False

    def set_parameters(self, p: np.ndarray) -> None:
        """Model parameters (``HvacModel.p_default`` order) of the next solves (a filter's, e.g. with its heat flow
        into the mixed air): a time-varying parameter of do-mpc's model, no rebuild."""
        self.p_model = np.array(p, float)

    def prepare(self, x_pred, u_prev, d, ref, w_y) -> float:
        return 0.0  # do-mpc warm-starts from its previous solution itself

    def feedback(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, time_limit_s: float = 0.0) -> SolveResult:
        t0 = time.perf_counter()
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure")
        pb, mpc = self.pb, self.mpc
        self._data = dict(d=np.asarray(d, float), ref=np.asarray(ref, float), w_y=np.asarray(w_y, float),
                          u_lo=u_lo, u_hi=u_hi)
        xa = np.concatenate([x0, u_prev]).reshape(-1, 1)
        mpc.u0 = np.asarray(u_prev, float).reshape(-1, 1)
        if not self._initialised:
            mpc.x0 = xa
            mpc.set_initial_guess()
            self._initialised = True
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                mpc.make_step(xa)
        except Exception as exc:  # noqa: BLE001 - reported as a failed solve
            return SolveResult(False, f"do-mpc error: {exc}", feedback_time_s=time.perf_counter() - t0)
        st = mpc.solver_stats
        status = str(st.get("return_status", "unknown"))
        iters = int(st.get("iter_count", 0))
        U = np.array([np.asarray(mpc.opt_x_num["_u", k, 0]).ravel() for k in range(pb.N)])
        X = np.array([np.asarray(mpc.opt_x_num["_x", k, 0, -1]).ravel()[:pb.nx] for k in range(pb.N + 1)])
        ok = bool(st.get("success", False)) and np.all(np.isfinite(U))
        return SolveResult(ok, status, X=X, U=U, S=np.zeros(pb.N), iterations=iters, qp_solves=0,
                           feedback_time_s=time.perf_counter() - t0)
