"""Two versions of the code side by side on ``hvac-mpc identify``: the CPU time of a change and whether it finds the same.

    python -m hvac_mpc.benchmarks.identify_versions --before main --log heating_ptc_delay2_duct4
    python -m hvac_mpc.benchmarks.identify_versions --before main --variant combo_recirc_delay_valve --seed 17
    python -m hvac_mpc.benchmarks.identify_versions --before main --set sweep --json out.json

``--before`` (and ``--after``, default: the installed version) is a git revision of the repository this package is
installed from, or an import root holding ``hvac_mpc`` (:func:`.step_versions.import_root`). Each log (a log of
:mod:`.identify_sweep` by ``--log`` or ``--set``, a log name of :mod:`.identify_time` by ``--variant``; 2 h, 1 Hz) is
written once, then identified by each version in a process of its own, one after the other (which goes first
alternates from log to log, so that the load of other processes on the shared machine falls on both alike), as
``hvac-mpc identify`` does (the documented effects, default mode). Printed per log: the CPU time of each (the process
and its forked workers), their ratio (before / after), each part's CPU time (``identify``'s ``timings``), what was
added, the held-out supply RMS before and after, and whether both versions found the same: the same effects and
terms, the same held-out errors and the same final parameter vector, to the bit.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from .identify_sweep import SETS, STRESS, SWEEP
from .identify_time import log_case
from .step_versions import version_arguments, version_roots

#: The worker each version runs on one log (argv: the log's path, its starting effects as JSON): prints one JSON line.
WORKER = """
import hashlib, json, sys
import numpy as np
from hvac_mpc.identification import log_data
from hvac_mpc.identification.pipeline import cpu_seconds, identify
c0 = cpu_seconds()
res = identify(log_data.load(sys.argv[1]), base_effects=tuple(json.loads(sys.argv[2])))
cpu = cpu_seconds() - c0
e = res.holdout_errors()
print(json.dumps({"cpu_s": cpu, "timings": res.timings,
                  "added": [a.name for a in res.accepted] + [f"term {t.formula()}" for t in res.terms],
                  "holdout": e, "supply_rms_before": e["supply_temp_c"]["rms_before"],
                  "supply_rms_after": e["supply_temp_c"]["rms_after"],
                  "final_p": hashlib.sha256(np.asarray(res.final.p, float).tobytes()).hexdigest()[:16],
                  "notes": res.notes}))
"""

#: The parts of ``identify``'s timings printed per log.
PARTS = ("nominal_fit", "candidates", "discovery", "pairs", "joint", "final_diagnostics")


def run_version(root: Path | None, log_path: Path, base_effects: tuple[str, ...]) -> dict:
    """One version's identification of the log at ``log_path`` in a process of its own."""
    env = dict(os.environ)
    if root is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    out = subprocess.run([sys.executable, "-c", WORKER, str(log_path), json.dumps(list(base_effects))],
                         capture_output=True, text=True, env=env, cwd=root or None)
    if out.returncode != 0:
        raise RuntimeError(f"the worker of {root or 'the installed version'} failed: {out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def same(before: dict, after: dict) -> bool:
    """Both versions found the same: effects and terms, held-out errors and final parameters, to the bit."""
    return all(before[k] == after[k] for k in ("added", "holdout", "final_p"))


def _cases(args) -> list[tuple[str, object]]:
    """(name, case) of every log asked for (an identify_sweep log or an identify_time log name)."""
    sweep = {log.name: log for log in SWEEP + STRESS}
    cases = [(name, sweep[name].case()) for name in args.log or ()]
    cases += [(log.name, log.case()) for log in SETS[args.set]] if args.set else []
    cases += [(name, log_case(name)) for name in args.variant or ()]
    return cases


def main(argv: list[str] | None = None) -> int:
    from hvac_mpc.mismatch import simulate_log

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    version_arguments(p)
    p.add_argument("--log", action="append", choices=[log.name for log in SWEEP + STRESS],
                   help="a log of identify_sweep (repeatable)")
    p.add_argument("--set", choices=sorted(SETS), default=None, help="every log of an identify_sweep set")
    p.add_argument("--variant", action="append", help="a log name of identify_time (repeatable)")
    p.add_argument("--seed", type=int, default=211)
    p.add_argument("--duration", type=float, default=7200.0, help="log length, s (default 7200)")
    p.add_argument("--json", type=Path, default=None, help="write the rows here")
    args = p.parse_args(argv)
    try:
        cases = _cases(args)
    except ValueError as exc:
        p.error(str(exc))
    if not cases:
        p.error("give at least one --log, --set or --variant")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        roots = version_roots(args, Path(tmp), "identify_versions")
        if roots is None:
            return 2
        for k, (name, case) in enumerate(cases):
            path = Path(tmp) / f"{name}.csv"
            simulate_log(path, case.variant, duration_s=args.duration, seed=args.seed, excitation=case.excitation,
                         bad_rows=case.bad_rows, omit=case.omit)
            order = ("before", "after") if k % 2 == 0 else ("after", "before")
            res = {v: run_version(roots[v], path, case.base_effects) for v in order}
            b, a = res["before"], res["after"]
            row = {"log": name, "seed": args.seed, "before": b, "after": a, "ratio": b["cpu_s"] / a["cpu_s"],
                   "same": same(b, a)}
            rows.append(row)
            parts = ", ".join(f"{q} {b['timings'].get(q + '_cpu_s', 0.0):.1f} -> {a['timings'].get(q + '_cpu_s', 0.0):.1f}"
                              for q in PARTS)
            print(f"{name:30s} CPU {b['cpu_s']:6.1f} -> {a['cpu_s']:6.1f} s ({row['ratio']:.2f}x less)  "
                  f"{'the same to the bit' if row['same'] else 'DIFFERENT'}: {a['added'] or ['nothing']}, supply RMS "
                  f"{a['supply_rms_before']:.3f} -> {a['supply_rms_after']:.3f} C"
                  + ("" if row["same"] else f" (before: {b['added'] or ['nothing']}, {b['supply_rms_after']:.3f} C)"),
                  flush=True)
            print(f"{'':30s} parts CPU s: {parts}", flush=True)
    total_b, total_a = sum(r["before"]["cpu_s"] for r in rows), sum(r["after"]["cpu_s"] for r in rows)
    print(f"total CPU {total_b:.1f} -> {total_a:.1f} s ({total_b / total_a:.2f}x less); the same on "
          f"{sum(r['same'] for r in rows)} of {len(rows)} logs; load average {os.getloadavg()[0]:.1f}")
    if args.json is not None:
        args.json.write_text(json.dumps({"versions": {"before": args.before, "after": args.after or "installed"},
                                         "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
