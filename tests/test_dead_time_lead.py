"""The dead-time estimate's lead rule (``EkfSettings.dead_time_lead_reach_s``, ``dead_time_lead_count_quiet``,
``dead_time_lead_tie_hold``; docs/robustness.md sec. 2.38), on boxes of the seeded sweep (``python -m
hvac_mpc.benchmarks.box_sweep``) run on the independent simulator (``hvac_mpc.mismatch``). On S1-13 (a 4.24 s dead
time the MPC is not told) the candidate ahead of the estimate moves from 3.0 s to 3.5 s, the neighbouring half sample
of the same minimum, and the count of samples it has stayed ahead restarts, and samples whose window holds too little
response do not count: counted across the neighbour and the quiet samples, the dead time is honoured sooner and the
flow jump's loss is smaller. On S0-10 (4.03 s) the dead time the lead moved to is taken back by the tie rule at once:
held against a tie, it stays.

Budget: a few seconds (the closed loops, the MPC alone on quick scenarios, 2-4 s each).
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
    with pytest.raises(InvalidSettings, match="ekf.dead_time_lead_tie_hold"):
        MpcSettings(ekf=EkfSettings(dead_time_lead_tie_hold="yes"))
    plain = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73)
    assert plain.lead_reach_steps == 0.0 and not plain.count_quiet and not plain.lead_tie_hold  # off: the rules before


def test_a_dead_time_the_lead_moved_to_gives_way_to_a_tie_only_when_asked():
    """The rule on its own: the estimate moved by the lead rule to 3.5 s (index 7); then a ranking whose least residual
    is a shorter candidate (0 s) tied with it (equal residuals, not clearly better, not a lead). Without
    ``lead_tie_hold`` the tie takes the estimate back to 0 s; with it the estimate stays. A tie with the neighbouring
    half sample (3.0 s, the same minimum's bottom) moves it within ``lead_reach_steps`` (0.5), not beyond (0)."""
    for hold, reach, tied, expected in ((False, 0.0, 0, 0.0), (True, 0.0, 0, 3.5), (True, 0.5, 0, 3.5),
                                        (True, 0.5, 6, 3.0), (True, 0.0, 6, 3.5)):
        est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73, lead_tie_hold=hold, lead_reach_steps=reach)
        est._best, est._by_lead = 7, True
        ranked = np.full(est.candidates.size, 2.0)
        ranked[tied] = ranked[7] = 1.0  # a tie, the shorter first
        if tied == 6:
            ranked[6] = 0.99  # the bottom of the one minimum: the neighbour, as low as 3.5 s within TIE_RATIO
        est._rank(ranked)
        assert est.steps == expected


def test_a_lead_made_estimate_stays_held_after_a_tie_within_reach_moved_it():
    """Two rankings: the estimate the lead rule moved to 3.5 s steps to its neighbour 3.0 s on a tie within reach
    (the same minimum's bottom), then a shorter candidate farther away (0 s) ties with 3.0 s. With
    ``lead_tie_hold`` the estimate is still the lead's and stays at 3.0 s; without it the tie takes it to 0 s."""
    for hold, expected in ((True, 3.0), (False, 0.0)):
        est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73, lead_tie_hold=hold, lead_reach_steps=0.5)
        est._best, est._by_lead = 7, True
        near = np.full(est.candidates.size, 2.0)
        near[7], near[6] = 1.0, 0.99
        est._rank(near)
        assert est.steps == 3.0
        far = np.full(est.candidates.size, 2.0)
        far[0] = far[6] = 1.0
        est._rank(far)
        assert est.steps == expected


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
def honoured_on_sweep_box(label: str, scenario: str, reach_s: float = 0.0, quiet: bool = False,
                          tie_hold: bool = False):
    """The quick ``scenario`` on sweep box ``label`` with the lead settings given: the MPC's IAE (degC s) and the dead
    time the filter in use honours after each step (s)."""
    honoured = []
    ekf = EkfSettings(dead_time_lead_reach_s=reach_s, dead_time_lead_count_quiet=quiet,
                      dead_time_lead_tie_hold=tie_hold)
    iae, _ = quick_scenario_on_sweep_box(label, ekf, scenario,
                                         record=lambda c: honoured.append(c.ekf.honoured_dead_time_s))
    return iae, np.array(honoured)


