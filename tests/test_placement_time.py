"""The side-by-side timing of the online placement choice (``benchmarks/placement_time.py``): a few steps of each
variant, so that the benchmark keeps running; the times themselves are the benchmark's, not asserted here."""

from hvac_mpc.benchmarks import placement_time


def test_both_settings_run_the_same_commands_on_the_built_in_plant():
    """On the solve-time loop the heater air's filter is never chosen, so the closed-loop cost is the same with the
    choice on and off, whichever way the filter not in use gets its time."""
    out = placement_time.measure(rounds=1, steps=6, seed=1)
    assert set(out) == {"idle", "back_to_back"}
    for by in out.values():
        assert by["on"]["placements"] == ["heater_outlet"] and by["off"]["placements"] == ["heater_outlet"]
        assert by["on"]["cost"] == by["off"]["cost"]
        assert 0.0 < by["off"]["median_ms"] <= by["off"]["p99_ms"]
