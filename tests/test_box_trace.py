"""The per-second trace of one box of the sweep (``python -m hvac_mpc.benchmarks.box_trace``; docs/robustness.md
sec. 2.26): its per-segment IAE adds up to the bench's own figure, and it records the MPC's filter per step."""

import pytest

from hvac_mpc.benchmarks import box_trace

#: S1-0 of ``box_sweep --seed 1`` (independent simulator): the literal cooler, a 7.6 W/K duct, a 3 s dead time.
S1_0 = ("S1-0:transport_delay_s=3.05,duct_loss_ua_w_per_k=7.6,cooler_literal_fit=true,thermocouple_tau_scale=1.45,"
        "blower_gain_scale=0.94,valve_shift_pct=-1.53,heater_power_scale=0.97,chiller_rate_scale=0.7")


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="scenario"):
        box_trace.run_trace(S1_0, "nope", quick=True)
    with pytest.raises(ValueError, match="unknown field"):
        box_trace.run_trace("X:nope=1", "winter_heating_steps", quick=True)
    assert box_trace.main(["--box", S1_0, "--scenario", "nope", "--quick"]) == 2


def test_the_segments_add_up_to_the_bench_s_iae_and_every_step_is_recorded():
    run = box_trace.run_trace(S1_0, "winter_heating_steps", quick=True)
    segments = box_trace.segment_iae(run)
    assert len(segments) == len(run["scenario"].segments)
    for c in ("mpc", "baseline"):  # the bench's figure (benchmarks/metrics.py) computed apart
        assert sum(s[c] for s in segments) == pytest.approx(run["iae"][c], rel=1e-6)
        assert sum(w[c] for w in box_trace.window_iae(run, 30.0)) == pytest.approx(run["iae"][c], rel=1e-6)
    assert run["ratio"] == pytest.approx(run["iae"]["mpc"] / run["iae"]["baseline"], rel=1e-6)
    assert len(run["stats"]) == len(run["mpc"].time_s)
    assert {s["offset_placement"] for s in run["stats"]} <= {"heater_outlet", "heater_air"}
    lines = box_trace.seconds(run, 30.0, 40.0)
    assert len(lines) == 11 and lines[1].startswith("30 12.00")
