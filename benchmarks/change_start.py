"""Where a reference change's QPs start: the shifted plan against the plan toward the steady-state target.

    python -m hvac_mpc.benchmarks.change_start [--seeds 3] [--steps 240] [--variant NAME ...] [--json FILE]

The solve-time loop (:class:`.solve_time.Loop`, the idle time of a sample between steps) with controllers at their
defaults but for ``MpcSettings.steady_start``, ``steady_start_on`` and ``reference_change_qps`` (:data:`VARIANTS`):
"shifted" (a change's QPs linearised at and warm-started from the plan shifted from the last step, made for the old
reference), "steady" (at every change from the plan toward the new reference's steady-state target,
:mod:`hvac_mpc.mpc.steady_target`) and "temperature" (so only where the supply-temperature reference changes; in
this loop's scenario every change does, so its figures are the "steady" ones but for the timing noise); on request
(``--variant one_qp``) the temperature-only start with one QP at a change instead of two; "rho_reset" (the shifted
start with OSQP's step size set to 1e-3 at every preparation, ``MpcSettings.osqp_rho_reset``), "rho_reset_change" (so
for the QPs of a change only) and "rho_reset_capped" (at every preparation, and each QP capped at 60 OSQP iterations,
the iterate at the cap taken); "split_N" (``MpcSettings.change_split_iter``: a change's QPs capped at N OSQP
iterations each in the step, finished to convergence on the second thread and collected by the next step) and
"split_every_N" (so also any step whose QP reaches the cap, ``split_every_step``) and "split_keep_rho_N" (the rest
leaving OSQP's step size as the change step found it, ``split_keeps_rho``) and "split_replay_N" (the rest solving the
change again from OSQP's workspace as the change step found it, ``split_replays_change``) and "split_every_replay_N"
(every step's QPs capped so, each capped step's QPs solved again on the second thread from the saved workspace);
"rho_max_R" (``MpcSettings.osqp_rho_max``: OSQP's step size at most R at each preparation) and "plain_cap_N"
(``osqp_plain_qp_cap``: each QP of a step that is not a change at most N OSQP iterations, the iterate taken), and
"split_replay_30_rho_max_R" / "split_replay_30_plain_cap_N" (each with the change split at 30 and replayed) and
"split_replay_30_plain_cap_60_run_R" (and at most R plain steps in a row at the cap, ``osqp_plain_cap_run``); a
change's step size (``osqp_change_rho``: "change_rho_M"; ``osqp_change_rho_restore``: "change_rho_restore", with "last"
"change_rho_last_restore"; OSQP's
step size R at each change, ``osqp_rho_reset_on`` "change": "rho_reset_change_R", "..._restore" with the restore;
the change's adaptation every N iterations at a factor T: "change_adapt_N_T"; the change's later QPs held at the
first's step size at its end or start, ``osqp_change_rho_hold`` H: "change_hold_H", with "last" / "kind"
"change_hold_H_last" / "change_hold_H_kind", each with the restore "..._restore"). Per
seed the loops run in
lockstep in one process, one step of each in turn (the order rotates from step to step), so that the load of other
processes falls on all alike.

Printed per seed and variant: the closed-loop cost (as ``solve-time`` computes it), OSQP's iterations (in all, on
the change steps, on the five steps after each change), the change steps' iterations one by one, the CPU time
of the thread that runs the step (``time.thread_time``: median, 99th percentile, largest; the change steps'
median and largest), the steps of most iterations and the slowest steps, and for the split variants the longest
wait of a step for the second thread and the rests' largest iterations and thread CPU time (not in the step's
time). The cold first step is left out.
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
from hvac_mpc.mpc.settings_file import settings_with  # noqa: E402

from . import solve_time  # noqa: E402

#: The flaps' flat direction priced, "flat_W" (``Weights.flap_closure_per_pct2`` W per %^2 per s, towards fully open) and
#: "flat_W_tT" (towards ``OcpSpec.flap_target_pct`` T): name -> the ``ocp`` fields.
FLAT = {f"{w}{'' if t == 100 else f'_t{t}'}": {"flap_target_pct": float(t), "weights": {"flap_closure_per_pct2": float(w)}}
        for w in ("1e-5", "3e-5", "1e-4") for t in (100, 70)}
#: Variant -> its ``MpcSettings`` fields (sub-tables as nested mappings, :func:`.settings_file.settings_with`).
VARIANTS = {"shifted": {"steady_start": False},
            "steady": {"steady_start": True, "steady_start_on": "any"},
            "temperature": {"steady_start": True, "steady_start_on": "temperature"},
            "one_qp": {"steady_start": True, "steady_start_on": "temperature", "reference_change_qps": 1},
            "rho_reset": {"steady_start": False, "osqp_rho_reset": 1e-3},
            "rho_reset_change": {"steady_start": False, "osqp_rho_reset": 1e-3, "osqp_rho_reset_on": "change"},
            "rho_reset_capped": {"steady_start": False, "osqp_rho_reset": 1e-3, "osqp_max_iter": 60,
                                 "osqp_accept_max_iter": True},
            **{f"split_{n}": {"change_split_iter": n} for n in (20, 30, 40, 60)},
            **{f"split_every_{n}": {"change_split_iter": n, "split_every_step": True} for n in (20, 30, 40, 60)},
            **{f"split_keep_rho_{n}": {"change_split_iter": n, "split_keeps_rho": True} for n in (30, 60)},
            **{f"split_replay_{n}": {"change_split_iter": n, "split_replays_change": True} for n in (20, 30, 40)},
            **{f"split_every_replay_{n}": {"change_split_iter": n, "split_every_step": True, "split_replays_change": True}
               for n in (30, 40, 60)},
            **{f"rho_max_{r}": {"osqp_rho_max": float(r)} for r in ("2e-3", "5e-3", "1e-2")},
            **{f"plain_cap_{n}": {"osqp_plain_qp_cap": n} for n in (40, 60, 80, 100)},
            **{f"split_replay_30_rho_max_{r}": {"change_split_iter": 30, "split_replays_change": True,
                                                "osqp_rho_max": float(r)} for r in ("2e-3", "5e-3")},
            **{f"split_replay_30_plain_cap_{n}": {"change_split_iter": 30, "split_replays_change": True,
                                                  "osqp_plain_qp_cap": n} for n in (40, 60, 100)},
            **{f"split_replay_30_plain_cap_60_run_{r}": {"change_split_iter": 30, "split_replays_change": True,
                                                         "osqp_plain_qp_cap": 60, "osqp_plain_cap_run": r}
               for r in (1, 2)},
            **{f"flat_{n}": {"ocp": ocp} for n, ocp in FLAT.items()},
            **{f"flat_{n}_plain_cap_60": {"ocp": ocp, "osqp_plain_qp_cap": 60} for n, ocp in FLAT.items()},
            **{f"split_replay_30_plain_cap_60_flat_{n}": {"change_split_iter": 30, "split_replays_change": True,
                                                         "osqp_plain_qp_cap": 60, "ocp": ocp}
               for n, ocp in FLAT.items()},
            # a change's step size (docs/architecture.md, 'The change's step size')
            **{f"change_rho_{m}": {"osqp_change_rho": m} for m in ("last", "kind", "last_each", "kind_each")},
            "change_rho_restore": {"osqp_change_rho_restore": True},
            "change_rho_last_restore": {"osqp_change_rho": "last", "osqp_change_rho_restore": True},
            **{f"rho_reset_change_{r}": {"osqp_rho_reset": float(r), "osqp_rho_reset_on": "change"}
               for r in ("3e-4", "1e-3", "3e-3")},
            **{f"rho_reset_change_{r}_restore": {"osqp_rho_reset": float(r), "osqp_rho_reset_on": "change",
                                                 "osqp_change_rho_restore": True} for r in ("3e-4", "1e-3")},
            **{f"change_adapt_{n}_{t}": {"osqp_change_rho_interval": n, "osqp_change_rho_tolerance": float(t)}
               for n in (10, 25) for t in (2, 5)},
            # a change's second QP held at the first's step size (docs/architecture.md, 'The change's second QP held')
            **{f"change_hold_{h}{m}{r}": {"osqp_change_rho_hold": h, **mode, **restore} for h in ("end", "start")
               for m, mode in (("", {}), ("_last", {"osqp_change_rho": "last"}), ("_kind", {"osqp_change_rho": "kind"}))
               for r, restore in (("", {}), ("_restore", {"osqp_change_rho_restore": True}))}}
#: The variants run unless ``--variant`` names others.
DEFAULT_VARIANTS = ("shifted", "steady", "temperature")
#: Steps after a change counted as its wake (the single QPs that follow it).
WAKE = 5
#: Largest steps listed per run.
TOP = 6


def change_steps(steps: int, scenario=solve_time.SCENARIO, dt_s: float = 1.0) -> list[int]:
    """The steps (after the first) whose reference differs from the step before's."""
    refs = [solve_time.reference_at(k * dt_s, scenario) for k in range(steps)]
    return [k for k in range(1, steps) if refs[k] != refs[k - 1]]


