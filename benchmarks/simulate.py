"""Closed loop of one controller on the simulated plant for one scenario, recorded sample by sample.

Per sample k (time k dt): read the sensors, record the noise-free truth, ask the controller for a
command (wall time measured around ``step``, BOPTEST's tic/tac view), apply it, advance the plant.
The plant's noise comes from its own seeded generator, one draw per reading, so two controllers on
the same scenario and seed see the same noise sequence.

The plant is the built-in :class:`SimulatedPlant` unless the caller hands one in (the seam of
``hvac-mpc bench --plant MODULE:FACTORY`` and of the mismatch suite, :mod:`.plant_seam`): any object
with ``apply``/``advance``/``read`` (the ``Plant`` protocol of ``hvac_mpc.contract``). Its
``set_environment`` and ``settle`` are used when it has them; without ``truth()`` the figures fall
back to the sensor readings.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from hvac_mpc.models.box import INPUT_LOWER, INPUTS, input_upper
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.models.plant import PLANT_EFFECTS, Environment, SimulatedPlant

from hvac_mpc.daemon.controllers import reset_controller

from .scenarios import Scenario

#: MpcSettings.deadline_s for simulated runs (bench, mismatch suite, sweeps, replays): the largest the
#: settings accept (1 h), so no solution is discarded for its wall time and OSQP's time limit never
#: binds; the iteration caps (osqp_max_iter, cold_start_qps, reference_change_qps) bound each step
#: instead, and a run gives the same figures on a loaded machine as on an idle one.
DETERMINISTIC_DEADLINE_S = 3600.0

#: Reference fields recorded per sample (NaN where the split is free).
REFERENCE_FIELDS = ("supply_temp_c", "volume_flow_m3s", "flow_m_m3s", "flow_f_m3s", "flow_w_m3s")
#: Noise-free plant outputs recorded per sample (``SimulatedPlant.truth()`` names).
TRUTH_FIELDS = ("supply_temp_c", "supply_air_temp_c", "volume_flow_m3s", "flow_m_m3s", "flow_f_m3s",
                "flow_w_m3s", "heater_temp_c", "heater_power_w", "heater_outlet_temp_c", "water_temp_c")
#: Sensor readings recorded per sample (``Measurement`` names; NaN where a plant does not measure one).
MEASURED_FIELDS = ("supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c", "cabin_temp_c")


@dataclass
class Trace:
    """Sampled record of one run; arrays of length n (commands n x 6 in ``INPUTS`` order)."""

    scenario: str
    controller: str
    dt_s: float
    time_s: np.ndarray
    reference: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    measured: dict[str, np.ndarray]
    requested: np.ndarray
    applied: np.ndarray
    step_time_s: np.ndarray
    fallback: list
    mode: list
    status: list
    metrics_start_s: float
    environment: dict = field(default_factory=dict)
    #: per sample: the controller's ``stats["out_of_reach"]`` (reference name -> shortfall) or None
    out_of_reach: list = field(default_factory=list)

    @property
    def actuators(self) -> tuple[str, ...]:
        return INPUTS


def plant_seed(seed: int, scenario_seed: int) -> int:
    """Noise seed of the plant for a benchmark seed and a scenario seed (independent streams)."""
    return int(np.random.SeedSequence([int(seed), int(scenario_seed)]).generate_state(1)[0])


def actuator_bounds(params: Parameters | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper actuator bounds in ``INPUTS`` order (docs/model.md sec. 2)."""
    params = params or Parameters()
    up = input_upper(params)
    return np.array([INPUT_LOWER[n] for n in INPUTS]), np.array([up[n] for n in INPUTS])


def prepare_plant(plant, scenario: Scenario) -> None:
    """Put an external plant into the scenario's conditions: environment and rest for the initial
    command when it can (``set_environment``, ``settle``), else just apply the initial command."""
    if callable(getattr(plant, "set_environment", None)):
        plant.set_environment(scenario.inlet_temp_c, scenario.chiller_setpoint_c)
    if callable(getattr(plant, "settle", None)):
        plant.settle(scenario.initial_command)
    else:
        plant.apply(scenario.initial_command)


def plant_outputs(plant, measurement) -> dict[str, float]:
    """Noise-free outputs for the figures: ``truth()`` where the plant has it, each missing name from
    the sensor reading of the same quantity (the mixed air from the supply reading), else NaN."""
    truth_fn = getattr(plant, "truth", None)
    y = dict(truth_fn()) if callable(truth_fn) else {}
    read = {f: getattr(measurement, f, None) for f in TRUTH_FIELDS}
    read["supply_air_temp_c"] = measurement.supply_temp_c
    out = {}
    for f in TRUTH_FIELDS:
        v = y.get(f, read.get(f))
        out[f] = np.nan if v is None else float(v)
    return out


