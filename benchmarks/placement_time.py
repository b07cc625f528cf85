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

``switch``: what a switch of filter costs inside its step, the thread CPU time of binding the other filter to the
prediction (``MpcController``'s switch: its fused prediction, its parameters), alternately with that filter's fused
prediction built at construction (``prebuilt``, the default) and built again at the switch (``rebuilt``, as before
it was built ahead), over ``--rounds`` times 40 switches each way after a few steps of the loop.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    if not os.environ.get(_var, "").isdigit() or int(os.environ[_var]) > 2:
        os.environ[_var] = "2"

import argparse  # noqa: E402

import time  # noqa: E402

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


SWITCHES = 20  # switches per round and way (each: to the other filter and back)


def switch_cost(rounds: int, seed: int, warm_steps: int = 5) -> dict[str, dict]:
    """Thread CPU time (ms) of one switch of filter, median and largest, with the other filter's fused prediction
    kept from construction (``prebuilt``) or built again at each switch (``rebuilt``); both alike otherwise."""
    ctrl = MpcController(settings=MpcSettings(choose_offset_placement=True))
    loop = Loop(ctrl, seed, idle_s=IDLE_S)
    for k in range(warm_steps):
        loop.step(k)
    times: dict[str, list[float]] = {"prebuilt": [], "rebuilt": []}
    for _ in range(rounds):
        for way in times:
            for _ in range(2 * SWITCHES):
                other = next(f for f in ctrl._filters if f is not ctrl.ekf)
                if way == "rebuilt":
                    ctrl.solver._fused.pop(id(other), None)
                t0 = time.thread_time()
                ctrl._use_filter(other)
                times[way].append(time.thread_time() - t0)
    return {way: {"median_ms": 1e3 * float(np.median(t)), "max_ms": 1e3 * float(np.max(t)), "switches": len(t)}
            for way, t in times.items()}


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
    sw = switch_cost(args.rounds, args.seed)
    print(f"switch: thread CPU per switch, rebuilt {sw['rebuilt']['median_ms']:.3f} ms (largest "
          f"{sw['rebuilt']['max_ms']:.3f}) -> prebuilt {sw['prebuilt']['median_ms']:.3f} ms (largest "
          f"{sw['prebuilt']['max_ms']:.3f}), {sw['prebuilt']['switches']} switches each")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
