"""Benchmark figures on synthetic signals whose answers are worked out by hand (budget: < 2 s)."""

import math

import numpy as np
import pytest

from hvac_mpc.benchmarks import criteria, metrics
from hvac_mpc.benchmarks.simulate import Trace
from hvac_mpc.models.box import INPUTS


def test_iae_is_rectangle_sum_and_skips_missing_references():
    assert metrics.iae([1, 2, 3], [1, 1, 1], 1.0) == pytest.approx(3.0)
    assert metrics.iae([1, 2, 3], [1, 1, 1], 0.5) == pytest.approx(1.5)
    assert metrics.iae([1, 2, 3], [np.nan, 1, 1], 1.0) == pytest.approx(3.0)
    assert metrics.iae([0, 5], [np.nan, 2], 1.0) == pytest.approx(3.0)


@pytest.mark.parametrize("dt", [0.0, -1.0, float("nan")])
def test_bad_sample_time_is_named(dt):
    with pytest.raises(ValueError, match="dt_s"):
        metrics.iae([1.0], [1.0], dt)


def test_length_mismatch_is_an_error():
    with pytest.raises(ValueError, match="same length"):
        metrics.iae([1, 2], [1], 1.0)


def test_rms_error_over_samples_and_columns():
    y = [[1, 2], [3, 4]]
    r = [[1, 1], [1, 1]]
    assert metrics.rms_error(y, r) == pytest.approx(math.sqrt((0 + 1 + 4 + 9) / 4))
    # a row with a missing reference is left out
    assert metrics.rms_error([[1, 2], [3, 4]], [[np.nan, np.nan], [1, 1]]) == pytest.approx(math.sqrt((4 + 9) / 2))
    assert metrics.rms_error([1.0], [np.nan]) is None


def test_step_indices():
    assert metrics.step_indices([0, 0, 1, 1, 2]) == [2, 4]
    assert metrics.step_indices([3, 3, 3]) == []


def test_time_in_band():
    # outside at samples 0, 1, 2 -> inside for good from sample 3 -> 3 s
    assert metrics.time_in_band_s([5, 3, 0.6, 0.4, 0.2, 0.1], 0.0, 0.5, 1.0) == 3.0
    # leaves the band again at sample 2: only "for good" counts
    assert metrics.time_in_band_s([1, 0.2, 0.7, 0.1], 0.0, 0.5, 1.0) == 3.0
    assert metrics.time_in_band_s([1, 0.2, 0.7, 0.1], 0.0, 0.5, 2.0) == 6.0
    assert metrics.time_in_band_s([0.1, 0.2], 0.0, 0.5, 1.0) == 0.0
    assert metrics.time_in_band_s([0.1, 0.9], 0.0, 0.5, 1.0) is None


def test_overshoot_in_the_direction_of_the_step():
    assert metrics.overshoot([0, 0.5, 1.2, 1.1, 1.0], 0.0, 1.0) == pytest.approx(0.2)
    assert metrics.overshoot([1, 0.3, -0.1, 0.0], 1.0, 0.0) == pytest.approx(0.1)
    assert metrics.overshoot([0, 0.5, 0.9], 0.0, 1.0) == 0.0
    assert metrics.overshoot([5, 7], 2.0, 2.0) == 0.0


def test_step_responses_absolute_and_relative_band():
    rec = metrics.step_responses([0, 0, 0, 0.8, 1.3, 1.0], [0, 0, 1, 1, 1, 1], 1.0, 0.5)
    assert len(rec) == 1
    r = rec[0]
    assert (r["time_s"], r["from"], r["to"]) == (2.0, 0.0, 1.0)
    assert r["time_to_band_s"] == 1.0  # outside only at the step sample itself
    assert r["overshoot"] == pytest.approx(0.3)
    assert r["response_s"] == 4.0
    assert r["final_error"] == pytest.approx(0.0)
    assert metrics.step_responses([0, 0, 0.4], [0, 1, 1], 1.0, 0.5)[0]["final_error"] == pytest.approx(-0.6)
    rel = metrics.step_responses([10, 10, 15, 19.5], [10, 10, 20, 20], 1.0, 0.05, relative_band=True)
    assert rel[0]["time_to_band_s"] == 1.0  # band 1.0 around 20: 15 out, 19.5 in
    two = metrics.step_responses([0, 1, 1, 3, 2], [0, 1, 1, 2, 2], 1.0, 0.5)
    assert [s["time_s"] for s in two] == [1.0, 3.0]
    assert two[0]["response_s"] == 2.0  # runs to the next step