def first_change_step(scenario=solve_time.SCENARIO, dt_s: float = 1.0, horizon_steps: int = solve_time.FULL_STEPS
                      ) -> int | None:
    """The first step whose reference differs from the step before's within ``horizon_steps`` (None: none)."""
    changes = change_steps(horizon_steps, scenario, dt_s)
    return changes[0] if changes else None


def summary(iterations: np.ndarray, thread_ms: np.ndarray, changes: list[int],
            qp_solves: np.ndarray | None = None) -> dict[str, Any]:
    """Figures of one loop from its per-step OSQP iterations, thread CPU times (ms) and QPs (default one a step),
    the cold step 0 left out. ``slowest_steps``: the :data:`TOP` steps of most CPU time as [step, ms, OSQP
    iterations, QPs, whether a change]. ValueError where ``changes`` is empty (a run too short to hold a reference
    change has no change figures)."""
    if not changes:
        raise ValueError(f"no reference change within the {iterations.size} steps run: the change figures need a run "
                         "that holds one (more steps)")
    steps = np.arange(1, iterations.size)
    it, cpu = iterations[1:], thread_ms[1:]
    qps = np.ones_like(iterations) if qp_solves is None else qp_solves
    wake = [k for c in changes for k in range(c + 1, c + 1 + WAKE) if k < iterations.size]
    top = np.argsort(-it, kind="stable")[:TOP]
    slow = np.argsort(-cpu, kind="stable")[:TOP] + 1
    return {"iterations": int(it.sum()), "change_iterations": [int(iterations[c]) for c in changes],
            "wake_iterations": int(iterations[wake].sum()),
            "step_iterations": {"median": float(np.median(it)), "p95": float(np.percentile(it, 95)),
                                "p99": float(np.percentile(it, 99)), "max": int(it.max())},
            "per_step_iterations": [int(v) for v in iterations],
            "cpu_median_ms": float(np.median(cpu)), "cpu_p99_ms": float(np.percentile(cpu, 99)),
            "cpu_max_ms": float(cpu.max()),
            "change_cpu_median_ms": float(np.median(thread_ms[changes])),
            "change_cpu_max_ms": float(thread_ms[changes].max()),
            "largest_steps": [[int(steps[k]), int(it[k])] for k in top],
            "slowest_steps": [[int(k), round(float(thread_ms[k]), 3), int(iterations[k]), int(qps[k]), k in changes]
                              for k in slow]}


