"""Where a reference change's QPs start: the shifted plan against the plan toward the steady-state target.

    python -m hvac_mpc.benchmarks.change_start [--seeds 3] [--steps 240] [--json FILE]

The solve-time loop (:class:`.solve_time.Loop`, the idle time of a sample between steps) with two controllers at
their defaults but for ``MpcSettings.steady_start``: off (a change's QPs linearised at and warm-started from the
plan shifted from the last step, made for the old reference) and on (at the plan toward the new reference's
steady-state target, :mod:`hvac_mpc.mpc.steady_target`). Per seed the two loops run in lockstep in one process,
one step of each in turn (which goes first alternates), so that the load of other processes falls on both alike.

Printed per seed and variant: the closed-loop cost (as ``solve-time`` computes it), OSQP's iterations (in all, on
the change steps, on the five steps after each change), the change steps' iterations one by one, the CPU time
of the thread that runs the step (``time.thread_time``: median, 99th percentile, largest; the change steps'
median and largest) and the largest steps. The cold first step is left out.
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

#: Variant -> ``MpcSettings.steady_start``.
VARIANTS = {"shifted": False, "steady": True}
#: Steps after a change counted as its wake (the single QPs that follow it).
WAKE = 5
#: Largest steps listed per run.
TOP = 6


def change_steps(steps: int, scenario=solve_time.SCENARIO, dt_s: float = 1.0) -> list[int]:
    """The steps (after the first) whose reference differs from the step before's."""
    refs = [solve_time.reference_at(k * dt_s, scenario) for k in range(steps)]
    return [k for k in range(1, steps) if refs[k] != refs[k - 1]]


def summary(iterations: np.ndarray, thread_ms: np.ndarray, changes: list[int]) -> dict[str, Any]:
    """Figures of one loop from its per-step OSQP iterations and thread CPU times (ms), the cold step 0 left out."""
    steps = np.arange(1, iterations.size)
    it, cpu = iterations[1:], thread_ms[1:]
    wake = [k for c in changes for k in range(c + 1, c + 1 + WAKE) if k < iterations.size]
    top = np.argsort(-it, kind="stable")[:TOP]
    return {"iterations": int(it.sum()), "change_iterations": [int(iterations[c]) for c in changes],
            "wake_iterations": int(iterations[wake].sum()),
            "cpu_median_ms": float(np.median(cpu)), "cpu_p99_ms": float(np.percentile(cpu, 99)),
            "cpu_max_ms": float(cpu.max()),
            "change_cpu_median_ms": float(np.median(thread_ms[changes])),
            "change_cpu_max_ms": float(thread_ms[changes].max()),
            "largest_steps": [[int(steps[k]), int(it[k])] for k in top]}


def run_seed(seed: int, steps: int) -> dict[str, dict[str, Any]]:
    """Both variants' loops of one seed in lockstep; their figures and closed-loop costs."""
    loops = {v: solve_time.Loop(MpcController(settings=MpcSettings(steady_start=on)), seed, idle_s=solve_time.IDLE_S)
             for v, on in VARIANTS.items()}
    iterations = {v: [] for v in VARIANTS}
    names = list(VARIANTS)
    for k in range(steps):
        for v in (names if k % 2 == 0 else names[::-1]):
            iterations[v].append(loops[v].step(k).stats["iterations"])
    changes = change_steps(steps)
    return {v: {"cost": float(sum(loop.cost.values())),
                **summary(np.array(iterations[v]), np.array(loop.thread_s) * 1e3, changes)}
            for v, loop in loops.items()}


def line(seed: int, variant: str, r: dict[str, Any]) -> str:
    return (f"seed {seed} {variant:<8} cost {r['cost']:8.1f} | OSQP iterations {r['iterations']:5d}, changes "
            f"{sum(r['change_iterations']):4d} {r['change_iterations']}, next {WAKE} steps {r['wake_iterations']:4d} | "
            f"thread CPU median {r['cpu_median_ms']:.3f} p99 {r['cpu_p99_ms']:.2f} max {r['cpu_max_ms']:.2f} ms, "
            f"changes median {r['change_cpu_median_ms']:.2f} max {r['change_cpu_max_ms']:.2f} ms | largest "
            f"{r['largest_steps'][:4]}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="plant noise seeds 1..N (default 3)")
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--json", type=Path, default=Path("change_start.json"))
    args = parser.parse_args(argv)
    if not 1 <= args.seeds <= 20 or args.steps < 3:
        parser.error("--seeds must be in [1, 20], --steps at least 3")
    solve_time.pin_cores(2)
    rows: dict[str, list[dict[str, Any]]] = {v: [] for v in VARIANTS}
    for seed in range(1, args.seeds + 1):
        result = run_seed(seed, args.steps)
        for v, r in result.items():
            rows[v].append({"seed": seed, **r})
            print(line(seed, v, r), flush=True)
    for v in VARIANTS:
        costs = [r["cost"] for r in rows[v]]
        print(f"{v:<8} cost sum {sum(costs):.1f} ({' / '.join(f'{c:.1f}' for c in costs)}), iterations "
              f"{sum(r['iterations'] for r in rows[v])}, on the changes "
              f"{sum(sum(r['change_iterations']) for r in rows[v])}, largest change "
              f"{max(max(r['change_iterations']) for r in rows[v])}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"steps": args.steps, "variants": VARIANTS, "rows": rows}, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