def test_lagged_reference_is_first_order_lag_held_per_sample():
    tau = 1.0 / math.log(2.0)  # exp(-1/tau) = 0.5
    y = metrics.lagged_reference([0, 1, 1, 1], tau, 1.0)
    assert y == pytest.approx([0.0, 0.0, 0.5, 0.75])
    assert metrics.iae(y, [0, 1, 1, 1], 1.0) == pytest.approx(1.75)
    with pytest.raises(ValueError, match="tau_s"):
        metrics.lagged_reference([0, 1], 0.0, 1.0)


def test_energy_in_wh():
    assert metrics.energy_wh(np.full(3600, 100.0), 1.0) == pytest.approx(100.0)
    assert metrics.energy_wh([360.0, 360.0], 5.0) == pytest.approx(1.0)


def test_actuator_travel_normalised_by_range():
    u = [[0, 0], [50, 10], [25, 10]]
    assert metrics.actuator_travel(u, [0, 0], [100, 20]) == pytest.approx([0.75, 0.5])
    with pytest.raises(ValueError):
        metrics.actuator_travel(u, [0, 0], [0, 20])


def test_bound_violations_count_out_of_range_and_non_finite():
    u = [[-1, 5], [50, 25], [np.nan, 0]]
    assert list(metrics.bound_violations(u, [0, 0], [100, 20])) == [2, 1]


def test_threshold_exceedance_and_heater_low_flow():
    e = metrics.threshold_exceedance([130, 141, 150, 139], 140.0, 1.0)
    assert e == {"samples": 2, "time_s": 2.0, "max_excess": pytest.approx(10.0)}
    assert metrics.heater_low_flow_samples([0, 100, 100, 0.5], [0.001, 0.003, 0.01, 0.001], 0.004, 1.0) == 1


def test_step_time_stats():
    t = [0.001] * 99 + [0.101]
    s = metrics.step_time_stats(t, 1.0)
    assert s["median_ms"] == pytest.approx(1.0)
    # 99th percentile, linear interpolation at position 98.01 of 0..99: 1 ms + 0.01 * 100 ms
    assert s["p99_ms"] == pytest.approx(2.0)
    assert s["time_ratio"] == pytest.approx(0.2 / 100)
    assert metrics.step_time_stats([], 1.0)["median_ms"] is None


def test_fallbacks_and_ratio():
    assert metrics.count_fallbacks([None, "a", "b", "a"]) == {"count": 3, "by_name": {"a": 2, "b": 1}}
    assert metrics.ratio(1.0, 2.0) == 0.5
    assert metrics.ratio(0.0, 0.0) == 1.0
    assert metrics.ratio(1.0, 0.0) == math.inf
    assert metrics.ratio(None, 1.0) is None


