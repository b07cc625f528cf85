"""The model monitor's residuals on healthy boxes and on boxes carrying an effect, through the daemon.

``python -m hvac_mpc.benchmarks.monitor_bounds`` runs the daemon (simulated backend, the bench's
reference schedules) with the MPC and with the thesis baseline on

* ``bench``: the bench's own plant (parameters perturbed 5-10 % by the seed, all plant effects,
  sensor noise), the plant ``hvac-mpc experiment`` runs;
* ``builtin``: the built-in plant with the nominal parameters (all plant effects, sensor noise);
* ``nominal``: the independent box of :mod:`hvac_mpc.mismatch`, nominal variant;
* any other variant of :mod:`hvac_mpc.mismatch` (``--effects``), boxes that carry an effect,

and records what the model monitor (:mod:`hvac_mpc.daemon.monitor`) sees: per signal the largest
one-step residual and the largest one-step RMS over a window, the largest horizon RMS, the time of
the first ``degraded`` and of the first evaluation beyond a bound. The monitor's default bounds are
set from the healthy maxima this prints (docs/real-box.md, model monitoring).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from hvac_mpc.daemon.loop import Daemon
from hvac_mpc.daemon.monitor import MONITORED, MonitorSettings
from hvac_mpc.models.parameters import Parameters

from . import scenarios as scenario_defs
from .experiment import PlantBackend, experiment_config, simulated_plant
from .simulate import scenario_plant

#: Plants of a healthy box: the bench's (perturbed), the built-in nominal one, the independent nominal box.
HEALTHY = ("bench", "builtin", "nominal")
#: Boxes that carry an effect the built-in model does not have (hvac_mpc.mismatch variants).
EFFECTS = ("blower_weak", "delay_3s", "duct_loss", "valve_shift", "heater_weak", "tc_slow", "cooler_literal")
SCENARIOS = ("summer_cooling_steps", "winter_heating_steps", "flow_split_changes")
CONTROLLERS = ("baseline", "mpc")


def make_plant(kind: str, sc: scenario_defs.Scenario, seed: int):
    """The plant ``kind`` (see the module docstring) for scenario ``sc`` and noise seed ``seed``."""
    if kind == "bench":
        return simulated_plant(sc, seed, None, sc.initial_command, sc.inlet_temp_c, sc.chiller_setpoint_c)
    if kind == "builtin":
        return scenario_plant(sc, Parameters(), seed)
    return simulated_plant(sc, seed, kind, sc.initial_command, sc.inlet_temp_c, sc.chiller_setpoint_c)


def run_one(kind: str, scenario: str, controller: str, seed: int = 0, quick: bool = False,
            settings: MonitorSettings | None = None, workdir: Path | None = None) -> dict[str, Any]:
    """One daemon run of ``scenario`` with ``controller`` on plant ``kind``; the monitor's record."""
    sc = scenario_defs.select([scenario], quick=quick)[0]
    settings = settings or MonitorSettings()
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        log = Path(tmp) / "log.csv"
        cfg = experiment_config({"backend": {"kind": "simulated"}}, Path(tmp), log, controller, {},
                                int(round(sc.duration_s)), sc.reference_at(0.0).as_dict(), True)
        one: dict[str, list[float]] = {o: [] for o in MONITORED}
        degraded_at: list[float] = []
        steps: list[float] = []

        def hook(d: Daemon, _sample: dict) -> None:
            ref = sc.reference_at(d.time_s)
            if ref != d.get_reference():
                d.set_reference(ref)
                steps.append(d.time_s)
            mon = d.models.current.monitor
            for o in MONITORED:
                v = mon.one_step[o]
                one[o].append(math.nan if v is None else v)
            if mon.degraded and not degraded_at:
                degraded_at.append(d.time_s)

        daemon = Daemon(cfg, backend=PlantBackend(make_plant(kind, sc, seed)), tick_hook=hook,
                        initial_command=sc.initial_command, monitor=settings)
        daemon.set_reference(sc.reference_at(daemon.time_s))
        daemon.run()
        mon = daemon.models.current.monitor
    return summarise(kind, scenario, controller, seed, one, mon, degraded_at[0] if degraded_at else None, steps)


