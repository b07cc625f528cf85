"""What a fit costs, without changing what it finds (identification/fitting.py, identification/simulator.py): the
Jacobian scipy's trust-region solver computes after its last evaluation is not computed (a sensitivity run of the
whole log) and a simulator keeps its last free runs."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from hvac_mpc.identification.fitting import NOMINAL_FREE, Fitter, capped_least_squares
from hvac_mpc.identification.log_data import load
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS
from hvac_mpc.identification.simulator import OutputPost
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.models import Parameters

T = np.linspace(0.0, 5.0, 200)
Y = 3.0 * np.exp(-0.7 * T) + 0.5 * np.sin(2.0 * T)


def _problem(jac_calls: list):
    def resid(th):
        return th[0] * np.exp(-th[1] * T) + th[2] * np.sin(th[3] * T) - Y

    def jac(th):
        jac_calls.append(th.copy())
        e = np.exp(-th[1] * T)
        return np.column_stack([e, -th[0] * T * e, np.sin(th[3] * T), th[2] * T * np.cos(th[3] * T)])
    return resid, jac


@pytest.mark.parametrize("max_nfev", [1, 2, 3, 6])
def test_the_capped_solver_finds_what_scipy_finds_with_one_jacobian_less(max_nfev):
    x0, bounds = np.array([1.0, 0.3, 0.1, 1.5]), ([0.0, 0.0, -5.0, 0.0], [10.0, 5.0, 5.0, 5.0])
    plain_calls, capped_calls = [], []
    resid, jac = _problem(plain_calls)
    plain = least_squares(resid, x0, jac=jac, bounds=bounds, method="trf", x_scale="jac", max_nfev=max_nfev,
                          ftol=1e-8, xtol=1e-8, gtol=1e-10)
    resid, jac = _problem(capped_calls)
    capped = capped_least_squares(resid, jac, x0, bounds, max_nfev)
    assert np.array_equal(capped.x, plain.x) and capped.nfev == plain.nfev == max_nfev
    assert capped.cost == plain.cost and capped.status == plain.status
    assert len(capped_calls) == len(plain_calls) - (1 if max_nfev > 1 else 0)


@pytest.fixture(scope="module")
def fitter(tmp_path_factory):
    path = tmp_path_factory.mktemp("fitcost") / "log.csv"
    simulate_log(path, "nominal", duration_s=900, seed=5)
    return Fitter(load(path), Parameters())


def test_a_simulator_keeps_its_last_runs_and_hands_out_copies(fitter):
    sim = fitter.simulator(DOCUMENTED_EFFECTS)
    p = np.array(Parameters().vector(), dtype=float)
    y1, x1 = sim.simulate(p)
    y1[:] = np.nan  # the caller's copy
    y2, x2 = sim.simulate(p)
    assert np.all(np.isfinite(y2)) and np.array_equal(x1, x2)
    q = p.copy()
    q[fitter.names.index("cooler_slope")] += 0.05
    assert not np.array_equal(sim.simulate(q)[0], y2)
    assert np.array_equal(sim.simulate(p)[0], y2)


def test_a_fit_stopped_at_its_cap_runs_one_sensitivity_less_than_evaluations(fitter, monkeypatch):
    sim = fitter.simulator(DOCUMENTED_EFFECTS)
    runs = []
    real = sim.simulate_with_sensitivity
    monkeypatch.setattr(sim, "simulate_with_sensitivity", lambda p, e, *rows: runs.append(1) or real(p, e, *rows))
    free = [fp for fp in NOMINAL_FREE if fp.name in ("cooler_slope", "motor_gain_max_c")]
    p = np.array(Parameters().vector(), dtype=float)
    p[fitter.names.index("cooler_slope")] += 0.05
    post = OutputPost(fitter.outputs, fitter.log.time_s)
    fit = fitter.fit(DOCUMENTED_EFFECTS, p, free, post, max_nfev=3)
    assert fit.nfev == 3 and fit.cost_train < fitter.evaluate(DOCUMENTED_EFFECTS, p, post).cost_train
    assert len(runs) <= fit.nfev - 1
