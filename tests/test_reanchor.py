"""States the readings do not tell apart, re-anchored to an open-loop shadow of their physics until and once a dead
time is found (``EkfSettings.reanchor_states``, :mod:`hvac_mpc.mpc.reanchor`; docs/robustness.md sec. 2.9).

Truth is the independent box (``hvac_mpc.mismatch``, its own equations and delay line). Budget: the open-loop runs
a few seconds together (no solver); the closed loop is marked slow.
"""

import numpy as np
import pytest

from ekf_helpers import SETPOINT_C, feed_open_loop
from hvac_mpc.contract import Command
from hvac_mpc.mismatch import make_plant
from hvac_mpc.models import HvacModel, Parameters
from hvac_mpc.mpc.estimator import DisturbanceEkf, EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc.reanchor import FilterLayout, reanchor

#: The filter without the re-anchor (the defaults hold the motor rise and the heater body, docs/robustness.md sec. 2.9),
#: all three here with the thermocouple weighed alike at rest and in transients (``r_supply_rest_c`` 0, as measured in
#: sec. 2.9; with the default rest gate of sec. 2.10 the filter without the re-anchor is 0.20 degC off from the second
#: step on, the gate taking part of the unwind) and the motor rise unbounded (``bound_motor_rise`` off, as measured in
#: sec. 2.9; the default bound of sec. 2.11 keeps the push this test undoes within [0, 2.4] degC): the tests are about
#: the re-anchor.
#: (The response wait off: it keeps the late response out of the states, docs/robustness.md sec. 2.17. The heat flow
#: into the mixed air off: released at the first response, it takes a share of the late response as well, which moves
#: the states' errors of delay_5s held from the start, 0.70 -> 1.01 degC in the heater body, sec. 2.29.)
HELD = EkfSettings(r_supply_rest_c=0.0, bound_motor_rise=False, response_wait_c=0.0, q_supply_heat_w=0.0)
PLAIN = EkfSettings(reanchor_states=(), r_supply_rest_c=0.0, bound_motor_rise=False, response_wait_c=0.0,
                    q_supply_heat_w=0.0)
#: ... and held from the start as well, until 20 s after the first response.
FROM_START = EkfSettings(reanchor_before_response=True, r_supply_rest_c=0.0, bound_motor_rise=False,
                         response_wait_c=0.0, q_supply_heat_w=0.0)
#: Valve-a openings held 40 s each (blower 150 W, outlets open, chiller 5 C, inlet 32 C), as tests/test_dead_time.py.
VALVE_A_STEPS = (40.0, 80.0, 55.0, 90.0, 30.0)
HOLD_S = 40


def run_open_loop(variant, settings: EkfSettings):
    """The filter fed open loop by the independent box; per sample (motor rise error, heater body error, dead time)
    against the box's own motor rise and heater body (degC, degC, s)."""
    plant = make_plant(variant, seed=3)
    plant.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
    commands = [Command(150.0, 0.0, a, 100.0, 100.0, 100.0) for a in VALVE_A_STEPS]
    plant.settle(commands[0])
    ekf = DisturbanceEkf(HvacModel(Parameters()), settings)
    i, j = ekf.model.states.index("motor_rise_c"), ekf.model.states.index("heater_temp_c")
    rows = []

    def record(e):
        truth = plant.truth()
        rows.append((e.x[i] - truth["motor_rise_c"], e.x[j] - truth["heater_temp_c"], e.dead_time_s))

    feed_open_loop(ekf, plant, commands, HOLD_S, record)
    return np.array(rows)


@pytest.mark.parametrize("variant, delay_s", [("delay_3s", 3.0), ("delay_5s", 5.0)])
def test_states_go_back_to_their_physics_once_the_dead_time_is_found(variant, delay_s):
    """Before the dead time is found (about 7 s after the first valve step, at 40 s), the step's late response goes
    into the motor rise and the heater body: 8.8 / 12.4 degC off the box's motor rise, 6.3 / 8.0 degC off its heater
    body (delay_3s / delay_5s). Without the re-anchor the motor rise is still 0.53 / 1.13 degC off from the second step
    on (its 268 s lag); re-anchored (the defaults) 0.25 / 0.28, the heater body within 0.48 / 0.68. Held from the
    start, the motor rise never leaves (0.24 / 0.27 over the whole run, the heater body 0.69 / 0.70). The dead time
    is found as before."""
    plain, held, start = (run_open_loop(variant, s) for s in (PLAIN, HELD, FROM_START))
    later = slice(2 * HOLD_S, None)
    assert np.max(np.abs(plain[:, 0])) > 5.0 and np.max(np.abs(plain[:, 1])) > 5.0  # the push it undoes
    assert np.max(np.abs(plain[later, 0])) > 0.5
    assert np.max(np.abs(held[later, 0])) < 0.35 and np.max(np.abs(held[later, 1])) < 1.0
    assert np.max(np.abs(start[:, 0])) < 0.35 and np.max(np.abs(start[:, 1])) < 1.0
    for run in (held, start):
        assert np.all(run[later, 2] == delay_s)