def _trace(temp, temp_ref, start_s=2.0):
    n = len(temp)
    flow_ref = np.full(n, 0.03)
    share = (0.5, 0.25, 0.25)
    ref = {"supply_temp_c": np.asarray(temp_ref, float), "volume_flow_m3s": flow_ref,
           "flow_m_m3s": flow_ref * share[0], "flow_f_m3s": flow_ref * share[1], "flow_w_m3s": flow_ref * share[2]}
    truth = {"supply_temp_c": np.asarray(temp, float), "supply_air_temp_c": np.asarray(temp_ref, float),
             "volume_flow_m3s": np.full(n, 0.03), "flow_m_m3s": np.full(n, 0.016), "flow_f_m3s": np.full(n, 0.007),
             "flow_w_m3s": np.full(n, 0.007), "heater_temp_c": np.full(n, 20.0), "heater_power_w": np.full(n, 36.0),
             "heater_outlet_temp_c": np.full(n, 20.0), "water_temp_c": np.full(n, 5.0)}
    cmd = np.tile([100.0, 36.0, 50.0, 100.0, 100.0, 100.0], (n, 1))
    cmd[3, 2] = 70.0  # valve a moves 50 -> 70 -> 50: travel 0.4 of its range
    return Trace(scenario="s", controller="c", dt_s=1.0, time_s=np.arange(n, dtype=float), reference=ref,
                 truth=truth, measured={"supply_temp_c": truth["supply_temp_c"], "volume_flow_m3s": flow_ref},
                 requested=cmd.copy(), applied=cmd, step_time_s=np.full(n, 0.002), fallback=[None, None, "x", None,
                                                                                              None, None],
                 mode=[None] * n, status=[None] * n, metrics_start_s=start_s)


def test_run_figures_on_a_hand_made_trace():
    tr = _trace([20, 20, 20, 18, 16, 15.2, 15.0], [20, 20, 15, 15, 15, 15, 15])
    tr.fallback.append(None)
    lo = [30, 0, 0, 0, 0, 0]
    hi = [300, 240, 100, 100, 100, 100]
    out = metrics.run_figures(tr, lo, hi, heater_temp_max_c=140.0, trap_threshold_pct=95.0, sensor_tau_s=5.0)
    f, d = out["figures"], out["details"]
    # scored from t = 2 s: |20-15| + |18-15| + |16-15| + 0.2 + 0 = 9.2 C s
    assert f["temp_iae_cs"] == pytest.approx(9.2)
    assert f["air_temp_iae_cs"] == pytest.approx(0.0)
    assert f["temp_steps"] == 1 and f["temp_unsettled"] == 0
    # step at t = 2 s; outside +-0.5 C at 20, 18, 16 (samples 2..4) -> in band from t = 5 s -> 3 s
    assert f["temp_time_to_band_max_s"] == 3.0
    assert f["temp_overshoot_max_c"] == 0.0
    # outlets: errors m 0.001, f -0.0005, w -0.0005 every sample
    assert f["outlet_rms_m3s"] == pytest.approx(math.sqrt((1e-6 + 2.5e-7 + 2.5e-7) / 3))
    assert f["flow_iae_m3"] == pytest.approx(0.0)
    # 5 scored samples of 100 W blower and 36 W heater
    assert f["blower_wh"] == pytest.approx(500 / 3600)
    assert f["heater_wh"] == pytest.approx(180 / 3600)
    assert f["energy_wh"] == pytest.approx(680 / 3600)
    assert d["travel"]["valve_a_pct"] == pytest.approx(0.4)
    assert f["travel_mean"] == pytest.approx(0.4 / 6)
    assert f["fallbacks"] == 1
    assert f["violations_total"] == 0
    assert f["step_median_ms"] == pytest.approx(2.0)
    assert f["time_ratio"] == pytest.approx(0.002)
    assert set(d["travel"]) == set(INPUTS)
    # the lag-only response of a 5 C step with tau 5 s, from the step sample on
    a = math.exp(-1 / 5.0)
    assert f["ideal_temp_iae_cs"] == pytest.approx(5 * (1 + a + a ** 2 + a ** 3 + a ** 4))


def test_run_figures_counts_violations():
    tr = _trace([20] * 6, [20] * 6)
    tr.requested[4, 0] = 310.0  # blower above its bound
    tr.truth["heater_temp_c"][3:5] = 150.0  # above the limit for two samples
    tr.truth["volume_flow_m3s"][5] = 0.002  # heater on with too little flow
    out = metrics.run_figures(tr, [30, 0, 0, 0, 0, 0], [300, 240, 100, 100, 100, 100], 140.0, 95.0, 5.0)
    f = out["figures"]
    assert (f["violations_bounds"], f["violations_heater_temp"], f["violations_heater_low_flow"]) == (1, 2, 1)
    assert out["details"]["heater_temp"]["max_excess"] == pytest.approx(10.0)
    assert f["temp_steps"] == 0 and f["temp_time_to_band_max_s"] is None


