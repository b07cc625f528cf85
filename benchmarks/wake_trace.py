"""The slow single QPs after a reference change, taken apart: OSQP's iterations, step size and residuals.

    python -m hvac_mpc.benchmarks.wake_trace [--seed 1] [--steps 240] [--min-iterations 100] [--settings JSON]
                                             [--json FILE]

Runs the solve-time loop (:class:`.solve_time.Loop`, the controller at its defaults but for ``--settings``, OSQP's
Python interface so that each QP's data and multipliers can be read) and records every QP OSQP is handed: the
matrices, vectors and warm start, OSQP's step size ``rho`` before and after the solve, its iterations and the
multipliers it ended with. Printed per QP of at least ``--min-iterations`` iterations that is not a change's
(a step with one QP; the step, the iterations, ``rho`` before / after) and, replayed offline in a fresh OSQP with
the loop's settings (:func:`replay`):

* the residuals along the way (the solve stopped every ``check_termination`` iterations: primal and dual residual,
  ``rho``; :func:`residual_trace`);
* which rows change activity between the warm start's multipliers and the answer's, by kind of row
  (:data:`ROW_KINDS`: the dynamics, the input bounds, the rate rows, the heater and PTC rows, the slacks, the flow
  floor; :func:`activity_changes`);
* the iterations from other starts and settings (:data:`STARTS`, :data:`SETTINGS`): cold, primal only, the
  multipliers shifted one stage like the plan, the rate rows' multipliers zeroed, ``rho`` from the last QP of the
  step before or set, OSQP's polish, and the exact answer (a check that the start, not the QP, is what costs).

The replay sets OSQP up afresh for each QP, so its multipliers are scaled with that QP's equilibration where the
loop's workspace holds them scaled with the last one's: its iterations are close to, not the loop's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Callable

import numpy as np
import osqp

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

from . import solve_time

#: Kinds of constraint row, by :class:`RtiOsqpSolver`'s row-index attribute.
ROW_KINDS = {"x0": "r_x0", "dynamics": "r_dyn", "input bounds": "r_u", "rate": "r_rate", "heater row": "r_soft",
             "slack": "r_slack", "ptc row": "r_ptc", "flow floor": "r_floor"}
#: A multiplier of at most this magnitude counts as inactive (the rows' scale is O(1)).
ACTIVE_TOL = 1e-6


class Recorder:
    """Stands in for the solver's OSQP core (:class:`.rti_osqp._OsqpCore`) and records each QP it is handed."""

    def __init__(self, core):
        self.core = core
        self.step = -1
        self.qps: list[dict[str, Any]] = []
        self._mat = self._vec = self._ws = None

    def __getattr__(self, name):
        return getattr(self.core, name)

    def update_matrices(self, Px, Ax):
        self._mat = (np.array(Px), np.array(Ax))
        self.core.update_matrices(Px, Ax)

    def update_vectors(self, q, l, u):
        self._vec = (np.array(q), np.array(l), np.array(u))
        self.core.update_vectors(q, l, u)

    def warm_start(self, x, y=None):
        self._ws = (np.array(x), None if y is None else np.array(y))
        self.core.warm_start(x, y)

    def _record(self, solve: Callable, *args):
        y_before = self._last_y()
        rho0 = self.core.rho
        out = solve(*args)
        x_ws, y_ws = self._ws
        self.qps.append({"step": self.step, "Px": self._mat[0], "Ax": self._mat[1], "q": self._vec[0],
                         "l": self._vec[1], "u": self._vec[2], "x_ws": x_ws,
                         "y_ws": y_before if y_ws is None else y_ws, "rho_before": rho0, "rho_after": self.core.rho,
                         "iterations": int(out[2]), "status": out[1], "x": np.array(out[3]), "y": self._last_y()})
        return out

    def _last_y(self):
        last = self.core._last
        if last is None:
            return None
        return np.array(last.solution.y if self.core.core is not None else last.y, float)

    def solve(self):
        return self._record(self.core.solve)

    def solve_capped(self, max_iter):
        return self._record(self.core.solve_capped, max_iter)


def record_loop(seed: int, steps: int, settings: dict[str, Any]) -> tuple[RtiOsqpSolver, Recorder, list]:
    """The loop of ``seed`` with the QPs recorded; the solver, the recorder and the step results."""
    ctrl = MpcController(settings=MpcSettings(**{**settings, "osqp_codegen": False}))
    loop = solve_time.Loop(ctrl, seed, idle_s=solve_time.IDLE_S)
    rec = Recorder(ctrl.solver._core)
    results = []
    for k in range(steps):
        if ctrl.solver._core is not rec:
            if not isinstance(ctrl.solver._core, Recorder):
                rec.core = ctrl.solver._core
            ctrl.solver._core = rec
        rec.step = k
        results.append(loop.step(k).stats)
    return ctrl.solver, rec, results


