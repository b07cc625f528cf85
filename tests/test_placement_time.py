"""The side-by-side timing of the online placement choice (``benchmarks/placement_time.py``): a few steps of each
variant, so that the benchmark keeps running; the times themselves are the benchmark's, not asserted here."""

import pytest

from hvac_mpc.benchmarks import placement_time


@pytest.mark.slow
def test_both_settings_run_the_same_commands_on_the_built_in_plant():
    """On the solve-time loop the heater air's filter is never chosen, so the closed-loop cost is the same with the
    choice on and off, whichever way the filter not in use gets its time."""
    out = placement_time.measure(rounds=1, steps=6, seed=1)
    assert set(out) == {"idle", "back_to_back"}
    for by in out.values():
        assert by["on"]["placements"] == ["heater_outlet"] and by["off"]["placements"] == ["heater_outlet"]
        assert by["on"]["cost"] == by["off"]["cost"]
        assert 0.0 < by["off"]["median_ms"] <= by["off"]["p99_ms"]


def test_the_switch_costs_are_measured_side_by_side():
    """The binding of the other filter (prebuilt and rebuilt) is measured on as many switches each way; a switch
    binds the filter not in use each time, so the controller alternates and ends where it started."""
    out = placement_time.switch_cost(rounds=1, seed=1, warm_steps=2)
    assert out["prebuilt"]["switches"] == out["rebuilt"]["switches"] == 2 * placement_time.SWITCHES
    assert all(0.0 < by["median_ms"] <= by["max_ms"] for by in out.values())


@pytest.mark.slow
def test_the_switch_step_is_found_and_timed_with_the_warm_switch_off_and_on():
    """On the box the benchmark runs (seed 0) the rule switches once, at the same step whether the switch step
    starts cold or warm (the sums do not depend on it before the switch)."""
    out = placement_time.switch_step(rounds=1)
    assert out["off"]["switch_steps"] == out["on"]["switch_steps"] and len(out["off"]["switch_steps"]) == 1
    assert len(out["off"]["switch_ms"]) == len(out["on"]["switch_ms"]) == 1
    assert out["off"]["iae_cs"] > 0.0 and out["on"]["iae_cs"] > 0.0
