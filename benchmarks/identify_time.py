"""Wall time of ``hvac-mpc identify`` on 2 h, 1 Hz logs of the independent box, on two cores.

    python -m hvac_mpc.benchmarks.identify_time                       # the default set of variants
    python -m hvac_mpc.benchmarks.identify_time --variant delay_3s --threads 2 --json out.json
    python -m hvac_mpc.benchmarks.identify_time --seed 23 --variant nominal+bad --variant shift_-1 \
        --variant heater_weak+hot+noptc                                # bad rows; a shift; the PTC fall to find

For each variant: a 2 h log is written by :func:`hvac_mpc.mismatch.simulate_log` (seeded), then
the command's own path runs on it (``log_data.load`` and ``identify`` from the documented effects,
default mode, as ``hvac-mpc identify`` does), pinned to ``--threads`` cores (Linux affinity). The
log generation is not timed. Printed per log: wall and CPU time (this process and its forked
workers; on a shared machine the CPU time is the honest figure, the wall time grows with the other
jobs' load, so the load average is printed too), the parts (load and checks, nominal fit,
diagnostics, candidates, discovery, pairs, joint refit, final diagnostics), what was added, held-out supply RMS before
and after. The budget of the issue is one minute per 2 h log on two cores.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from hvac_mpc.identification import log_data
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS, cpu_seconds, identify
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.mismatch.variants import Variant, get_variant

#: Logs timed by default: clean, single effects, effects outside the library, several together, shifted, the
#: PTC fall to find on a log that excites it.
DEFAULT_VARIANTS = ("nominal", "delay_3s", "heater_weak", "duct_loss", "cooler_literal", "combo_delay_loss_cooler",
                    "shift_1", "nominal+hot+noptc")
BUDGET_S = 60.0


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"


#: Suffixes of a log name: ``+bad`` bad rows injected, ``+hot`` the "hot_heater" excitation (the heater
#: body past the PTC's knee), ``+noptc`` identification starts without the PTC power fall (it must find it),
#: ``+nowater`` the log without the water-temperature column (a box without that sensor).
FLAGS = ("bad", "hot", "noptc", "nowater")


@dataclass(frozen=True)
class LogCase:
    """One timed log: the variant for :func:`simulate_log`, its excitation, bad rows, the starting effects."""

    variant: object
    excitation: str = "steps"
    bad_rows: bool = False
    base_effects: tuple[str, ...] = DOCUMENTED_EFFECTS
    omit: tuple[str, ...] = ()


def log_case(name: str) -> LogCase:
    """The :class:`LogCase` of a log name: a registry name or ``shift_N`` (outputs N samples late), with
    any of the :data:`FLAGS` as ``+flag`` suffixes (``nominal+hot+noptc``)."""
    base, *flags = name.split("+")
    unknown = [f for f in flags if f not in FLAGS]
    if unknown:
        raise ValueError(f"log {name!r}: unknown suffix {unknown[0]!r}; allowed: {', '.join(FLAGS)}")
    variant = Variant(log_shift_samples=int(base.split("_", 1)[1])) if base.startswith("shift_") else base
    get_variant(variant)  # an unknown name: ValueError naming the allowed ones
    effects = tuple(e for e in DOCUMENTED_EFFECTS if not ("noptc" in flags and e == "ptc_power_fall"))
    return LogCase(variant, "hot_heater" if "hot" in flags else "steps", "bad" in flags, effects,
                   ("water_temp_c",) if "nowater" in flags else ())


def time_one(name: str, duration_s: float, seed: int, folder: Path, pairs: bool = True, joint: bool = True) -> dict:
    """Generate one log (untimed) and time the identification of it (``pairs``: with the pair step; ``joint``: with
    the joint refit)."""
    return time_case(name, log_case(name), duration_s, seed, folder, pairs, joint)


def time_case(name: str, case: LogCase, duration_s: float, seed: int, folder: Path, pairs: bool = True,
              joint: bool = True, best_place: bool = False) -> dict:
    """:func:`time_one` for a :class:`LogCase` given directly (a variant that has no registry name; ``best_place``:
    ``identify``'s setting of that name)."""
    path = folder / f"{name}.csv"
    simulate_log(path, case.variant, duration_s=duration_s, seed=seed, excitation=case.excitation,
                 bad_rows=case.bad_rows, omit=case.omit)
    t0, c0 = time.perf_counter(), cpu_seconds()
    log = log_data.load(path)
    load_wall, load_cpu = time.perf_counter() - t0, cpu_seconds() - c0
    res = identify(log, base_effects=case.base_effects, pairs=pairs, joint=joint, best_place=best_place)
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    errors = res.holdout_errors()
    e = errors["supply_temp_c"]
    flow = errors.get("volume_flow_m3s", {})
    added = [a.name for a in res.accepted] + [f"term {t.formula()}" for t in res.terms]
    return {"log": name, "wall_s": wall, "cpu_s": cpu, "added": added, "supply_rms_before": e["rms_before"],
            "supply_rms_after": e["rms_after"], "supply_max_before": e["max_before"], "supply_max_after": e["max_after"],
            "flow_rms_before": flow.get("rms_before", float("nan")),
            "flow_rms_after": flow.get("rms_after", float("nan")),
            "added_params": {k: round(v, 3) for a in res.accepted for k, v in a.params.items()},
            "timing_shift_samples": res.timing_shift_samples,
            "moved": {c["name"]: round(c["change"], 4) for c in res.parameter_confidence if c["moved"]},
            "timings_s": dict(res.timings, load_s=load_wall, load_cpu_s=load_cpu),
            "terms_in_words": [t.description for t in res.terms], "pairs": res.pairs, "joint": res.joint,
            "notes": list(res.notes),
            # the main process's whole-log runs: found built in the code cache, built during this run, or not
            # (docs/identification.md "Runs as generated C")
            "runs_as_c": res.fitter.builds.summary()}


PARTS = ("load", "nominal_fit", "diagnostics", "candidates", "discovery", "pairs", "joint", "final_diagnostics")


def _parts(t: dict) -> str:
    return ", ".join(f"{p} {t.get(p + '_s', 0.0):.1f}/{t.get(p + '_cpu_s', 0.0):.1f}" for p in PARTS)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", action="append", default=None,
                        help="hvac_mpc.mismatch variant, or shift_N for a log shifted by N samples; suffixes +bad (bad "
                             "rows), +hot (heater past the PTC's knee), +noptc (start without the PTC fall), +nowater "
                             "(no water-temperature column) (repeatable)")
    parser.add_argument("--duration", type=float, default=7200.0, help="log length, s (default 7200)")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, choices=(1, 2), help="cores to use (default 2)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument("--no-pairs", action="store_true",
                        help="identify without the pair step (effects that only help together), as before it")
    parser.add_argument("--no-joint", action="store_true",
                        help="identify without the joint refit (several effects refit at once, eliminated backward), "
                             "as before it")
    args = parser.parse_args(argv)
    for name in args.variant or ():
        try:
            log_case(name)
        except ValueError as exc:
            parser.error(str(exc))
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:args.threads])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.variant or DEFAULT_VARIANTS:
            r = time_one(name, args.duration, args.seed, Path(tmp), pairs=not args.no_pairs,
                         joint=not args.no_joint)
            rows.append(r)
            print(f"{name:28s} wall {r['wall_s']:6.1f} s, CPU {r['cpu_s']:6.1f} s  added {r['added'] or ['nothing']}  "
                  f"supply RMS {r['supply_rms_before']:.3f} -> {r['supply_rms_after']:.3f} C, flow RMS "
                  f"{1e3 * r['flow_rms_before']:.2f} -> {1e3 * r['flow_rms_after']:.2f} l/s"
                  + (f"  params {r['added_params']}" if r["added_params"] else "")
                  + (f"  shift {r['timing_shift_samples']} sample(s)" if r["timing_shift_samples"] else "")
                  + (f"  moved {r['moved']}" if r["moved"] else ""),
                  flush=True)
            print(f"{'':28s} parts wall/CPU s: {_parts(r['timings_s'])}", flush=True)
    worst = max(r["wall_s"] for r in rows)
    worst_cpu = max(r["cpu_s"] for r in rows)
    print(f"slowest: wall {worst:.1f} s, CPU {worst_cpu:.1f} s (this process and its workers) on {args.threads} "
          f"core(s), budget {BUDGET_S:g} s; load average at the end {_load()}")
    if args.json:
        args.json.write_text(json.dumps({"threads": args.threads, "duration_s": args.duration, "runs": rows},
                                        indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
