"""Closed loop on the independent box (hvac_mpc.mismatch) for the tests of the heater body's value and readiness."""

import dataclasses

import numpy as np

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings


def body_at_step_and_iae(scenario_name: str, variant: str, settings: MpcSettings, model=None, step_s: int | None = None,
                         observe=None) -> tuple[float, float]:
    """The quick ``scenario_name`` on the box ``variant`` (noise seed 0) with an MPC of ``settings`` (its initial
    command and the deterministic deadline set here) and ``model`` (None: nominal): the box's heater body at the
    first scored sample (C) and the thermocouple IAE over the scored part (C s). ``step_s``: that sample and the start
    of the IAE instead (s); ``observe(controller)``: called after each of the controller's steps."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S, plant_seed
    from hvac_mpc.mismatch import make_plant

    sc = scenarios.select([scenario_name], quick=True)[0]
    step_s = int(sc.metrics_start_s) if step_s is None else int(step_s)
    settings = dataclasses.replace(settings, initial_command=sc.initial_command, deadline_s=DETERMINISTIC_DEADLINE_S)
    ctrl = MpcController(settings=settings, model=model)
    plant = make_plant(variant, seed=plant_seed(0, sc.seed), inlet_temp_c=sc.inlet_temp_c,
                       chiller_setpoint_c=sc.chiller_setpoint_c, initial_command=sc.initial_command)
    ctrl.reset(sc.initial_command)
    iae, body_at_step = 0.0, None
    for k in range(int(sc.duration_s)):
        r = sc.reference_at(float(k))
        m, truth = plant.read(), plant.truth()
        if k == step_s:
            body_at_step = truth["heater_temp_c"]
        if k >= step_s:
            iae += abs(truth["supply_temp_c"] - r.supply_temp_c)
        plant.apply(np.asarray(ctrl.step(m, r).command.vector(), float))
        plant.advance()
        if observe is not None:
            observe(ctrl)
    return body_at_step, iae