def simulate(scenario: Scenario, controller, plant_params: Parameters, seed: int, name: str = "controller",
             progress: Callable[[int, int], None] | None = None, dt_s: float = 1.0, plant=None) -> Trace:
    """Run ``controller`` (Controller protocol) through ``scenario`` on a plant with ``plant_params``.

    All plant effects are on (``PLANT_EFFECTS``). ``plant``: a fresh external plant (``Plant``
    protocol) to run on instead; it is put into the scenario's conditions (:func:`prepare_plant`)
    and ``plant_params`` is not used. A command with a non-finite value is recorded as requested
    and the previous command is held. ``progress(k, n)`` is called every sample.
    """
    if abs(getattr(controller, "dt_s", dt_s) - dt_s) > 1e-9:
        raise ValueError(f"controller {name}: sample time {controller.dt_s} s differs from the plant's {dt_s} s")
    if plant is None:
        plant = SimulatedPlant(plant_params, effects=PLANT_EFFECTS, seed=plant_seed(seed, scenario.seed),
                               dt_s=dt_s, environment=Environment(scenario.inlet_temp_c, scenario.chiller_setpoint_c),
                               initial_command=scenario.initial_command)
    else:
        if abs(float(getattr(plant, "dt_s", dt_s)) - dt_s) > 1e-9:
            raise ValueError(f"plant: sample time {plant.dt_s} s differs from the benchmark's {dt_s} s")
        prepare_plant(plant, scenario)
    plant = couple_cabin(scenario, plant)
    reset_controller(controller, scenario.initial_command)  # bumpless from the command in force, as the daemon
    n = int(round(scenario.duration_s / dt_s))
    ref = {f: np.full(n, np.nan) for f in REFERENCE_FIELDS}
    truth = {f: np.full(n, np.nan) for f in TRUTH_FIELDS}
    meas = {f: np.full(n, np.nan) for f in MEASURED_FIELDS}
    requested = np.full((n, len(INPUTS)), np.nan)
    applied = np.full((n, len(INPUTS)), np.nan)
    step_time = np.zeros(n)
    fallback: list = [None] * n
    mode: list = [None] * n
    status: list = [None] * n
    out_of_reach: list = [None] * n
    for k in range(n):
        t = k * dt_s
        r = scenario.reference_at(t)
        for f in REFERENCE_FIELDS:
            v = getattr(r, f)
            ref[f][k] = np.nan if v is None else v
        m = plant.read()
        y = plant_outputs(plant, m)
        for f in TRUTH_FIELDS:
            truth[f][k] = y[f]
        for f in MEASURED_FIELDS:
            v = getattr(m, f, None)
            meas[f][k] = np.nan if v is None else v
        tic = time.perf_counter()
        try:
            result = controller.step(m, r)
        except Exception as exc:  # the benchmark names the run that failed
            raise RuntimeError(f"controller {name} raised at t = {t:.0f} s in scenario {scenario.name}: {exc!r}") from exc
        step_time[k] = time.perf_counter() - tic
        u = np.asarray(result.command.vector(), float)
        requested[k] = u
        stats = result.stats or {}
        fallback[k] = stats.get("fallback")
        mode[k] = stats.get("mode")
        status[k] = stats.get("status")
        out_of_reach[k] = stats.get("out_of_reach") or None
        if np.all(np.isfinite(u)):
            applied[k] = plant.apply(u)
        else:
            applied[k] = plant.command.vector()
        plant.advance()
        if progress is not None:
            progress(k + 1, n)
    return Trace(scenario=scenario.name, controller=name, dt_s=dt_s, time_s=np.arange(n) * dt_s, reference=ref,
                 truth=truth, measured=meas, requested=requested, applied=applied, step_time_s=step_time,
                 fallback=fallback, mode=mode, status=status, out_of_reach=out_of_reach,
                 metrics_start_s=scenario.metrics_start_s,
                 environment={"inlet_temp_c": scenario.inlet_temp_c,
                              "chiller_setpoint_c": scenario.chiller_setpoint_c})



def couple_cabin(scenario: Scenario, plant):
    """The plant with the scenario's cabin feeding its inlet (``scenario.cabin``), or the plant itself."""
    if getattr(scenario, "cabin", None) is None:
        return plant
    from hvac_mpc.mismatch.cabin import CabinLoop

    return CabinLoop(plant, scenario.cabin)


def scenario_plant(scenario: Scenario, plant_params: Parameters, seed: int, dt_s: float = 1.0):
    """The plant :func:`simulate` runs for ``scenario`` and benchmark ``seed`` (for runs outside it,
    e.g. the same plant behind the daemon in ``hvac-mpc experiment``)."""
    plant = SimulatedPlant(plant_params, effects=PLANT_EFFECTS, seed=plant_seed(seed, scenario.seed), dt_s=dt_s,
                           environment=Environment(scenario.inlet_temp_c, scenario.chiller_setpoint_c),
                           initial_command=scenario.initial_command)
    return couple_cabin(scenario, plant)
