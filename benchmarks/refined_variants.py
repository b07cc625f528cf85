"""The data loop closed, per plant variant: log -> identify -> model file -> MPC, nominal against refined.

    python -m hvac_mpc.benchmarks.refined_variants                 # the variants of the issue
    python -m hvac_mpc.benchmarks.refined_variants --variant duct_loss --json out.json

For each variant of the independent box (:mod:`hvac_mpc.mismatch`): a 2 h, 1 Hz open-loop log
(seeded) is identified as ``hvac-mpc identify`` does, the model file written, and the MPC with it
run against the MPC with the nominal model on the same variant, through every bench scenario
(quick versions unless ``--full``) with the same noise seed (:func:`hvac_mpc.benchmarks.refined_model.compare`, what
``hvac-mpc bench --model FILE --model-plant VARIANT`` adds to its report). Printed per variant:
what was added, held-out supply RMS before and after, thermocouple and flow IAE of both MPCs.

``ptc_fall`` is the nominal box (its heater's power falls with the body temperature) identified
from the thesis model without the PTC fall (the fan curve and the leaks only), so the fall must
be found in the log.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from hvac_mpc.identification import log_data, write_model_file
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS, identify
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.mismatch.logs import EXCITATIONS
from hvac_mpc.models.parameters import Parameters

from . import scenarios
from .refined_model import compare

#: Variants run by default: a delay, an effect outside the library with the cabin temperature logged
#: (duct loss), one outside it without (cooler core independent of the inlet air), the PTC fall, a
#: bypass split depending on the flow (in the library, left out of the thesis model and the nominal
#: MPC's prediction), several together, and valve curves shifted 10 % of travel (the model's valve-curve shifts).
DEFAULT_VARIANTS = ("delay_3s", "duct_loss", "cooler_literal", "ptc_fall", "bypass_flow", "combo_delay_loss_cooler",
                    "combo_heater_chiller_delay", "valve_shift")
#: Plant variant and starting effects of each case (the documented physics unless said otherwise).
CASES = {"ptc_fall": ("nominal", ("fan_curve", "valve_leakage"))}


def run_one(name: str, folder: Path, seed: int, duration_s: float, scenario_names: list[str] | None,
            quick: bool = True, deadline_s: float | None = None, attribution: bool = True,
            overrides: dict | None = None, weights: dict | None = None, candidates: tuple[str, ...] = (),
            excitation: str = "steps", thesis_unless_moved: bool = False) -> dict:
    """Log, identification, model file and closed-loop comparison of one variant (``quick``: the scenarios'
    quick versions, their first segments only; ``deadline_s``: the MPCs' feedback deadline, None the default;
    ``attribution``: both MPCs once more without the effects the file lists as absent; ``overrides``, ``weights``:
    both MPCs' settings and cost weights changed alike, :func:`.refined_model.with_overrides`; ``candidates``: optional
    library candidates identification also scores, ``identify(optional_candidates=...)``; ``excitation``: the log's
    open-loop excitation, :data:`hvac_mpc.mismatch.logs.EXCITATIONS`, e.g. ``hot_heater``, whose heating phases drive
    the heater body past the PTC's knee; ``thesis_unless_moved``: ``identify(thesis_unless_moved=...)``)."""
    variant, effects = CASES.get(name, (name, DOCUMENTED_EFFECTS))
    path = folder / f"{name}.csv"
    simulate_log(path, variant, duration_s=duration_s, seed=seed, excitation=excitation)
    res = identify(log_data.load(path), Parameters(), effects, optional_candidates=candidates,
                   thesis_unless_moved=thesis_unless_moved)
    model = write_model_file(folder / f"{name}.toml", res.params, res.effects, res.extras, res.terms, res.absent)
    cmp = compare(model, variant, scenarios.select(scenario_names, quick=quick), seed=0, attribution=attribution,
                  deadline_s=deadline_s, overrides=overrides, weights=weights)
    e = res.holdout_errors()["supply_temp_c"]
    return {"case": name, "variant": variant, "added": [a.name for a in res.accepted], "absent": list(res.absent),
            "terms": [t.formula() for t in res.terms], "term_words": [t.description for t in res.terms],
            "supply_rms_before": e["rms_before"], "supply_rms_after": e["rms_after"],
            "supply_rms_written": (res.written or {}).get("supply_temp_c", {}).get("rms_after", e["rms_after"]),
            "model_file": model.read_text(), "comparison": cmp}


def _print_details(r: dict) -> None:
    """Per scenario, both MPCs (and without the absent effects where those runs were made)."""
    t = r["comparison"]["total"]
    attributed = "ratio_as_identified" in t
    if attributed:
        print(f"{'':26s} absent {r['absent'] or ['nothing']}; both MPCs without them: thermocouple IAE nominal "
              f"{t['nominal_as_identified']['temp_iae_cs']:.1f}, refined {t['refined_as_identified']['temp_iae_cs']:.1f} "
              f"C s (ratio {t['ratio_as_identified']:.3f})", flush=True)
    print(f"{'':28s}{'scenario':24s} {'nominal':>7s} {'refined':>7s} C s  flow nominal refined m3"
          + (f"   | without absent: {'nominal':>7s} {'refined':>7s} C s" if attributed else ""), flush=True)
    for sc, s in r["comparison"]["scenarios"].items():
        print(f"{'':28s}{sc:24s} {s['nominal']['temp_iae_cs']:7.1f} {s['refined']['temp_iae_cs']:7.1f} C s  "
              f"flow {s['nominal']['flow_iae_m3']:.3f} {s['refined']['flow_iae_m3']:.3f} m3"
              + (f"   | {s['nominal_as_identified']['temp_iae_cs']:7.1f} {s['refined_as_identified']['temp_iae_cs']:7.1f} "
                 f"C s" if attributed else ""), flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", action="append", default=None,
                        help=f"case (repeatable; default {', '.join(DEFAULT_VARIANTS)})")
    parser.add_argument("--scenario", action="append", default=None, help="bench scenario (default: all, quick)")
    parser.add_argument("--full", action="store_true",
                        help="the scenarios' full versions (default: quick, the first segments only; in "
                             "winter_heating_steps two steps up)")
    parser.add_argument("--duration", type=float, default=7200.0, help="log length, s (default 7200)")
    parser.add_argument("--seed", type=int, default=5, help="seed of the identification log (default 5)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument("--deadline", type=float, default=None,
                        help="the MPCs' feedback deadline, s (default: 3600, no wall-clock fallback, so the ratios do "
                             "not depend on the machine's load; 0.5 is the box's)")
    parser.add_argument("--no-attribution", action="store_true",
                        help="skip the runs of both MPCs without the effects the file lists as absent (half the time)")
    parser.add_argument("--settings", type=json.loads, default=None,
                        help='both MPCs\' settings changed alike, JSON of MpcSettings fields, e.g. '
                             '\'{"rti_step_fractions": [0.5, 0.25]}\'')
    parser.add_argument("--weights", type=json.loads, default=None,
                        help='both MPCs\' cost weights changed alike, JSON of Weights fields, e.g. '
                             '\'{"heater_ready_per_c2": 0.5}\'')
    parser.add_argument("--candidate", action="append", default=[],
                        help="optional library candidate identification also scores (repeatable; e.g. "
                             "cooler_literal_fit, docs/identification.md)")
    parser.add_argument("--excitation", default="steps", choices=EXCITATIONS,
                        help="the identification log's open-loop excitation (default steps; hot_heater: heating phases "
                             "near full heater power at low flow, the heater body past the PTC's knee)")
    parser.add_argument("--thesis-unless-moved", action="store_true",
                        help="where nothing is added, the file holds the thesis value of every refit parameter the "
                             "log does not move (off by default; docs/identification.md)")
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.variant or DEFAULT_VARIANTS:
            r = run_one(name, Path(tmp), args.seed, args.duration, args.scenario, quick=not args.full,
                        deadline_s=args.deadline, attribution=not args.no_attribution, overrides=args.settings,
                        weights=args.weights, candidates=tuple(args.candidate), excitation=args.excitation,
                        thesis_unless_moved=args.thesis_unless_moved)
            rows.append(r)
            t = r["comparison"]["total"]
            print(f"{name:26s} added {r['added'] + r['terms'] or ['nothing']}", flush=True)
            written = (f" (the file's model {r['supply_rms_written']:.3f})"
                       if r["supply_rms_written"] != r["supply_rms_after"] else "")
            print(f"{'':26s} held-out supply RMS {r['supply_rms_before']:.3f} -> {r['supply_rms_after']:.3f} C{written}; "
                  f"thermocouple IAE nominal {t['nominal']['temp_iae_cs']:.1f}, refined {t['refined']['temp_iae_cs']:.1f} "
                  f"C s (ratio {t['ratio']:.3f}); flow IAE {t['nominal']['flow_iae_m3']:.2f} / "
                  f"{t['refined']['flow_iae_m3']:.2f} m3; whole runs (warm-up included) "
                  f"{t['nominal']['run_temp_iae_cs']:.1f} / {t['refined']['run_temp_iae_cs']:.1f} C s "
                  f"(ratio {t['run_ratio']:.3f})", flush=True)
            _print_details(r)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