def flow_jump_on_s1_13(reach_s: float, quiet: bool = False):
    """The quick flow jump (18 C, 90 -> 200 m3/h at 30 s) on S1-13: the MPC's IAE (degC s) and the first second a
    dead time is honoured by the filter in use."""
    iae, honoured = honoured_on_sweep_box("S1-13", "flow_out_of_reach", reach_s, quiet)
    return iae, float(np.flatnonzero(honoured > 0.0)[0])  # the samples are 1 s from 0 s


@pytest.mark.slow  # closed-loop runs on a sweep box (3-6 s each)
def test_lead_counted_across_neighbours_honours_the_dead_time_sooner():
    """Measured (sec. 2.38): without the reach the leader 3.0 s (from 20 s) gives way to 3.5 s at 38 s, the count
    restarts and the dead time is honoured at 50 s, after valve a's move at 45-47 s that the reading's dip at 51-55 s
    answers; with half a sample it is honoured at 48 s and the MPC's IAE is 10.06 against 10.92 C s (the baseline's
    6.97)."""
    iae_0, first_0 = flow_jump_on_s1_13(0.0)
    iae_1, first_1 = flow_jump_on_s1_13(0.5)
    assert first_1 <= first_0 - 2.0
    assert iae_1 <= 0.95 * iae_0


@pytest.mark.slow  # closed-loop runs on a sweep box (3-6 s each)
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


@pytest.mark.slow  # closed-loop runs on a sweep box (3-6 s each)
def test_a_dead_time_the_lead_moved_to_is_held_against_a_tie():
    """Box S0-10 (``box_sweep --seed 0``; a 4.03 s dead time the MPC is not told), quick heating steps, measured in
    sec. 2.38: with the lead counted across neighbours and quiet samples, the lead moves the estimate to 3.5 s at 59 s,
    and the tie rule takes it back to 0 s within 4 s (a flat ranking, 0 s tied with 3.5 s); the step at 90 s then
    runs with no dead time honoured and the MPC's IAE is 87.7 C s (the baseline's 84.8; 73.9 with today's rules).
    Held against a tie, 3.5 s stays from 59 s to the end and the IAE is 73.4 C s."""
    iae_free, free = honoured_on_sweep_box("S0-10", "winter_heating_steps", 0.5, True)
    iae_held, held = honoured_on_sweep_box("S0-10", "winter_heating_steps", 0.5, True, True)
    first = int(np.flatnonzero(held > 0.0)[0])
    assert first == int(np.flatnonzero(free > 0.0)[0])  # the same switch by the lead
    assert np.all(held[first:] > 0.0)
    assert np.any(free[first:first + 10] == 0.0)
    assert iae_held <= 0.9 * iae_free


@pytest.mark.slow  # closed-loop runs on a sweep box (3-6 s each)
def test_a_dead_time_the_lead_moved_to_still_follows_its_minimum():
    """Box S0-8 (``box_sweep --seed 0``; 2.19 s), the quick proband sequence, measured in sec. 2.38: the estimate
    alternates between 2.0 s and 2.5 s, the two halves of one minimum; the lead moves it to 2.5 s at 137 s and at
    154 s the tie rule to 2.0 s, the minimum's bottom. Held against every tie (no reach) 2.5 s stays and the MPC's IAE
    is 124.5 C s against 121.3; with the reach of half a sample the tie within it still moves the estimate, and the
    run is today's."""
    iae_today, today = honoured_on_sweep_box("S0-8", "proband_sequence")
    iae_all, held_all = honoured_on_sweep_box("S0-8", "proband_sequence", 0.0, False, True)
    iae_reach, held_reach = honoured_on_sweep_box("S0-8", "proband_sequence", 0.5, True, True)
    assert np.any(today == 2.0) and np.any(today == 2.5)
    assert not np.array_equal(held_all, today) and iae_all > iae_today
    assert np.array_equal(held_reach, today) and iae_reach == pytest.approx(iae_today)
