"""The MPC's problem stage by stage, apart from any solver (acados style): :class:`StageOcp`.

docs/architecture.md, 'The stage-wise description'. Built from a
:class:`~hvac_mpc.mpc.ocp.TrackingProblem`, it says per stage what acados' ``AcadosOcp`` says:

* **state** ``xa_k = [x_k, u_{k-1}]``: the model states augmented with the input applied before
  (``u_{-1}`` the last command), so every term that couples two stages lives within one;
* **dynamics** ``xa_{k+1} = [F_k(x_k, u_k, d, p), u_k]`` (RK4 with the stage's own substeps,
  :attr:`StageOcp.dynamics` by substep count);
* **cost**, nonlinear least squares: the residual ``r(xa, u) = [y(x, u), P_el(x, u), u - u_prev]``
  (tracked outputs, electric power blower plus heater in W, move) against ``[ref, 0, 0]`` with the
  weights ``[dt_k w_y / s^2, dt_k w_e / (100 W)^2, w_du]`` (:meth:`StageOcp.weights`); terminal
  residual ``y(x_N, u_{N-1})`` with ``T_term w_y / s^2``;
* **constraint rows** ``lh <= h(xa, u) <= uh`` per stage (:class:`Stage`): the rate limits
  ``u_k - u_{k-1}`` (k >= 1; stage 0's are in its input bounds, exact in the valve angle), the
  heater-body row of ``x_k`` (k >= 1, and the terminal stage), the PTC row of ``x_k`` and the
  heater command ``u_k`` (k = 1..N-1) and the flow floor while the heater is on (k = 0..N-1, hard,
  ``TrackingProblem.floor_row``: the total flow of ``x_k``, ``u_k`` with the disturbances and the
  model parameters, and the heater command). Rows marked **soft** relax their upper bound by the stage's
  one slack ``s_k >= 0`` at the cost ``l1_k s_k + l2_k s_k^2``; a solver that holds soft
  constraints takes them as they are, the transcriptions for IPOPT and fatrop
  (:mod:`hvac_mpc.mpc.stage_nlp`) add the slack as a variable;
* **input bounds** per stage and step (``TrackingProblem.input_bounds``) and the initial state
  ``xa_0 = [estimate, last command]``;
* **parameters**: disturbances ``d``, reference ``ref``, output weights ``w_y`` and the model
  parameters ``p`` (``HvacModel.p_default`` order) as inputs of every function.

Term by term this is the problem of :mod:`hvac_mpc.mpc.ocp` (its module docstring): the same
optimum. The functions reuse the model's stage functions (``TrackingProblem.stages_p``), the ones
the real-time iteration linearises.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hvac_mpc.models.box import INPUTS

from .ocp import STAGE_OUTPUTS, TrackingProblem

#: Constraint rows a stage may carry, in the order of its ``h``.
ROW_KINDS = ("rate", "heater", "ptc", "floor")


@dataclass(frozen=True)
class Stage:
    """One stage of the description.

    Attributes:
        index: k, 0..N.
        terminal: True for stage N (no input, no dynamics).
        dt_s: duration (s; the terminal stage repeats the last one, unused).
        substeps: RK4 substeps of the dynamics.
        rows: constraint row kinds (:data:`ROW_KINDS`), each ``nu`` rows for ``rate``, one otherwise.
        h: CasADi function of the rows, ``(xa, u, d, p) -> h`` (terminal: ``(xa, d, p) -> h``).
        lh, uh: bounds of the rows (scaled units; degC for the heater and PTC rows, L/s for the floor).
        soft: per row, True where the stage's slack relaxes the upper bound.
        slack_l1, slack_l2: cost of the stage's slack per degC and degC^2 (0 without soft rows).
        cost_s: the residual weights' time factor: ``dt_s``, or ``T_term`` at the terminal stage.
    """

    index: int
    terminal: bool
    dt_s: float
    substeps: int
    rows: tuple[str, ...]
    h: ca.Function
    lh: np.ndarray
    uh: np.ndarray
    soft: np.ndarray
    slack_l1: float
    slack_l2: float
    cost_s: float

    @property
    def n_rows(self) -> int:
        return int(self.lh.size)

    @property
    def has_slack(self) -> bool:
        return bool(self.soft.any())

    def row_slices(self, nu: int) -> dict[str, slice]:
        """Where each kind of row sits in ``h``."""
        out, o = {}, 0
        for kind in self.rows:
            size = nu if kind == "rate" else 1
            out[kind] = slice(o, o + size)
            o += size
        return out


class StageOcp:
    """The stage-wise description of a :class:`TrackingProblem` (module docstring).

    Attributes: ``N``, ``nx`` (model states), ``nu``, ``nd``, ``ny`` (stage outputs), ``nxa`` (augmented
    state), ``nr`` / ``nr_e`` (stage / terminal residual sizes); ``stages`` (N + 1 :class:`Stage`);
    CasADi functions ``dynamics`` (substeps -> ``(xa, u, d, dt, p) -> xa_next``), ``residual``
    (``(xa, u, d, p) -> r``) and ``terminal_residual`` (``(xa, d, p) -> r_e``); ``p_model`` the model
    parameters the problem was built with.
    """

    def __init__(self, problem: TrackingProblem):
        self.problem = pb = problem
        self.N, self.nx, self.nu, self.nd, self.ny = pb.N, pb.nx, pb.nu, pb.nd, pb.ny
        self.nxa = self.nx + self.nu
        self.nr = self.ny + 1 + self.nu
        self.nr_e = self.ny
        self.p_model = np.array(pb.model.p_default, float)
        self._build_functions()
        self.stages = tuple(self._stage(k) for k in range(self.N + 1))

    # ------------------------------------------------------------------ functions
    def _build_functions(self) -> None:
        pb, nx, nu = self.problem, self.nx, self.nu
        xa, u = ca.SX.sym("xa", self.nxa), ca.SX.sym("u", nu)
        d, dt = ca.SX.sym("d", self.nd), ca.SX.sym("dt")
        p = ca.SX.sym("p", self.p_model.size)
        x, u_prev = xa[:nx], xa[nx:]
        sl = pb.out_slices
        self.dynamics = {n: ca.Function(f"dynamics{n}", [xa, u, d, dt, p],
                                        [ca.vertcat(f(x, u, d, dt, p)[sl["xn"]], u)],
                                        ["xa", "u", "d", "dt", "p"], ["xa_next"])
                         for n, f in pb.stages_p.items()}
        outputs = pb.stages_p[min(pb.stages_p)]  # outputs do not depend on the substeps

        def y_of(x_, u_):
            return outputs(x_, u_, d, 1.0, p)[sl["y"]]

        ib = INPUTS.index("blower_power_w")
        y = y_of(x, u)
        power_w = y[STAGE_OUTPUTS.index("heater_power_w")] + u[ib] * pb.u_sc[ib] + pb.u_off[ib]
        self.residual = ca.Function("residual", [xa, u, d, p], [ca.vertcat(y, power_w, u - u_prev)],
                                    ["xa", "u", "d", "p"], ["r"])
        self.terminal_residual = ca.Function("terminal_residual", [xa, d, p], [y_of(x, u_prev)],
                                             ["xa", "d", "p"], ["r_e"])
        heater = pb.heater_row_coef * x[pb.i_heater]
        ptc = heater + pb.ptc_row_coef_u * u[pb.i_heater_cmd]  # TrackingProblem.ptc_row, its bound apart
        ih = pb.i_heater_cmd
        floor = pb.floor_row(y[STAGE_OUTPUTS.index("volume_flow_m3s")], pb.u_off[ih] + pb.u_sc[ih] * u[ih])
        self._row_expr = {"rate": u - u_prev, "heater": heater, "ptc": ptc, "floor": floor}
        self._row_sym = (xa, u, d, p)

    def _stage(self, k: int) -> Stage:
        pb, N, nu = self.problem, self.N, self.nu
        terminal = k == N
        rows: list[str] = []
        if 1 <= k <= N - 1:
            rows.append("rate")
        if k >= 1:
            rows.append("heater")
        if pb.ptc_limit and 1 <= k <= N - 1:
            rows.append("ptc")
        if pb.floor and k <= N - 1:
            rows.append("floor")
        rb = pb.rate_bounds()
        lh, uh, soft = [], [], []
        for kind in rows:
            if kind == "rate":
                lh.append(-rb[k - 1]), uh.append(rb[k - 1]), soft.append(np.zeros(nu, bool))
            elif kind == "floor":
                lh.append([0.0]), uh.append([np.inf]), soft.append([False])
            else:
                bound = pb.heater_row_bound if kind == "heater" else pb.ptc_row_bound
                lh.append([-np.inf]), uh.append([bound]), soft.append([True])
        xa, u, d, p = self._row_sym
        expr = ca.vertcat(*[self._row_expr[kind] for kind in rows]) if rows else ca.SX(0, 1)
        h = (ca.Function(f"h{k}", [xa, d, p], [expr], ["xa", "d", "p"], ["h"]) if terminal
             else ca.Function(f"h{k}", [xa, u, d, p], [expr], ["xa", "u", "d", "p"], ["h"]))
        soft_rows = _concat(soft, bool)
        dt = float(pb.dt[min(k, N - 1)])
        slack_dt = float(pb.dt[k - 1]) if soft_rows.any() else 0.0  # s_k weighs dt_{k-1}
        return Stage(index=k, terminal=terminal, dt_s=dt, substeps=int(pb.stage_substeps[k]), rows=tuple(rows), h=h,
                     lh=_concat(lh), uh=_concat(uh), soft=soft_rows, slack_l1=pb.slack_l1 * slack_dt,
                     slack_l2=pb.slack_l2 * slack_dt, cost_s=pb.terminal_s if terminal else dt)

    # ------------------------------------------------------------------ data
    def weights(self, k: int, w_y):
        """Residual weights of stage k for output weights ``w_y`` (numpy or CasADi)."""
        st = self.stages[k]
        if st.terminal:
            return st.cost_s * w_y / (self.problem.y_scale ** 2)
        return self.path_weights(st.dt_s, w_y)

    def path_weights(self, dt_s, w_y):
        """Residual weights of a (non-terminal) stage of duration ``dt_s`` (s; a number or CasADi)."""
        pb = self.problem
        tracking = dt_s * w_y / (pb.y_scale ** 2)
        energy = dt_s * pb.energy_weight / pb.energy_scale_w ** 2
        if isinstance(w_y, (ca.SX, ca.MX)):
            return ca.vertcat(tracking, energy, ca.DM(pb.w_du))
        return np.concatenate([tracking, [energy], pb.w_du])

    def target(self, k: int, ref):
        """Residual target of stage k for the output reference ``ref`` (numpy or CasADi)."""
        if self.stages[k].terminal:
            return ref
        zeros = self.nr - self.ny
        return ca.vertcat(ref, ca.DM.zeros(zeros)) if isinstance(ref, (ca.SX, ca.MX)) \
            else np.concatenate([ref, np.zeros(zeros)])

    def stage_cost(self, k: int, xa, u, slack, d, ref, w_y, p):
        """Cost of stage k (``u`` None at the terminal stage; ``slack`` 0 without soft rows)."""
        st = self.stages[k]
        r = self.terminal_residual(xa, d, p) if st.terminal else self.residual(xa, u, d, p)
        e = r - self.target(k, ref)
        cost = ca.dot(self.weights(k, w_y), e * e)
        if st.has_slack:
            cost += st.slack_l1 * slack + st.slack_l2 * slack * slack
        return cost

    def rows(self, k: int, xa, u, slack, d, p):
        """Rows of stage k with the soft ones relaxed by ``slack``: ``lh <= h - soft * slack <= uh``
        (``d`` the disturbances, ``p`` the model parameters)."""
        st = self.stages[k]
        h = st.h(xa, d, p) if st.terminal else st.h(xa, u, d, p)
        if st.has_slack:
            h = h - ca.DM(st.soft.astype(float)) * slack
        return h

    def initial_state(self, x0, u_prev):
        """``xa_0`` from the estimate and the last command (scaled)."""
        return ca.vertcat(x0, u_prev) if isinstance(x0, (ca.SX, ca.MX)) else np.concatenate([x0, u_prev])

    def summary(self) -> dict:
        """What the description holds, for benchmark reports."""
        kinds = {kind: sum(kind in st.rows for st in self.stages) for kind in ROW_KINDS}
        pb = self.problem
        return {"description": "StageOcp", "stages": self.N, "stage_durations_s": pb.dt.tolist(),
                "model_effects": list(pb.spec.model_effects), "augmented_state": "[x, u_prev]",
                "nx": self.nx, "nxa": self.nxa, "nu": self.nu, "stage_rows": kinds,
                "soft_rows": "heater, ptc (one slack per stage, l1 + l2)", "hard_rows": "rate, floor",
                "cost": "nonlinear least squares (outputs, electric power, move)"}


def _concat(parts: list, dtype=float) -> np.ndarray:
    """The rows' values of one stage as one array (empty for a stage without rows)."""
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)
