"""Where a median control step's time goes: wall time around each part of ``MpcController.step``.

    python -m hvac_mpc.benchmarks.step_parts [--loops 3] [--seed 1] [--max-iterations 20] [--settings JSON]

Runs the solve-time loop (:class:`.solve_time.Loop`, default :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`,
the idle time of a sample between steps) with a timer around each of the parts below, and prints each
part's median over the steps with one QP of at most ``--max-iterations`` OSQP iterations (the median
step's kind). ``--settings '{"rti_relinearise_every": 5}'``: with these
:class:`~hvac_mpc.mpc.mpc_controller.MpcSettings` fields (JSON lists become tuples). The timers are put on the
classes for the run and taken off after it; their own cost (a microsecond or so per call) is in the times, so
the parts are shares, not exact times. A part nested in another (OSQP's calls in the feedback) is counted in
both.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from collections import defaultdict
from typing import Iterator

import numpy as np

from hvac_mpc.mpc import estimator, mpc_controller, ocp, osqp_embedded, priorities, rti_osqp
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
    (rti_osqp.RtiOsqpSolver, "_q", "  gradient (generated call)"),
    (rti_osqp.RtiOsqpSolver, "_floor_bounds", "  flow floor bounds"),
    (rti_osqp._OsqpCore, "update_vectors", "  OSQP vectors"),
    (osqp_embedded.EmbeddedOsqp, "update_vectors", "  OSQP vectors"),
    (estimator.DisturbanceEkf, "update", "estimator update"),
    (ocp.TrackingProblem, "input_bounds", "input bounds"),
    (ocp.TrackingProblem, "command_bounds", "command bounds"),
    (priorities.ReachableFlow, "check", "priorities check"),
    (priorities.ReachableFlow, "transient_flow_error", "flow-weight factor's flow error"),
    (mpc_controller.MpcController, "_trap_cap", "trapped-air cap"),
    (mpc_controller.MpcController, "_stats", "statistics"),
)


@contextlib.contextmanager
def timed(totals: dict[str, float]) -> Iterator[None]:
    """Timers around :data:`PARTS` (wall time added to ``totals`` by label) for the ``with`` block."""
    saved = []
    for cls, name, label in PARTS:
        original = cls.__dict__[name]

        def wrapper(*args, _f=original, _label=label, **kwargs):
            t0 = time.perf_counter()
            try:
                return _f(*args, **kwargs)
            finally:
                totals[_label] = totals.get(_label, 0.0) + time.perf_counter() - t0

        saved.append((cls, name, original))
        setattr(cls, name, wrapper)
    try:
        yield
    finally:
        for cls, name, original in saved:
            setattr(cls, name, original)


def measure(loops: int, seed: int, max_iterations: int, steps: int = solve_time.FULL_STEPS,
            settings: dict | None = None) -> dict[str, float]:
    """Median wall time (s) of each part over the selected steps of ``loops`` loops (``settings``: MpcSettings
    fields)."""
    rows: dict[str, list[float]] = defaultdict(list)
    selected = 0
    for _ in range(loops):
        totals: dict[str, float] = {}
        with timed(totals):
            ctrl = MpcController(settings=MpcSettings(**(settings or {})))
            loop = solve_time.Loop(ctrl, seed, idle_s=solve_time.IDLE_S)
            for k in range(steps):
                totals.clear()
                st = loop.step(k).stats
                if k > 0 and st["qp_solves"] == 1 and st["iterations"] <= max_iterations:
                    selected += 1
                    for _, _, label in PARTS:
                        rows[label].append(totals.get(label, 0.0))
    return {"steps": selected, **{label: float(np.median(v)) for label, v in rows.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loops", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-iterations", type=int, default=20)
    parser.add_argument("--settings", default=None, metavar="JSON", help="MpcSettings fields, e.g. "
                        "'{\"rti_relinearise_every\": 5}'")
    args = parser.parse_args(argv)
    if args.loops < 1 or args.max_iterations < 1:
        parser.error("--loops and --max-iterations must be at least 1")
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(args.settings or "{}").items()}
    out = measure(args.loops, args.seed, args.max_iterations, settings=fields)
    print(f"median over {out.pop('steps')} steps with one QP of at most {args.max_iterations} OSQP iterations "
          "(wall time, timers' own cost included):")
    for label, value in out.items():
        print(f"  {label:<66} {value * 1e3:7.3f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
