"""One closed-loop run of a sweep: build the plant and controller from a :class:`RunSpec`, simulate,
and return one result row (every input, every figure, or the error), docs/sweep.md.

Runs are deterministic: the MPC runs with iteration caps only (its wall-clock deadline at the
largest allowed value, :data:`DETERMINISTIC_DEADLINE_S`), so a row replays to the same figures;
the step-time figures (:data:`TIMING_KPIS`) are reported but depend on the machine.

Building an MPC (CasADi functions, OSQP setup) costs about as much as a short run, so each
process keeps the controllers it built in a :class:`ControllerCache`, one per structure and
settings, and makes a reused controller start like a fresh one (:func:`fresh_start`).
"""

from __future__ import annotations

import json
import math
import os
import socket
import time
import traceback
from collections import OrderedDict

import numpy as np

from hvac_mpc.models.parameters import Parameters

from . import metrics
from .simulate import DETERMINISTIC_DEADLINE_S, actuator_bounds, plant_seed, simulate
from .sweep_spec import RunSpec, file_hash, scenario_of

DT_S = 1.0

#: Figures of ``metrics.run_figures`` stored per run (its flat ``figures``), plus the sweep's own.
FIGURE_KPIS = ("temp_iae_cs", "air_temp_iae_cs", "ideal_temp_iae_cs", "ideal_temp_time_to_band_max_s", "temp_steps",
               "temp_unsettled", "temp_time_to_band_median_s", "temp_time_to_band_max_s", "temp_overshoot_max_c",
               "flow_iae_m3", "flow_steps", "flow_unsettled", "flow_time_to_band_median_s",
               "flow_time_to_band_max_s", "outlet_rms_m3s", "blower_wh", "heater_wh", "travel_mean",
               "violations_bounds", "violations_heater_temp", "violations_heater_low_flow", "step_median_ms",
               "step_p99_ms", "time_ratio", "fallbacks", "energy_wh", "violations_total")
#: Share of the scored time the supply temperature is within +-metrics.TEMP_BAND_C of its reference.
BAND_KPI = "temp_within_band_frac"
KPIS = FIGURE_KPIS + (BAND_KPI,)
#: Wall-clock figures: reported, not part of the exact replay comparison.
TIMING_KPIS = ("step_median_ms", "step_p99_ms", "time_ratio")
#: Input columns of a result row (``RunSpec`` fields; weights and horizon as JSON text).
INPUT_COLUMNS = ("scenario", "length", "max_duration_s", "seed", "plant", "inlet_temp_c", "controller", "weights",
                 "stage_durations_s", "model_file", "model_hash")


# ---------------------------------------------------------------------------- controllers
class ControllerCache:
    """Controllers built in this process, by everything that shapes them (least recently used dropped)."""

    def __init__(self, size: int = 32):
        self.size = int(size)
        self._items: OrderedDict[str, object] = OrderedDict()
        self.builds = 0

    def get(self, key: str, build):
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        ctrl = build()
        self.builds += 1
        self._items[key] = ctrl
        if len(self._items) > self.size:
            self._items.popitem(last=False)
        return ctrl


def fresh_start(ctrl) -> None:
    """Make a reused controller start as a fresh one would.

    ``MpcController.reset()`` clears estimates and plans but keeps the OSQP workspace (its dual
    warm start and adapted step size) and the fallback baseline's loop state; both change the
    iterates of the next run. A new OSQP setup (about 2 ms) and a baseline reset remove them.
    """
    solver = getattr(ctrl, "solver", None)
    if solver is not None and callable(getattr(solver, "_setup_osqp", None)):
        solver._setup_osqp()
    fallback = getattr(ctrl, "_baseline", None)
    if fallback is not None:
        fallback.reset()
    ctrl.reset()


def controller_params(run: RunSpec) -> Parameters:
    """The controllers' parameters: nominal, or the run's model file (checked against its hash)."""
    if run.model_file is None:
        return Parameters()
    from hvac_mpc.identification.model_file import load_model_file

    found = file_hash(run.model_file)
    if found != run.model_hash:
        raise RuntimeError(f"model file {run.model_file} changed since the sweep was planned "
                           f"(hash {found[:12]}, expected {run.model_hash[:12]})")
    return load_model_file(run.model_file)[0]


def mpc_settings(run: RunSpec, initial_command):
    """The MPC's settings for a run: its weights and horizon, deterministic budgets."""
    from dataclasses import replace

    from hvac_mpc.mpc.mpc_controller import MpcSettings
    from hvac_mpc.mpc.ocp import OcpSpec, Weights

    ocp = OcpSpec(weights=Weights(**run.weights))
    if run.stage_durations_s is not None:
        ocp = replace(ocp, stage_durations_s=tuple(run.stage_durations_s))
    return MpcSettings(dt_s=DT_S, ocp=ocp, deadline_s=DETERMINISTIC_DEADLINE_S, initial_command=initial_command)


def build_controller(run: RunSpec, scenario, cache: ControllerCache):
    """The run's controller from ``cache`` (built on first use), ready for a fresh run."""
    key = json.dumps({"controller": run.controller, "weights": run.weights, "stages": run.stage_durations_s,
                      "model": run.model_hash, "initial": list(scenario.initial_command.vector())}, sort_keys=True)
    params = controller_params(run)
    if run.controller == "mpc":
        from hvac_mpc.mpc.mpc_controller import MpcController

        settings = mpc_settings(run, scenario.initial_command)
        ctrl = cache.get(key, lambda: MpcController(params, settings))
    else:
        from hvac_mpc.mpc.baseline import BaselineController

        ctrl = cache.get(key, lambda: BaselineController(params, dt_s=DT_S))
    fresh_start(ctrl)
    return ctrl


