"""What the online choice of the heater outlet error's placement adds to a control step, side by side.

    python -m hvac_mpc.benchmarks.placement_time [--rounds 3] [--steps 240] [--seed 1]

The solve-time loop (:class:`~hvac_mpc.benchmarks.solve_time.Loop`: the built-in plant, the reference scenario)
with the controller at its defaults but ``MpcSettings.choose_offset_placement`` off and on, alternately for
``--rounds`` rounds so that a change of the machine's load meets both alike. Two ways of giving the filter not in
use its time (docs/robustness.md sec. 2.14): ``idle`` (the loop gives the controller the rest of a sample between
steps, :meth:`~hvac_mpc.mpc.mpc_controller.MpcController.wait_background`, as ``solve-time`` does) and
``back_to_back`` (none: that filter's updates run at the start of the next step, as in a loop that never calls
``wait_background``). Per variant the CPU time of the thread that runs the step (``time.thread_time``, ms):
median and 99th percentile over all rounds, the cold first step left out, and the closed-loop cost (the commands
are the same with the choice on where it never switches, as on this plant).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    if not os.environ.get(_var, "").isdigit() or int(os.environ[_var]) > 2:
        os.environ[_var] = "2"

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings  # noqa: E402

from .solve_time import FULL_STEPS, IDLE_S, Loop  # noqa: E402


def run_once(choose: bool, idle_s: float, steps: int, seed: int) -> tuple[list[float], float, set[str]]:
    """One closed loop: the step thread's CPU times (s; cold step left out), its cost and the placements used."""
    ctrl = MpcController(settings=MpcSettings(choose_offset_placement=choose))
    loop = Loop(ctrl, seed, idle_s=idle_s)
    placements = {loop.step(k).stats["offset_placement"] for k in range(steps)}
    return loop.thread_s[1:], float(sum(loop.cost.values())), placements


def measure(rounds: int, steps: int, seed: int) -> dict[str, dict]:
    """Per way (idle, back to back) and setting (off, on): median and 99th percentile of the thread CPU time (ms),
    the cost and the placements used."""
    out: dict[str, dict] = {}
    for way, idle_s in (("idle", IDLE_S), ("back_to_back", 0.0)):
        times: dict[bool, list[float]] = {False: [], True: []}
        rest = {}
        for _ in range(rounds):
            for choose in (False, True):
                t, cost, placements = run_once(choose, idle_s, steps, seed)
                times[choose] += t
                rest[choose] = (cost, placements)
        out[way] = {("on" if c else "off"): {"median_ms": 1e3 * float(np.median(times[c])),
                                              "p99_ms": 1e3 * float(np.percentile(times[c], 99)),
                                              "cost": rest[c][0], "placements": sorted(rest[c][1])}
                    for c in (False, True)}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hvac_mpc.benchmarks.placement_time", description=__doc__.split(
        "\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=FULL_STEPS)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.steps < 2:
        parser.error("--rounds must be at least 1 and --steps at least 2")
    for way, by in measure(args.rounds, args.steps, args.seed).items():
        off, on = by["off"], by["on"]
        print(f"{way}: thread CPU per step median {off['median_ms']:.3f} -> {on['median_ms']:.3f} ms "
              f"(+{on['median_ms'] - off['median_ms']:.3f}), 99th percentile {off['p99_ms']:.3f} -> "
              f"{on['p99_ms']:.3f} ms; cost {off['cost']:.2f} / {on['cost']:.2f}; placements used {on['placements']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
