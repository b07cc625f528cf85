"""``hvac-mpc identify``: refine the model from a measurement log, or from the thesis's tables 3-6.

    hvac-mpc identify LOG.csv [--map lab_name=schema_name ...] [--out DIR] [--params BASE.toml]
    hvac-mpc identify --thesis-tables [--out DIR]

Writes ``report.md`` (with PNG plots when matplotlib is installed), ``summary.json`` and the
model file ``model.toml`` (parameters and ``[model] effects``, loadable with
:func:`hvac_mpc.identification.load_model_file`) into the output folder.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from hvac_mpc.models.measurement_log import LogFormatError


#: Names of :data:`.candidates.OPTIONAL_CANDIDATES` (here so that the command line builds without the model's imports).
OPTIONAL_CANDIDATE_NAMES = ("cooler_literal_fit",)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", nargs="?", help="measurement log (CSV, or Parquet with pyarrow installed)")
    parser.add_argument("--map", action="append", default=[], metavar="OLD=NEW",
                        help="read the log's column OLD as schema column NEW (repeatable)")
    parser.add_argument("--out", default=None, help="output folder (default out/identify or out/identify-tables)")
    parser.add_argument("--params", default=None, metavar="BASE.toml",
                        help="starting model file (parameters and [model] effects); default: thesis model")
    parser.add_argument("--holdout-fraction", type=float, default=1 / 3,
                        help="share of the log, at its end, held out from fitting (default 1/3, allowed 0.1-0.6)")
    parser.add_argument("--max-effects", type=int, default=4, help="most effects added (default 4, allowed 0-6)")
    parser.add_argument("--quick", action="store_true", help="fewer solver iterations (for tests and previews)")
    parser.add_argument("--no-plots", action="store_true", help="write the report without plots")
    parser.add_argument("--no-pairs", action="store_true",
                        help="no pair step (pairs of effects that only help together; on by default)")
    parser.add_argument("--best-place", action="store_true",
                        help="a discovered term's place: the best after the refit among those that pass (held-out "
                             "error), not the first that passes (off by default)")
    parser.add_argument("--thesis-unless-moved", action="store_true",
                        help="where nothing is added, write the thesis value of every refit nominal parameter the log "
                             "does not move (Wald test at 1 %%, each alone; off by default: docs/identification.md, "
                             "'A log that adds nothing')")
    parser.add_argument("--thesis-tables", action="store_true",
                        help="run the loop on the thesis's valve measurements (tables 3-6) instead of a log")
    parser.add_argument("--candidate", action="append", default=[], choices=OPTIONAL_CANDIDATE_NAMES,
                        help="also score this optional library candidate (repeatable; off by default: "
                             "docs/identification.md, 'The literal cooler as a library effect')")
    parser.add_argument("--quiet", action="store_true", help="no progress messages")


def _mapping(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        old, sep, new = item.partition("=")
        if not sep or not old.strip() or not new.strip():
            raise ValueError(f"--map expects OLD=NEW (a log column and a schema column), got {item!r}")
        out[old.strip()] = new.strip()
    return out


def run(args: argparse.Namespace) -> int:
    say = (lambda msg: None) if args.quiet else (lambda msg: print(f"identify: {msg}", file=sys.stderr))
    try:
        if args.thesis_tables:
            return _run_tables(args, say)
        if not args.log:
            raise ValueError("give a LOG file or --thesis-tables")
        return _run_log(args, say)
    except (ValueError, KeyError, FileNotFoundError, LogFormatError) as exc:
        print(f"identify: error: {exc}", file=sys.stderr)
        return 2


def _run_log(args, say) -> int:
    from hvac_mpc.models.parameters import Parameters

    from . import log_data
    from .model_file import load_model_file
    from .pipeline import DOCUMENTED_EFFECTS, identify
    from .report import write_report

    if not 0 <= args.max_effects <= 6:
        raise ValueError(f"--max-effects = {args.max_effects} is outside the allowed range [0, 6]")
    path = Path(args.log)
    if not path.exists():
        raise FileNotFoundError(f"log file {path} does not exist")
    base, effects = (load_model_file(args.params) if args.params else (Parameters(), DOCUMENTED_EFFECTS))
    t0 = time.perf_counter()
    log = log_data.load(path, _mapping(args.map), args.holdout_fraction)
    say(f"{log.n} rows, outputs {', '.join(log.output_names())}")
    res = identify(log, base, effects, quick=args.quick, max_effects=args.max_effects, progress=say,
                   pairs=not args.no_pairs, best_place=args.best_place, optional_candidates=args.candidate,
                   thesis_unless_moved=args.thesis_unless_moved)
    out = Path(args.out or "out/identify")
    files = write_report(res, out, plots=not args.no_plots)
    added = [a.name for a in res.accepted] or ["none"]
    print(f"effects added: {', '.join(added)}")
    for term in res.terms:
        print(f"  discovered term {term.name}: {term.formula()}")
    if res.timing_shift_samples:
        print(f"  {next(n for n in res.notes if n.startswith('log timing'))}")
    for o, e in res.holdout_errors().items():
        print(f"  held-out {o}: RMS {e['rms_before']:.4g} -> {e['rms_after']:.4g}, "
              f"max {e['max_before']:.4g} -> {e['max_after']:.4g}")
    for loc in res.localisation:
        from .localise import describe
        print(f"  unexplained: {describe(loc)}")
    print(f"report: {files['report']}  model file: {files['model']}  ({time.perf_counter() - t0:.1f} s)")
    return 0


def _run_tables(args, say) -> int:
    from hvac_mpc.models.parameters import Parameters

    from .model_file import load_model_file
    from .tables_report import write_tables_report
    from .thesis_tables import run as run_tables

    base = load_model_file(args.params)[0] if args.params else Parameters()
    say("thesis tables 3-6: fitting on tables 3-5, checking table 6 leave-one-row-out")
    res = run_tables(base)
    out = Path(args.out or "out/identify-tables")
    files = write_tables_report(res, out, plots=not args.no_plots)
    print(f"effects added: {', '.join(res.accepted) or 'none'}")
    for key, label in (("total_rms_m3s", "total flow RMS"), ("split_rms_m3s", "outlet-split RMS")):
        print(f"  table 6 {label}: {res.before[key]:.4f} -> {res.after[key]:.4f} m3/s")
    print(f"report: {files['report']}  model file: {files['model']}")
    return 0
