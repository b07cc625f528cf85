"""One scenario of the built-in bench over several seeds, variants against the first: the IAE and where the paths part.

    python -m hvac_mpc.benchmarks.path_trace [--scenario winter_heating_steps] [--seeds 5] [--first-seed 0] [--quick]
        [--variant NAME=JSON ...] [--window 420-480 ...] [--json FILE]

Each variant (``NAME=JSON``: MpcSettings fields, e.g. ``flat={"ocp": {"weights": {"flap_closure_per_pct2": 1e-4}}}``;
default "defaults={}" only) runs the full scenario (``--quick``: its short version) on the bench's plant of each of
``--seeds`` seeds from ``--first-seed`` on (plant and deadline as ``hvac-mpc bench``). Printed per seed and variant:
the supply-temperature IAE (the bench's: noise-free thermocouple against the reference from the scored start, C s)
and its difference to the first variant; the estimator's discrete choices as they change (the dead-time estimate,
``stats["dead_time_s"]``, and the offset's placement, ``stats["offset_placement"]``); the steps of
:data:`SLOW_ITERATIONS` OSQP iterations or more (iterations / QPs) and the steps whose QP status is not "solved"; the
mean command (blower W, heater W, valve a %, flaps m, f, w %) and heater body temperature (C) over each ``--window``
(s, "A-B"). Then per variant the IAE summed over the seeds.
The MPC alone runs: ratios to the baseline come from ``hvac-mpc bench``. Measured in docs/architecture.md, 'The flat
direction priced, winter traced'.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from . import scenarios as scenario_defs, split_trace

#: A step with at least this many OSQP iterations is listed (a plain step takes 15-50).
SLOW_ITERATIONS = 300
#: The per-step statistics recorded.
STATS = ("iterations", "qp_solves", "status", "dead_time_s", "offset_placement")


class Recorder(split_trace.Recorder):
    """A controller that records :data:`STATS` of each step (passes every other call through)."""

    def record(self, result) -> dict[str, Any]:
        stats = result.stats or {}
        return {k: stats.get(k) for k in STATS}


def run_variant(scenario: scenario_defs.Scenario, seed: int, settings: Mapping[str, Any]) -> dict[str, Any]:
    """The MPC with ``settings`` through ``scenario`` on the bench's plant of ``seed``: IAE, commands, records."""
    return split_trace.run_variant(scenario, seed, settings, Recorder)


def changes(steps: list[dict[str, Any]], key: str) -> list[tuple[int, Any]]:
    """(step, value) where ``key`` takes a new value (the first step's included)."""
    return [(k, s[key]) for k, s in enumerate(steps) if k == 0 or s[key] != steps[k - 1][key]]


def describe(run: dict[str, Any], windows: list[tuple[int, int]]) -> list[str]:
    """The lines of one run: discrete choices, slow and inexact steps, mean commands over the windows."""
    steps = run["steps"]
    slow = [(k, s["iterations"], s["qp_solves"]) for k, s in enumerate(steps)
            if (s["iterations"] or 0) >= SLOW_ITERATIONS]
    inexact = [(k, s["status"]) for k, s in enumerate(steps) if s["status"] not in (None, "solved")]
    lines = [f"    dead time (s) {changes(steps, 'dead_time_s')}; placement {changes(steps, 'offset_placement')}",
             f"    steps of {SLOW_ITERATIONS}+ iterations (step, iterations, QPs) {slow}; not 'solved' {inexact}"]
    for a, b in windows:
        if b > len(run["commands"]):
            lines.append(f"    {a}-{b} s: beyond the run's {len(run['commands'])} samples")
            continue
        u = np.round(run["commands"][a:b].mean(axis=0), 1).tolist()
        lines.append(f"    {a}-{b} s: mean command {u}, heater body {run['body_c'][a:b].mean():.1f} C")
    return lines


def report(runs: dict[int, dict[str, dict[str, Any]]], windows: list[tuple[int, int]]) -> list[str]:
    """Per seed each variant's IAE against the first's and its lines; then the sums over the seeds."""
    lines = []
    names = list(next(iter(runs.values())))
    for seed, by_name in runs.items():
        first = by_name[names[0]]["iae"]
        for name, run in by_name.items():
            lines.append(f"seed {seed} {name}: IAE {run['iae']:.2f} C s ({run['iae'] - first:+.2f})")
            lines += describe(run, windows)
    for name in names:
        iae = [runs[s][name]["iae"] for s in runs]
        base = sum(runs[s][names[0]]["iae"] for s in runs)
        lines.append(f"{name}: IAE per seed {[round(v, 2) for v in iae]}, sum {sum(iae):.2f} C s "
                     f"({100.0 * (sum(iae) / base - 1.0):+.1f} %)")
    return lines


def parse_window(text: str) -> tuple[int, int]:
    a, sep, b = text.partition("-")
    if not sep or not a.isdigit() or not b.isdigit() or int(b) <= int(a):
        raise argparse.ArgumentTypeError(f"--window {text!r}: expected A-B, whole seconds, A < B")
    return int(a), int(b)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hvac_mpc.benchmarks.path_trace",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="winter_heating_steps", choices=list(scenario_defs.all_scenarios()))
    parser.add_argument("--seeds", type=int, default=5, help="how many plant seeds (the bench's is 0)")
    parser.add_argument("--first-seed", type=int, default=0, help="the first plant seed")
    parser.add_argument("--variant", action="append", metavar="NAME=JSON",
                        help="MpcSettings fields of a variant (repeatable; the first is the reference of the "
                             "differences)")
    parser.add_argument("--window", action="append", type=parse_window, default=[], metavar="A-B",
                        help="seconds over which the mean command is printed (repeatable; samples of the bench's 1 s)")
    parser.add_argument("--quick", action="store_true", help="the scenario's short version")
    parser.add_argument("--json", type=Path, default=None, help="also write the IAE and the per-step records here")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error("--seeds: at least 1")
    chosen = {}
    for text in args.variant or ["defaults={}"]:
        name, sep, fields = text.partition("=")
        if not sep:
            parser.error(f"--variant {text!r}: expected NAME=JSON")
        if name in chosen:
            parser.error(f"--variant {text!r}: the name {name!r} is given twice")
        try:
            chosen[name] = json.loads(fields)
        except json.JSONDecodeError as err:
            parser.error(f"--variant {text!r}: its settings are not JSON ({err})")
    scenario = scenario_defs.select([args.scenario], quick=args.quick)[0]
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    runs = {seed: {n: run_variant(scenario, seed, s) for n, s in chosen.items()} for seed in seeds}
    print("\n".join(report(runs, args.window)))
    if args.json:
        args.json.write_text(json.dumps({str(seed): {n: {"settings": chosen[n], "iae": r["iae"], "steps": r["steps"]}
                                                     for n, r in by_name.items()} for seed, by_name in runs.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
