"""``hvac-mpc daemon``: run the controller daemon from a TOML configuration.

    hvac-mpc daemon --config daemon.toml                 # 1 s loop, until SIGTERM/SIGINT
    hvac-mpc daemon --config daemon.toml --speedup max   # simulated plant as fast as possible
    hvac-mpc daemon --soak 24 --soak-log soak.csv        # 24 h plant-time soak run (accelerated)

Exit codes: 0 after a clean shutdown, 1 after a fatal error (outputs left safe), 2 for a bad
configuration or a failure to start (nothing was driven).
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
from pathlib import Path

from .config import ConfigError, load_config


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="daemon configuration (TOML); see hvac_mpc.daemon.config")
    parser.add_argument("--speedup", help="override loop.speedup (a factor, or 'max' for as fast as possible)")
    parser.add_argument("--max-ticks", type=int, help="override loop.max_ticks (stop after N samples)")
    parser.add_argument("--log", metavar="CSV", help="override log.path")
    parser.add_argument("--model", metavar="FILE",
                        help="refined model file (hvac-mpc identify) for the MPC: override controller.model_file")
    parser.add_argument("--verbose", "-v", action="store_true", help="log every mode change")
    parser.add_argument("--example-config", action="store_true", help="print a commented configuration and exit")
    parser.add_argument("--soak", type=float, metavar="HOURS",
                        help="instead of serving: a soak run of HOURS plant hours at full speed")
    parser.add_argument("--soak-log", default="soak_log.csv", help="log of the soak run (overwritten)")
    parser.add_argument("--soak-controller", default="baseline", help="controller of the soak run")
    parser.add_argument("--soak-every-s", type=float, default=300.0, help="new reference every N plant seconds")
    parser.add_argument("--soak-tracemalloc", action="store_true", help="also track Python allocations")


def _overrides(cfg, args):
    loop, log = cfg.loop, cfg.log
    if args.speedup is not None:
        try:
            speed = math.inf if args.speedup.lower() in ("max", "inf") else float(args.speedup)
        except ValueError:
            raise ConfigError(f"--speedup {args.speedup!r}: a positive number or 'max'") from None
        if not speed > 0:
            raise ConfigError(f"--speedup {args.speedup!r}: a positive number or 'max'")
        loop = loop.replace(speedup=speed)
    if args.max_ticks is not None:
        if args.max_ticks < 0:
            raise ConfigError("--max-ticks: 0 (run until stopped) or a positive count")
        loop = loop.replace(max_ticks=args.max_ticks)
    if args.log:
        log = log.replace(path=args.log)
    controller = cfg.controller
    if getattr(args, "model", None):
        from hvac_mpc.models.model_file import ModelFileError, load

        try:
            load(args.model)
        except (ModelFileError, FileNotFoundError) as exc:
            raise ConfigError(f"--model: {exc}") from None
        controller = controller.replace(model_file=str(Path(args.model).resolve()))
    return cfg.model_copy(update={"loop": loop, "log": log, "controller": controller})


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.example_config:
        from .config import EXAMPLE_TOML

        print(EXAMPLE_TOML, end="")
        return 0
    if args.soak is not None:
        from .soak import print_report, run_soak

        report = run_soak(hours=args.soak, log_path=args.soak_log, controller=args.soak_controller,
                          reference_every_s=args.soak_every_s, tracemalloc_on=args.soak_tracemalloc)
        print_report(report)
        return 0 if report["ok"] else 1
    if not args.config:
        print("hvac-mpc daemon: --config FILE is required (or --soak HOURS)", file=sys.stderr)
        return 2
    try:
        cfg = _overrides(load_config(args.config), args)
    except (ConfigError, ValueError) as exc:
        print(f"hvac-mpc daemon: configuration error: {exc}", file=sys.stderr)
        return 2

    from .controllers import ControllerLoadError
    from .loop import Daemon

    try:
        daemon = Daemon(cfg)
    except (ControllerLoadError, ValueError, OSError, RuntimeError) as exc:
        print(f"hvac-mpc daemon: cannot start: {exc}", file=sys.stderr)
        return 2

    def on_signal(signum, _frame):
        daemon.request_stop(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return daemon.run()
