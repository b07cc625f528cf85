"""The simulated plant: effects switch by name, runs repeat, and a step is cheap."""

import time

import numpy as np
import pytest

from hvac_mpc.models import PLANT_EFFECTS, Environment, Parameters, SimulatedPlant

from hvac_mpc.contract import Command


def run(plant, command, seconds):
    plant.apply(command)
    out = []
    for _ in range(seconds):
        plant.advance()
        out.append(plant.truth())
    return out


def test_same_seed_repeats_exactly_and_other_seed_differs():
    a, b, c = (SimulatedPlant(seed=s) for s in (7, 7, 8))
    for pl in (a, b, c):
        pl.apply(Command(200, 0, 90, 100, 50, 50))
        pl.advance(30)
    assert a.read() == b.read()
    assert a.read().supply_temp_c != c.read().supply_temp_c


def test_unknown_effect_is_rejected_with_the_allowed_names():
    with pytest.raises(ValueError, match="allowed"):
        SimulatedPlant(effects=["fan_curve", "warp_drive"])


def test_step_costs_well_under_a_millisecond():
    plant = SimulatedPlant()
    plant.apply(Command(150, 100, 80, 100, 60, 40))
    t0 = time.perf_counter()
    plant.advance(1000)
    per_step = (time.perf_counter() - t0) / 1000
    assert plant.time_s == pytest.approx(1000.0)
    assert per_step < 1e-3


def test_fan_curve_closing_valves_reduces_flow_like_tables_3_to_5():
    env = Environment(25.9, 5.0)
    # the tables measure the whole network (other valves closed, leaking): fan curve and leakage together
    on = SimulatedPlant(effects=["fan_curve", "valve_leakage"], environment=env)
    off = SimulatedPlant(effects=[], environment=Environment(25.9, 5.0))
    # table 3 rows 1 and 11 (m closed / open, f and w closed): 0.02833 and 0.05167 m3/s at full power
    for angle, expected in ((0.0, 0.02833), (100.0, 0.05167)):
        for pl in (on, off):
            pl.settle(Command(300, 0, 0, angle, 0, 0))
        assert on.truth()["volume_flow_m3s"] == pytest.approx(expected, rel=0.06)
        assert off.truth()["volume_flow_m3s"] == pytest.approx(0.057, rel=1e-6)


def test_chiller_hysteresis_makes_the_water_oscillate_within_the_band():
    plant = SimulatedPlant(effects=["chiller_hysteresis"])
    water = [t["water_temp_c"] for t in run(plant, Command(150, 0, 100, 100, 100, 100), 2400)]
    assert max(water) == pytest.approx(6.0, abs=0.05) and min(water) == pytest.approx(4.0, abs=0.05)
    nominal = SimulatedPlant(effects=[])
    water0 = [t["water_temp_c"] for t in run(nominal, Command(150, 0, 100, 100, 100, 100), 600)]
    assert max(water0) - min(water0) < 1e-6


def test_ptc_power_falls_when_the_heater_runs_hot():
    hot = SimulatedPlant(effects=["ptc_power_fall"], environment=Environment(20.0, 20.0))
    ideal = SimulatedPlant(effects=[], environment=Environment(20.0, 20.0))
    for pl in (hot, ideal):
        pl.settle(Command(30, 240, 100, 100, 100, 100))
    assert ideal.truth()["heater_power_w"] == pytest.approx(240.0)
    assert hot.truth()["heater_power_w"] < 200.0
    assert hot.truth()["heater_temp_c"] < ideal.truth()["heater_temp_c"]


def test_motor_heats_faster_than_it_cools():
    plant = SimulatedPlant(effects=["motor_asymmetry"], environment=Environment(25.0, 25.0))
    plant.settle(Command(30, 0, 0, 100, 100, 100))
    base = plant.x[0]
    up = [plant.x[0] for _ in run(plant, Command(300, 0, 0, 100, 100, 100), 300)]
    top = plant.x[0]
    down = [plant.x[0] for _ in run(plant, Command(30, 0, 0, 100, 100, 100), 300)]
    rise_frac = (up[149] - base) / (top - base)
    fall_frac = (top - down[149]) / (top - base)
    assert rise_frac > fall_frac + 0.1


def test_trapped_air_spike_when_valve_a_leaves_saturation_in_heating():
    env = Environment(15.0, 15.0)  # winter: chiller off, water at inlet temperature
    spikes = {}
    for effects in ([], ["trapped_air"]):
        plant = SimulatedPlant(effects=effects, environment=Environment(15.0, 15.0))
        plant.settle(Command(60, 240, 100, 100, 100, 100))
        before = plant.truth()["supply_air_temp_c"]
        after = [t["supply_air_temp_c"] for t in run(plant, Command(60, 240, 70, 100, 100, 100), 20)]
        spikes[bool(effects)] = max(after) - after[-1]
    assert spikes[True] > 1.5
    assert spikes[False] < 0.2
    assert env.inlet_temp_c == 15.0


def test_bypass_split_depends_on_mass_flow():
    def supply(effects, power):
        pl = SimulatedPlant(effects=effects, environment=Environment(30.0, 5.0))
        pl.settle(Command(power, 0, 50, 100, 100, 100))
        return pl.truth()["supply_air_temp_c"]
    nominal = supply([], 250) - supply([], 60)
    with_effect = supply(["bypass_flow"], 250) - supply(["bypass_flow"], 60)
    assert abs(with_effect - nominal) > 1.0


def test_noise_only_with_sensor_noise_effect():
    quiet = SimulatedPlant(effects=[])
    noisy = SimulatedPlant(effects=["sensor_noise"])
    for pl in (quiet, noisy):
        pl.advance(5)
    assert quiet.read().supply_temp_c == quiet.truth()["supply_temp_c"]
    assert noisy.read().supply_temp_c != noisy.truth()["supply_temp_c"]


def test_commands_are_clipped_and_bad_commands_rejected():
    plant = SimulatedPlant()
    applied = plant.apply(Command(500, -10, 120, 50, 50, 50))
    assert applied[0] == 300 and applied[1] == 0 and applied[2] == 100
    before = plant.command
    with pytest.raises(ValueError, match="finite"):
        plant.apply([np.nan, 0, 0, 0, 0, 0])
    assert plant.command == before
    assert set(PLANT_EFFECTS) >= {"ptc_power_fall", "chiller_hysteresis", "motor_asymmetry", "bypass_flow",
                                  "trapped_air", "sensor_noise", "fan_curve"}
    assert Parameters().heater_power_max_w == 240.0
