"""What a fit costs, without changing what it finds (identification/fitting.py, identification/simulator.py): the
Jacobian scipy's trust-region solver computes after its last evaluation is not computed (a sensitivity run of the
whole log), a simulator keeps its last free runs and runs the log in calls of a few hundred rows, and a fit runs the
training rows alone: each checked against the plain form, to the bit."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from hvac_mpc.identification import discovery
from hvac_mpc.identification.diagnostics import innovations_nll, training_nll
from hvac_mpc.identification.fitting import NOMINAL_FREE, Fitter, capped_least_squares
from hvac_mpc.identification.log_data import load
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS, identify
from hvac_mpc.identification.simulator import CHUNK_ROWS, INITIAL_STD, PROCESS_NOISE, OutputPost, Simulator
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.models import Parameters
from hvac_mpc.models.discovered import DiscoveredTerm

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


def _whole_log(fn, n, x0, *args):
    """``fn`` mapped over the whole log in one call (the form the runs had before they were chained)."""
    xs, ys = fn.mapaccum("whole", n, [0], [0])(x0, *args)
    return np.asarray(xs).T, np.asarray(ys).T


def test_a_run_in_calls_of_200_rows_is_the_run_over_the_whole_log_to_the_bit(fitter):
    sim = fitter.simulator(DOCUMENTED_EFFECTS)
    n = fitter.log.n
    assert n % CHUNK_ROWS != 0 and n > 2 * CHUNK_ROWS  # whole calls and a shorter last one
    p = np.array(Parameters().vector(), dtype=float)
    p[fitter.names.index("cooler_slope")] += 0.03
    x0, dx0 = sim.initial_state(p)
    _, y_whole = _whole_log(sim.f_step_y, n, x0, sim.z_for(p), p)
    assert np.array_equal(sim.simulate(p)[0], y_whole)
    free = [fp for fp in NOMINAL_FREE if fp.name in ("cooler_slope", "heater_kp")]
    e = fitter._e_matrix(p, free)
    xa0 = np.concatenate([x0, (dx0 @ e).ravel(order="F")])
    scale = np.array([e[fitter.names.index(fp.name), j] for j, fp in enumerate(free)])
    idx = tuple(fitter.names.index(fp.name) for fp in free)
    _, out = _whole_log(sim._aug(idx), n, xa0, sim.z_for(p), p, scale)
    y, dy = sim.simulate_with_sensitivity(p, e)
    assert np.array_equal(y, out[:, :sim.ny]) and np.array_equal(y, y_whole)  # the free run inside it too
    assert np.array_equal(dy, out[:, sim.ny:].reshape(n, sim.ny, len(free), order="F"))


def test_a_run_of_the_training_rows_is_the_whole_runs_start_and_continues_to_it(fitter):
    sim = fitter.simulator(DOCUMENTED_EFFECTS, ())
    rows = fitter.train_rows
    assert rows == np.flatnonzero(fitter.log.train)[-1] + 1 and fitter.log.holdout[rows:].all()
    p = np.array(Parameters().vector(), dtype=float)
    p[fitter.names.index("heater_kp")] *= 0.97
    y_part, x_part = sim.simulate(p, rows)
    assert np.all(np.isnan(y_part[rows:])) and np.all(np.isfinite(y_part[:rows]))
    y_full, x_full = sim.simulate(p)  # continued from the kept shorter run
    y_ref, x_ref = Simulator(fitter.log, fitter.base, DOCUMENTED_EFFECTS, fitter.outputs).simulate(p)  # from the start
    assert np.array_equal(y_full, y_ref) and np.array_equal(x_full, x_ref)
    assert np.array_equal(y_part[:rows], y_ref[:rows]) and np.array_equal(x_part[:rows], x_ref[:rows])
    free = [fp for fp in NOMINAL_FREE if fp.name in ("cooler_slope", "motor_gain_max_c")]
    e = fitter._e_matrix(p, free)
    _, dy_part = sim.simulate_with_sensitivity(p, e, rows)
    _, dy_full = sim.simulate_with_sensitivity(p, e)
    assert np.array_equal(dy_part[:rows], dy_full[:rows]) and np.all(np.isnan(dy_part[rows:]))


def test_the_training_cost_and_a_fit_from_training_rows_are_those_from_whole_runs(fitter):
    p = np.array(Parameters().vector(), dtype=float)
    p[fitter.names.index("cooler_slope")] += 0.05
    post = OutputPost(fitter.outputs, fitter.log.time_s, bias={"supply_temp_c": (0.1, -0.05)})
    assert fitter.train_cost(DOCUMENTED_EFFECTS, p, post) == fitter.evaluate(DOCUMENTED_EFFECTS, p, post).cost_train
    free = [fp for fp in NOMINAL_FREE if fp.name in ("cooler_slope", "motor_gain_max_c", "heater_kp")]
    short = fitter.fit(DOCUMENTED_EFFECTS, p, free, post, max_nfev=4, bias_outputs=["heater_outlet_temp_c"])
    whole = Fitter(fitter.log, fitter.base)
    whole.train_rows = fitter.log.n  # every run over the whole log
    ref = whole.fit(DOCUMENTED_EFFECTS, p, free, post, max_nfev=4, bias_outputs=["heater_outlet_temp_c"])
    assert np.array_equal(short.p, ref.p) and short.post.bias == ref.post.bias
    assert short.cost_train == ref.cost_train and short.cost_holdout == ref.cost_holdout
    assert short.p[fitter.names.index("cooler_slope")] != p[fitter.names.index("cooler_slope")]  # it moved


def test_the_filters_innovations_in_calls_of_200_rows_are_those_of_one_call(fitter):
    sim = fitter.simulator(DOCUMENTED_EFFECTS)
    p = np.array(Parameters().vector(), dtype=float)
    nu, s = sim.innovations(p, fitter.y_meas, fitter.sigma ** 2)
    names = sim.model.states.names
    x0, _ = sim.initial_state(p)
    q = np.array([PROCESS_NOISE[nm] ** 2 for nm in names]) * fitter.log.dt_s
    if sim._flag:  # the logged water temperature replaces the state
        q[sim.model.states.index("water_temp_c")] = 0.0
    mask = np.isfinite(fitter.y_meas).astype(float)
    xa0 = np.concatenate([x0, np.diag([INITIAL_STD[nm] ** 2 for nm in names]).ravel()])
    _, out = _whole_log(sim._ekf(), fitter.log.n, xa0, sim.z_for(p), p, fitter.sigma ** 2, q,
                        np.where(mask > 0, fitter.y_meas, 0.0).T, mask.T)
    nu_ref = out[:, :sim.ny]
    nu_ref[mask == 0] = np.nan
    assert np.array_equal(nu, nu_ref, equal_nan=True) and np.array_equal(s, out[:, sim.ny:])


def test_the_training_likelihood_and_a_terms_coefficients_from_training_rows_are_those_from_whole_runs(fitter):
    p = np.array(Parameters().vector(), dtype=float)
    p[fitter.names.index("heater_kp")] *= 1.04
    post = OutputPost(fitter.outputs, fitter.log.time_s, delays={"supply_temp_c": 2})
    fit = fitter.evaluate(DOCUMENTED_EFFECTS, p, post)
    assert training_nll(fitter, fit) == innovations_nll(fitter, fit)[2]
    term = DiscoveredTerm("box_inlet_term", "box_in", ("inlet", "one"), (0.01, -0.2))
    with_term = fitter.evaluate(DOCUMENTED_EFFECTS, p, post, terms=(term,))
    short = discovery.refit_coefficients(fitter, with_term, term)
    whole = Fitter(fitter.log, fitter.base)
    whole.train_rows = fitter.log.n
    assert short.coefficients == discovery.refit_coefficients(whole, with_term, term).coefficients
    assert short.coefficients != term.coefficients


@pytest.mark.slow
def test_identify_runs_the_linear_algebra_on_one_thread_and_gives_the_threads_back(tmp_path):
    threadpoolctl = pytest.importorskip("threadpoolctl", reason="threadpoolctl comes with scikit-learn "
                                                                "(pip install 'hvac-mpc[discovery]')")

    def blas_threads():
        return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
    seen = []
    path = tmp_path / "log.csv"
    simulate_log(path, "nominal", duration_s=600, seed=3)
    # the suite runs BLAS on one thread (conftest): give it two here, so the limit inside identify shows
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        if not before or set(before) != {2}:
            pytest.skip(f"the BLAS library here does not take two threads (reports {before})")
        res = identify(load(path), quick=True, progress=lambda msg: seen.append(blas_threads()))
        assert seen and all(set(s) == {1} for s in seen)
        assert blas_threads() == before
    t = res.timings
    assert 0.0 <= t["further_discovery_cpu_s"] <= t["discovery_cpu_s"] + 1e-9  # its share of the discovery's time