def test_without_a_dead_time_nothing_is_re_anchored():
    """On the box without a delay the re-anchor waits for a dead time, so the filter with it is the one without it
    exactly (without ``reanchor_before_response``): the re-anchor changes nothing where no dead time is found."""
    assert np.array_equal(run_open_loop("nominal", PLAIN), run_open_loop("nominal", HELD))


def test_the_re_anchor_moves_the_difference_into_the_offsets():
    """The states set to the shadow's values, the offsets take the change: the model's supply air and heater outlet
    reading, as the filter predicts them, do not move; the covariance stays symmetric and positive semidefinite and the
    moved states are independent of the rest."""
    ekf = DisturbanceEkf(HvacModel(Parameters()), EkfSettings())
    plant = make_plant("nominal", seed=0)
    u = Command(150.0, 600.0, 40.0, 100.0, 100.0, 100.0).vector()
    ekf.initialise(plant.read(), u, SETPOINT_C)
    m, i = ekf.model, ekf.model.states.index("motor_rise_c")
    ekf.z[i] -= 2.0  # a misplaced late response
    ekf.P[i, ekf.i_mix_offset] = ekf.P[ekf.i_mix_offset, i] = -0.05
    p = ekf.model_parameters()

    def disturbance():
        return m.d_vector(ekf.inlet_temp_c, SETPOINT_C, ekf.mix_offset_c, ekf.flow_offset_m3s)

    def seen():  # the supply air and the heater outlet reading the filter explains
        y = m.outputs.dict(m.y(ekf.x, u, disturbance(), p))
        return y["supply_air_temp_c"], y["heater_outlet_temp_c"] + ekf.z[ekf.i_outlet_offset]

    before = seen()
    layout = FilterLayout(ekf.nx, ekf.i_mix_offset, ekf.i_outlet_offset)
    change = reanchor(ekf.shadow, ekf.z, ekf.P, layout, np.array([0.1, 0.2]), u, disturbance(), p)
    assert ekf.z[i] == pytest.approx(ekf.shadow.values[0]) and change < -1.0
    assert np.allclose(seen(), before, atol=1e-9)
    assert np.allclose(ekf.P, ekf.P.T) and np.min(np.linalg.eigvalsh(ekf.P)) > -1e-12
    assert ekf.P[i, i] == pytest.approx(0.01) and np.count_nonzero(ekf.P[i]) == 1


def test_reanchor_settings_are_checked():
    for field, bad in (("reanchor_states", ("motor",)), ("reanchor_states", ["motor_rise_c"]),
                       ("reanchor_states", ("motor_rise_c", "motor_rise_c")), ("reanchor_hold_s", -1.0),
                       ("reanchor_hold_s", 7200.0), ("reanchor_hold_q_mix_c", -0.1),
                       ("reanchor_before_response", "yes")):
        with pytest.raises(InvalidSettings, match=f"ekf.{field}"):
            MpcSettings(ekf=EkfSettings(**{field: bad}))


@pytest.mark.slow
def test_flow_out_of_reach_on_a_long_dead_time_with_a_duct_loss_with_the_states_re_anchored():
    """The quick flow-out-of-reach cell on a box not in the suite (4 s dead time, duct loss 6 W/K, literal cooler
    fit; seed 0): 1.21 of the baseline's IAE without the re-anchor, 0.82 measured with the defaults."""
    from test_robust import UNLISTED_LONG_DELAY_LOSS_COOLER, assert_out_of_reach_cell

    assert_out_of_reach_cell(UNLISTED_LONG_DELAY_LOSS_COOLER, EkfSettings(), limit=0.9)