# ---------------------------------------------------------------------------- plants
def build_plant(run: RunSpec, scenario):
    """``(plant or None, plant_params, sensor_tau_s)``: None means simulate() builds its SimulatedPlant."""
    if run.plant == "simulated":
        p = Parameters()
        return None, p, p.tau_tc_s
    if run.plant == "simulated_perturbed":
        from .perturbation import perturb_parameters

        p = perturb_parameters(Parameters(), run.seed)[0]
        return None, p, p.tau_tc_s
    from hvac_mpc.mismatch import VARIANTS, make_plant
    from hvac_mpc.mismatch.constants import THERMOCOUPLE_TAU_S

    plant = make_plant(run.plant, seed=plant_seed(run.seed, scenario.seed), dt_s=DT_S,
                       inlet_temp_c=scenario.inlet_temp_c, chiller_setpoint_c=scenario.chiller_setpoint_c,
                       initial_command=scenario.initial_command)
    return plant, Parameters(), THERMOCOUPLE_TAU_S * VARIANTS[run.plant].thermocouple_tau_scale


# ---------------------------------------------------------------------------- one run
def within_band_fraction(trace) -> float:
    """Share of scored samples with |supply temperature - reference| <= metrics.TEMP_BAND_C."""
    k0 = int(np.searchsorted(trace.time_s, trace.metrics_start_s - 1e-9))
    e = trace.truth["supply_temp_c"][k0:] - trace.reference["supply_temp_c"][k0:]
    ok = np.isfinite(e)
    return float(np.mean(np.abs(e[ok]) <= metrics.TEMP_BAND_C)) if ok.any() else math.nan


def figures_of(run: RunSpec, cache: ControllerCache) -> dict:
    """Simulate one run and return its KPIs (:data:`KPIS`)."""
    sc = scenario_of(run)
    plant, plant_params, tau_s = build_plant(run, sc)
    ctrl = build_controller(run, sc, cache)
    trace = simulate(sc, ctrl, plant_params, run.seed, name=run.controller, dt_s=DT_S, plant=plant)
    nominal = Parameters()
    lower, upper = actuator_bounds(nominal)
    fig = metrics.run_figures(trace, lower, upper, nominal.heater_temp_max_c, nominal.trap_threshold_pct, tau_s)
    out = {k: fig["figures"].get(k) for k in FIGURE_KPIS}
    out[BAND_KPI] = within_band_fraction(trace)
    return out


def input_columns(run: RunSpec) -> dict:
    """The run's inputs as result columns (weights and horizon as JSON text)."""
    d = run.inputs()
    d["weights"] = json.dumps(d["weights"], sort_keys=True)
    d["stage_durations_s"] = None if d["stage_durations_s"] is None else json.dumps(d["stage_durations_s"])
    return {k: d[k] for k in INPUT_COLUMNS}


def run_from_row(row: dict) -> RunSpec:
    """The :class:`RunSpec` of a result row (inverse of :func:`input_columns`)."""
    d = {k: row[k] for k in INPUT_COLUMNS}
    d["weights"] = json.loads(d["weights"] or "{}")
    d["stage_durations_s"] = None if d["stage_durations_s"] is None else tuple(json.loads(d["stage_durations_s"]))
    for k in ("max_duration_s", "inlet_temp_c"):
        if d[k] is not None and isinstance(d[k], float) and math.isnan(d[k]):
            d[k] = None
    return RunSpec(**d)


_PROCESS_CACHE = ControllerCache()


def execute(inputs: dict, cache: ControllerCache | None = None) -> dict:
    """One result row for a run (``RunSpec`` fields as plain data); never raises.

    A run that raises gives a row with ``error`` set and no figures. ``cache`` defaults to one per
    process (each Dask worker keeps its own).
    """
    cache = _PROCESS_CACHE if cache is None else cache
    t0 = time.perf_counter()
    run = RunSpec(**inputs)
    row = {"run_id": run.run_id, **input_columns(run), "pair_key": run.pair_key()}
    error = None
    try:
        kpis = figures_of(run, cache)
    except Exception as exc:  # noqa: BLE001 - a failing run is a result, recorded with its error
        kpis = {k: None for k in KPIS}
        error = f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"
    row.update({k: _number(v) for k, v in kpis.items()})
    row.update({"error": error, "elapsed_s": time.perf_counter() - t0, "host": f"{socket.gethostname()}:{os.getpid()}"})
    return row


def _number(v) -> float | None:
    return None if v is None else float(v)


def differing_kpis(a: dict, b: dict) -> list[str]:
    """Names of the KPIs (all but :data:`TIMING_KPIS`) that differ between two rows (NaN equals NaN)."""
    diff = []
    for k in KPIS:
        if k in TIMING_KPIS:
            continue
        x, y = a.get(k), b.get(k)
        if x is None or y is None:
            if (x is None) != (y is None):
                diff.append(k)
        elif not (x == y or (math.isnan(x) and math.isnan(y))):
            diff.append(k)
    if (a.get("error") is None) != (b.get("error") is None):
        diff.append("error")
    return diff
