"""OSQP settings of the RTI side by side: the closed loop of ``hvac-mpc solve-time`` with two settings.

    python -m hvac_mpc.benchmarks.qp_settings [--steps 240] [--rounds 3] [--seed 1] [--json FILE]

Both controllers run the solve-time scenario (:mod:`.solve_time`: the same plant, seed and references)
in lockstep, one step of each in turn (which goes first alternates), so that the load of other
processes on a shared machine falls on both alike. Step times are this process's CPU time
(``time.process_time``) per ``MpcController.step``, the cold first step excluded. Reported per round:
median, 99th percentile, the ratio of the medians (after / before), OSQP iterations and the
closed-loop cost of each (deterministic: the same in every round). ``before`` is OSQP's own setup,
the defaults of :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings` (``BEFORE``: ten equilibration
passes on every matrix update, the duality gap checked, no first pass); ``after`` the lighter
settings of ``AFTER`` (four passes, no gap check), which are settings, not defaults (README,
"Solve time").
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings

from . import solve_time

#: The OSQP settings before (OSQP's own scaling default, its duality-gap check, no first pass: the defaults).
BEFORE = {"osqp_scaling": 10, "osqp_check_dualgap": True, "osqp_first_pass_iter": 0}
#: The lighter settings measured against them (four equilibration passes, no gap check, no first pass).
AFTER = {"osqp_scaling": 4, "osqp_check_dualgap": False, "osqp_first_pass_iter": 0}


def _summary(loop: solve_time.Loop, iterations: list[int]) -> dict[str, float]:
    """CPU time per step (ms, the cold first step excluded), OSQP iterations and the closed-loop cost."""
    c = np.array(loop.cpu_s[1:]) * 1e3
    return {"cpu_median_ms": float(np.median(c)), "cpu_p99_ms": float(np.percentile(c, 99)),
            "median_iterations": float(np.median(iterations[1:])),
            "total_iterations": int(sum(iterations)), "cost": float(sum(loop.cost.values()))}


def side_by_side(before: MpcSettings, after: MpcSettings, steps: int, seed: int) -> dict[str, Any]:
    """One round: both loops in lockstep; returns each one's summary and the ratio of the medians."""
    loops = {"before": solve_time.Loop(MpcController(settings=before), seed),
             "after": solve_time.Loop(MpcController(settings=after), seed)}
    iterations: dict[str, list[int]] = {name: [] for name in loops}
    for _, name, res in solve_time.lockstep(loops, steps):
        iterations[name].append(int(res.stats["iterations"]))
    out = {name: _summary(loop, iterations[name]) for name, loop in loops.items()}
    out["median_ratio"] = out["after"]["cpu_median_ms"] / out["before"]["cpu_median_ms"]
    out["p99_ratio"] = out["after"]["cpu_p99_ms"] / out["before"]["cpu_p99_ms"]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    solve_time.side_by_side_arguments(p)
    args = p.parse_args(argv)
    if solve_time.side_by_side_refused(args, "qp_settings"):
        return 2
    before, after = MpcSettings(**BEFORE), MpcSettings(**AFTER)
    rounds = [side_by_side(before, after, args.steps, args.seed) for _ in range(args.rounds)]
    for i, r in enumerate(rounds, 1):
        b, a = r["before"], r["after"]
        print(f"round {i}: median {b['cpu_median_ms']:.3f} -> {a['cpu_median_ms']:.3f} ms "
              f"({r['median_ratio']:.2f}x), p99 {b['cpu_p99_ms']:.2f} -> {a['cpu_p99_ms']:.2f} ms, "
              f"iterations median {b['median_iterations']:.0f} -> {a['median_iterations']:.0f}, "
              f"total {b['total_iterations']} -> {a['total_iterations']}, cost {b['cost']:.1f} -> {a['cost']:.1f}")
    if args.json is not None:
        args.json.write_text(json.dumps({"before": BEFORE, "after": AFTER, "steps": args.steps, "seed": args.seed,
                                         "rounds": rounds}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