def osqp_for(solver: RtiOsqpSolver, qp: dict[str, Any], **overrides) -> osqp.OSQP:
    """A fresh OSQP set up with ``qp``'s data and the loop's settings (``overrides`` by OSQP's names)."""
    st = {**solver._osqp_settings, **overrides}
    st.pop("time_limit", None)
    o = osqp.OSQP()
    o.setup(solver.P.matrix(qp["Px"]), qp["q"], solver.A.matrix(qp["Ax"]), qp["l"], qp["u"], **st)
    return o


def replay(solver: RtiOsqpSolver, qp: dict[str, Any], x: np.ndarray | None, y: np.ndarray | None,
           rho: float, **overrides) -> dict[str, Any]:
    """``qp`` solved in a fresh OSQP from the start ``x``, ``y`` (None: zero) with step size ``rho``."""
    o = osqp_for(solver, qp, rho=rho, **overrides)
    o.warm_start(x=np.zeros(solver.n) if x is None else x, y=np.zeros(solver.m) if y is None else y)
    r = o.solve(raise_error=False)
    return {"iterations": int(r.info.iter), "status": str(r.info.status), "rho": float(r.info.rho_estimate),
            "x": np.array(r.x), "y": np.array(r.y)}


def residual_trace(solver: RtiOsqpSolver, qp: dict[str, Any], every: int = 5, limit: int = 400) -> list[list[float]]:
    """[iterations, primal residual, dual residual, rho] every ``every`` iterations of ``qp`` replayed from the
    loop's start (its warm start, multipliers and step size), up to convergence or ``limit``."""
    rows = []
    for k in range(every, limit + 1, every):
        o = osqp_for(solver, qp, rho=qp["rho_before"], max_iter=k)
        o.warm_start(x=qp["x_ws"], y=qp["y_ws"])
        r = o.solve(raise_error=False)
        rows.append([int(r.info.iter), float(r.info.prim_res), float(r.info.dual_res),
                     float(o._solver.get_settings().rho)])
        if r.info.status_val == 1:
            break
    return rows


def activity_changes(solver: RtiOsqpSolver, y_start: np.ndarray, y_end: np.ndarray) -> dict[str, list[int]]:
    """Per kind of row (:data:`ROW_KINDS`): [rows active at the start, rows active at the end, rows that changed]
    (active: a multiplier above :data:`ACTIVE_TOL`; a change: inactive to active, active to inactive, or the
    bound's side)."""
    out = {}
    for kind, attr in ROW_KINDS.items():
        rows = np.asarray(getattr(solver, attr)).ravel()
        if rows.size == 0:
            continue
        a = np.sign(np.where(np.abs(y_start[rows]) > ACTIVE_TOL, y_start[rows], 0.0))
        b = np.sign(np.where(np.abs(y_end[rows]) > ACTIVE_TOL, y_end[rows], 0.0))
        out[kind] = [int(np.count_nonzero(a)), int(np.count_nonzero(b)), int(np.count_nonzero(a != b))]
    return out


def shifted_duals(solver: RtiOsqpSolver, y: np.ndarray) -> np.ndarray:
    """The multipliers moved one stage earlier as the plan is (each stage's the next one's, the last kept): the
    rows of every stage-indexed kind; the initial state's rows kept."""
    out = y.copy()
    for kind, attr in ROW_KINDS.items():
        rows = np.asarray(getattr(solver, attr))
        if kind == "x0" or rows.size == 0:
            continue
        stages = rows.reshape(rows.shape[0], -1)
        out[stages[:-1].ravel()] = y[stages[1:].ravel()]
    return out


def rate_rows_zeroed(solver: RtiOsqpSolver, y: np.ndarray) -> np.ndarray:
    """The multipliers with the rate rows' set to zero."""
    out = y.copy()
    out[np.asarray(solver.r_rate).ravel()] = 0.0
    return out


