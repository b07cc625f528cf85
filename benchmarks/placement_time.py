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

``switch_step``: the whole step that switches, in closed loop on a box whose core is not the model's (the quick
winter heating steps on the independent box with a 4.5 s dead time, the literal cooler fit and a thermocouple 30 %
faster, seed 0, where the rule switches once), with ``MpcSettings.placement_warm_switch`` off (the switch step's QP
starts cold) and on (prepared again at the new filter's prediction), alternately for ``--rounds`` rounds: the
switch step's thread CPU time against the median of the other steps, and the run's thermocouple IAE.
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


#: The box of ``switch_step`` (hvac_mpc.mismatch.Variant fields; docs/robustness.md sec. 2.11, "R4").
SWITCH_BOX = dict(transport_delay_s=4.5, thermocouple_tau_scale=0.7, cooler_literal_fit=True)


def switch_step(rounds: int, seed: int = 0) -> dict[str, dict]:
    """Per setting of ``placement_warm_switch`` (off, on): the switch steps' thread CPU time (ms, each), the median of
    the other steps (ms) and the thermocouple IAE of the scored part (degC s)."""
    import functools

    from hvac_mpc.mismatch import Variant, make_plant

    from . import plant_seam, scenarios
    from .bench import DETERMINISTIC_DEADLINE_S
    from .simulate import plant_seed, simulate

    sc = scenarios.mismatch_scenarios()["winter_heating_steps"].quick()
    factory = functools.partial(make_plant, Variant(**SWITCH_BOX))
    out: dict[str, dict] = {"off": {"switch_ms": [], "other_ms": []}, "on": {"switch_ms": [], "other_ms": []}}
    for _ in range(rounds):
        for way, warm in (("off", False), ("on", True)):
            ctrl = MpcController(settings=MpcSettings(initial_command=sc.initial_command, placement_warm_switch=warm,
                                                      deadline_s=DETERMINISTIC_DEADLINE_S))
            times, used, step = [], [], ctrl.step

            def timed(measurement, reference, step=step, times=times, used=used):
                t0 = time.thread_time()
                res = step(measurement, reference)
                times.append(time.thread_time() - t0)
                used.append(res.stats["offset_placement"])
                return res

            ctrl.step = timed
            plant = plant_seam.build_plant(factory, plant_seed(seed, sc.seed), 1.0)
            tr = simulate(sc, ctrl, ctrl.params, seed, name="mpc", dt_s=1.0, plant=plant)
            switches = [k for k in range(1, len(used)) if used[k] != used[k - 1]]
            t = 1e3 * np.array(times)
            out[way]["switch_ms"] += [float(t[k]) for k in switches]
            out[way]["other_ms"].append(float(np.median(np.delete(t[1:], [k - 1 for k in switches]))))
            scored = tr.time_s >= tr.metrics_start_s
            out[way]["iae_cs"] = float(np.sum(np.abs(tr.truth["supply_temp_c"] - tr.reference["supply_temp_c"])[scored]))
            out[way]["switch_steps"] = switches
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
    sw = switch_cost(args.rounds, args.seed)
    print(f"switch: thread CPU per switch, rebuilt {sw['rebuilt']['median_ms']:.3f} ms (largest "
          f"{sw['rebuilt']['max_ms']:.3f}) -> prebuilt {sw['prebuilt']['median_ms']:.3f} ms (largest "
          f"{sw['prebuilt']['max_ms']:.3f}), {sw['prebuilt']['switches']} switches each")
    st = switch_step(args.rounds)
    for way in ("off", "on"):
        r = st[way]
        print(f"switch step, placement_warm_switch {way}: switch at {r['switch_steps']} s, thread CPU "
              f"{np.median(r['switch_ms']):.2f} ms (median of {len(r['switch_ms'])}), the other steps' median "
              f"{np.median(r['other_ms']):.2f} ms; IAE {r['iae_cs']:.1f} degC s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
