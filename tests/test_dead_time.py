"""The estimator's dead-time handling (issue 11): the dead time of the thermocouple found online from
readings of the independent simulator (``hvac_mpc.mismatch``, its own delay line), the Smith-predictor
measurement model that keeps a delay out of the mixed-air offset, and a closed loop on a delayed box.

Budget: the fast tests a few seconds together (open-loop runs of the estimator, no solver); the
closed loop is marked slow.
"""

import functools

import numpy as np
import pytest

from ekf_helpers import feed_open_loop
from hvac_mpc.benchmarks import bench, scenarios as S
from hvac_mpc.contract import Command
from hvac_mpc.mismatch import make_plant
from hvac_mpc.models import HvacModel, Parameters
from hvac_mpc.mpc.dead_time import DeadTimeEstimator
from hvac_mpc.mpc.estimator import DisturbanceEkf, EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings

#: Valve-a openings held 40 s each (blower 150 W, outlets open, chiller 5 C, inlet 32 C): cooling steps.
VALVE_A_STEPS = (40.0, 80.0, 55.0, 90.0, 30.0)
HOLD_S = 40


def run_filter(variant: str, settings: EkfSettings | None = None, seed: int = 3):
    """The estimator fed open loop by the independent box of ``variant``; per sample (dead time s, mix offset C)."""
    plant = make_plant(variant, seed=seed)
    plant.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
    commands = [Command(150.0, 0.0, a, 100.0, 100.0, 100.0) for a in VALVE_A_STEPS]
    plant.settle(commands[0])
    ekf = DisturbanceEkf(HvacModel(Parameters()), settings or EkfSettings())
    dead, offset = [], []

    def record(e):
        dead.append(e.dead_time_s)
        offset.append(e.mix_offset_c)

    feed_open_loop(ekf, plant, commands, HOLD_S, record)
    return np.array(dead), np.array(offset)


@pytest.mark.parametrize("variant, delay_s", [("nominal", 0.0), ("delay_1s", 1.0), ("delay_3s", 3.0),
                                              ("delay_5s", 5.0)])
def test_dead_time_found_from_the_independent_box(variant, delay_s):
    dead, _ = run_filter(variant)
    # nothing moves before the first valve step: the estimate stays at none ...
    assert np.all(dead[:HOLD_S] == 0.0)
    # ... or at a prior (docs/robustness.md sec. 2.4), which the first step's response replaces
    primed, _ = run_filter(variant, EkfSettings(dead_time_prior_s=1.5))
    assert np.all(primed[:HOLD_S] == 1.5)
    for est in (dead, primed):
        # within 15 s of the first step it is within half a sample of the box's delay, and from the
        # second step on it is the delay
        assert np.all(np.abs(est[HOLD_S + 15:] - delay_s) <= 0.5)
        assert np.all(est[2 * HOLD_S:] == delay_s)


def test_dead_time_is_not_a_mixed_air_offset():
    """On a 3 s delay, the plain filter's offset swings with every valve step while the sensor has not
    answered yet; honouring the estimated dead time the swing is several times smaller, and the offset
    at rest is the one the same filter finds on the box without the delay (same steady physics).
    Without the heater outlet reading's own offset: with it the split between the two offsets settles
    in about 150 s rather than within a 40 s hold (0.15 C apart after 150 s, 0.46 C after 40 s)."""
    _, plain = run_filter("delay_3s", EkfSettings(dead_time_max_s=0.0, q_heater_outlet_offset_c=0.0))
    dead, smith = run_filter("delay_3s", EkfSettings(q_heater_outlet_offset_c=0.0))
    _, undelayed = run_filter("nominal", EkfSettings(q_heater_outlet_offset_c=0.0))
    late = slice(2 * HOLD_S, None)  # from the second step on, the dead time is known (test above)
    swing = lambda off: float(np.max(np.abs(np.diff(off[late]))))  # noqa: E731 - largest move per sample
    assert np.all(dead[late] == 3.0)
    assert swing(smith) < 0.4 * swing(plain)
    ends = [HOLD_S * (i + 1) - 1 for i in range(2, len(VALVE_A_STEPS))]  # the end of each later hold
    smith_err = np.max(np.abs(smith[ends] - undelayed[ends]))
    assert smith_err < 0.25
    # the plain filter is still swinging (0.42 C with the motor rise bounded, 0.5 and more without)
    assert np.max(np.abs(plain[ends] - undelayed[ends])) > max(0.3, 3.0 * smith_err)


def test_without_a_response_the_estimate_stays():
    est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73)
    rng = np.random.default_rng(0)
    for _ in range(200):  # constant air, noisy readings: no candidate explains more than another
        est.push_air(20.0)
        est.observe(20.0 + 0.05 * rng.standard_normal())
    assert est.seconds == 0.0 and np.all(np.isnan(est.residuals))
    assert not est.informed  # nothing to rank: the gates on a response seen stay shut


