"""A globalised real-time iteration step: the QP's plan checked on the nonlinear cost (a line search).

The real-time iteration (:mod:`.rti_osqp`) takes the QP's answer as the next plan whole: one
Gauss-Newton step from the linearisation point. Where the QP's linear model is wrong about the sign of an
input's effect along the horizon, the step overshoots, the next linearisation at its end points back, and
the input alternates between two plans from sample to sample
(docs/identification.md 'A globalised step in the real-time iteration').
:class:`PlanMerit` checks the step on the problem's own nonlinear cost:

* the **merit** of a plan (scaled inputs ``U``, N x nu) is the cost of :mod:`.ocp` (its module docstring)
  along the model's rollout from the estimate ``x0`` with those inputs (single shooting: no defects), the
  soft rows' slack at what the rollout needs (the heater and PTC rows' largest excess, at least 0) and the
  hard flow floor priced like a slack (per L/s below it, :data:`FLOOR_PENALTY_PER_LS`), and the heater
  readiness (:mod:`.readiness`, a setting) where it counts: its one-sided penalty on the rollout's body below the
  floor, so that the QP's pull towards the floor is judged on the cost that asks for it;
* after the QP, the merit of the QP's plan is compared with that of the linearisation point (the shifted
  plan, the command in force first). Where the QP's plan is no worse (within :data:`MERIT_TOLERANCE`), it
  is taken as it is (the common step: one call of a generated function with the two rollouts). Otherwise
  the damped steps ``z_lin + fraction (z_qp - z_lin)`` for the configured fractions are rolled out too (a
  second call) and the plan with the least merit among the QP's and the damped ones is taken.

The linearisation point itself is not a candidate: the step always moves towards the QP's answer, by
the smallest fraction at least, so a plan the merit cannot rank (a flat cost) still moves.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hvac_mpc.models.box import INPUTS

from .casadi_eval import BufferedFunction
from .codegen import expression_key, kept
from .ocp import STAGE_OUTPUTS, TrackingProblem

#: Price of the flow floor's shortfall in the merit, as a multiple of the soft rows' L1 price per degC, per
#: L/s below the floor and s of stage: the floor is a hard row of the QP, a plan short of it is not one the
#: QP could take, so a shortfall costs like the heater's slack (ASSUMPTION: 1 L/s weighs like 1 C of slack).
FLOOR_PENALTY_PER_LS = 1.0
#: The QP's plan is taken whole unless its merit exceeds the linearisation point's by more than this share of it.
#: ASSUMPTION: below that the two differ by what separates the QP from the merit without a wrong linearisation
#: (OSQP's tolerance, the Levenberg-Marquardt term, the interpolated shift of the plan), not traced. Measured (docs/identification.md
#: 'A globalised step in the real-time iteration'): up to 4 % on steps of the nominal box's chiller_hysteresis_step,
#: 0.6 to 18 times more on every second step where valve a alternates on the recirculating box.
MERIT_TOLERANCE = 0.05
#: The merit function's arguments, in order.
ARGUMENTS = ("x0", "U", "d", "SW", "ref", "u_prev", "p", "ready_floor", "ready_w")


class PlanMerit:
    """The nonlinear cost of plans of a :class:`TrackingProblem`, and the choice of the step (module
    docstring).

    Args:
        problem: the OCP.
        fractions: the damped steps tried when the QP's plan does not lower the merit, each in (0, 1).
        wrap: applied to each CasADi function before use (generated C, :func:`.codegen.compiled`).
    """

    def __init__(self, problem: TrackingProblem, fractions: tuple[float, ...], wrap=lambda f: f, several: int = 0):
        self.pb = problem
        self.fractions = tuple(float(a) for a in fractions)
        if not self.fractions or any(not 0.0 < a < 1.0 for a in self.fractions):
            raise ValueError(f"step fractions {fractions!r} must be a non-empty sequence of numbers in (0, 1)")
        # the move weights an input, filled once: one build serves every set of them (docs/architecture.md 'A default
        # controller's keys after other tests')
        one = self.cost_function(move_weights_input=True)
        key = expression_key(one)  # the merit's structure (the model parameters and the move weights inputs)
        move = {len(ARGUMENTS): problem.w_du}
        self._pair = BufferedFunction(wrap(_mapped(one, 2, "hvac_plan_merit2", key)), fixed=move)
        self._damped = BufferedFunction(wrap(_mapped(one, len(self.fractions), f"hvac_plan_merit{len(fractions)}d",
                                                     key)), fixed=move)
        # ``several`` plans priced in one call (:meth:`costs`; 0: none), built here, not in a control step
        self._several = BufferedFunction(wrap(_mapped(one, several, f"hvac_plan_merit{several}s", key)),
                                         fixed=move) if several else None
        self.several = int(several)

    def cost_function(self, move_weights_input: bool = False) -> ca.Function:
        """``(x0, U, d, SW, ref, u_prev, p, ready_floor, ready_w) -> cost``: the merit of one plan, scaled
        ``x0`` (nx) and ``U`` (nu x N), the stage weights ``SW`` ((ny + 1) x (N + 1),
        :meth:`.rti_osqp.RtiOsqpSolver._stage_weights` order: the outputs' weights and the energy weight per
        stage), the reference of the stage outputs, the command in force (scaled), the model parameters, and the
        heater readiness's scaled floor and weights of stages 1..N (:meth:`.readiness.HeaterReadiness.scaled`;
        zero weights: out). ``move_weights_input``: the scaled move weights (``TrackingProblem.w_du``, nu) a last
        input ``w_du`` instead of constants, so that problems differing only in them share one function."""
        pb = self.pb
        N, nx, nu, ny = pb.N, pb.nx, pb.nu, pb.ny
        x0, U = ca.SX.sym("x0", nx), ca.SX.sym("U", nu, N)
        d, SW, ref = ca.SX.sym("d", pb.nd), ca.SX.sym("SW", ny + 1, N + 1), ca.SX.sym("ref", ny)
        u_prev, p = ca.SX.sym("u_prev", nu), ca.SX.sym("p", len(pb.model.p_default))
        ready_floor, ready_w = ca.SX.sym("ready_floor"), ca.SX.sym("ready_w", N)
        w_du = ca.SX.sym("w_du", nu) if move_weights_input else ca.DM(pb.w_du)
        values = {n: pb.stage_values_function(n) for n in sorted(set(pb.stage_substeps.tolist()))}
        dt = np.append(pb.dt, pb.dt[-1])
        ib, ip = INPUTS.index("blower_power_w"), STAGE_OUTPUTS.index("heater_power_w")
        i_flow = STAGE_OUTPUTS.index("volume_flow_m3s")
        x, prev, cost = x0, u_prev, 0
        # the rows' constants from the parameters: one build serves every parameter set of the same structure
        rows = pb.parameter_rows(p)
        # the flaps' target (OcpSpec.flap_target_from_split: from the reference's split where its weights are on)
        flap_target = pb.flap_target_for(ref, SW[STAGE_OUTPUTS.index("flow_m_m3s"), 0] > 0.0)
        for k in range(N + 1):
            u = U[:, min(k, N - 1)]
            x_next, y = values[int(pb.stage_substeps[k])](x, u, d, dt[k], p)
            power = y[ip] + u[ib] * pb.u_sc[ib] + pb.u_off[ib]
            r = ca.vertcat(y - ref, power)
            cost += ca.dot(SW[:, k], r * r)
            if k >= 1:
                cost += self._slack_cost(k, x, u, rows)
                short = ca.fmax(ready_floor - x[pb.i_heater], 0.0)
                cost += ready_w[k - 1] * short * short
            if k < N:
                du = u - prev
                cost += ca.dot(w_du, du * du) + pb.flap_closure_cost(u, k, flap_target)
                if pb.floor:
                    ih = pb.i_heater_cmd
                    row = pb.floor_row(y[i_flow], pb.u_off[ih] + pb.u_sc[ih] * u[ih])
                    cost += FLOOR_PENALTY_PER_LS * pb.slack_l1 * pb.dt[k] * ca.fmax(0.0, -row)
                prev, x = u, x_next
        cost += pb.body_heat_cost(x0, x, u_prev, rows.body_heat_coef)  # x: the last node's state
        args, names = [x0, U, d, SW, ref, u_prev, p, ready_floor, ready_w], list(ARGUMENTS)
        if move_weights_input:
            args, names = [*args, w_du], [*names, "w_du"]
        return ca.Function("hvac_plan_merit", args, [cost], names, ["cost"])

    def _slack_cost(self, k: int, x, u, rows):
        """The soft rows' price at stage k (1..N): the least slack that holds the heater row (and the PTC
        row, stages 1..N-1; :meth:`.ocp.TrackingProblem.ptc_row`), at the QP's L1 and L2 prices over the stage
        before; ``rows``: :meth:`.ocp.TrackingProblem.parameter_rows` of the merit's parameters."""
        pb = self.pb
        excess = pb.heater_row_coef * x[pb.i_heater] - rows.heater_bound_c
        if pb.ptc_limit and k < pb.N:
            excess = ca.fmax(excess, pb.ptc_row(x[pb.i_heater], u[pb.i_heater_cmd], rows))
        s = ca.fmax(0.0, excess)
        return pb.dt[k - 1] * (pb.slack_l1 * s + pb.slack_l2 * s * s)

    def pair(self, U_lin: np.ndarray, U_qp: np.ndarray, x0: np.ndarray, d: np.ndarray, sw: np.ndarray,
             ref: np.ndarray, u_prev: np.ndarray, p: np.ndarray,
             ready: tuple[float, np.ndarray] | None = None) -> tuple[float, float]:
        """The merits of two plans (N x nu, scaled), the arguments as :meth:`choose`'s."""
        r_floor, r_w = (0.0, np.zeros(self.pb.N)) if ready is None else ready
        costs = self._pair(x0, np.concatenate([U_lin, U_qp]), d, sw, ref, u_prev, p, r_floor, r_w)[0].ravel()
        return float(costs[0]), float(costs[1])

    def costs(self, plans: list[np.ndarray], x0: np.ndarray, d: np.ndarray, sw: np.ndarray, ref: np.ndarray,
              u_prev: np.ndarray, p: np.ndarray, ready: tuple[float, np.ndarray] | None = None) -> np.ndarray:
        """The merits of :attr:`several` plans (each N x nu, scaled), the arguments as :meth:`choose`'s."""
        if self._several is None or len(plans) != self.several:
            raise ValueError(f"PlanMerit.costs: {len(plans)} plans given, built for {self.several}")
        r_floor, r_w = (0.0, np.zeros(self.pb.N)) if ready is None else ready
        return np.asarray(self._several(x0, np.concatenate(plans), d, sw, ref, u_prev, p, r_floor, r_w)[0],
                          float).ravel()

    def choose(self, U_lin: np.ndarray, U_qp: np.ndarray, x0: np.ndarray, d: np.ndarray, sw: np.ndarray,
               ref: np.ndarray, u_prev: np.ndarray, p: np.ndarray,
               ready: tuple[float, np.ndarray] | None = None) -> float:
        """The fraction of the step from the linearisation point's inputs ``U_lin`` to the QP's ``U_qp`` (both
        N x nu, scaled) to take: 1 where the QP's plan has no more merit than the linearisation point (within
        :data:`MERIT_TOLERANCE`), else the one of least merit among 1 and :attr:`fractions` (ties to the longer
        step). ``ready``: the heater readiness's scaled floor and stage weights, None while it is out."""
        r_floor, r_w = (0.0, np.zeros(self.pb.N)) if ready is None else ready
        costs = self._pair(x0, np.concatenate([U_lin, U_qp]), d, sw, ref, u_prev, p, r_floor, r_w)[0].ravel()
        fraction = 1.0
        if costs[1] > costs[0] * (1.0 + MERIT_TOLERANCE):
            step = U_qp - U_lin
            damped = np.concatenate([U_lin + a * step for a in self.fractions])
            c = self._damped(x0, damped, d, sw, ref, u_prev, p, r_floor, r_w)[0].ravel()
            best = int(np.argmin(c))
            if c[best] < costs[1]:
                fraction = self.fractions[best]
        return fraction


def _mapped(fn: ca.Function, n: int, name: str, key: str) -> ca.Function:
    """``fn`` over ``n`` plans side by side (their inputs stacked along the columns of ``U``; the other
    arguments shared), the costs in a row.

    ``key``: :func:`.codegen.expression_key` of ``fn`` (its structure; the model parameters and the move weights are
    arguments): the function built for a key, ``n`` and ``name`` is kept (:func:`.codegen.kept`) and returned as it
    is to the next call with the same ones, since the common subexpressions of a merit of the default horizon take
    2-7 s to find."""
    return kept(f"plan merit {key} {n} {name}", lambda: _mapped_afresh(fn, n, name))


def _mapped_afresh(fn: ca.Function, n: int, name: str) -> ca.Function:
    """:func:`_mapped` without the memo."""
    args = fn.sx_in()
    x0, U, *rest = args
    nu, N = U.shape
    Us = ca.SX.sym("Us", nu, N * n)
    costs = [fn(x0, Us[:, i * N:(i + 1) * N], *rest) for i in range(n)]
    # common subexpressions computed once (the plans share the start and the parameters' terms)
    return ca.Function(name, [x0, Us, *rest], [ca.cse(ca.horzcat(*costs))], fn.name_in(), ["cost"])