def _figs(**kw):
    base = {"temp_iae_cs": 100.0, "outlet_rms_m3s": 0.004, "energy_wh": 10.0, "blower_wh": 10.0, "heater_wh": 0.0,
            "temp_overshoot_max_c": 0.1, "fallbacks": 0, "violations_total": 0, "flow_iae_m3": 0.1,
            "temp_time_to_band_max_s": 15.0, "temp_unsettled": 0, "ideal_temp_iae_cs": 50.0}
    base.update(kw)
    return base


def _details(times=(15.0,)):
    steps = [{"time_s": 10.0 * i, "from": 20.0, "to": 15.0, "time_to_band_s": t, "overshoot": 0.0,
              "response_s": 60.0} for i, t in enumerate(times)]
    return {"temperature_steps": steps, "steady_samples": 0, "temp_iae_steady_cs": 0.0,
            "temp_mean_abs_steady_c": None, "outlet_rms_m3s": {"flow_m_m3s": 0.004, "flow_f_m3s": 0.004,
                                                                "flow_w_m3s": 0.004},
            "fallbacks": {"count": 0, "by_name": {}}, "flow_mean_excess_m3s": 0.0, "valve_a_saturated_s": 0.0}


def test_criteria_met_and_not_met_with_ratios():
    mpc = _figs(temp_iae_cs=30.0, outlet_rms_m3s=0.002, energy_wh=9.0, temp_time_to_band_max_s=12.0)
    res = criteria.judge("cooling", mpc, _figs(), _details((12.0,)), _details())
    status = {c["criterion"]: (c["status"], c["ratio"]) for c in res}
    assert [c["status"] for c in res] == ["met"] * 5
    assert not any(c["note"] for c in res)
    # a met comparison carries a caveat when the MPC tracks the total flow much worse
    d = _details((12.0,))
    d["flow_mean_excess_m3s"] = -2.0 / 3600
    res = criteria.judge("cooling", dict(mpc, flow_iae_m3=0.3), _figs(), d, _details())
    assert "volume-flow IAE 3.00 x the baseline's (mean flow -2.0 m3/h" in res[0]["note"]
    assert res[3]["note"] == ""
    assert status["supply-temperature IAE below the baseline's"][1] == pytest.approx(0.3)
    worse = _figs(temp_iae_cs=120.0, outlet_rms_m3s=0.005, energy_wh=10.5, blower_wh=10.5,
                  temp_time_to_band_max_s=25.0)
    res = criteria.judge("cooling", worse, _figs(), _details((25.0,)), _details())
    assert [c["status"] for c in res] == ["not met"] * 5
    assert all(c["why"] for c in res)
    energy = res[2]
    assert energy["ratio"] == pytest.approx(1.05) and "blower 10.50 vs 10.00 Wh" in energy["why"]
    assert "25 s" in res[4]["why"]
    # the aim's reason quotes the lag-only floor: 50 / 100 of the baseline's IAE, above the 0.4 aim
    assert "0.50 x the baseline's IAE, so the aim needs the air temperature to overshoot" in res[3]["why"]


def test_criteria_not_applicable():
    res = criteria.judge("heating", _figs(outlet_rms_m3s=None), _figs(outlet_rms_m3s=None), _details(), _details())
    assert res[1]["status"] == "n/a" and res[4]["status"] == "n/a"
    # an unsettled cooling step misses the time aim
    mpc_d = _details((None,))
    mpc_d["temperature_steps"][0]["final_error"] = 0.8
    res = criteria.judge("cooling", _figs(temp_unsettled=1, temp_iae_cs=150.0), _figs(), mpc_d, _details())
    assert res[4]["status"] == "not met" and "not settled" in res[4]["why"]
    assert "never settles within +-0.5 C: 0.80 C above the reference" in res[0]["why"]
