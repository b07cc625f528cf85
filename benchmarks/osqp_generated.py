"""OSQP's generated C against its Python interface on the RTI's own QPs, side by side.

    python -m hvac_mpc.benchmarks.osqp_generated [--steps 240] [--seed 1] [--rounds 2]
                                                 [--scaling-intervals 5,20] [--json FILE]

The QPs the solve-time loop (:mod:`.solve_time`, default :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`)
hands OSQP are recorded (:func:`.qp_dense.record`) and replayed in order, one QP of each route in turn
(which goes first alternates), each route with a workspace of its own set up like the controller's:

* ``python``: OSQP's Python interface as the controller called it before (:class:`~hvac_mpc.mpc.rti_osqp._OsqpCore`);
* ``generated``: OSQP's generated C (:class:`~hvac_mpc.mpc.osqp_embedded.EmbeddedOsqp`), the same calls;
* ``kept_K`` (``--scaling-intervals``): the generated C equilibrating on every K-th matrix update only.

Per QP the CPU time of the thread (``time.thread_time``) of the matrix update alone and of the whole
update, vectors, warm start and solve; the iterations; the largest difference of the answer from the
Python interface's (0 when the arithmetic is the same). Reported: median, 99th percentile and largest time,
the per-QP time ratio to ``python`` (median), and the time per iteration on the QPs of 100 iterations or
more (the reference changes' QPs, the 99th percentile's).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from hvac_mpc.mpc import osqp_embedded
from hvac_mpc.mpc.codegen import CodegenReport
from hvac_mpc.mpc.rti_osqp import _OsqpCore

from . import qp_dense, solve_time

#: QPs with at least this many OSQP iterations count as the hard ones (the reference changes').
HARD_ITERATIONS = 100


def routes(qps: list[dict], lay: qp_dense.Layout, intervals: list[int]) -> dict[str, Any]:
    """Fresh workspaces of every route (the generated ones from the same set-up as the Python one)."""
    out: dict[str, Any] = {"python": _python(qps, lay)}
    for name, interval in [("generated", 1)] + [(f"kept_{k}", k) for k in intervals]:
        report = CodegenReport()
        core = osqp_embedded.load(qp_dense.OsqpReplay(qps, lay).solver, lay.P_pattern, lay.A_pattern,
                                  report=report, scaling_interval=interval)
        if core is None:
            raise RuntimeError(f"the generated OSQP is not available: {report.outcomes['osqp']}")
        out[name] = core
    return out


def _python(qps: list[dict], lay: qp_dense.Layout) -> _OsqpCore:
    """OSQP's Python interface set up as the controller sets it up (the gradient zero: the first matrix
    update's cost scaling sees it), with the first QP's matrices and bounds."""
    replay = qp_dense.OsqpReplay([{**qps[0], "q": np.zeros_like(qps[0]["q"])}], lay)
    return replay.core


def solve(core, qp: dict) -> tuple[float, float, int, np.ndarray]:
    """Thread CPU time (s) of the matrix update and of the whole QP, the iterations and the answer."""
    t0 = time.thread_time()
    core.update_matrices(qp["Px"], qp["Ax"])
    t1 = time.thread_time()
    core.update_vectors(qp["q"], qp["l"], qp["u"])
    core.warm_start(qp["warm"])
    _, _, iterations, x = core.solve()
    return t1 - t0, time.thread_time() - t0, int(iterations), np.array(x)


def replay(qps: list[dict], lay: qp_dense.Layout, intervals: list[int]) -> dict[str, dict]:
    """The recorded QPs through every route, one QP of each route in turn."""
    cores = routes(qps, lay, intervals)
    names = list(cores)
    rows: dict[str, list] = {name: [] for name in names}
    for i, qp in enumerate(qps):
        for name in (names if i % 2 == 0 else names[::-1]):
            rows[name].append(solve(cores[name], qp))
    base = rows["python"]
    result = {}
    for name, r in rows.items():
        update = np.array([x[0] for x in r]) * 1e3
        total = np.array([x[1] for x in r]) * 1e3
        its = np.array([x[2] for x in r])
        hard = its >= HARD_ITERATIONS
        result[name] = {
            "update_ms": {"median": float(np.median(update))},
            "qp_ms": {"median": float(np.median(total)), "p99": float(np.percentile(total, 99)),
                      "max": float(total.max())},
            "ratio_to_python": float(np.median(total / (np.array([x[1] for x in base]) * 1e3))),
            "iterations": {"total": int(its.sum()), "median": float(np.median(its)), "max": int(its.max()),
                           "hard_qps": int(hard.sum())},
            "us_per_iteration_hard": float(total[hard].sum() * 1e3 / its[hard].sum()) if hard.any() else None,
            "largest_difference": float(max(np.abs(x[3] - b[3]).max() for x, b in zip(r, base))),
        }
    return result


def main(argv: list[str] | None = None) -> int:
    p = qp_dense.replay_arguments(__doc__.splitlines()[0])
    p.add_argument("--scaling-intervals", default="",
                   help="generated routes equilibrating on every K-th update only, e.g. 5,20")
    p.add_argument("--json", type=Path, help="write the results here")
    args = p.parse_args(argv)
    intervals = [int(k) for k in args.scaling_intervals.split(",") if k.strip()]
    if args.steps < 2 or args.rounds < 1 or any(k < 1 for k in intervals):
        p.error("--steps must be at least 2, --rounds and the scaling intervals at least 1")
    saved = solve_time.pin_cores(2)
    try:
        qps, lay, cost = qp_dense.record(args.steps, args.seed)
        print(f"{len(qps)} QPs recorded ({args.steps} steps, seed {args.seed}, closed-loop cost {cost:.2f})")
        results = []
        for r in range(args.rounds):
            res = replay(qps, lay, intervals)
            results.append(res)
            print(f"round {r + 1} (thread CPU time per QP: matrix update + vectors + warm start + solve)")
            for name, x in res.items():
                q = x["qp_ms"]
                per_it = x["us_per_iteration_hard"]
                print(f"  {name:<10} median {q['median']:.3f} ms (update {x['update_ms']['median']:.3f}), "
                      f"p99 {q['p99']:.3f}, max {q['max']:.3f} ms, {x['ratio_to_python']:.2f}x per QP; "
                      f"iterations {x['iterations']['total']} (max {x['iterations']['max']}, "
                      f"{x['iterations']['hard_qps']} QPs >= {HARD_ITERATIONS}: "
                      f"{per_it:.1f} us/iteration); largest difference {x['largest_difference']:.3g}"
                      if per_it is not None else f"  {name}: {q}")
    finally:
        if saved is not None:
            os.sched_setaffinity(0, saved)
    if args.json:
        args.json.write_text(json.dumps({"seed": args.seed, "steps": args.steps, "rounds": results}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