def run_seed(seed: int, steps: int, names: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """The loops of one seed (the variants ``names``, default :data:`DEFAULT_VARIANTS`) in lockstep; their figures
    and closed-loop costs."""
    names = list(DEFAULT_VARIANTS) if names is None else names
    loops = {v: solve_time.Loop(MpcController(settings=settings_with(MpcSettings(), VARIANTS[v])), seed,
                                idle_s=solve_time.IDLE_S)
             for v in names}
    iterations = {v: [] for v in names}
    qps = {v: [] for v in names}
    for _, v, res in solve_time.lockstep(loops, steps):
        iterations[v].append(res.stats["iterations"])
        qps[v].append(res.stats["qp_solves"])
    changes = change_steps(steps)
    return {v: {"cost": float(sum(loop.cost.values())),
                **summary(np.array(iterations[v]), np.array(loop.thread_s) * 1e3, changes, np.array(qps[v])),
                "step_wait_max_ms": float(max(loop.step_wait_s[1:], default=0.0) * 1e3),
                **solve_time.change_rests(loop.change_rests)}
            for v, loop in loops.items()}


def line(seed: int, variant: str, r: dict[str, Any]) -> str:
    q = r["step_iterations"]
    return (f"seed {seed} {variant:<11} cost {r['cost']:8.1f} | OSQP iterations {r['iterations']:5d} (a step: median "
            f"{q['median']:.0f}, p95 {q['p95']:.0f}, p99 {q['p99']:.0f}, max {q['max']}), changes "
            f"{sum(r['change_iterations']):4d} {r['change_iterations']}, next {WAKE} steps {r['wake_iterations']:4d} | "
            f"thread CPU median {r['cpu_median_ms']:.3f} p99 {r['cpu_p99_ms']:.2f} max {r['cpu_max_ms']:.2f} ms, "
            f"changes median {r['change_cpu_median_ms']:.2f} max {r['change_cpu_max_ms']:.2f} ms | largest "
            f"{r['largest_steps'][:4]} | slowest (step, ms, iterations, QPs, change) {r['slowest_steps'][:4]}"
            + (f" | rests on the second thread {r['change_rests']}, up to {r['change_rest_iterations_max']} "
               f"iterations, {r['change_rest_thread_cpu_max_ms']:.2f} ms of its CPU; a step's wait at most "
               f"{r['step_wait_max_ms']:.3f} ms" if r.get("change_rests") else ""))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="plant noise seeds 1..N (default 3)")
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--variant", action="append", choices=list(VARIANTS),
                        help=f"run this variant (repeatable; default: {', '.join(DEFAULT_VARIANTS)})")
    parser.add_argument("--json", type=Path, default=Path("change_start.json"))
    args = parser.parse_args(argv)
    if not 1 <= args.seeds <= 20 or args.steps < 3:
        parser.error("--seeds must be in [1, 20], --steps at least 3")
    first = first_change_step()
    if first is not None and args.steps <= first:
        parser.error(f"--steps {args.steps} holds no reference change: the scenario's first change is at step "
                     f"{first}, so --steps must be at least {first + 1}")
    names = list(dict.fromkeys(args.variant)) if args.variant else list(DEFAULT_VARIANTS)
    solve_time.pin_cores(2)
    rows: dict[str, list[dict[str, Any]]] = {v: [] for v in names}
    for seed in range(1, args.seeds + 1):
        result = run_seed(seed, args.steps, names)
        for v, r in result.items():
            rows[v].append({"seed": seed, **r})
            print(line(seed, v, r), flush=True)
    for v in names:
        costs = [r["cost"] for r in rows[v]]
        print(f"{v:<11} cost sum {sum(costs):.1f} ({' / '.join(f'{c:.1f}' for c in costs)}), iterations "
              f"{sum(r['iterations'] for r in rows[v])}, on the changes "
              f"{sum(sum(r['change_iterations']) for r in rows[v])}, largest change "
              f"{max(max(r['change_iterations']) for r in rows[v])}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"steps": args.steps, "variants": {v: VARIANTS[v] for v in names}, "rows": rows},
                                    indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
