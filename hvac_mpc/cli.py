"""Command-line entry point ``hvac-mpc`` with one subcommand per job.

Each subcommand lives in its own module exposing ``configure(parser)`` and ``run(args) -> int``;
modules are imported only when their subcommand runs.
"""

from __future__ import annotations

import argparse
import importlib
import sys

SUBCOMMANDS = {
    "bench": ("hvac_mpc.benchmarks.bench", "MPC against the thesis baseline on the simulated plant"),
    "baseline": ("hvac_mpc.benchmarks.baseline_demo", "thesis baseline checks on the simulated plant, with plots"),
    "solve-time": ("hvac_mpc.benchmarks.solve_time", "MPC step time against IPOPT and do-mpc"),
    "identify": ("hvac_mpc.identification.cli", "refine the model from a measurement log"),
    "daemon": ("hvac_mpc.daemon.main", "run the controller daemon"),
    "ctl": ("hvac_mpc.daemon.ctl", "talk to a running daemon: status, mode, manual setting, reference"),
    "experiment": ("hvac_mpc.benchmarks.experiment", "a bench scenario or an identification excitation through the daemon"),
    "report": ("hvac_mpc.benchmarks.report_logs", "the bench's report (figures, ratios, plots) from logs of real runs"),
    "sweep": ("hvac_mpc.benchmarks.sweep", "thousands of closed-loop runs on Dask, one Parquet row per run"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hvac-mpc", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        if only is None or only == name:
            importlib.import_module(module).configure(sp)
        sp.set_defaults(_module=module)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = next((a for a in argv if a in SUBCOMMANDS), None)
    parser = build_parser(only=chosen)
    args = parser.parse_args(argv)
    return int(importlib.import_module(args._module).run(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
