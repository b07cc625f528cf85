"""The cabin in the loop: the cabin model's balance, the recirculated inlet, the bench scenarios with it."""

import math

import numpy as np
import pytest

from hvac_mpc.benchmarks import bench, scenarios as S
from hvac_mpc.contract import Command
from hvac_mpc.mismatch import make_plant
from hvac_mpc.mismatch.cabin import CP_AIR_J_PER_KGK, CabinLoop, CabinSetup, cabin_step


def settle(setup, supply_c, mass_kgs, seconds=80000.0):
    air, interior = setup.cabin_temp_c, setup.interior_temp_c
    for _ in range(int(seconds / 100)):
        air, interior = cabin_step(setup, air, interior, supply_c, mass_kgs, 100.0)
    return air, interior


def test_cabin_settles_at_its_heat_balance():
    setup = CabinSetup(outside_temp_c=30.0, cabin_temp_c=40.0, interior_temp_c=45.0, solar_w=300.0)
    m, t_sup = 0.03, 12.0
    air, interior = settle(setup, t_sup, m)
    # at rest the interior passes the sun to the air; the air balances supply, walls, driver and sun
    g = m * CP_AIR_J_PER_KGK
    expected_air = (g * t_sup + setup.wall_w_per_k * 30.0 + setup.driver_w + setup.solar_w) / (g + setup.wall_w_per_k)
    assert air == pytest.approx(expected_air, abs=1e-3)
    assert interior == pytest.approx(air + setup.solar_w / setup.air_interior_w_per_k, abs=1e-3)
    # no flow, no loads: the cabin goes to the outside temperature
    still = CabinSetup(outside_temp_c=5.0, cabin_temp_c=20.0, interior_temp_c=20.0, driver_w=0.0)
    assert settle(still, 50.0, 0.0)[0] == pytest.approx(5.0, abs=1e-2)


def test_inlet_is_the_recirculation_mix_and_bad_setups_are_refused():
    setup = CabinSetup(outside_temp_c=30.0, recirculation=0.7)
    assert setup.inlet_c(20.0) == pytest.approx(0.7 * 20.0 + 0.3 * 30.0)
    with pytest.raises(ValueError, match="recirculation"):
        CabinSetup(recirculation=1.5)
    with pytest.raises(ValueError, match="wall_w_per_k"):
        CabinSetup(wall_w_per_k=-1.0)


def test_cooling_the_supply_cools_the_cabin_and_the_box_inlet_follows():
    setup = CabinSetup(outside_temp_c=32.0, cabin_temp_c=40.0, interior_temp_c=40.0)
    runs = {}
    for name, valve_a in (("cooling", 100.0), ("bypass", 0.0)):
        box = make_plant("nominal", seed=1, inlet_temp_c=setup.inlet_c(40.0), chiller_setpoint_c=5.0,
                         initial_command=Command(200.0, 0.0, valve_a, 100.0, 100.0, 100.0))
        loop = CabinLoop(box, setup)
        inlets = []
        for _ in range(600):
            loop.apply(Command(200.0, 0.0, valve_a, 100.0, 100.0, 100.0))
            loop.advance()
            m = loop.read()
            inlets.append(m.hvac_inlet_temp_c)
        runs[name] = (loop.truth(), m, np.array(inlets))
    cool, bypass = runs["cooling"], runs["bypass"]
    # the cabin is cooler with the air through the core, and so is the air the box takes in
    assert cool[0]["cabin_temp_c"] < bypass[0]["cabin_temp_c"] - 3.0
    assert cool[1].cabin_temp_c == cool[0]["cabin_temp_c"]
    assert cool[2][-1] < cool[2][0] - 3.0
    assert cool[0]["hvac_inlet_temp_c"] == pytest.approx(setup.inlet_c(cool[0]["cabin_temp_c"]))


@pytest.mark.slow
def test_bench_runs_both_controllers_on_the_cabin_scenarios():
    chosen = [S.all_scenarios()[n].quick() for n in ("cabin_cooldown_summer", "cabin_warmup_winter")]
    results, traces = bench.run_benchmark(chosen, {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()},
                                          seed=0)
    pull_down = traces["cabin_cooldown_summer"]["mpc"]
    a = pull_down.applied[:, 2]
    # the heater stays off in the pull-down, so the trapped-air guard must not hold valve a at its
    # 90 % cap (docs/robustness.md sec. 1), and the MPC is no worse than the baseline there. Single samples of a few
    # watts are the QP's answers within its tolerance: 2.0 W at most on one machine; on another (AMD EPYC, the same
    # code) the step up at 70 s takes 17.5 W for one sample with valve a closing. So the check is on the heater's
    # share of the time and of the energy (below 1 % of the blower's), not on a single sample.
    heater_w, blower_w = pull_down.applied[:, 1], pull_down.applied[:, 0]
    assert np.mean(heater_w <= 1.0) > 0.95
    assert heater_w.sum() < 0.01 * blower_w.sum()
    assert a.max() > 95.0
    assert results["scenarios"]["cabin_cooldown_summer"]["ratios"]["temp_iae_cs"] <= 1.0
    for sc in chosen:
        r = results["scenarios"][sc.name]
        assert math.isfinite(r["ratios"]["temp_iae_cs"]) and math.isfinite(r["ratios"]["energy_wh"])
        for c in ("baseline", "mpc"):
            tr = traces[sc.name][c]
            inlet = tr.measured["hvac_inlet_temp_c"]
            cabin = tr.measured["cabin_temp_c"]
            assert np.all(np.isfinite(cabin)) and r[c]["figures"]["violations_total"] == 0
            # the inlet is a consequence of the control: it moves with the cabin, from the start value
            assert abs(cabin[-1] - cabin[0]) > 0.5
            assert np.mean(inlet[-10:]) == pytest.approx(sc.cabin.inlet_c(np.mean(cabin[-10:])), abs=0.1)
