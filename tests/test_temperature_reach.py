"""The supply temperature reported out of reach while the actuators that move it are saturated
(mpc/temperature_reach.py). Closed loop on the independent box: tests/test_robust.py."""

import numpy as np
import pytest

from hvac_mpc.contract import Command
from hvac_mpc.models.box import INPUTS
from hvac_mpc.mpc.temperature_reach import SaturatedTemperature

I_HEATER, I_VALVE_A = INPUTS.index("heater_cmd_w"), INPUTS.index("valve_a_pct")
U_HI = Command(200.0, 240.0, 90.0, 100.0, 100.0, 100.0).vector()  # valve a at a trapped-air cap of 90 %
HEATING_FULL = Command(35.0, 240.0, 90.0, 80.0, 60.0, 20.0).vector()
COOLING_FULL = Command(150.0, 0.0, 90.0, 80.0, 60.0, 20.0).vector()


def run(readings, reference_c, command, u_hi=U_HI):
    watch = SaturatedTemperature(I_HEATER, I_VALVE_A, dt_s=1.0)
    return [watch.update(r, reference_c, command, u_hi) for r in readings]


def test_a_steady_gap_with_the_heater_and_valve_a_at_their_limits_is_reported_after_the_hold():
    rng = np.random.default_rng(0)
    readings = 20.8 + 0.05 * rng.standard_normal(60)  # 1.2 C below 22 C, not closing in
    out = run(readings, 22.0, HEATING_FULL)
    assert all(v is None for v in out[:19])
    reported = [v for v in out[19:] if v is not None]
    assert len(reported) == len(out) - 19
    assert np.allclose(reported, 1.2, atol=0.1)


def test_a_heater_body_still_warming_up_is_not_out_of_reach():
    readings = 16.0 + 0.1 * np.arange(60)  # 6 C below, closing at 0.1 C/s: there in 60 s
    assert all(v is None for v in run(readings, 22.0, HEATING_FULL))


def test_a_slow_approach_that_would_not_arrive_within_the_outlook_is_reported():
    readings = 20.5 + 0.005 * np.arange(60)  # 0.3 C per minute from 1.5 C below
    out = run(readings, 22.0, HEATING_FULL)
    assert out[-1] is not None and out[-1] == pytest.approx(22.0 - readings[-5:].mean())


@pytest.mark.parametrize("actuator, value", [("heater_cmd_w", 200.0), ("valve_a_pct", 80.0)])
def test_an_actuator_below_its_limit_means_the_temperature_is_not_out_of_reach(actuator, value):
    command = HEATING_FULL.copy()
    command[INPUTS.index(actuator)] = value
    assert all(v is None for v in run(np.full(60, 20.8), 22.0, command))


def test_cooling_with_the_heater_off_and_all_air_through_the_core_is_reported_and_released():
    watch = SaturatedTemperature(I_HEATER, I_VALVE_A, dt_s=1.0)
    out = [watch.update(13.0, 12.0, COOLING_FULL, U_HI) for _ in range(30)]
    assert out[-1] == pytest.approx(1.0)
    assert watch.update(12.1, 12.0, COOLING_FULL, U_HI) is None  # within the tolerance: released at once
    heating_on = COOLING_FULL.copy()
    heating_on[I_HEATER] = 50.0
    assert all(watch.update(13.0, 12.0, heating_on, U_HI) is None for _ in range(30))  # the heater on: not saturated


def test_a_missing_reading_forgets_the_history():
    watch = SaturatedTemperature(I_HEATER, I_VALVE_A, dt_s=1.0)
    for _ in range(19):
        assert watch.update(20.8, 22.0, HEATING_FULL, U_HI) is None
    assert watch.update(float("nan"), 22.0, HEATING_FULL, U_HI) is None
    assert watch.update(20.8, 22.0, HEATING_FULL, U_HI) is None  # the hold starts again
