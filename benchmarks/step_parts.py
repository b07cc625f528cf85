"""Where a median control step's time goes: wall time around each part of ``MpcController.step``.

    python -m hvac_mpc.benchmarks.step_parts [--loops 3] [--seed 1] [--max-iterations 20]
                                             [--changes] [--settings JSON] [--thread-cpu] [--back-to-back]
                                             [--mean]

Runs the solve-time loop (:class:`.solve_time.Loop`, default :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`,
the idle time of a sample between steps) with a timer around each of the parts below, and prints each
part's median over the steps with one QP of at most ``--max-iterations`` OSQP iterations (the median
step's kind); with ``--changes`` over the steps with two QPs or more instead (a reference change's), and
``--settings`` changes :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings` fields (e.g. the steady-state start).
``--thread-cpu`` times with the CPU time of the
thread (``time.thread_time``; every part runs on the step's thread) instead of wall time, for a loaded machine.
Parts that take no time in the selected steps are not printed. The timers are put on the classes for the
run and taken off after it; their own cost (a microsecond or so per call) is in the times, so the parts are
shares, not exact times. A part nested in another (OSQP's calls in the feedback) is counted in both. A part
counts only inside the step: the filter not in use (``choose_offset_placement``) is brought up to the sample
between the steps, in the loop's idle time (:meth:`MpcController.wait_background`), and its updates are not the
step's (with ``--back-to-back``, the steps one after the other as ``step_versions`` runs them, they are, under
"the other filter").
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from collections import defaultdict
from typing import Iterator

import numpy as np

from hvac_mpc.mpc import casadi_eval, estimator, mpc_controller, ocp, osqp_embedded, priorities, rti_osqp
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings

from . import solve_time

#: (class, method, label) of the parts timed.
PARTS = (
    (mpc_controller.MpcController, "step", "whole step"),
    (rti_osqp.RtiOsqpSolver, "prepare_predicted", "prediction and preparation (generated call, OSQP matrix update)"),
    (rti_osqp._OsqpCore, "update_matrices", "  OSQP matrix update (equilibration, refactorisation)"),
    (osqp_embedded.EmbeddedOsqp, "update_matrices", "  OSQP matrix update (equilibration, refactorisation)"),
    (rti_osqp.RtiOsqpSolver, "_prepare_vectors", "  of it, a multi-level preparation (vector step or full)"),
    (rti_osqp.RtiOsqpSolver, "feedback", "feedback (gradient, bounds, OSQP solve)"),
    (osqp_embedded.TwoPassSolve, "solve", "  OSQP solve"),
    (rti_osqp.RtiOsqpSolver, "_start_steady", "  steady-state start (generated call, linearisation, matrix update)"),
    (rti_osqp.RtiOsqpSolver, "prepare", "  preparation in the feedback (linearisation, matrix update)"),
    (rti_osqp.RtiOsqpSolver, "_relinearise", "  relinearisation for a further QP (matrix update)"),
    (rti_osqp.RtiOsqpSolver, "_q", "  gradient (generated call)"),
    (rti_osqp.RtiOsqpSolver, "_floor_bounds", "  flow floor bounds"),
    (rti_osqp._OsqpCore, "update_vectors", "  OSQP vectors"),
    (osqp_embedded.EmbeddedOsqp, "update_vectors", "  OSQP vectors"),
    (estimator.DisturbanceEkf, "update", "estimator update"),
    (mpc_controller.MpcController, "_run_other_filter", "the other filter (measurement and time update)"),
    (ocp.TrackingProblem, "input_bounds", "input bounds"),
    (ocp.TrackingProblem, "command_bounds", "command bounds"),
    (priorities.ReachableFlow, "flows", "reachable-flow check's flows (generated call)"),
    (priorities.ReachableFlow, "check", "priorities check"),
    (priorities.ReachableFlow, "transient_flow_error", "flow-weight factor's flow error"),
    (mpc_controller.MpcController, "_trap_cap", "trapped-air cap"),
    (mpc_controller.MpcController, "_check_valve_sign", "valve a sign check (with its predicted air changes)"),
    (casadi_eval.BufferedFunction, "__call__", "  generated calls through buffers (all of them, within the parts above)"),
    (casadi_eval.BufferedFunction, "views", "  generated calls through buffers (all of them, within the parts above)"),
    (mpc_controller.MpcController, "_stats", "statistics"),
)


#: The label of the whole step, within which the other parts are timed.
WHOLE = "whole step"


@contextlib.contextmanager
def timed(totals: dict[str, float], clock=time.perf_counter) -> Iterator[None]:
    """Timers around :data:`PARTS` (``clock``'s time, wall time by default, added to ``totals`` by label) for the
    ``with`` block; a part's time counts only inside the step (:data:`WHOLE`)."""
    saved = []
    depth = [0]  # steps under way (the parts' calls between the steps are not the step's)
    for cls, name, label in PARTS:
        original = cls.__dict__[name]

        def wrapper(*args, _f=original, _label=label, **kwargs):
            whole = _label == WHOLE
            if not (whole or depth[0]):
                return _f(*args, **kwargs)
            depth[0] += whole
            t0 = clock()
            try:
                return _f(*args, **kwargs)
            finally:
                totals[_label] = totals.get(_label, 0.0) + clock() - t0
                depth[0] -= whole

        saved.append((cls, name, original))
        setattr(cls, name, wrapper)
    try:
        yield
    finally:
        for cls, name, original in saved:
            setattr(cls, name, original)


def selected(stats: dict, max_iterations: int, changes: bool) -> bool:
    """Whether a step with these statistics is one of those measured: one QP of at most ``max_iterations``
    OSQP iterations, or with ``changes`` two QPs or more."""
    return stats["qp_solves"] >= 2 if changes else stats["qp_solves"] == 1 and stats["iterations"] <= max_iterations


def measure(loops: int, seed: int, max_iterations: int, steps: int = solve_time.FULL_STEPS, changes: bool = False,
            settings: dict | None = None, clock=time.perf_counter, idle_s: float = solve_time.IDLE_S,
            mean: bool = False) -> dict[str, float]:
    """Median time (s, ``clock``'s) of each part over the selected steps (:func:`selected`) of ``loops`` loops, and the
    median OSQP iterations of those steps; with ``mean`` each part's mean instead (a part that runs in some of the
    steps only, the sign check's predictions in about a third, has a median that hides it). ``idle_s``: the time
    given between the steps (:class:`.solve_time.Loop`; 0: back to back)."""
    rows: dict[str, list[float]] = defaultdict(list)
    iterations = []
    for _ in range(loops):
        totals: dict[str, float] = {}
        with timed(totals, clock):
            fields = {k: tuple(v) if isinstance(v, list) else v for k, v in (settings or {}).items()}  # JSON lists
            ctrl = MpcController(settings=MpcSettings(**fields))
            loop = solve_time.Loop(ctrl, seed, idle_s=idle_s)
            for k in range(steps):
                totals.clear()
                st = loop.step(k).stats
                if k > 0 and selected(st, max_iterations, changes):
                    iterations.append(st["iterations"])
                    for _, _, label in PARTS:
                        rows[label].append(totals.get(label, 0.0))
    return {"steps": len(iterations), "iterations": float(np.median(iterations)) if iterations else 0.0,
            **{label: float(np.mean(v) if mean else np.median(v)) for label, v in rows.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loops", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-iterations", type=int, default=20)
    parser.add_argument("--changes", action="store_true", help="the steps with two QPs or more (the changes')")
    parser.add_argument("--settings", type=json.loads, default=None,
                        help='MpcSettings fields as a JSON object, e.g. \'{"steady_start": true}\'')
    parser.add_argument("--thread-cpu", action="store_true", help="the thread's CPU time instead of wall time")
    parser.add_argument("--back-to-back", action="store_true",
                        help="no idle time between the steps (the filter not in use then updates inside the step)")
    parser.add_argument("--mean", action="store_true", help="each part's mean over the steps instead of its median")
    args = parser.parse_args(argv)
    if args.loops < 1 or args.max_iterations < 1:
        parser.error("--loops and --max-iterations must be at least 1")
    clock = time.thread_time if args.thread_cpu else time.perf_counter
    out = measure(args.loops, args.seed, args.max_iterations, changes=args.changes, settings=args.settings,
                  clock=clock, idle_s=0.0 if args.back_to_back else solve_time.IDLE_S, mean=args.mean)
    kind = "two QPs or more" if args.changes else f"one QP of at most {args.max_iterations} OSQP iterations"
    print(f"{'mean' if args.mean else 'median'} over {out.pop('steps')} steps with {kind} (OSQP iterations {out.pop('iterations'):.0f}; "
          f"{'thread CPU' if args.thread_cpu else 'wall'} time, timers' own cost included):")
    for label, value in out.items():
        if value > 0.0:
            print(f"  {label:<66} {value * 1e3:7.3f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
