"""The slow steps of the solve-time loop, before and after, side by side: the reachable-flow solve inside
the step against on a second thread, and OSQP's iterations per QP capped.

    python -m hvac_mpc.benchmarks.step_tail [--rounds 3] [--steps 240] [--seed 1] [--json FILE]

The solve-time loop (:mod:`hvac_mpc.benchmarks.solve_time`: 240 closed-loop steps, eight references)
with the RTI as configured by default except for the settings each variant names (all of them, so
the comparison does not move with the defaults):

* ``inline``: the reachable flow (:mod:`hvac_mpc.mpc.priorities`) solved inside the step that needs
  it, OSQP capped at 400 iterations per QP with a QP at the cap a failure (earlier settings);
* ``reach_thread``: that solve started in the step on a second thread and applied from the next
  step on (``reach_deferred=True, reach_background=True``);
* ``reach_thread_cap60``: as well, OSQP capped at 60 iterations per QP with the iterate at the cap
  the QP's answer (``osqp_max_iter=60, osqp_accept_max_iter=True``);
* ``changes_thread``: ``reach_thread`` with the solve at a change of the references on the second thread
  too, the step answering from the last solve (``reach_changes_deferred=True``);
* ``changes_thread_cap60``: both (the cap of 60 is a setting, not a default).

The variants run alternately, ``--rounds`` times each, on at most two cores (the solve-time
benchmark's limit); between steps the loop gives the second thread up to a sample's time, untimed, as
``solve-time`` does (``--back-to-back``: none). Per step: the wall time of ``MpcController.step`` and the CPU time of the thread
that runs it (``time.thread_time``; the process CPU time would count the second thread's solve too),
the cold first step excluded; per loop the closed-loop cost (as ``solve-time`` computes it), the
reachable-flow solves and the OSQP iterations of the slowest steps. The commands of ``reach_thread`` and
``changes_thread_cap60`` are checked against the same settings without the thread (the same bit for bit).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    if not os.environ.get(_var, "").isdigit() or int(os.environ[_var]) > 2:
        os.environ[_var] = "2"

import argparse  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings  # noqa: E402

from . import solve_time  # noqa: E402

BEFORE = {"reach_deferred": False, "reach_background": False, "reach_changes_deferred": False, "osqp_max_iter": 400,
          "osqp_accept_max_iter": False}
VARIANTS = {"inline": BEFORE,
            "reach_thread": {**BEFORE, "reach_deferred": True, "reach_background": True},
            "reach_thread_cap60": {**BEFORE, "reach_deferred": True, "reach_background": True, "osqp_max_iter": 60,
                                   "osqp_accept_max_iter": True},
            "changes_thread": {**BEFORE, "reach_deferred": True, "reach_background": True,
                               "reach_changes_deferred": True},
            "changes_thread_cap60": {**BEFORE, "reach_deferred": True, "reach_background": True,
                                     "reach_changes_deferred": True, "osqp_max_iter": 60, "osqp_accept_max_iter": True}}
#: The variants whose commands are checked against the same settings without the second thread.
THREADED = ("reach_thread", "changes_thread_cap60")


def run_loop(settings: MpcSettings, steps: int, seed: int, idle_s: float = solve_time.IDLE_S) -> dict[str, Any]:
    """One closed loop of the solve-time scenario: per-step wall and thread CPU times (ms), commands,
    the steps that started a reachable-flow solve, and the closed-loop cost. ``idle_s``: the time the loop
    gives the second thread between steps (``solve_time.Loop``; 0 back to back)."""
    ctrl = MpcController(settings=settings)
    solver, started = ctrl.reach.solver, []
    k = 0

    def counted(**kw):
        started.append(k)
        return solver(**kw)

    ctrl.reach.solver = counted  # the index is read when the call starts: on a thread it may be k + 1
    loop = solve_time.Loop(ctrl, seed, idle_s=idle_s)
    wall, commands, iterations = [], [], []
    for k in range(steps):
        res = loop.step(k)
        wall.append(res.stats["step_time_s"])
        iterations.append(res.stats["iterations"])
        commands.append(res.command.vector())
    ctrl.reach.reset()
    cpu, cost = loop.thread_s, sum(loop.cost.values())
    return {"wall_ms": np.array(wall[1:]) * 1e3, "cpu_ms": np.array(cpu[1:]) * 1e3, "commands": np.array(commands),
            "solves": started, "cost": cost, "iterations": np.array(iterations[1:]),
            "background": solve_time.background_waits(loop, idle_s)}


def figures(times_ms: np.ndarray) -> dict[str, float]:
    return {"median_ms": float(np.median(times_ms)), "p99_ms": float(np.percentile(times_ms, 99)),
            "max_ms": float(times_ms.max())}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cost-seeds", type=int, default=1,
                        help="closed-loop cost of every variant on seeds --seed ... --seed + N - 1 (untimed beyond --seed)")
    parser.add_argument("--json", type=Path, default=Path("step_tail.json"))
    parser.add_argument("--back-to-back", action="store_true",
                        help="no time for the second thread between steps (as solve-time --back-to-back)")
    args = parser.parse_args(argv)
    idle_s = 0.0 if args.back_to_back else solve_time.IDLE_S
    if args.rounds < 1 or args.steps < 3 or not 1 <= args.cost_seeds <= 20:
        parser.error("--rounds must be at least 1, --steps at least 3 and --cost-seeds in [1, 20]")
    solve_time.pin_cores(2)
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name in VARIANTS}
    loops: dict[str, dict[str, Any]] = {}
    for r in range(args.rounds):
        for name, extra in VARIANTS.items():
            loop = run_loop(MpcSettings(**extra), args.steps, args.seed, idle_s)
            loops[name] = loop
            rows[name].append({"round": r, "wall": figures(loop["wall_ms"]), "thread_cpu": figures(loop["cpu_ms"]),
                               "reach_solves": len(loop["solves"]), "cost": loop["cost"],
                               "osqp_iterations_top": [int(v) for v in np.sort(loop["iterations"])[::-1][:8]]})
            w, c = rows[name][-1]["wall"], rows[name][-1]["thread_cpu"]
            print(f"round {r} {name:<18} wall median {w['median_ms']:.2f} p99 {w['p99_ms']:.2f} max {w['max_ms']:.2f} ms"
                  f" | thread CPU median {c['median_ms']:.2f} p99 {c['p99_ms']:.2f} max {c['max_ms']:.2f} ms"
                  f" | solves {len(loop['solves'])}, cost {loop['cost']:.2f}"
                  f" | OSQP iterations, largest {rows[name][-1]['osqp_iterations_top'][:4]}"
                  f" | steps waiting for the thread {loop['background']['steps_waiting']}", flush=True)
    same = all(np.array_equal(loops[name]["commands"], run_loop(
        MpcSettings(**{**VARIANTS[name], "reach_background": False}), args.steps, args.seed)["commands"])
        for name in THREADED)
    print(f"{' and '.join(THREADED)} commands equal to the deferred solve on the step's own thread: {same}")
    costs = {name: [rows[name][0]["cost"]] for name in VARIANTS}
    for seed in range(args.seed + 1, args.seed + args.cost_seeds):
        for name, extra in VARIANTS.items():
            costs[name].append(run_loop(MpcSettings(**extra), args.steps, seed)["cost"])
    if args.cost_seeds > 1:
        for name, c in costs.items():
            print(f"closed-loop cost {name:<18} seeds {args.seed}-{args.seed + args.cost_seeds - 1}: "
                  + " / ".join(f"{v:.1f}" for v in c) + f", sum {sum(c):.1f}")
    out = {"steps": args.steps, "seed": args.seed, "variants": VARIANTS, "rounds": rows, "thread_equals_deferred": same,
           "cost_by_seed": costs,
           "inline_solve_steps": loops["inline"]["solves"]}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.json}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
