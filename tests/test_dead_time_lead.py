"""The dead-time estimate's lead count across neighbouring half samples and quiet samples
(``EkfSettings.dead_time_lead_reach_s``, ``dead_time_lead_count_quiet``; docs/robustness.md sec. 2.38): on box S1-13 of the seeded sweep (``python -m hvac_mpc.benchmarks.box_sweep --seed 1
--count 14 --only S1-13``; a 4.24 s dead time the MPC is not told, the independent simulator ``hvac_mpc.mismatch``)
the candidate ahead of the estimate moves from 3.0 s to 3.5 s, the neighbouring half sample of the same minimum, and
the count of samples it has stayed ahead restarts, and samples whose window holds too little response do not count;
counted across the neighbour (and the quiet samples), the dead time is honoured sooner and the flow jump's loss is
smaller.

Budget: a few seconds (the closed loops of the quick flow jump, the MPC alone, about 2 s each).
"""

import functools

import numpy as np
import pytest

from ekf_helpers import quick_scenario_on_sweep_box
from hvac_mpc.mpc.dead_time import DeadTimeEstimator
from hvac_mpc.mpc.estimator import EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings


def test_lead_settings_are_checked():
    for bad in (-0.5, 7.0):  # below 0, above dead_time_max_s (6 s)
        with pytest.raises(InvalidSettings, match="ekf.dead_time_lead_reach_s"):
            MpcSettings(ekf=EkfSettings(dead_time_lead_reach_s=bad))
    with pytest.raises(InvalidSettings, match="ekf.dead_time_lead_count_quiet"):
        MpcSettings(ekf=EkfSettings(dead_time_lead_count_quiet=1))
    plain = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73)
    assert plain.lead_reach_steps == 0.0 and not plain.count_quiet  # off by default: the rule as before


def test_quiet_samples_count_for_a_standing_lead_only_when_asked():
    """The rule on its own: a candidate ahead of the estimate for 5 samples, then 3 samples whose window holds no
    response (constant air and reading: nothing ranked). Without ``count_quiet`` they neither count nor break the
    row; with it they add to it. Without a lead there is nothing to count."""
    for quiet, expected in ((False, 5), (True, 8)):
        est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73, count_quiet=quiet)
        est.push_air(20.0)
        est.observe(20.0)
        est._lead, est._lead_samples = 6, 5
        for _ in range(3):
            est.push_air(20.0)
            est.observe(20.0)
            assert np.all(np.isnan(est.residuals))  # quiet: nothing ranked
        assert est._lead_samples == expected and est.steps == 0.0
        est._lead, est._lead_samples = None, 0
        est.push_air(20.0)
        est.observe(20.0)
        assert est._lead_samples == 0


@functools.lru_cache(maxsize=None)
def flow_jump_on_s1_13(reach_s: float, quiet: bool = False):
    """The quick flow jump (18 C, 90 -> 200 m3/h at 30 s) on S1-13: the MPC's IAE (degC s) and the first second a
    dead time is honoured by the filter in use."""
    honoured = []
    ekf = EkfSettings(dead_time_lead_reach_s=reach_s, dead_time_lead_count_quiet=quiet)
    iae, trace = quick_scenario_on_sweep_box("S1-13", ekf,
                                             "flow_out_of_reach", record=lambda c: honoured.append(
                                                 c.ekf.honoured_dead_time_s))
    first = int(np.flatnonzero(np.array(honoured) > 0.0)[0])
    return iae, float(trace.time_s[first])


def test_lead_counted_across_neighbours_honours_the_dead_time_sooner():
    """Measured (sec. 2.38): without the reach the leader 3.0 s (from 20 s) gives way to 3.5 s at 38 s, the count
    restarts and the dead time is honoured at 50 s, after valve a's move at 45-47 s that the reading's dip at 51-55 s
    answers; with half a sample it is honoured at 48 s and the MPC's IAE is 10.06 against 10.92 C s (the baseline's
    6.97)."""
    iae_0, first_0 = flow_jump_on_s1_13(0.0)
    iae_1, first_1 = flow_jump_on_s1_13(0.5)
    assert first_1 <= first_0 - 2.0
    assert iae_1 <= 0.95 * iae_0


def test_quiet_samples_counted_honour_the_dead_time_before_the_move():
    """Measured (sec. 2.38): the 8 quiet samples (23-26 s, 34-37 s) counted as well, the dead time is honoured at
    40 s, before valve a's move, and the MPC's IAE is 5.67 C s (0.81 of the baseline's); the quiet samples alone do
    nothing here (the neighbour's move still restarts the count)."""
    iae_0, first_0 = flow_jump_on_s1_13(0.0)
    iae_q, first_q = flow_jump_on_s1_13(0.0, quiet=True)
    iae_b, first_b = flow_jump_on_s1_13(0.5, quiet=True)
    assert first_q == first_0 and iae_q == pytest.approx(iae_0)
    assert first_b <= first_0 - 8.0
    assert iae_b <= 0.6 * iae_0
