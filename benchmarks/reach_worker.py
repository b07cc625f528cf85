"""The steps that hand the reachable-flow solve to the second thread: one persistent worker against a thread per solve.

    python -m hvac_mpc.benchmarks.reach_worker [--rounds 3] [--steps 240] [--seed 1] [--idle-s 0.05]

Two default controllers on the solve-time loop (:class:`~hvac_mpc.benchmarks.solve_time.Loop`), stepped side by
side in one process (:func:`~hvac_mpc.benchmarks.solve_time.lockstep`, which goes first alternates): ``worker``
as they are (each solve handed to the controller's one thread, :class:`~hvac_mpc.mpc.background.BackgroundWorker`)
and ``thread_per_solve`` with the worker taken away (``reach.worker = None``: each solve starts a thread of its
own, as before the worker). Between steps the loop gives the second thread up to ``--idle-s`` (the rest of a
sample, as ``solve-time`` does). Per round the commands must be the same; reported over all rounds, per variant:
the step thread's CPU time (``time.thread_time``) and the step's wall time, ms, median over the steps that hand a
solve over (the reachable flow's hand-over steps: a changed flow reference in doubt and every ``reach_every_s``
after it; step 150 and 160, 170 on seed 1) and of the steps right after them (which collect the answer), and the
99th percentile and median of all steps but the cold first one; then per hand-over step and the step after it the
medians over the rounds.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings

from .solve_time import FULL_STEPS, Loop, lockstep

VARIANTS = ("worker", "thread_per_solve")


def _timed(ctrl: MpcController, handed: list[int], walls: list[float]) -> None:
    """Record each step's wall time (s) and whether it handed a solve to the second thread (1/0)."""
    step = ctrl.step

    def timed(measurement, reference):
        before = ctrl.reach._pending
        t0 = time.perf_counter()
        res = step(measurement, reference)
        walls.append(time.perf_counter() - t0)
        handed.append(int(ctrl.reach._pending is not None and ctrl.reach._pending is not before))
        return res

    ctrl.step = timed


def run_round(steps: int, seed: int, idle_s: float) -> dict[str, dict[str, np.ndarray]]:
    """One round, both variants side by side: per variant the thread CPU and wall times (s), the hand-over flags and
    the commands."""
    loops, record = {}, {}
    for name in VARIANTS:
        ctrl = MpcController(settings=MpcSettings())
        if name == "thread_per_solve":
            ctrl.reach.close()
            ctrl.reach.worker = None
        record[name] = {"handed": [], "wall": [], "commands": []}
        _timed(ctrl, record[name]["handed"], record[name]["wall"])
        loops[name] = Loop(ctrl, seed, idle_s=idle_s)
    for _, name, res in lockstep(loops, steps):
        record[name]["commands"].append(res.command.vector())
    for name, loop in loops.items():
        loop.ctrl.reach.close()
        record[name]["thread"] = loop.thread_s
    return {name: {k: np.asarray(v) for k, v in r.items()} for name, r in record.items()}


def summary(rounds: list[dict[str, dict[str, np.ndarray]]]) -> dict[str, dict[str, float]]:
    """Per variant, ms: medians over the hand-over steps and the steps after them, and over all steps but the first."""
    out = {}
    for name in VARIANTS:
        rows: dict[str, list[float]] = {}
        for r in rounds:
            v = r[name]
            at = np.flatnonzero(v["handed"][1:]) + 1  # the cold first step left out
            after = at[at + 1 < len(v["handed"])] + 1
            for kind in ("thread", "wall"):
                rows.setdefault(f"{kind}_handover", []).extend(v[kind][at])
                rows.setdefault(f"{kind}_after", []).extend(v[kind][after])
                rows.setdefault(f"{kind}_all", []).extend(v[kind][1:])
        out[name] = {"handover_steps": float(len(rows["thread_handover"]))}
        for key, values in rows.items():
            out[name][f"{key}_median_ms"] = 1e3 * float(np.median(values))
            if key.endswith("_all"):
                out[name][f"{key}_p99_ms"] = 1e3 * float(np.percentile(values, 99))
    return out


def per_step(rounds: list[dict[str, dict[str, np.ndarray]]]) -> dict[int, dict[str, tuple[float, float]]]:
    """Per hand-over step of the first round and the step after it: per variant the median over the rounds of the
    thread CPU and wall times (ms)."""
    steps = np.flatnonzero(rounds[0]["worker"]["handed"][1:]) + 1
    steps = sorted({int(k) for k in steps} | {int(k) + 1 for k in steps if k + 1 < len(rounds[0]["worker"]["handed"])})
    return {k: {name: tuple(1e3 * float(np.median([r[name][kind][k] for r in rounds])) for kind in ("thread", "wall"))
                for name in VARIANTS} for k in steps}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=FULL_STEPS)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--idle-s", type=float, default=0.05, help="time given to the second thread between steps (s)")
    args = ap.parse_args(argv)
    rounds = []
    for i in range(args.rounds):
        r = run_round(args.steps, args.seed, args.idle_s)
        diff = float(np.abs(r["worker"]["commands"] - r["thread_per_solve"]["commands"]).max())
        steps = np.flatnonzero(r["worker"]["handed"]).tolist()
        print(f"round {i + 1}: hand-over steps {steps}, largest command difference {diff:g}", flush=True)
        rounds.append(r)
    for name, row in summary(rounds).items():
        print(name + ": " + ", ".join(f"{k} {v:.3f}" for k, v in row.items()))
    for k, row in per_step(rounds).items():
        print(f"step {k} (thread CPU / wall, ms, median of the rounds): "
              + ", ".join(f"{name} {t:.2f} / {w:.2f}" for name, (t, w) in row.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
