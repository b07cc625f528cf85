"""Valve a's heating weight on a shifted valve-a curve: on the opening the model reads, not on the command.

A model file with a valve-a shift (``valve_a_shift_pct``, models/valves.py: positive acts less open) reads valve a's
curve at the command less the shift, so its shut valve is the command equal to the shift. The weight that holds valve
a low while heating (``Weights.valve_a_heating_per_pct2``) is on the stage output ``valve_a_pct`` against the
reference's valve-a row (``TrackingProblem.reference_vector``), which is that command (docs/identification.md, "The
variants that still lose, traced").
"""

from __future__ import annotations

import numpy as np
import pytest

from hvac_mpc.benchmarks import scenarios
from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S, plant_seed
from hvac_mpc.contract import Reference
from hvac_mpc.mismatch import make_plant
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import STAGE_OUTPUTS

#: The box's shift of every valve curve in the ``valve_shift`` variant (hvac_mpc.mismatch), % of travel.
BOX_SHIFT_PCT = 10.0
I_VALVE_A = STAGE_OUTPUTS.index("valve_a_pct")
REF = Reference.from_split(12.0, 0.011, (0.3, 0.5, 0.2))


def _shifted(shift_pct: float) -> Parameters:
    return Parameters(valve_a_shift_pct=shift_pct, valve_m_shift_pct=shift_pct, valve_f_shift_pct=shift_pct,
                      valve_w_shift_pct=shift_pct)


@pytest.mark.parametrize("shift_pct", [0.0, 9.97, -5.0])
def test_valve_a_reference_is_the_command_the_model_reads_shut(shift_pct):
    """The reference's valve-a row is the model's shift (0 % for the thesis curve), so the weighted residual of a
    command is its opening as the model reads it, the command less the shift; the other rows as before."""
    pb = MpcController(_shifted(shift_pct), settings=MpcSettings(deadline_s=3600.0)).problem
    ref = pb.reference_vector(REF)
    assert ref[I_VALVE_A] == pytest.approx(shift_pct)
    plain = MpcController(settings=MpcSettings(deadline_s=3600.0)).problem.reference_vector(REF)
    assert plain[I_VALVE_A] == 0.0
    np.testing.assert_array_equal(np.delete(ref, I_VALVE_A), np.delete(plain, I_VALVE_A))


def _valve_a_opening(variant: str, params: Parameters, shift_pct: float) -> tuple[np.ndarray, float]:
    """Mean opening of valve a as the box reads it (command less the box's shift, %) over the 12 C segment of full
    winter_heating_steps (120-300 s) and the thermocouple IAE (C s, scored part): the MPC with ``params`` on the
    independent box of ``variant``, noise seed 0."""
    sc = scenarios.select(["winter_heating_steps"], quick=False)[0]
    ctrl = MpcController(params, settings=MpcSettings(initial_command=sc.initial_command,
                                                      deadline_s=DETERMINISTIC_DEADLINE_S))
    plant = make_plant(variant, seed=plant_seed(0, sc.seed), dt_s=1.0, inlet_temp_c=sc.inlet_temp_c,
                       chiller_setpoint_c=sc.chiller_setpoint_c, initial_command=sc.initial_command)
    ctrl.reset(sc.initial_command)
    valve_a, iae = [], 0.0
    for k in range(int(sc.duration_s)):
        r = sc.reference_at(float(k))
        m, y = plant.read(), plant.truth()
        if k >= sc.metrics_start_s:
            iae += abs(y["supply_temp_c"] - r.supply_temp_c)
        u = np.asarray(ctrl.step(m, r).command.vector(), float)
        if 120 <= k < 300:
            valve_a.append(u[2] - shift_pct)
        plant.apply(u)
        plant.advance()
    return float(np.mean(valve_a)), iae


@pytest.mark.slow
def test_a_model_shifted_as_the_box_is_holds_the_unshifted_pair_s_opening():
    """The independent box (hvac_mpc.mismatch) with every valve curve moved 10 % of travel (``valve_shift``), the MPC
    with those shifts (thesis parameters otherwise), against the nominal box with the thesis MPC, full
    winter_heating_steps: where valve a's weight decides the rest (the 12 C segment, the heater not limiting) the
    shifted pair holds valve a at the unshifted pair's opening. Measured: 41.1 against 42.6 % (weighted on the
    command: 31.1 %, the shut valve weighed as 10 % open), IAE 102.3 against 101.9 C s (94.3 on the command). Valves
    m, f, w reach their stops at other openings (100 % less the shift), so the pair is not the same to the digit."""
    plain, plain_iae = _valve_a_opening("nominal", Parameters(), 0.0)
    shifted, shifted_iae = _valve_a_opening("valve_shift", _shifted(BOX_SHIFT_PCT), BOX_SHIFT_PCT)
    assert abs(shifted - plain) < 4.0, (shifted, plain)
    assert abs(shifted_iae - plain_iae) < 0.05 * plain_iae, (shifted_iae, plain_iae)
