"""Multi-level steps against the plain real-time iteration, side by side on the solve-time loop.

    python -m hvac_mpc.benchmarks.multilevel [--seeds 1,2,3] [--steps 240] [--every 20] [--move 0.3]
                                             [--suboptimality] [--json FILE]

Two controllers at their defaults but for ``MpcSettings.rti_relinearise_every`` / ``rti_relinearise_move``:
``full`` (every preparation a full linearisation, the default) and ``multilevel`` (a full one at least every
``--every`` preparations, the ones between keeping the QP's matrices where the plan has moved by at most
``--move``; :mod:`hvac_mpc.mpc.multilevel`). Per seed the two loops (:class:`.solve_time.Loop`, the idle time of a
sample between steps) run in lockstep in one process, one step of each in turn (which goes first alternates),
so that the load of other processes falls on both alike.

Printed per seed: the CPU time of the thread that runs the step (``time.thread_time``: median and 99th
percentile, the cold first step left out) of both and their ratio (multilevel / full), the closed-loop cost of
each, OSQP's iterations, the full and the vector preparations and the largest difference between the two
controllers' commands (W and %). ``--suboptimality``: then, per variant, the per-step suboptimality against the
converged solution (:func:`.solve_time.rti_suboptimality`, the loop of seed ``--seeds``' first again, untimed;
the move applied and the whole plan, median and 95th percentile, %).
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


def variants(every: int, move: float) -> dict[str, MpcSettings]:
    """The two controllers' settings: the defaults, and the defaults with multi-level steps."""
    return {"full": MpcSettings(), "multilevel": MpcSettings(rti_relinearise_every=every, rti_relinearise_move=move)}


def run_seed(seed: int, steps: int, settings: dict[str, MpcSettings]) -> dict[str, Any]:
    """Both loops of one seed in lockstep: per variant the step times, cost, iterations and preparations, and the
    largest difference between the commands."""
    loops = {v: solve_time.Loop(MpcController(settings=s), seed, idle_s=solve_time.IDLE_S) for v, s in settings.items()}
    iterations = {v: 0 for v in loops}
    commands = {v: [] for v in loops}
    names = list(loops)
    for _, v, res in solve_time.lockstep(loops, steps):
        iterations[v] += int(res.stats["iterations"])
        commands[v].append(res.command.vector())
    out: dict[str, Any] = {}
    for v, loop in loops.items():
        cpu = np.array(loop.thread_s[1:]) * 1e3
        out[v] = {"cost": float(sum(loop.cost.values())), "iterations": iterations[v],
                  "cpu_median_ms": float(np.median(cpu)), "cpu_p99_ms": float(np.percentile(cpu, 99)),
                  "levels": loop.ctrl.solver.levels}
    a, b = (np.array(commands[v]) for v in names)
    out["command_difference"] = float(np.abs(a - b).max())
    return out


def line(seed: int, r: dict[str, Any]) -> str:
    f, m = r["full"], r["multilevel"]
    return (f"seed {seed}: thread CPU median {f['cpu_median_ms']:.3f} -> {m['cpu_median_ms']:.3f} ms "
            f"({m['cpu_median_ms'] / f['cpu_median_ms']:.2f}x), p99 {f['cpu_p99_ms']:.2f} -> {m['cpu_p99_ms']:.2f} ms "
            f"({m['cpu_p99_ms'] / f['cpu_p99_ms']:.2f}x) | cost {f['cost']:.1f} -> {m['cost']:.1f} | OSQP iterations "
            f"{f['iterations']} -> {m['iterations']} | preparations {m['levels']} | largest command difference "
            f"{r['command_difference']:.3g}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2,3", help="plant noise seeds, comma separated (default 1,2,3)")
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--every", type=int, default=20, help="MpcSettings.rti_relinearise_every (default 20)")
    parser.add_argument("--move", type=float, default=0.3, help="MpcSettings.rti_relinearise_move (default 0.3)")
    parser.add_argument("--suboptimality", action="store_true",
                        help="also the per-step suboptimality of each variant against converged IPOPT")
    parser.add_argument("--json", type=Path, default=Path("multilevel.json"))
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if not seeds or args.steps < 3:
        parser.error("--seeds must name at least one seed, --steps at least 3")
    settings = variants(args.every, args.move)  # raises InvalidSettings naming the field on a bad value
    solve_time.pin_cores(2)
    rows = []
    for seed in seeds:
        r = run_seed(seed, args.steps, settings)
        rows.append({"seed": seed, **r})
        print(line(seed, r), flush=True)
    med = [r["multilevel"]["cpu_median_ms"] / r["full"]["cpu_median_ms"] for r in rows]
    costs = {v: sum(r[v]["cost"] for r in rows) for v in ("full", "multilevel")}
    print(f"median ratio {' / '.join(f'{x:.2f}' for x in med)}; cost sum {costs['full']:.1f} -> "
          f"{costs['multilevel']:.1f}")
    sub = {}
    if args.suboptimality:
        for v, s in settings.items():
            r = solve_time.rti_suboptimality(lambda s=s: MpcController(settings=s), args.steps, seeds[0], False)
            sub[v] = {k: r[k] for k in ("plan", "decision", "steps", "ipopt_failures") if k in r}
            print(f"{v:<10} suboptimality, seed {seeds[0]}: " + ", ".join(
                f"{k} median {sub[v][k]['median_pct']:.3f} % p95 {sub[v][k]['p95_pct']:.2f} %"
                for k in ("decision", "plan") if k in sub[v]), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"steps": args.steps, "every": args.every, "move": args.move, "rows": rows,
                                     "suboptimality": sub}, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
