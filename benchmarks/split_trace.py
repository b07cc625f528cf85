"""One scenario of the built-in bench with and without a split reference change, step by step.

    python -m hvac_mpc.benchmarks.split_trace [--scenario winter_heating_steps] [--seed 0]
        [--variant NAME=JSON ...] [--window 15] [--json FILE]

Each variant (``NAME=JSON``: MpcSettings fields; default "defaults={}" and "split_30={"change_split_iter": 30}")
runs the full scenario on the bench's plant (:func:`.bench.mpc_factory`, seed and deadline as ``hvac-mpc bench``)
and records per step: OSQP's iterations and QPs, the split rest's iterations (collected by the step after it),
OSQP's step size ``rho`` after the step (and its rest) and the command. Printed: the supply-temperature IAE (the
bench's: noise-free thermocouple against the reference from the scored start) of each variant and its difference
to the first variant per segment of the reference and per window of ``--window`` steps, with the
largest command differences in the window; OSQP's iterations of the twelve steps from each change of the
reference (any of its fields: temperature, flow, outlet flows); the steps on which OSQP's step size changed. The MPC
alone runs: ratios to the baseline come from ``hvac-mpc bench``. Measured in docs/architecture.md, 'The rest of a split change, traced'.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from hvac_mpc.models.parameters import Parameters

from . import bench, box_trace, scenarios as scenario_defs
from .perturbation import perturb_parameters
from .simulate import simulate

#: Steps from a change whose OSQP iterations are listed.
AFTER_CHANGE = 12
#: Longest wait for a split change's rest after its step (s): it takes milliseconds.
REST_WAIT_S = 60.0


class Recorder:
    """A controller that records each step's statistics and OSQP's step size (passes every other call through)."""

    def __init__(self, controller):
        self.controller = controller
        self.steps: list[dict[str, Any]] = []

    def __getattr__(self, name):
        return getattr(self.controller, name)

    def step(self, measurement, reference):
        result = self.controller.step(measurement, reference)
        self.steps.append(self.record(result))
        return result

    def record(self, result) -> dict[str, Any]:
        """What is kept of one step: OSQP's iterations and QPs, the split rest's iterations, the step size after."""
        rest = getattr(self.controller, "_change_call", None)
        if rest is not None:  # a split change's rest done before the step size is read (the commands do not change)
            rest.wait(REST_WAIT_S)
        stats = result.stats or {}
        rest = stats.get("change_finish") or {}
        core = getattr(getattr(self.controller, "solver", None), "_core", None)
        return {"iterations": int(stats.get("iterations") or 0), "qp_solves": int(stats.get("qp_solves") or 0),
                "rest_iterations": int(rest.get("iterations", 0)),
                "rho": float(core.rho) if core is not None and hasattr(core, "rho") else None}


def run_variant(scenario: scenario_defs.Scenario, seed: int, settings: Mapping[str, Any],
                recorder: type = Recorder) -> dict[str, Any]:
    """The MPC with ``settings`` through ``scenario`` on the bench's plant of ``seed``; per-step records (kept by
    ``recorder``, a :class:`Recorder`)."""
    plant_params, _ = perturb_parameters(Parameters(), seed)
    ctrl = recorder(bench.mpc_factory(settings=dict(settings))(scenario.initial_command))
    tr = simulate(scenario, ctrl, plant_params, seed, name="mpc")
    ctrl.close()
    k0 = int(np.searchsorted(tr.time_s, scenario.metrics_start_s - 1e-9))
    err = box_trace.abs_error(tr, scenario.metrics_start_s) * tr.dt_s
    ref = tr.reference["supply_temp_c"]
    return {"error": err, "reference": ref, "commands": tr.requested, "steps": ctrl.steps, "k0": k0,
            "changes": reference_changes(tr.reference), "iae": float(err.sum()), "body_c": tr.truth["heater_temp_c"]}


def reference_changes(reference: Mapping[str, np.ndarray]) -> list[int]:
    """The steps whose reference (any of its fields: temperature, flow, outlet flows) differs from the step before's
    (a field without a value, NaN, in both is unchanged)."""
    fields = [np.asarray(v, float) for v in reference.values()]
    n = fields[0].size
    return [k for k in range(1, n)
            if any(v[k] != v[k - 1] and not (np.isnan(v[k]) and np.isnan(v[k - 1])) for v in fields)]


def report(runs: dict[str, dict[str, Any]], window: int) -> list[str]:
    """The printed comparison of each variant with the first."""
    names = list(runs)
    first = runs[names[0]]
    lines = [f"{n}: IAE {r['iae']:.2f} C s, OSQP iterations in the steps {sum(s['iterations'] for s in r['steps'])}, "
             f"in the rests {sum(s['rest_iterations'] for s in r['steps'])}" for n, r in runs.items()]
    bounds = [first["k0"], *[c for c in first["changes"] if c > first["k0"]], first["reference"].size]
    for n in names[1:]:
        r = runs[n]
        d = r["error"] - first["error"]
        lines.append(f"{n} - {names[0]}, per segment: " + ", ".join(
            f"{a}-{b} s {d[a:b].sum():+.2f}" for a, b in zip(bounds[:-1], bounds[1:])))
        for a in range(first["k0"], d.size, window):
            du = np.abs(r["commands"][a:a + window] - first["commands"][a:a + window]).max(axis=0)
            lines.append(f"  {a:4d}-{a + window:4d} s: {d[a:a + window].sum():+6.2f} (so far {d[:a + window].sum():+6.2f})"
                         f" | largest command differences {np.round(du, 1).tolist()}")
    for n, r in runs.items():
        for c in r["changes"]:
            lines.append(f"{n} change at {c} s: OSQP iterations of the steps from it "
                         f"{[s['iterations'] for s in r['steps'][c:c + AFTER_CHANGE]]}, rests "
                         f"{[s['rest_iterations'] for s in r['steps'][c:c + 2] if s['rest_iterations']]}")
        rho = [s["rho"] for s in r["steps"]]
        moves = [(k, f"{rho[k]:.3g}") for k in range(1, len(rho)) if rho[k] is not None and rho[k] != rho[k - 1]]
        lines.append(f"{n} OSQP step size after step 0 {rho[0]:.3g}; changed after the steps {moves}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hvac_mpc.benchmarks.split_trace", description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="winter_heating_steps", choices=list(scenario_defs.all_scenarios()))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--variant", action="append", metavar="NAME=JSON",
                        help='MpcSettings fields of a variant, e.g. split_30={"change_split_iter": 30} (repeatable; '
                             'the first is the reference of the differences)')
    parser.add_argument("--window", type=int, default=15, help="steps per window of the IAE differences")
    parser.add_argument("--json", type=Path, default=None, help="also write the per-step records here")
    args = parser.parse_args(argv)
    variants = args.variant or ["defaults={}", 'split_30={"change_split_iter": 30}']
    chosen = {}
    for text in variants:
        name, sep, fields = text.partition("=")
        if not sep:
            parser.error(f"--variant {text!r}: expected NAME=JSON")
        chosen[name] = json.loads(fields)
    scenario = scenario_defs.select([args.scenario])[0]
    runs = {n: run_variant(scenario, args.seed, s) for n, s in chosen.items()}
    print("\n".join(report(runs, args.window)))
    if args.json:
        args.json.write_text(json.dumps({n: {"settings": chosen[n], "iae": r["iae"], "changes": r["changes"],
                                             "steps": r["steps"], "commands": r["commands"].tolist()}
                                         for n, r in runs.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
