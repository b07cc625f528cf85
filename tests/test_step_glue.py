"""The step's glue restructured (docs/architecture.md "The step's glue"): each new compiled piece gives the values of
the separate calls it replaces to the bit, and a closed loop with it gives the commands of the same loop with the
separate calls put back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.sign_check import HeldAirChange, ValveSignCheck, predicted_air_change_c


def _bits(x: float) -> int:
    return int(np.float64(x).view(np.int64))


@pytest.fixture(scope="module")
def looped():
    """A controller after 40 steps of the solve-time loop (a reference change at 30 s and its wake included), with
    the filters' states of each step kept."""
    ctrl = MpcController(settings=MpcSettings())
    loop = solve_time.Loop(ctrl, 1)
    states = []
    for k in range(40):
        loop.step(k)
        states.append([(f.z.copy(), f.p.copy()) if f.initialised else None for f in ctrl._filters])
    yield ctrl, states
    ctrl.close()


def test_the_held_air_change_in_one_call_is_the_separate_calls_of_f_p_to_the_bit(looped):
    """Both filters, the generated function the controller uses and the interpreted one, at the loop's states and
    at commands drawn around the loop's (inputs at and beyond their bounds included), setpoints from 0 to 12 C."""
    ctrl, states = looped
    assert ctrl.sign_check is not None and len(ctrl._filters) == 2
    horizon = ctrl.sign_check.horizon
    rng = np.random.default_rng(3)
    checked = 0
    for i, f in enumerate(ctrl._filters):
        in_use = ctrl._air_change[id(f)]
        interpreted = HeldAirChange(f, horizon)
        assert in_use.steps == interpreted.steps == horizon
        saved = f.z.copy(), f.p.copy()
        try:
            for step_states in states[::3]:
                if step_states[i] is None:
                    continue
                f.z[...], f.p[...] = step_states[i]
                for _ in range(3):
                    u_before = ctrl.u_prev + rng.normal(0.0, 10.0, ctrl.u_prev.size)
                    u_after = u_before + rng.normal(0.0, 40.0, ctrl.u_prev.size)
                    setpoint = float(rng.uniform(0.0, 12.0))
                    expected = predicted_air_change_c(f, u_before, u_after, setpoint, horizon)
                    assert math.isfinite(expected)
                    for held in (in_use, interpreted):
                        assert _bits(held(u_before, u_after, setpoint)) == _bits(expected)
                    checked += 1
        finally:
            f.z[...], f.p[...] = saved
    assert checked >= 60


def test_the_held_air_change_of_a_filter_not_initialised_is_nan():
    ctrl = MpcController(settings=MpcSettings())
    try:
        f = ctrl._filters[1]
        assert not f.initialised
        u = np.zeros(ctrl.u_prev.size)
        assert math.isnan(ctrl._air_change[id(f)](u, u, 5.0))
        assert math.isnan(predicted_air_change_c(f, u, u, 5.0, ctrl.sign_check.horizon))
    finally:
        ctrl.close()


@pytest.mark.slow
def test_the_loop_with_the_one_call_gives_the_commands_of_the_separate_calls(monkeypatch):
    """60 steps of the solve-time loop (the sign check predicting in about a third of them), the held air change in
    one call and then as the separate calls of ``f_p`` it replaces: the same commands and the same verdicts."""
    def run():
        ctrl = MpcController(settings=MpcSettings())
        loop = solve_time.Loop(ctrl, 1)
        try:
            commands = np.array([loop.step(k).command.vector() for k in range(60)])
            return commands, ctrl.sign_check.verdicts
        finally:
            ctrl.close()
    calls = []
    original = HeldAirChange.__call__

    def counted(self, u_before, u_after, setpoint_c):
        calls.append(1)
        return original(self, u_before, u_after, setpoint_c)
    monkeypatch.setattr(HeldAirChange, "__call__", counted)
    one_call = run()
    assert len(calls) >= 20  # the check predicted in the loop

    def separate(self, u_before, u_after, setpoint_c):
        return predicted_air_change_c(self.ekf, u_before, u_after, setpoint_c, self.steps)
    monkeypatch.setattr(HeldAirChange, "__call__", separate)
    separate_calls = run()
    assert np.array_equal(one_call[0], separate_calls[0])
    assert one_call[1] == separate_calls[1]


def test_the_rest_computed_once_per_sample_is_the_rest_of_the_history_as_it_is():
    """The sign check's rest, kept from its first computation until the next sample, at every call of a run of
    rests, departures, verdicts, abandoned departures and resets (``_rest_now`` computes it afresh)."""
    rng = np.random.default_rng(4)
    check = ValveSignCheck(20.0, 0.5, 15.0, 10.0, 1.0)
    valve, reading, asked = 0.0, 20.0, 0
    for k in range(3000):
        if rng.random() < 0.03:
            valve = float(rng.uniform(0.0, 100.0))
        reading += float(rng.normal(0.0, 0.05)) + (0.3 if rng.random() < 0.05 else 0.0)
        for _ in range(int(rng.integers(1, 3))):
            assert check._rest() == check._rest_now()
            check.wants_prediction(valve)
            asked += check._rest() is not None
        check.observe(reading, valve, float(rng.normal()), float(rng.normal()))
        assert check._rest() == check._rest_now()
        if rng.random() < 0.01:
            check.abandon()
        if rng.random() < 0.002:
            check.reset()
    assert asked > 100 and check.verdicts > 0


def _rest_general(check: ValveSignCheck):
    """The rest as first written (np.ptp, np.mean)."""
    if len(check._history) < check.rest:
        return None
    valve, reading = np.array(check._history).T
    if np.ptp(valve) > check.rest_tol_pct or np.ptp(reading) > check.rest_tol_c:
        return None
    return float(np.mean(valve)), float(np.mean(reading))


@pytest.mark.parametrize("rest_s", [2.0, 10.0, 37.0, 600.0])
def test_the_rest_without_numpys_wrappers_is_its_general_form_to_the_bit(rest_s):
    """Histories of 2 to 600 samples (numpy's pairwise summation over more than eight), at rest and not."""
    rng = np.random.default_rng(int(rest_s))
    check = ValveSignCheck(20.0, 0.5, 15.0, rest_s, 1.0)
    rests = 0
    for k in range(1500):
        scale = 10.0 ** float(rng.uniform(-3.0, 1.5)) if k >= 800 else 0.01  # at rest first, then mostly not
        valve = 40.0 + float(rng.normal(0.0, 0.3)) * scale
        check.observe(15.0 + float(rng.normal(0.0, 0.02)) + 1e-7 * k, valve)
        check.abandon()
        got, expected = check._rest_now(), _rest_general(check)
        assert (got is None) == (expected is None)
        if got is not None:
            rests += 1
            assert [_bits(v) for v in got] == [_bits(v) for v in expected]
    assert rests > 20
