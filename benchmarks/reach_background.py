"""The reachable-flow solve inside the step against on a second thread, side by side.

    python -m hvac_mpc.benchmarks.reach_background [--rounds 3] [--steps 240] [--seed 1] [--json FILE]

The solve-time loop (:mod:`hvac_mpc.benchmarks.solve_time`: 240 closed-loop steps, eight references)
with the RTI as configured by default except for the reachable flow (:mod:`hvac_mpc.mpc.priorities`):
``inline`` solves it inside the step that needs it (``reach_deferred=False``), ``background`` starts it
in that step on a second thread and applies it from the next step on (``reach_deferred=True,
reach_background=True``). The two loops run alternately, ``--rounds`` times each, on at most two
cores (the solve-time benchmark's limit). Per step: the wall time of ``MpcController.step`` and the
CPU time of the thread that runs it (``time.thread_time``; the process CPU time would count the
second thread's solve too), the cold first step excluded; per loop the closed-loop cost (as
``solve-time`` computes it) and which steps started a solve. The background loop's commands are
checked against ``reach_deferred=True`` without the thread (the same bit for bit).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    if not os.environ.get(_var, "").isdigit() or int(os.environ[_var]) > 2:
        os.environ[_var] = "2"

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from hvac_mpc.models.plant import Environment, SimulatedPlant  # noqa: E402
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings  # noqa: E402

from . import solve_time  # noqa: E402

VARIANTS = {"inline": {}, "background": {"reach_deferred": True, "reach_background": True}}


def run_loop(settings: MpcSettings, steps: int, seed: int) -> dict[str, Any]:
    """One closed loop of the solve-time scenario: per-step wall and thread CPU times (ms), commands,
    the steps that started a reachable-flow solve, and the closed-loop cost."""
    ctrl = MpcController(settings=settings)
    solver, started = ctrl.reach.solver, []
    k = 0

    def counted(**kw):
        started.append(k)
        return solver(**kw)

    ctrl.reach.solver = counted  # the index is read when the call starts: on a thread it may be k + 1
    plant = SimulatedPlant(seed=seed, environment=Environment(solve_time.INLET_C, 5.0))
    plant.settle(solve_time.INITIAL)
    ctrl.reset(plant.command)
    previous = plant.command.vector()
    wall, cpu, commands, cost = [], [], [], 0.0
    for k in range(steps):
        ref = solve_time.reference_at(k * plant.dt_s)
        measurement = plant.read()
        c0 = time.thread_time()
        res = ctrl.step(measurement, ref)
        cpu.append(time.thread_time() - c0)
        wall.append(res.stats["step_time_s"])
        command = plant.apply(res.command)
        plant.advance()
        cost += sum(solve_time.stage_cost(ctrl.problem, plant.truth(), ref, command, previous).values())
        previous = command
        commands.append(res.command.vector())
    ctrl.reach.reset()
    return {"wall_ms": np.array(wall[1:]) * 1e3, "cpu_ms": np.array(cpu[1:]) * 1e3, "commands": np.array(commands),
            "solves": started, "cost": cost}


def figures(times_ms: np.ndarray) -> dict[str, float]:
    return {"median_ms": float(np.median(times_ms)), "p99_ms": float(np.percentile(times_ms, 99)),
            "max_ms": float(times_ms.max())}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=Path, default=Path("reach_background.json"))
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.steps < 3:
        parser.error("--rounds must be at least 1 and --steps at least 3")
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:2])
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name in VARIANTS}
    loops: dict[str, dict[str, Any]] = {}
    for r in range(args.rounds):
        for name, extra in VARIANTS.items():
            loop = run_loop(MpcSettings(**extra), args.steps, args.seed)
            loops[name] = loop
            rows[name].append({"round": r, "wall": figures(loop["wall_ms"]), "thread_cpu": figures(loop["cpu_ms"]),
                               "reach_solves": len(loop["solves"]), "cost": loop["cost"]})
            w, c = rows[name][-1]["wall"], rows[name][-1]["thread_cpu"]
            print(f"round {r} {name:<10} wall median {w['median_ms']:.2f} p99 {w['p99_ms']:.2f} max {w['max_ms']:.2f} ms"
                  f" | thread CPU median {c['median_ms']:.2f} p99 {c['p99_ms']:.2f} max {c['max_ms']:.2f} ms"
                  f" | solves {len(loop['solves'])}, cost {loop['cost']:.2f}", flush=True)
    same = bool(np.array_equal(loops["background"]["commands"], run_loop(
        MpcSettings(reach_deferred=True), args.steps, args.seed)["commands"]))
    print(f"background commands equal to the deferred solve on the step's own thread: {same}")
    out = {"steps": args.steps, "seed": args.seed, "rounds": rows, "background_equals_deferred": same,
           "inline_solve_steps": loops["inline"]["solves"]}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.json}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