def test_a_response_informs_the_estimate():
    est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73)
    reading = 20.0
    for k in range(40):
        air = 20.0 if k < 20 else 17.0
        est.push_air(air)
        reading += (1.0 - est.lag) * (air - reading)
        est.observe(reading)
        if k < 20:
            assert not est.informed
    assert est.informed


def test_the_prior_dead_time_stands_until_a_response_shows_another():
    """The prior is the estimate while the readings hold no response; a response that another dead time
    explains clearly better (none here: shorter, as well as longer) replaces it."""
    est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73, prior_steps=3.0)
    rng = np.random.default_rng(0)
    reading = 20.0
    for k in range(200):
        air = 20.0 if k < 100 else 17.0  # a 3 C step of the air at 100 s, seen without delay
        est.push_air(air)
        reading += (1.0 - est.lag) * (air - reading)
        est.observe(reading + 0.01 * rng.standard_normal())
        if k < 100:
            assert est.seconds == 3.0
    assert est.seconds == 0.0


def test_dead_time_settings_are_checked():
    with pytest.raises(InvalidSettings, match="ekf.dead_time_max_s"):
        MpcSettings(ekf=EkfSettings(dead_time_max_s=-1.0))
    with pytest.raises(InvalidSettings, match="ekf.dead_time_window_s"):
        MpcSettings(ekf=EkfSettings(dead_time_window_s=0.0))
    with pytest.raises(InvalidSettings, match="ekf.dead_time_prior_s"):
        MpcSettings(ekf=EkfSettings(dead_time_prior_s=-0.5))
    # a model that names its transport delay needs no prior
    told = DisturbanceEkf(HvacModel(Parameters().replace(transport_delay_s=3.0)), EkfSettings(dead_time_prior_s=1.5))
    assert told.dead_time_prior_s == 0.0 and told.dead_time_s == 0.0
    # 0 turns the handling off: no register, the plain filter
    ekf = DisturbanceEkf(HvacModel(Parameters()), EkfSettings(dead_time_max_s=0.0))
    assert ekf.nz == ekf.nc


@pytest.mark.slow
def test_mpc_holds_cooling_steps_on_a_5_s_delay_it_was_not_told():
    """delay_5s on the nominal parameters: the unaware MPC rang at 3.3 times the baseline's IAE on
    the quick cooling steps; finding the dead time online it stays below the baseline."""
    sc = S.mismatch_scenarios()["summer_cooling_steps"].quick()
    factories = {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()}
    res, tr = bench.run_benchmark([sc], factories, seed=0, plant_factory=functools.partial(make_plant, "delay_5s"))
    r = res["scenarios"][sc.name]
    assert r["ratios"]["temp_iae_cs"] <= 1.0
    assert r["mpc"]["figures"]["fallbacks"] == 0 and r["mpc"]["figures"]["violations_total"] == 0


def test_ties_within_one_minimum_take_its_bottom_and_separate_minima_the_shortest():
    from hvac_mpc.mpc.dead_time import shortest_tied_minimum
    # one flat minimum (a response the model's air explains poorly): its bottom, not its shorter flank
    flat = np.array([1.23, 1.20, 1.15, 1.09, 1.03, 1.015, 1.0, 1.03, 1.09])
    assert shortest_tied_minimum(flat) == 6
    # two minima a ring period apart, within the tie ratio: the shorter one
    aliased = np.array([3.0, 2.0, 1.04, 1.5, 2.5, 1.5, 1.0, 1.6])
    assert shortest_tied_minimum(aliased) == 2
    # a second minimum outside the tie ratio does not count
    assert shortest_tied_minimum(np.array([3.0, 1.2, 2.0, 1.0, 2.0])) == 3


def _tied_minimum_by_concatenation(res: np.ndarray) -> int:
    """The ranking's first formulation (neighbour masks built by concatenation), the reference of the one in use."""
    res = np.maximum(res, 0.0)
    lower_left = np.r_[True, res[1:] <= res[:-1]]
    lower_right = np.r_[res[:-1] <= res[1:], True]
    return int(np.flatnonzero(lower_left & lower_right & (res <= 1.1 * res.min()))[0])


def test_shortest_tied_minimum_takes_the_index_of_its_first_formulation():
    from hvac_mpc.mpc.dead_time import shortest_tied_minimum
    rng = np.random.default_rng(7)
    cases = [rng.uniform(0.0, 2.0, 13) for _ in range(300)]
    # plateaus and ties (equal neighbours), minima at either end, round-off below zero, a single candidate
    cases += [np.round(rng.uniform(0.0, 2.0, 13), 1) for _ in range(300)]
    cases += [np.array([1.0, 2.0, 3.0]), np.array([3.0, 2.0, 1.0]), np.array([-1e-12, 1.0, -2e-12]),
              np.full(5, 0.7), np.array([0.4])]
    for res in cases:
        assert shortest_tied_minimum(res) == _tied_minimum_by_concatenation(res), res
    with pytest.raises(IndexError):  # no minimum among nan residuals: an error, as before
        shortest_tied_minimum(np.array([np.nan, 1.0, 2.0]))
    with pytest.raises(IndexError):
        _tied_minimum_by_concatenation(np.array([np.nan, 1.0, 2.0]))


