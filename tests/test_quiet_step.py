"""The quiet step's glue with fewer numpy and interpreter calls (mpc/arrays.py and its uses; docs/architecture.md
"The quiet step's glue"): each shortcut gives its general form's answer to the bit, and a closed loop with the
shortcuts gives the commands of the same loop with the general forms put back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc import arrays, dead_time, estimator, mpc_controller, rti_osqp, valve_map
from hvac_mpc.mpc.dead_time import DeadTimeEstimator
from hvac_mpc.mpc.estimator import finite_or
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.rti_osqp import same_values
from hvac_mpc.mpc.valve_map import ValveMap
from hvac_mpc.models.parameters import Parameters


def _arrays(rng: np.random.Generator) -> list[np.ndarray]:
    """Float arrays of the step's sizes and kinds: finite, with a nan or an infinity of either sign, finite values
    whose sum overflows, empty, two-dimensional and transposed (a view that is not contiguous)."""
    out = [np.zeros(0), np.array([1e308, 1e308]), np.array([-1e308, -1e308, 1.0]), np.full((3, 3), 1e308).T]
    for size in (1, 6, 14, 279):
        a = rng.normal(size=size) * 10.0 ** rng.integers(-3, 4)
        out.append(a)
        for bad in (np.nan, np.inf, -np.inf):
            b = a.copy()
            b[rng.integers(size)] = bad
            out.append(b)
        both = a.copy()
        both[0], both[-1] = np.inf, -np.inf
        out.append(both)
    m = rng.normal(size=(14, 14))
    out += [m, m.T, np.where(m > 2.0, np.nan, m).T]
    return out


def test_all_finite_and_the_reductions_answer_as_numpys_methods():
    rng = np.random.default_rng(0)
    for a in _arrays(rng):
        assert arrays.all_finite(a) is bool(np.isfinite(a).all()), a
        assert arrays.all_reduce(a > 0.0, axis=None) == (a > 0.0).all()
        with np.errstate(all="ignore"):
            pairs = [(arrays.sum_reduce(a, axis=None), a.sum())]
        if a.size:
            pairs.append((arrays.min_reduce(a, axis=None), a.min()))
        for got, expected in pairs:
            assert np.array_equal(np.float64(got).view(np.int64), np.float64(expected).view(np.int64)), a


def test_interp_gives_numpys_interp_to_the_bit_on_the_valve_tables():
    vm = ValveMap(Parameters())
    rng = np.random.default_rng(1)
    for x in (rng.uniform(-50.0, 700.0, size=(40, 3)), np.array([[np.nan, 0.0, 600.0]]), np.linspace(0.0, 600.0, 7)):
        for xp, fp in ((vm._t_stack, vm._v_of_t), (vm._v_stack, vm._t_of_v)):
            expected = np.interp(x, xp, fp)
            got = arrays.interp(x, xp, fp)
            assert got.shape == expected.shape
            assert np.array_equal(got.view(np.int64), expected.view(np.int64))  # the bits, nan included


def test_a_candidates_prediction_is_read_at_its_index_as_the_nearest_search_finds_it():
    est = DeadTimeEstimator(max_steps=8, sensor_tau_s=5.73)
    rng = np.random.default_rng(2)
    for air in 20.0 + rng.normal(size=12):
        est.push_air(float(air))

    def nearest(steps: float) -> float:  # the general form
        return float(est._pred[int(np.argmin(np.abs(est.candidates - float(steps))))])
    for steps in [*est.candidates, 0.25, 3.7, -1.0, 8.5, 100.0, np.float64(2.5), math.nan, math.inf]:
        got, expected = est.prediction_c(steps), nearest(steps)
        assert got == expected or (math.isnan(got) and math.isnan(expected)), steps


def test_same_values_is_numpys_array_equal():
    rng = np.random.default_rng(3)
    a = rng.normal(size=7)
    for b in (a.copy(), a[:6], a.reshape(7, 1), np.where(a > 0, np.nan, a), a + 1e-16 * (a == a.max())):
        assert same_values(a, b) is np.array_equal(a, b)
    nan = np.array([np.nan, 1.0])
    assert same_values(nan, nan.copy()) is np.array_equal(nan, nan.copy()) is False


@pytest.mark.parametrize("value", [1.5, np.float64(-2.0), np.float32(3.0), 7, True, "4.5", math.inf, -math.inf,
                                   math.nan, np.float64(np.nan), None, "x", object()])
def test_finite_or_takes_a_finite_number_and_the_default_otherwise(value):
    got = finite_or(value, -9.0)
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = None
    expected = v if v is not None and np.isfinite(v) else -9.0
    assert got == expected and type(got) is float


def _commands(steps: int) -> np.ndarray:
    loop = solve_time.Loop(MpcController(settings=MpcSettings()), 1)
    try:
        return np.array([loop.step(k).command.vector() for k in range(steps)])
    finally:
        loop.ctrl.close()


@pytest.mark.slow
def test_the_loop_with_the_shortcuts_gives_the_commands_of_their_general_forms(monkeypatch):
    """40 steps of the solve-time loop (a reference change at 30 s and its wake included), the shortcuts of
    mpc/arrays.py in use and then their general forms put back in every module that uses them: the same commands."""
    steps = 40
    fast = _commands(steps)

    def general_interp(x, xp, fp):
        return np.interp(x, xp, fp)
    for module in (estimator, mpc_controller, rti_osqp):
        monkeypatch.setattr(module, "all_finite", lambda a: bool(np.isfinite(a).all()))
    monkeypatch.setattr(valve_map, "interp", general_interp)
    monkeypatch.setattr(dead_time, "min_reduce", lambda a: a.min())
    monkeypatch.setattr(rti_osqp, "all_reduce", lambda a, axis=None: a.all())
    monkeypatch.setattr(rti_osqp, "sum_reduce", lambda a, axis=None: a.sum())
    general = _commands(steps)
    assert np.array_equal(fast, general)
