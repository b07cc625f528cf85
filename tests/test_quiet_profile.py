"""benchmarks/quiet_profile.py: the kinds a profiled function is counted under, the quiet steps, and a short profiled
loop beside an unprofiled one (the same commands; OSQP's and CasADi's calls found); benchmarks/split_trace.py's
reference changes of any field; the generated OSQP's data address."""

import numpy as np
import pytest

from hvac_mpc.benchmarks import change_start, quiet_profile, split_trace
from hvac_mpc.mpc.osqp_embedded import data_address


@pytest.mark.parametrize("filename, name, kind", [
    ("/x/hvac_mpc/mpc/osqp_embedded.py", "_solve_once", "osqp"),
    ("/x/site-packages/osqp/interface.py", "solve", "osqp"),
    ("/x/hvac_mpc/mpc/casadi_eval.py", "__call__", "casadi"),
    ("~", "<built-in method casadi._casadi.Function_call>", "casadi"),
    ("/x/site-packages/numpy/_core/fromnumeric.py", "sum", "numpy"),
    ("~", "<method 'copy' of 'numpy.ndarray' objects>", "numpy"),
    ("/x/hvac_mpc/mpc/rti_osqp.py", "feedback", "python"),  # the RTI's glue, not OSQP's own time
    ("/work/repo/mpc/mpc_controller.py", "_step", "python"),
    ("~", "<built-in method builtins.len>", "other"),
])
def test_each_function_is_counted_under_its_kind(filename, name, kind):
    assert quiet_profile.kind_of(filename, name) == kind


def test_the_quiet_steps_leave_out_the_cold_start_and_each_change_with_its_wake():
    steps = 120
    quiet = quiet_profile.quiet_steps(steps)
    changes = change_start.change_steps(steps)
    assert changes and 0 not in quiet
    for c in changes:
        assert not quiet & set(range(c, c + quiet_profile.WAKE + 1))
        if c + quiet_profile.WAKE + 1 < steps and c + quiet_profile.WAKE + 1 not in changes:
            assert c + quiet_profile.WAKE + 1 in quiet
    assert len(quiet) == steps - len({0} | {k for c in changes for k in range(c, min(c + quiet_profile.WAKE + 1, steps))})


@pytest.mark.slow
def test_a_short_profiled_loop_gives_the_unprofiled_commands_and_finds_the_solvers_calls():
    out = quiet_profile.measure(12, seed=1)
    assert out["steps"] == 11 and out["commands_equal"]
    assert out["calls"]["osqp"] >= 4 and out["calls"]["casadi"] >= 1  # matrix update, vectors, warm start, solve
    assert out["by_kind_ms"]["osqp"] > 0 and out["median_ms"]["plain"] > 0


def test_a_change_of_any_reference_field_counts_and_nan_stays_unchanged():
    ref = {"supply_temp_c": np.array([18.0, 18.0, 18.0, 20.0, 20.0]),
           "volume_flow_m3s": np.array([0.02, 0.02, 0.03, 0.03, 0.03]),
           "flow_m_m3s": np.array([np.nan, np.nan, np.nan, np.nan, 0.01])}
    assert split_trace.reference_changes(ref) == [2, 3, 4]


def test_the_data_address_is_numpys_for_writable_and_read_only_arrays():
    a = np.arange(6.0)
    assert data_address(a) == a.ctypes.data
    b = a.copy()
    b.flags.writeable = False
    assert data_address(b) == b.ctypes.data
    assert data_address(a[2:]) == a.ctypes.data + 2 * a.itemsize


def test_the_address_timing_runs_both_ways_and_gives_their_ratio():
    out = quiet_profile.address_times(size=10, rounds=2, calls=50)
    assert out["data_address"] > 0 and out["ndarray.ctypes.data"] > 0
    assert 0 < out["ratio"] < 10