def summarise(kind: str, scenario: str, controller: str, seed: int, one: dict[str, list[float]],
              monitor: Any, degraded_at: float | None, steps: list[float]) -> dict:
    """Per signal: largest |one-step residual|, largest one-step RMS and horizon RMS over the
    monitor's evaluations (and when), the largest horizon RMS of the evaluations whose window holds no
    reference step (what a hold-off of one window after each step would leave), the first
    evaluation beyond a bound; and every evaluation (time, horizon RMS, one-step RMS) per signal."""
    settings = monitor.settings
    out: dict[str, Any] = {"plant": kind, "scenario": scenario, "controller": controller, "seed": seed,
                           "degraded_at_s": degraded_at, "evaluations": monitor.evaluations, "steps_s": steps,
                           "signals": {}}
    one_hist = dict(monitor.one_step_rms_history)
    for o in MONITORED:
        r = np.asarray(one[o], dtype=float)
        hz = [(t, h[o], one_hist.get(t, {}).get(o)) for t, h in monitor.horizon_rms_history]
        worst = max(((t, v) for t, v, _ in hz if v is not None), key=lambda x: x[1], default=(None, None))
        settled = [v for t, v, _ in hz if v is not None and not any(t - settings.horizon_s <= ts <= t for ts in steps)]
        beyond = next((t for t, v, w in hz if (v is not None and v > settings.bounds[o])
                       or (w is not None and w > settings.one_step_bounds[o])), None)
        out["signals"][o] = {"one_step_max": float(np.nanmax(np.abs(r))) if np.isfinite(r).any() else None,
                             "one_step_rms_max": max((w for _, _, w in hz if w is not None), default=None),
                             "horizon_rms_max": worst[1], "horizon_rms_max_at_s": worst[0],
                             "horizon_rms_max_settled": max(settled, default=None),
                             "first_beyond_s": beyond, "history": hz}
    return out


def run_all(plants, scenarios, controllers, seeds, quick=False, settings=None) -> list[dict]:
    rows = []
    for kind in plants:
        for sc in scenarios:
            for ctrl in controllers:
                for seed in seeds:
                    rows.append(run_one(kind, sc, ctrl, seed, quick, settings))
                    print(format_row(rows[-1]), flush=True)
    return rows


def _f(v: float | None, digits: int = 4) -> str:
    return "-" if v is None else f"{v:.{digits}g}"


def format_row(r: dict) -> str:
    s = r["signals"]
    cells = [f"{o.split('_')[0]} 1s {_f(s[o]['one_step_max'], 3)} 1sRMS {_f(s[o]['one_step_rms_max'], 3)} "
             f"hz {_f(s[o]['horizon_rms_max'], 3)}@{_f(s[o]['horizon_rms_max_at_s'], 4)} "
             f"settled {_f(s[o].get('horizon_rms_max_settled'), 3)}" for o in MONITORED]
    return (f"{r['plant']:>14} {r['scenario']:>22} {r['controller']:>8} s{r['seed']} "
            f"degraded@{_f(r['degraded_at_s'])} beyond@{_f(min((s[o]['first_beyond_s'] for o in MONITORED if s[o]['first_beyond_s'] is not None), default=None))} | " + " | ".join(cells))


def healthy_maxima(rows: list[dict]) -> dict[str, dict[str, float]]:
    """The largest of each statistic per signal over the rows."""
    out = {}
    for o in MONITORED:
        out[o] = {k: max((r["signals"][o][k] for r in rows if r["signals"][o][k] is not None), default=math.nan)
                  for k in ("one_step_max", "one_step_rms_max", "horizon_rms_max")}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plants", nargs="*", default=list(HEALTHY))
    ap.add_argument("--effects", nargs="*", default=list(EFFECTS))
    ap.add_argument("--scenarios", nargs="*", default=list(SCENARIOS))
    ap.add_argument("--controllers", nargs="*", default=list(CONTROLLERS))
    ap.add_argument("--seeds", nargs="*", type=int, default=[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", metavar="FILE", help="write every run's record (with every evaluation) here")
    args = ap.parse_args(argv)
    logging.getLogger("hvac_mpc.daemon").setLevel(logging.ERROR)
    healthy = run_all(args.plants, args.scenarios, args.controllers, args.seeds, args.quick)
    print("healthy maxima:", json.dumps(healthy_maxima(healthy)))
    effects = run_all(args.effects, args.scenarios, args.controllers, args.seeds, args.quick)
    if args.json:
        Path(args.json).write_text(json.dumps({"healthy": healthy, "effects": effects}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
