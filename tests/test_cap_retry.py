"""The retry of a QP at OSQP's iteration cap (``MpcSettings.osqp_cap_retry_rho`` / ``osqp_cap_retry_share``;
docs/robustness.md sec. 2.40): the reserve's step down at 390 s on the independent literal-cooler box
(tests/test_reserve_step_down.py's run) with sec. 2.37's heat package F, whose change's first QP ends at OSQP's 1000
iterations without an answer and so falls back to the shifted plan."""

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.benchmarks.change_rho import reserve_run
from hvac_mpc.mpc import codegen, osqp_embedded
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings


@pytest.mark.slow
def test_the_reserves_step_down_with_the_heat_package_is_answered_by_the_retry_at_the_cap():
    """Measured: the change's first QP at OSQP's cap ("maximum iterations reached", the step size 0.009 it started
    from) takes 150 iterations from 3e-3 warm-started at the capped iterate; its second QP (1000, solved inaccurate)
    460; no fallback, valve a 0.0 % (41.3 % on the shifted plan without the retry), IAE from 390 s 40.86 C s (46.43
    without)."""
    run = reserve_run(True, {"osqp_cap_retry_rho": 3e-3}, interface=False)
    assert run["fallback"] is None, run["fallback"]
    qps = run["changes"][0]["qps"]  # each OSQP solve of the step at 390 s, the retries included
    capped, retried = qps[0], qps[1]
    assert capped["iterations"] == 1000 and capped["status"] == "maximum iterations reached", capped
    assert retried["rho_start"] == 3e-3 and retried["iterations"] < 500 and retried["status"] == "solved", retried
    assert run["valve_a_pct"] < 10.0, run["valve_a_pct"]
    assert run["iae_cs"] < 44.0, run["iae_cs"]


def test_the_retry_settings_are_checked():
    for fields, named in ((dict(osqp_cap_retry_rho=-1.0), "osqp_cap_retry_rho"),
                          (dict(osqp_cap_retry_rho=1e7), "osqp_cap_retry_rho"),
                          (dict(osqp_cap_retry_share=1.5), "osqp_cap_retry_share"),
                          (dict(osqp_cap_retry_rho=1e-2, osqp_cap_retry_share=0.3), "both set"),
                          (dict(osqp_cap_retry_rho=None), "osqp_cap_retry_rho"),
                          (dict(osqp_cap_retry_rho="abc"), "osqp_cap_retry_rho"),
                          (dict(osqp_cap_retry_cold=1), "osqp_cap_retry_cold")):
        with pytest.raises(InvalidSettings, match=named):
            MpcSettings(**fields)
    s = MpcSettings()  # the default since docs/robustness.md sec. 2.44: 3e-3, not on a cold start
    assert (s.osqp_cap_retry_rho, s.osqp_cap_retry_share, s.osqp_cap_retry_cold,
            s.osqp_cap_retry_on_cold_start) == (3e-3, 0.0, False, False)
    solver = MpcController(settings=MpcSettings(osqp_cap_retry_share=0.3, osqp_cap_retry_cold=True)).solver
    assert (solver.settings["cap_retry_rho"], solver.settings["cap_retry_share"],
            solver.settings["cap_retry_cold"]) == (0.0, 0.3, True)  # the share replaces the default step size
    for fields in (dict(osqp_cap_retry_share=0.3), dict(osqp_cap_retry_cold=True)):
        with pytest.raises(InvalidSettings, match=r"osqp_cap_retry_share / osqp_cap_retry_cold "
                                                  r"with .*solver = 'ipopt'.*allowed: solver 'rti' or 'sqp'"):
            MpcSettings(solver="ipopt", **fields)
    # the step size alone does nothing with IPOPT (as osqp_max_iter): the default accepted there
    assert MpcSettings(solver="ipopt").osqp_cap_retry_rho == 3e-3


