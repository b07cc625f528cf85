"""``hvac-mpc experiment``: a bench scenario or an identification excitation run through the daemon.

The daemon's own loop (:class:`hvac_mpc.daemon.loop.Daemon`) runs the chosen controller with its
safety layer, sensor checks, shutdown sequence and log; the experiment only feeds it:

* ``--scenario NAME``: the scenario's reference schedule, set before each sample, with the MPC
  (``--controller mpc``) or the thesis baseline (``--controller baseline``);
* ``--excitation steps|prbs|multisine``: open-loop actuator sequences
  (:class:`hvac_mpc.daemon.excitation.ExcitationController` in the controller slot, so the heater
  interlock and every bound still hold) for identification.

Backends: by default the bench's simulated plant for the scenario (perturbed parameters, all
effects, the noise seed ``hvac-mpc bench --seed`` uses, the cabin when the scenario has one), so
two experiments and ``hvac-mpc report`` reproduce the bench's ratios; ``--plant VARIANT`` runs the
independent box of :mod:`hvac_mpc.mismatch` instead; ``--config FILE`` takes the backend (and
safety settings) of a daemon configuration, e.g. the lab's Modbus box. Next to the log a
``LOG.json`` sidecar records what ran (scenario, warm-up, seed, controller) for the report.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from pathlib import Path
from typing import Any, Callable

from hvac_mpc.contract import Command
from hvac_mpc.daemon.config import ConfigError, config_from_mapping
from hvac_mpc.daemon.io import BackendError
from hvac_mpc.daemon.loop import Daemon
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.models.plant import PLANT_EFFECTS, Environment, SimulatedPlant

from . import scenarios as scenario_defs
from .perturbation import perturb_parameters
from .simulate import plant_seed, scenario_plant

EXCITATION_CONTROLLER = "excitation"  # registered entry point (pyproject.toml)
CONTROLLERS = ("mpc", "baseline")
#: Deadline of a controller step on a simulated plant run as fast as possible (s of wall time): the
#: largest the configuration allows, so the run does not depend on the machine's load.
SIMULATED_DEADLINE_S = 60.0


class PlantBackend:
    """Any plant object (``apply``/``advance``/``read``) as a daemon backend, advanced one sample
    per written command, in lockstep with the daemon clock."""

    def __init__(self, plant: Any):
        self.plant = plant

    def connect(self) -> None:
        """The plant is always there."""

    def read(self):
        return self.plant.read()

    def write(self, command: Command) -> None:
        self.plant.apply(command)
        self.plant.advance()

    def close(self) -> None:
        """Nothing to release."""


def sidecar_path(log: Path) -> Path:
    return log.with_suffix(log.suffix + ".json")


def _base_mapping(config_file: str | None) -> tuple[dict, Path]:
    if not config_file:
        return {}, Path(".")
    path = Path(config_file)
    try:
        return tomllib.loads(path.read_text()), path.parent
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None


def experiment_config(base: dict, base_dir: Path, log: Path, controller: str, settings: dict, ticks: int,
                      reference: dict, simulated: bool):
    """The daemon configuration of an experiment: ``base`` (a daemon configuration's mapping) with
    the log, the controller, the sample count and no HTTP API."""
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    data["log"] = {**data.get("log", {}), "path": str(log.resolve()), "fsync": False}
    data["api"] = {"enabled": False}
    loop = {**data.get("loop", {}), "max_ticks": int(ticks)}
    if simulated:
        loop.update({"speedup": "max", "deadline_s": SIMULATED_DEADLINE_S})
    data["loop"] = loop
    ctrl = {**data.get("controller", {}), "name": controller, "settings": settings}
    if controller == EXCITATION_CONTROLLER:
        ctrl["fallback"] = []
    data["controller"] = ctrl
    data["reference"] = reference
    data.pop("faults", None)
    return config_from_mapping(data, base_dir=base_dir)


def run_daemon(config, backend, schedule: Callable[[float], Any] | None, initial_command: Command | None,
               monitor=None) -> Daemon:
    """Run the daemon until its sample count and shutdown are done; ``schedule(t)`` gives the
    reference for sample time t (None: the configured one throughout)."""
    def feed(d: Daemon, _sample: dict) -> None:
        ref = schedule(d.time_s)
        if ref != d.get_reference():
            d.set_reference(ref)

    daemon = Daemon(config, backend=backend, tick_hook=feed if schedule else None,
                    initial_command=initial_command, monitor=monitor)
    if schedule is not None:
        daemon.set_reference(schedule(daemon.time_s))
    daemon.run()
    return daemon


def simulated_plant(scenario: scenario_defs.Scenario | None, seed: int, variant: str | None,
                    initial_command: Command, inlet_temp_c: float, chiller_setpoint_c: float):
    """The plant of a simulated experiment: the bench's for a scenario, or the independent box."""
    if variant:
        from hvac_mpc.mismatch import make_plant
        return make_plant(variant, seed=seed, inlet_temp_c=inlet_temp_c, chiller_setpoint_c=chiller_setpoint_c,
                          initial_command=initial_command)
    plant_params, _ = perturb_parameters(Parameters(), seed)
    if scenario is None:
        return SimulatedPlant(plant_params, effects=PLANT_EFFECTS, seed=plant_seed(seed, 0),
                              environment=Environment(inlet_temp_c, chiller_setpoint_c), initial_command=initial_command)
    return scenario_plant(scenario, plant_params, seed)


# ---------------------------------------------------------------------------- CLI
def configure(parser: argparse.ArgumentParser) -> None:
    names = list(scenario_defs.all_scenarios())
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--scenario", metavar="NAME", help=f"a bench scenario: {', '.join(names)}")
    what.add_argument("--excitation", choices=("steps", "prbs", "multisine"),
                      help="an identification excitation (open loop through the safety layer)")
    parser.add_argument("--controller", choices=CONTROLLERS, default="mpc",
                        help="controller for a scenario (default: mpc)")
    parser.add_argument("--log", required=True, metavar="CSV", help="the daemon log to write (must not exist)")
    parser.add_argument("--quick", action="store_true", help="the scenario's short version")
    parser.add_argument("--seed", type=int, default=0, metavar="N",
                        help="plant perturbation and noise seed, as in hvac-mpc bench (default: 0)")
    parser.add_argument("--duration", type=float, default=1800.0, metavar="S",
                        help="excitation length in seconds (default: 1800)")
    parser.add_argument("--hold", type=float, nargs=2, default=(20.0, 120.0), metavar=("MIN_S", "MAX_S"),
                        help="excitation hold times (default: 20 120)")
    parser.add_argument("--inlet", type=float, default=28.0, metavar="C",
                        help="inlet air of a simulated excitation (default: 28 C)")
    parser.add_argument("--chiller", type=float, default=5.0, metavar="C",
                        help="chiller set point of a simulated excitation (default: 5 C)")
    parser.add_argument("--plant", metavar="VARIANT", default=None,
                        help="simulate the independent box of hvac_mpc.mismatch with this variant "
                             "(e.g. blower_weak) instead of the bench's plant")
    parser.add_argument("--config", metavar="TOML", default=None,
                        help="a daemon configuration: its backend (e.g. the lab's Modbus box) and safety settings")


def run(args: argparse.Namespace) -> int:
    log = Path(args.log)
    if log.exists():
        print(f"hvac-mpc experiment: --log {log} exists; choose a new file", file=sys.stderr)
        return 2
    try:
        info = run_experiment(args, log)
    except (ValueError, ConfigError, BackendError) as exc:
        print(f"hvac-mpc experiment: {exc}", file=sys.stderr)
        return 2
    print(f"log: {log}  ({info['samples']} samples, {info['what']}); sidecar {sidecar_path(log)}")
    return 0


def run_experiment(args: argparse.Namespace, log: Path) -> dict:
    """Build the configuration, backend and schedule from the options, run, write the sidecar."""
    if args.seed < 0:
        raise ValueError(f"--seed must be an integer >= 0, got {args.seed}")
    base, base_dir = _base_mapping(args.config)
    simulated = args.config is None or base.get("backend", {}).get("kind", "simulated") == "simulated"
    log.parent.mkdir(parents=True, exist_ok=True)
    if args.scenario:
        sc = scenario_defs.select([args.scenario], quick=args.quick)[0]
        ticks = int(round(sc.duration_s))
        controller, settings, schedule = args.controller, {}, sc.reference_at
        initial = sc.initial_command
        reference = sc.reference_at(0.0).as_dict()
        inlet, chiller = sc.inlet_temp_c, sc.chiller_setpoint_c
        info = {"what": f"scenario {sc.name} with {controller}", "scenario": sc.name, "kind": sc.kind,
                "warmup_s": sc.metrics_start_s, "duration_s": sc.duration_s, "quick": bool(args.quick),
                "controller": controller, "description": sc.description, "inlet_temp_c": sc.inlet_temp_c,
                "chiller_setpoint_c": sc.chiller_setpoint_c, "scenario_seed": sc.seed}
    else:
        if not (math.isfinite(args.duration) and 60.0 <= args.duration <= 86400.0):
            raise ValueError(f"--duration = {args.duration} is outside the allowed range [60, 86400] s")
        sc = None
        ticks = int(round(args.duration))
        controller = EXCITATION_CONTROLLER
        settings = {"kind": args.excitation, "seed": int(args.seed), "duration_s": float(args.duration),
                    "hold_min_s": float(args.hold[0]), "hold_max_s": float(args.hold[1])}
        schedule = None
        initial = Command(150.0, 0.0, 50.0, 100.0, 100.0, 100.0)
        reference = {"supply_temp_c": 20.0, "volume_flow_m3s": 0.03}
        inlet, chiller = args.inlet, args.chiller
        info = {"what": f"{args.excitation} excitation", "excitation": settings, "controller": "excitation",
                "warmup_s": 0.0, "duration_s": float(args.duration)}
    if simulated:
        base = {**base, "backend": {"kind": "simulated"}}
    cfg = experiment_config(base, base_dir, log, controller, settings, ticks, reference, simulated)
    backend = None
    if simulated:
        backend = PlantBackend(simulated_plant(sc, args.seed, args.plant, initial, inlet, chiller))
    daemon = run_daemon(cfg, backend, schedule, initial if simulated else None)
    info.update({"samples": ticks, "seed": int(args.seed), "plant": (f"mismatch:{args.plant}" if args.plant else
                                                                      "bench" if simulated else cfg.backend.kind),
                 "exit_code": daemon.exit_code, "counters": daemon.status()["counters"]})
    sidecar_path(log).write_text(json.dumps(info, indent=2, default=str))
    return info