#: Starts replayed: name -> (x, y) from the recorded QP (and the solver).
STARTS: dict[str, Callable] = {
    "as the loop": lambda s, qp: (qp["x_ws"], qp["y_ws"]),
    "cold (zero)": lambda s, qp: (None, None),
    "primal only": lambda s, qp: (qp["x_ws"], None),
    "duals shifted": lambda s, qp: (qp["x_ws"], shifted_duals(s, qp["y_ws"])),
    "rate duals zeroed": lambda s, qp: (qp["x_ws"], rate_rows_zeroed(s, qp["y_ws"])),
    "exact answer": lambda s, qp: (qp["x"], qp["y"]),
}
#: Settings replayed from the loop's start: name -> (rho from the recorded QP and the one before, OSQP overrides).
SETTINGS: dict[str, tuple[Callable, dict[str, Any]]] = {
    "rho 1e-3": (lambda qp, prev: 1e-3, {}),
    "rho 3e-3": (lambda qp, prev: 3e-3, {}),
    "rho 1e-2": (lambda qp, prev: 1e-2, {}),
    "rho as it ended": (lambda qp, prev: qp["rho_after"], {}),
    "rho interval 5": (lambda qp, prev: qp["rho_before"], {"adaptive_rho_interval": 5}),
    "rho tolerance 2": (lambda qp, prev: qp["rho_before"], {"adaptive_rho_tolerance": 2.0}),
    "polish": (lambda qp, prev: qp["rho_before"], {"polishing": True}),
    "eps 1e-3": (lambda qp, prev: qp["rho_before"], {"eps_abs": 1e-3, "eps_rel": 1e-3}),
}


def slow_qps(rec: Recorder, results: list, min_iterations: int) -> list[int]:
    """Indices of the recorded QPs of at least ``min_iterations`` in steps of one QP (not a change's two)."""
    return [i for i, qp in enumerate(rec.qps)
            if qp["iterations"] >= min_iterations and results[qp["step"]]["qp_solves"] == 1 and qp["step"] > 0]


def trace(seed: int, steps: int, min_iterations: int, settings: dict[str, Any]) -> dict[str, Any]:
    solver, rec, results = record_loop(seed, steps, settings)
    out = []
    for i in slow_qps(rec, results, min_iterations):
        qp = rec.qps[i]
        prev = rec.qps[i - 1]
        row = {"step": qp["step"], "iterations": qp["iterations"], "rho_before": qp["rho_before"],
               "rho_after": qp["rho_after"], "activity": activity_changes(solver, qp["y_ws"], qp["y"]),
               "residuals": residual_trace(solver, qp, solver._osqp_settings["check_termination"]),
               "starts": {}, "settings": {}}
        for name, start in STARTS.items():
            x, y = start(solver, qp)
            row["starts"][name] = replay(solver, qp, x, y, qp["rho_before"])["iterations"]
        for name, (rho, over) in SETTINGS.items():
            row["settings"][name] = replay(solver, qp, qp["x_ws"], qp["y_ws"], rho(qp, prev), **over)["iterations"]
        out.append(row)
    all_iterations = [qp["iterations"] for qp in rec.qps]
    rhos = [[qp["step"], qp["iterations"], qp["rho_before"], qp["rho_after"]] for qp in rec.qps]
    return {"seed": seed, "iterations": int(sum(all_iterations)), "slow": out, "rho_by_qp": rhos}


def print_trace(t: dict[str, Any]) -> None:
    print(f"seed {t['seed']}: {t['iterations']} OSQP iterations in all")
    for r in t["slow"]:
        print(f"step {r['step']}: {r['iterations']} iterations, rho {r['rho_before']:.3g} -> {r['rho_after']:.3g}")
        print("  activity [start, end, changed]: " + ", ".join(f"{k} {v}" for k, v in r["activity"].items() if v[2]))
        res = r["residuals"]
        pick = res[:4] + res[4:-2:max(1, (len(res) - 6) // 6)] + res[-2:] if len(res) > 10 else res
        print("  residuals [it, prim, dual, rho]: "
              + " ".join(f"[{a}, {b:.2g}, {c:.2g}, {d:.2g}]" for a, b, c, d in pick))
        print("  starts: " + ", ".join(f"{k} {v}" for k, v in r["starts"].items()))
        print("  settings: " + ", ".join(f"{k} {v}" for k, v in r["settings"].items()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--min-iterations", type=int, default=100)
    parser.add_argument("--settings", type=json.loads, default={}, help="MpcSettings fields (JSON)")
    parser.add_argument("--json", type=Path, default=Path("wake_trace.json"))
    args = parser.parse_args(argv)
    t = trace(args.seed, args.steps, args.min_iterations, args.settings)
    print_trace(t)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(t, indent=1))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