def _plain_residuals(air, reading, max_steps=6, sensor_tau_s=5.73, window_s=60.0, min_excitation_c=0.05):
    """The ranking's residuals per sample in their first formulation (each sum apart, the wrong sign's residual by
    ``np.where``), nan where the window holds no response: the reference of the one-pass sums in use."""
    lag, forget = np.exp(-1.0 / sensor_tau_s), np.exp(-1.0 / window_s)
    cand = np.arange(2 * max_steps + 1) / 2.0
    i0 = np.floor(cand).astype(int)
    w1 = cand - i0
    w0, i1 = 1.0 - w1, np.minimum(i0 + 1, max_steps)
    held = np.full(max_steps + 1, air[0])
    pred, last_pred = np.full(cand.size, air[0]), None
    w = syy = 0.0
    sss, ssy = np.zeros(cand.size), np.zeros(cand.size)
    out, last_y = [], None
    for k, (a, y) in enumerate(zip(air, reading)):
        if k > 0:
            held = np.r_[a, held[:-1]]
        last_pred = pred
        pred = lag * pred + (1.0 - lag) * (w0 * held[i0] + w1 * held[i1])
        if last_y is None:
            last_y = y
            out.append(np.full(cand.size, np.nan))
            continue
        ds, dy, last_y = pred - last_pred, y - last_y, y
        w, syy = forget * w + 1.0, forget * syy + dy * dy
        sss, ssy = forget * sss + ds * ds, forget * ssy + ds * dy
        if sss.min() / w < min_excitation_c ** 2:
            out.append(np.full(cand.size, np.nan))
            continue
        out.append(np.where(ssy > 0.0, syy - ssy ** 2 / sss, syy) / w)
    return out


def test_the_one_pass_sums_give_the_residuals_of_their_first_formulation():
    """The candidates' sums updated together (one array, the wrong sign's residual as syy less 0) give each
    residual of the sums apart to the bit, on responses of both signs, a quiet stretch and a sign flip of the
    reading."""
    rng = np.random.default_rng(11)
    n = 300
    air = np.r_[np.full(40, 20.0), 20.0 + np.cumsum(rng.normal(0.0, 0.5, n - 40))]
    reading = np.r_[np.full(45, 20.0), 40.0 - air[40:n - 5]] + rng.normal(0.0, 0.02, n)  # a response of wrong sign
    reading[200:] = air[196:n - 4] + rng.normal(0.0, 0.05, n - 200)  # then the right sign, 4 samples late
    est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73)
    informed = 0
    for a, y, ref in zip(air, reading, _plain_residuals(air, reading)):
        est.push_air(a)
        est.observe(y)
        assert np.array_equal(est.residuals, ref, equal_nan=True)
        informed += bool(np.isfinite(ref).all())
    assert 100 < informed < n - 40  # the quiet start ranks nothing, the responses rank every sample after it


def _walk_response(est_settings, n=400, delay=4, seed=4):
    """Estimators fed the model's air (a random walk) and a reading that is that air ``delay`` samples late
    through the sensor lag plus an unmodelled random walk of its own (0.25 C per sample); their estimates."""
    rng = np.random.default_rng(seed)
    air = np.cumsum(rng.normal(0.0, 0.4, n))
    lag = np.exp(-1.0 / 5.73)
    sensed = np.zeros(n)
    for k in range(1, n):
        sensed[k] = lag * sensed[k - 1] + (1.0 - lag) * air[max(k - delay, 0)]
    reading = sensed + np.cumsum(rng.normal(0.0, 0.25, n))
    out = []
    for switch_ratio in est_settings:
        est = DeadTimeEstimator(max_steps=6, sensor_tau_s=5.73, switch_ratio=switch_ratio)
        for a, y in zip(air, reading):
            est.push_air(a)
            est.observe(y)
        out.append(est)
    return out


def test_a_candidate_persistently_ahead_takes_over_without_being_clearly_better(monkeypatch):
    """The unmodelled walk keeps every candidate's residual within 0.85 of the others, so none is ever
    "clearly" better (``switch_ratio``); a candidate below LEAD_RATIO of the estimate for LEAD_SAMPLES in a row
    takes over all the same. Without that rule the estimate stays at 0."""
    from hvac_mpc.mpc import dead_time as dtm
    (default, never) = _walk_response((0.7, 0.0))
    assert 3.0 <= default.steps <= 5.0 and 3.0 <= never.steps <= 5.0
    assert np.nanmin(never.residuals) > 0.7 * never.residuals[0]  # never clearly better than 0
    monkeypatch.setattr(dtm, "LEAD_SAMPLES", 10 ** 9)
    (old,) = _walk_response((0.7,))
    assert old.steps == 0.0
