"""The stage QP's curvature along valve a, captured on a box of the sweep (docs/robustness.md sec. 2.43).

    python -m hvac_mpc.benchmarks.valve_a_curvature --box LABEL:FIELD=VALUE,... [--scenario NAME] [--quick]
        [--from S] [--to S] [--settings JSON] [--second-order]

Both controllers run the scenario on the box as :mod:`.box_trace` runs them; the MPC's solver
(:class:`~hvac_mpc.mpc.rti_osqp.RtiOsqpSolver`) is wrapped to keep each plain step's first QP from ``--from`` to
``--to`` s (OSQP's data before its scaling: ``P``, ``q``, ``A``, ``l``, ``u``; the linearisation point, the QP's
answer, the stage residuals' weighted Jacobians). For each step printed: valve a's first six stages (the
linearisation point's and the QP's, %), and the QP's curvature along valve a's horizon entries
(:func:`reduced_hessian`): the states eliminated through the dynamics rows, the other inputs fixed
(``fixed``) or free where they are off their bounds at the QP's answer (``free``, their Schur complement), each
term's share (:func:`term_curvatures`), the smallest and largest eigenvalues, the linear term's pull on valve a at the
answer and at the linearisation point (:func:`valve_a_pull`; per scaled unit, 1 = 50 % of valve a's travel), and the
problem's nonlinear cost differenced along each stage's valve a entry at both (:func:`exact_curvature`): the
curvature the Gauss-Newton Hessian keeps against the one the cost has. :class:`SecondOrderDiagonal` puts the
difference on the QP's diagonal at the heater's bound (a measurement, not a setting; ``--second-order``). Measured in
docs/robustness.md sec. 2.43.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.sparse as sp

from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.ocp import STAGE_OUTPUTS
from hvac_mpc.mpc.reversal_search import at_upper_bound
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

from . import box_trace

#: Names of the residual rows of the stage QP data (the stage outputs, then the electric power).
RESIDUALS = STAGE_OUTPUTS + ("energy",)
#: Where a decision counts as at its bound in the QP's answer (scaled units: 1e-3 of 50 % is 0.05 %).
BOUND_TOL = 1e-3


class _SolverPatch:
    """Methods of :class:`RtiOsqpSolver` replaced on the class while open (a measurement's wrapping); :meth:`close`
    (or leaving a ``with`` block) puts the originals back, which ``_saved`` keeps by name."""

    def __init__(self, names: Sequence[str]):
        self._saved = {n: getattr(RtiOsqpSolver, n) for n in names}

    def _install(self, **methods) -> None:
        for n, f in methods.items():
            setattr(RtiOsqpSolver, n, f)

    def close(self) -> None:
        self._install(**self._saved)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class QpRecorder(_SolverPatch):
    """Wraps :class:`RtiOsqpSolver`'s methods (class-level, undone by :meth:`close`) to keep each step's first QP
    between ``start_s`` and ``end_s`` (the feedback calls counted from 0, one a second)."""

    def __init__(self, start_s: float, end_s: float):
        self.start_s, self.end_s = start_s, end_s
        self.records: list[dict] = []
        self.solver: RtiOsqpSolver | None = None
        self._step = -1
        self._current: dict | None = None
        super().__init__(("feedback", "_floor_bounds", "_solve_qps", "_q"))
        rec = self

        def feedback(solver, *args, **kwargs):
            rec.solver = solver
            rec._step += 1
            rec._current = {"t": rec._step} if rec.start_s <= rec._step < rec.end_s else None
            result = rec._saved["feedback"](solver, *args, **kwargs)
            if rec._current is not None and "z" in rec._current:
                rec._current["u_applied"] = None if result.U is None else result.U[0].copy()
                rec._current["search_taken"] = solver.reversal_taken
                rec.records.append(rec._current)
            rec._current = None
            return result

        def floor_bounds(solver, d, x0, u_lo, u_hi):
            rec._saved["_floor_bounds"](solver, d, x0, u_lo, u_hi)
            cur = rec._current
            if cur is not None and "l" not in cur:
                Px, Ax = solver._written
                cur.update(Px=np.array(Px, float), Ax=np.array(Ax, float), l=solver.l.copy(), u=solver.u.copy(),
                           z_lin=solver._z_lin.copy(), gw2=np.array(solver._prepared["data"]["gw2"], float),
                           sw=solver._weights(solver._prepared["w_y"]).copy(), u_lo=u_lo.copy(), u_hi=u_hi.copy())

        def gradient(solver, ref, d, u_prev):
            q = rec._saved["_q"](solver, ref, d, u_prev)
            cur = rec._current
            if cur is not None and "q" not in cur:
                cur["q"] = np.array(q, float)
            return q

        def solve_qps(solver, x0, u_prev, d, ref, w_y, *args, **kwargs):
            cur = rec._current
            if cur is not None and "ref" not in cur:
                cur.update(ref=np.array(ref, float), u_prev=np.array(u_prev, float), x0=np.array(x0, float),
                           d=np.array(d, float), w_y=np.array(w_y, float))
            out = rec._saved["_solve_qps"](solver, x0, u_prev, d, ref, w_y, *args, **kwargs)
            if cur is not None and "z" not in cur and out[0] is not None and "l" in cur:
                cur["z"] = np.array(out[0], float)
            return out

        self._install(feedback=feedback, _floor_bounds=floor_bounds, _solve_qps=solve_qps, _q=gradient)



def full_p(solver: RtiOsqpSolver, Px: np.ndarray) -> np.ndarray:
    """The symmetric Hessian (dense) of OSQP's upper-triangular ``P`` data."""
    upper = solver.P.matrix(Px).toarray()
    return upper + upper.T - np.diag(np.diag(upper))


def input_map(solver: RtiOsqpSolver, Ax: np.ndarray) -> np.ndarray:
    """``T`` (n x N nu): a change of the scaled inputs to the change of the whole decision vector with the first node
    and the dynamics rows held (the states follow the linearised dynamics; the slacks held)."""
    pb = solver.pb
    A = solver.A.matrix(Ax).tocsr()
    rows = np.concatenate([solver.r_x0, solver.r_dyn.ravel()])
    E = A[rows].toarray()
    nxs = (pb.N + 1) * pb.nx
    E_x, E_u = E[:, :nxs], E[:, solver.iu0:solver.is0]
    T = np.zeros((solver.n, pb.N * pb.nu))
    T[:nxs] = -np.linalg.solve(E_x, E_u)
    T[solver.iu0:solver.is0] = np.eye(pb.N * pb.nu)
    return T


def free_inputs(solver: RtiOsqpSolver, rec: Mapping, tol: float = BOUND_TOL) -> np.ndarray:
    """Mask (N, nu) of the inputs off their bounds (the stage's input rows) in the QP's answer ``rec['z']``."""
    pb = solver.pb
    U = rec["z"][solver.iu0:solver.is0].reshape(pb.N, pb.nu)
    lo, hi = rec["l"][solver.r_u], rec["u"][solver.r_u]
    return (U > lo + tol) & (U < hi - tol)


def reduced_hessian(solver: RtiOsqpSolver, P: np.ndarray, T: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
    """Valve a's (N x N) reduced Hessian: ``T' P T`` on valve a's horizon entries, the other inputs fixed (``free``
    None) or, where ``free`` (N, nu) marks them, minimised out (the Schur complement over those entries)."""
    pb = solver.pb
    H = T.T @ P @ T
    ia = pb.i_valve_a + pb.nu * np.arange(pb.N)
    Haa = H[np.ix_(ia, ia)]
    if free is None:
        return Haa
    mask = free.copy()
    mask[:, pb.i_valve_a] = False
    io = np.flatnonzero(mask.ravel())
    if not io.size:
        return Haa
    Hoo, Hao = H[np.ix_(io, io)], H[np.ix_(ia, io)]
    return Haa - Hao @ np.linalg.solve(Hoo, Hao.T)


def term_curvatures(solver: RtiOsqpSolver, rec: Mapping, T: np.ndarray) -> dict[str, np.ndarray]:
    """Valve a's reduced Hessian (other inputs fixed) by term: each residual row's Gauss-Newton part
    (:data:`RESIDUALS`), and the constant part (the move cost, the Levenberg-Marquardt term, the slack and flap terms)."""
    pb = solver.pb
    N, nu, nzs = pb.N, pb.nu, solver.nz_stage
    nr = pb.ny + 1
    ia = pb.i_valve_a + nu * np.arange(N)
    Ta = T[:, ia]
    gw2 = np.asarray(rec["gw2"], float).reshape(N + 1, nr * nzs)  # per stage vec(2 w G), column-major
    sw = np.asarray(rec["sw"], float)
    out = {}
    for i, name in enumerate(RESIDUALS):
        H = np.zeros((N, N))
        for k in range(N + 1):
            m = gw2[k].reshape(nr, nzs, order="F")
            w = sw[k, i]
            if w <= 0.0:
                continue
            g2 = m[i]  # 2 w G_i
            Tk = Ta[solver.stage_cols[k]]
            v = Tk.T @ g2  # 2 w (G_i T)
            H += np.outer(v, v) / (2.0 * w)
        out[name] = H
    P0 = full_p(solver, np.asarray(solver._P_const, float))
    out["constant (move, LM)"] = Ta.T @ P0 @ Ta
    return out


def valve_a_pull(solver: RtiOsqpSolver, rec: Mapping, P: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The QP's gradient along valve a's horizon entries (states following, other inputs fixed) at the QP's answer and
    at the linearisation point (``T' (P z + q)``, valve a's rows)."""
    pb = solver.pb
    ia = pb.i_valve_a + pb.nu * np.arange(pb.N)
    g_sol = T.T @ (P @ rec["z"] + rec["q"])
    g_lin = T.T @ (P @ rec["z_lin"] + rec["q"])
    return g_sol[ia], g_lin[ia]


def exact_curvature(solver: RtiOsqpSolver, rec: Mapping, stages: int = 6, h: float = 0.04,
                    at: str = "z") -> np.ndarray:
    """The nonlinear cost's second difference along valve a's entry of each of the first ``stages`` stages at the QP's
    plan (per scaled unit squared; the problem's own cost along the model's rollout, :class:`~.plan_merit.PlanMerit`,
    the search's merit): the Gauss-Newton Hessian's curvature plus the second-order terms it drops. Central where the
    plan is off valve a's bounds by ``2 h`` (scaled), else one-sided into the travel. ``at``: "z" the QP's plan,
    "z_lin" the linearisation point's."""
    pb = solver.pb
    merit = solver._search_merit
    if merit is None:
        return np.full(stages, np.nan)
    args = (rec["x0"], rec["d"], solver._weights(rec["w_y"]), rec["ref"], rec["u_prev"], solver._p,
            solver.readiness_target)
    U = rec[at][solver.iu0:solver.is0].reshape(pb.N, pb.nu)
    ia = pb.i_valve_a
    lo, hi = rec["l"][solver.r_u][:, ia], rec["u"][solver.r_u][:, ia]
    out = np.empty(stages)
    for k in range(stages):
        steps = (-h, 0.0, h) if U[k, ia] - 2 * h > lo[k] and U[k, ia] + 2 * h < hi[k] else \
            ((0.0, h, 2 * h) if U[k, ia] - 2 * h <= lo[k] else (-2 * h, -h, 0.0))
        plans = []
        for s_ in steps:
            V = U.copy()
            V[k, ia] += s_
            plans.append(V)
        c = np.asarray(merit.costs(np.array(plans), *args), float)
        out[k] = (c[0] - 2.0 * c[1] + c[2]) / h ** 2
    return out


def analyse(solver: RtiOsqpSolver, rec: Mapping, stages: int = 6) -> dict[str, Any]:
    """The numbers of one recorded QP (:func:`reduced_hessian`, :func:`term_curvatures`, :func:`valve_a_pull`)."""
    pb = solver.pb
    P = full_p(solver, rec["Px"])
    T = input_map(solver, rec["Ax"])
    free = free_inputs(solver, rec)
    h_fixed = reduced_hessian(solver, P, T)
    h_free = reduced_hessian(solver, P, T, free)
    with_heater = free.copy()
    with_heater[:, pb.i_heater_cmd] = True  # the heater as if its bound were not there
    h_heater = reduced_hessian(solver, P, T, with_heater)
    terms = term_curvatures(solver, rec, T)
    g_sol, g_lin = valve_a_pull(solver, rec, P, T)
    ia, ih = pb.i_valve_a, pb.i_heater_cmd
    others = [i for i in range(pb.nu) if i not in (ia, ih)]  # blower and the three outlet valves
    pct = lambda v: pb.u_off[ia] + pb.u_sc[ia] * v  # noqa: E731
    U_lin = rec["z_lin"][solver.iu0:solver.is0].reshape(pb.N, pb.nu)
    U = rec["z"][solver.iu0:solver.is0].reshape(pb.N, pb.nu)
    s = slice(0, stages)
    # the unconstrained step along valve a from the QP's answer with the others fixed / free: -H^-1 g (% of travel)
    step_fixed = -np.linalg.solve(h_fixed, g_sol) * pb.u_sc[ia]
    ev_fixed, ev_free = np.linalg.eigvalsh(h_fixed), np.linalg.eigvalsh(h_free)
    return {
        "t": rec["t"], "exact_diag": exact_curvature(solver, rec, stages),
        "exact_lin": exact_curvature(solver, rec, stages, at="z_lin"), "a_lin_pct": pct(U_lin[s, ia]), "a_qp_pct": pct(U[s, ia]),
        "heater_w": pb.u_off[ih] + pb.u_sc[ih] * U[s, ih], "free_others": int(free[:, others].sum()),
        "diag_fixed": np.diag(h_fixed)[s], "diag_free": np.diag(h_free)[s], "diag_heater_free": np.diag(h_heater)[s],
        "terms_diag": {k: np.diag(v)[s] for k, v in terms.items()},
        "eig_fixed": (float(ev_fixed[0]), float(ev_fixed[-1])), "eig_free": (float(ev_free[0]), float(ev_free[-1])),
        "lead_fixed": np.linalg.eigvalsh(h_fixed[s, s]), "lead_free": np.linalg.eigvalsh(h_free[s, s]),
        "grad_sol": g_sol[s], "grad_lin": g_lin[s], "newton_fixed_pct": step_fixed[s],
    }


class SecondOrderDiagonal(_SolverPatch):
    """A measurement, not a controller setting: while open, each step's first QP with the linearisation point's
    heater command at its upper bound gets ``max(0, c_k - g_k)`` more on valve a's diagonal at each of the first
    ``stages`` stages (and the matching gradient, a proximal term around the linearisation point), ``c_k`` the nonlinear
    cost's second difference along that entry at the linearisation point (:func:`exact_curvature`) and ``g_k`` the QP's
    own (:func:`reduced_hessian`, the other inputs held): the curvature the Gauss-Newton Hessian drops, on the diagonal.
    OSQP refactorises once more on such a step; 3 ``stages`` prices of the plan a step (the search's merit, so only
    with ``rti_reversal_search`` on). ``added`` keeps each step's additions."""

    def __init__(self, stages: int = 8):
        self.stages = stages
        self.added: list[np.ndarray] = []
        super().__init__(("_solve_qps", "_q"))
        meas = self

        def solve_qps(solver, x0, u_prev, d, ref, w_y, *args, **kwargs):
            extra = None
            if kwargs.get("at") is None and solver._search_merit is not None and solver.X is not None:
                extra = meas._extra(solver, x0, u_prev, d, ref, w_y)
            solver._so_extra = extra
            try:
                return meas._saved["_solve_qps"](solver, x0, u_prev, d, ref, w_y, *args, **kwargs)
            finally:
                solver._so_extra = None

        def gradient(solver, ref, d, u_prev):
            q = meas._saved["_q"](solver, ref, d, u_prev)
            held = getattr(solver, "_so_extra", None)
            if held is None or solver._written is not held[1]:
                return q  # no extra, or a relinearisation since wrote a P without it
            extra = held[0]
            q = np.array(q, float)
            ia = solver._i_valve_a[:extra.size]
            q[ia] -= extra * solver._z_lin[ia]
            return q

        self._install(_solve_qps=solve_qps, _q=gradient)

    def _extra(self, solver, x0, u_prev, d, ref, w_y) -> tuple[np.ndarray, tuple] | None:
        """The added diagonal and the P data (``solver._written``) it was added to, or None off the bound."""
        pb = solver.pb
        U_lin = solver._z_lin[solver.iu0:solver.is0].reshape(pb.N, pb.nu)
        ih = pb.i_heater_cmd
        if not at_upper_bound(U_lin, pb.u_hi, ih, float(pb.u_hi[ih] - pb.u_lo[ih])):
            return None
        Px, Ax = solver._written
        P, T = full_p(solver, np.asarray(Px, float)), input_map(solver, np.asarray(Ax, float))
        ia = pb.i_valve_a + pb.nu * np.arange(self.stages)
        Ta = T[:, ia]
        own = np.einsum("ij,ij->j", Ta, P @ Ta)
        rec = {"x0": x0, "d": d, "w_y": w_y, "ref": ref, "u_prev": u_prev, "z_lin": solver._z_lin,
               "l": solver.l, "u": solver.u}
        extra = np.maximum(exact_curvature(solver, rec, self.stages, at="z_lin") - own, 0.0)
        extra[~np.isfinite(extra)] = 0.0
        self.added.append(extra)
        Px2 = np.array(Px, float)
        Px2[solver._P_valve_a_slots[:self.stages]] += extra
        solver._core.update_matrices(Px2, np.asarray(Ax, float))
        return extra, solver._written



def capture(box: str, scenario: str = "winter_heating_steps", quick: bool = True, start_s: float = 90.0,
            end_s: float = 140.0, settings: Mapping[str, Any] | None = None) -> tuple[dict, QpRecorder]:
    """:func:`.box_trace.run_trace` with the solver's first QP of each plain step kept from ``start_s`` to ``end_s``."""
    with QpRecorder(start_s, end_s) as rec:
        run = box_trace.run_trace(box, scenario, quick, 0, settings)
    return run, rec


def second_order_run(box: str, scenario: str = "winter_heating_steps", quick: bool = True,
                     settings: Mapping[str, Any] | None = None, stages: int = 8) -> tuple[dict, SecondOrderDiagonal]:
    """:func:`.box_trace.run_trace` with :class:`SecondOrderDiagonal` open over the whole run."""
    with SecondOrderDiagonal(stages) as meas:
        run = box_trace.run_trace(box, scenario, quick, 0, settings)
    return run, meas


def _fmt(v) -> str:
    return " ".join(f"{x:.3g}" for x in np.ravel(v))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hvac_mpc.benchmarks.valve_a_curvature",
                                description=__doc__.split("\n")[0])
    p.add_argument("--box", required=True)
    p.add_argument("--scenario", default="winter_heating_steps")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--from", dest="start_s", type=float, default=90.0)
    p.add_argument("--to", dest="end_s", type=float, default=140.0)
    p.add_argument("--settings", type=json.loads, default=None)
    p.add_argument("--second-order", action="store_true",
                   help="run with the dropped curvature on valve a's diagonal at the heater's bound and print the "
                        "ratio and valve a's reversals there (SecondOrderDiagonal)")
    args = p.parse_args(argv)
    if args.second_order:
        run, meas = second_order_run(args.box, args.scenario, args.quick, args.settings)
        turns = box_trace.reversals_at_heater_bound(run["mpc"].applied, Parameters().heater_power_max_w)[1]
        print(f"{run['label']} / {args.scenario}: ratio {run['ratio']:.3f}, valve a reversals at the heater's bound "
              f"{turns}, steps with the diagonal {len(meas.added)}")
        return 0
    run, rec = capture(args.box, args.scenario, args.quick, args.start_s, args.end_s, args.settings)
    print(f"{run['label']} / {args.scenario}: ratio {run['ratio']:.3f}")
    for r in rec.records:
        a = analyse(rec.solver, r)
        print(f"t={a['t']} a_lin% {_fmt(a['a_lin_pct'])} | a_qp% {_fmt(a['a_qp_pct'])} | heater W "
              f"{_fmt(a['heater_w'])} | free others {a['free_others']} | search {r['search_taken']}")
        print(f"  diag fixed {_fmt(a['diag_fixed'])} | free {_fmt(a['diag_free'])} | the heater free too "
              f"{_fmt(a['diag_heater_free'])} | nonlinear cost's at the "
              f"answer {_fmt(a['exact_diag'])} | at the lin point {_fmt(a['exact_lin'])}")
        print(f"  eig fixed {_fmt(a['eig_fixed'])} lead6 {_fmt(a['lead_fixed'])} | free {_fmt(a['eig_free'])} "
              f"lead6 {_fmt(a['lead_free'])}")
        for k, v in a["terms_diag"].items():
            if np.abs(v).max() > 1e-9:
                print(f"  term {k}: {_fmt(v)}")
        print(f"  grad at answer {_fmt(a['grad_sol'])} | at lin point {_fmt(a['grad_lin'])} | newton step (fixed) % "
              f"{_fmt(a['newton_fixed_pct'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
