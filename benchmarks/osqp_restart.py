"""OSQP's restarts at a reference change and its step-size adaptation, on the solve-time loop.

    python -m hvac_mpc.benchmarks.osqp_restart [--seeds 3] [--steps 240] [--json FILE]

The slow steps of the loop (docs/architecture.md 'Slow steps') are the QPs of a reference change and
the single QPs after them: 150-435 OSQP iterations where a step's median is 15. Variants of how OSQP
meets them, each the controller at its defaults (:class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`)
but for the one thing it names:

* ``defaults``;
* ``dual_restart``: the first QP of a reference change starts from zero multipliers, not from the last
  QP's (``RtiOsqpSolver(restart_duals_on_change=True)``);
* ``rho_interval_25``, ``rho_interval_10``: OSQP adapts its step size every 25 or 10 iterations
  instead of 50 (``adaptive_rho_interval``, :meth:`~hvac_mpc.mpc.rti_osqp.RtiOsqpSolver.set_osqp_options`);
* ``rho_tolerance_2``: it adapts on a change of the step size by a factor of 2 instead of 5
  (``adaptive_rho_tolerance``).

Per seed (the plant's noise), the variants one after the other: the closed-loop cost (as ``solve-time``
computes it), OSQP's iterations (in all, median per step, the largest steps with their index), and the
CPU time of the thread that runs the step (``time.thread_time``: median, 99th percentile, largest; the
reachable-flow solve on the second thread given the idle time of a sample between steps, as in
``solve-time``). The cold first step is left out.
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

#: Variant -> (restart the duals at a change, further OSQP settings).
VARIANTS: dict[str, tuple[bool, dict[str, Any]]] = {
    "defaults": (False, {}),
    "dual_restart": (True, {}),
    "rho_interval_25": (False, {"adaptive_rho_interval": 25}),
    "rho_interval_10": (False, {"adaptive_rho_interval": 10}),
    "rho_tolerance_2": (False, {"adaptive_rho_tolerance": 2.0}),
}
#: Largest steps listed per run.
TOP = 8


def run_loop(variant: str, steps: int, seed: int) -> dict[str, Any]:
    """One closed loop of the solve-time scenario with ``variant``: cost, iterations, thread CPU times."""
    restart, options = VARIANTS[variant]
    ctrl = MpcController(settings=MpcSettings())
    ctrl.solver.restart_duals_on_change = restart
    if options:
        ctrl.solver.set_osqp_options(**options)
    loop = solve_time.Loop(ctrl, seed, idle_s=solve_time.IDLE_S)
    iterations = np.array([loop.step(k).stats["iterations"] for k in range(steps)])[1:]
    cpu = np.array(loop.thread_s[1:]) * 1e3
    top = np.argsort(-iterations, kind="stable")[:TOP]
    return {"cost": float(sum(loop.cost.values())), "iterations": int(iterations.sum()),
            "iterations_median": float(np.median(iterations)),
            "largest_steps": [[int(k) + 1, int(iterations[k])] for k in top],
            "cpu_median_ms": float(np.median(cpu)), "cpu_p99_ms": float(np.percentile(cpu, 99)),
            "cpu_max_ms": float(cpu.max())}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="plant noise seeds 1..N (default 3)")
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated, of: " + ", ".join(VARIANTS))
    parser.add_argument("--json", type=Path, default=Path("osqp_restart.json"))
    args = parser.parse_args(argv)
    names = [v for v in args.variants.split(",") if v]
    if not 1 <= args.seeds <= 20 or args.steps < 3 or not names or any(v not in VARIANTS for v in names):
        parser.error(f"--seeds must be in [1, 20], --steps at least 3, --variants of {', '.join(VARIANTS)}")
    solve_time.pin_cores(2)
    rows: dict[str, list[dict[str, Any]]] = {v: [] for v in names}
    for seed in range(1, args.seeds + 1):
        for v in names:
            r = run_loop(v, args.steps, seed)
            rows[v].append({"seed": seed, **r})
            print(f"seed {seed} {v:<16} cost {r['cost']:8.1f} | OSQP iterations {r['iterations']:5d}, median "
                  f"{r['iterations_median']:.0f}, largest (step, iterations) {r['largest_steps'][:5]} | thread CPU "
                  f"median {r['cpu_median_ms']:.3f} p99 {r['cpu_p99_ms']:.2f} max {r['cpu_max_ms']:.2f} ms", flush=True)
    for v in names:
        costs = [r["cost"] for r in rows[v]]
        print(f"{v:<16} cost sum {sum(costs):.1f} ({' / '.join(f'{c:.1f}' for c in costs)}), iterations "
              f"{sum(r['iterations'] for r in rows[v])}, largest step "
              f"{max(r['largest_steps'][0][1] for r in rows[v])} iterations")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"steps": args.steps, "variants": {v: VARIANTS[v] for v in names},
                                     "rows": rows}, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