@pytest.mark.parametrize("generated", [False, True])
def test_a_retry_not_taken_leaves_osqps_workspace_as_the_capped_qp_left_it(generated, code_cache, monkeypatch):
    """OSQP capped at 10 iterations: the cold first steps' QP ends at the cap without an answer, the retry at
    rho 1e-3 (from OSQP's 0.1) too; the capped solve's status is the step's, and OSQP's step size is the one before
    the retry again (the generated solver's whole workspace, multipliers and factorisation included, to the bit), so
    the next step does not start from the retry's. Each step's retries in ``extra["cap_retries"]``. Both
    steps fail, so both are cold starts: the retry is set on them (``osqp_cap_retry_on_cold_start`` True)."""
    if generated:
        monkeypatch.setenv(codegen.CACHE_ENV, str(code_cache))
        monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=generated, osqp_max_iter=10,
                                              osqp_cap_retry_rho=1e-3, osqp_cap_retry_on_cold_start=True))
    solver = ctrl.solver
    core = solver._core
    if generated and not isinstance(core, osqp_embedded.EmbeddedOsqp):
        ctrl.close()
        pytest.skip("OSQP's generated solver not built here")
    retried, results, seen = solver._retry_at_cap, [], []
    feedback = solver.feedback

    def retry(first, *args):
        before = (core.rho, core.save_state())
        taken = retried(first, *args)
        seen.append((first, taken, before, (core.rho, core.save_state())))
        return taken

    solver._retry_at_cap = retry
    solver.feedback = lambda *a, **k: results.append(feedback(*a, **k)) or results[-1]
    loop = solve_time.Loop(ctrl, 1)
    for k in range(2):
        loop.step(k)
    ctrl.close()
    assert len(seen) == 2 and [r.extra["cap_retries"] for r in results] == [1, 1]
    for (first, taken, before, after), result in zip(seen, results):
        # the capped solve's answer taken (none: the step fails), the retry's 10 iterations counted
        assert taken[0] is first and taken[1] == 10 and not result.ok and result.status == str(first[1])
        assert before[0] == after[0] == 0.1  # the retry ran at 1e-3, the step size set back
        if generated:
            assert np.array_equal(before[1]["buf"].view(np.int64), after[1]["buf"].view(np.int64))
    assert solver.cap_retries[0]["rho"] == (0.1, 1e-3)


def test_a_retry_is_counted_per_step_and_absent_when_off():
    """``cap_retries`` holds the step's retries (reset at each step, not at each QP run) and the result's extra
    has the count only with the retry set (with ``osqp_cap_retry_rho`` 0 the step's extra as before the retry)."""
    for rho, extra in ((0.0, {}), (3e-3, {"cap_retries": 0})):
        ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False, osqp_cap_retry_rho=rho))
        loop = solve_time.Loop(ctrl, 1)
        results = []
        feedback = ctrl.solver.feedback
        ctrl.solver.feedback = lambda *a, _f=feedback, _r=results, **k: _r.append(_f(*a, **k)) or _r[-1]
        loop.step(0)
        ctrl.close()
        assert {k: v for k, v in results[0].extra.items() if k == "cap_retries"} == extra, results[0].extra
        assert ctrl.solver.cap_retries == []


def _retries_per_step(on_cold_start: bool, steps: int, reset_at: int) -> list[tuple[bool, int]]:
    """OSQP capped at 10 iterations (its iterate at the cap taken, ``osqp_accept_max_iter``), the retry at 3e-3 with
    ``osqp_cap_retry_on_cold_start`` as given, the solve-time loop: per step (the controller reset before step
    ``reset_at``), whether the step was a cold start and how many of its QPs were retried at the cap."""
    ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False, osqp_max_iter=10,
                                              osqp_accept_max_iter=True, osqp_cap_retry_rho=3e-3,
                                              osqp_cap_retry_on_cold_start=on_cold_start))
    loop = solve_time.Loop(ctrl, 1)
    results = []
    feedback = ctrl.solver.feedback
    ctrl.solver.feedback = lambda *a, **k: results.append(feedback(*a, **k)) or results[-1]
    for k in range(steps):
        if k == reset_at:
            ctrl.reset(loop.plant.command)
        loop.step(k)
    ctrl.close()
    return [(r.extra["cold_start"], r.extra["cap_retries"]) for r in results]


def test_a_cold_starts_qps_are_retried_only_with_the_setting_and_a_reset_arms_the_skip_again():
    """With ``osqp_cap_retry_on_cold_start`` False the first step's QPs at the cap (a cold start: measured 10 QPs
    at the cap of 10 iterations, all retried with True) are not retried, the next step's (one QP at the cap) is; the
    step after a reset is a cold start again and not retried, the one after it is. With True every step's QPs at the
    cap are retried (the retry as in docs/robustness.md sec. 2.40)."""
    skipped = _retries_per_step(False, 4, reset_at=2)
    retried = _retries_per_step(True, 4, reset_at=2)
    assert [cold for cold, _ in skipped] == [cold for cold, _ in retried] == [True, False, True, False], skipped
    assert [n for _, n in skipped][0::2] == [0, 0], skipped  # the cold starts (start, after the reset)
    assert all(n > 0 for _, n in skipped[1::2]), skipped  # the steps after them
    assert all(n > 0 for _, n in retried) and retried[0][1] > 1, retried


def test_the_cold_start_setting_is_checked_and_reported():
    with pytest.raises(InvalidSettings, match="osqp_cap_retry_on_cold_start"):
        MpcSettings(osqp_cap_retry_on_cold_start=0)
    solver = MpcController(settings=MpcSettings(osqp_cap_retry_rho=3e-3, osqp_cap_retry_on_cold_start=False)).solver
    assert solver.settings["cap_retry_on_cold_start"] is False
    assert MpcSettings(solver="ipopt", osqp_cap_retry_on_cold_start=True).osqp_cap_retry_on_cold_start is True
    assert MpcSettings(osqp_cap_retry_share=0.3).cap_retry_rho_used == 0.0  # the share replaces the default
    assert MpcSettings(osqp_cap_retry_rho=0.0).cap_retry_rho_used == 0.0  # off
