"""The single QPs in the wake of a reference change (docs/architecture.md, 'The wake of a reference change'): the cap on
the QPs of a plain step (``MpcSettings.osqp_plain_qp_cap``, ``RtiOsqpSolver(plain_qp_cap=...)``) and the ceiling on
OSQP's step size at each preparation (``osqp_rho_max``), on the solve-time loop (seed 1) up to the wake of its change at
60 s, where OSQP took 210 iterations at 62 s with the defaults; the trace tool's multiplier shift; the fields checked.

Budget: about 15 s on a loaded two-core machine (three closed loops of 65 steps, the two tests that run them marked
slow; a build of the generated solver, about 3 s, where the code cache does not hold it yet)."""

import time

import numpy as np
import pytest

from hvac_mpc.benchmarks import change_start, solve_time, wake_trace
from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S
from hvac_mpc.mpc import codegen
from hvac_mpc.mpc.mpc_controller import InvalidSettings, MpcController, MpcSettings
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver
from recording_helpers import StartingRho

#: The loop's change to 20 C at 60 s and the slow single QP two samples after it (the flow weights' return).
CHANGE, WAKE = 60, 62
CAP = 60
RHO_MAX = 2e-3
#: A generous bound on the thread CPU time of a capped step (s): 60 OSQP iterations are about 1 ms on this machine.
CAPPED_STEP_BUDGET_S = 0.05


@pytest.fixture(scope="module")
def cache():
    """The code generation switched on while this module's tests run (the generated solver is what runs by default;
    built into the code cache in use where it is not there yet)."""
    mp = pytest.MonkeyPatch()
    mp.setenv(codegen.SWITCH_ENV, "1")
    yield
    mp.undo()


def _loop(steps: int, **fields):
    # the deadline lifted: a missed wall-clock deadline on a loaded machine is the load's, not the solver's
    ctrl = MpcController(settings=MpcSettings(deadline_s=DETERMINISTIC_DEADLINE_S, **fields))
    loop = solve_time.Loop(ctrl, seed=1)
    ctrl.solver._core = rec = StartingRho(ctrl.solver._core)
    rows, thread_s = [], []
    for k in range(steps):
        rec.step = k
        t0 = time.thread_time()
        rows.append(loop.step(k))
        thread_s.append(time.thread_time() - t0)
    assert all(r.stats["fallback"] is None for r in rows)
    return rec, rows, thread_s


@pytest.fixture(scope="module")
def plain(cache):
    return _loop(WAKE + 3)


@pytest.mark.slow
def test_the_cap_bounds_every_plain_steps_qp_and_leaves_the_change_uncapped(plain):
    _, rows, _ = plain
    assert rows[WAKE].stats["iterations"] > CAP  # without the cap: the wake's QP runs on (210 iterations measured)
    _, capped, thread_s = _loop(WAKE + 3, osqp_plain_qp_cap=CAP)
    changes = set(change_start.change_steps(WAKE + 3))
    assert CHANGE in changes
    for k, r in enumerate(capped):
        if k == 0 or k in changes:  # the cold start and the changes (30 s, 60 s): uncapped, two QPs at a change
            continue
        assert r.stats["qp_solves"] == 1 and r.stats["iterations"] <= CAP, k
    assert capped[CHANGE].stats["qp_solves"] == 2 and capped[CHANGE].stats["iterations"] > CAP
    assert capped[WAKE].stats["iterations"] == CAP  # the iterate at the cap taken ...
    # OSQP's inaccurate tolerance met there, not its own
    assert capped[WAKE].stats["status"].startswith(("solved inaccurate", "maximum iterations"))
    assert rows[WAKE].stats["status"].startswith("solved") and "inaccurate" not in rows[WAKE].stats["status"]
    # ... and the steps after start from it: the wake's convergence carried on, within the cap, in fewer iterations
    # than the uncapped QP took alone (measured: 60, 60, 20 against 210, 30, 25)
    assert capped[WAKE + 2].stats["iterations"] < CAP and capped[WAKE + 2].stats["status"] == "solved"
    wake = slice(WAKE, WAKE + 3)
    assert sum(r.stats["iterations"] for r in capped[wake]) < sum(r.stats["iterations"] for r in rows[wake])
    np.testing.assert_array_equal([r.command.vector() for r in capped[:WAKE]],
                                  [r.command.vector() for r in rows[:WAKE]])  # no step before the wake reached it
    assert thread_s[WAKE] < CAPPED_STEP_BUDGET_S


#: A cap low enough that quiet steps reach it too, for the run limit's test.
LOW_CAP = 15


@pytest.mark.slow
@pytest.mark.parametrize("run", [1, 2])
def test_the_run_limit_uncaps_the_plain_step_after_run_capped_ones(run):
    _, capped, _ = _loop(WAKE + 3, osqp_plain_qp_cap=LOW_CAP)
    _, limited, _ = _loop(WAKE + 3, osqp_plain_qp_cap=LOW_CAP, osqp_plain_cap_run=run)
    changes = set(change_start.change_steps(WAKE + 3)) | {0}
    plain_steps = [k for k in range(WAKE + 3) if k not in changes]
    assert all(capped[k].stats["iterations"] <= LOW_CAP for k in plain_steps)  # without the limit: every one capped
    at_cap, over, in_row = 0, 0, 0
    for k in range(1, WAKE + 3):
        its = limited[k].stats["iterations"]
        if k in changes:  # a change's QPs are uncapped: the run is broken
            in_row = 0
            continue
        if in_row == run:  # the step after `run` capped plain steps in a row: uncapped
            over += its > LOW_CAP
            in_row = 0
            continue
        assert its <= LOW_CAP, k  # any other plain step within the cap
        at_cap += its == LOW_CAP
        in_row = in_row + 1 if its == LOW_CAP else 0
    assert at_cap > 0 and over > 0  # both happened: capped steps, and uncapped ones that needed more


@pytest.mark.slow
def test_the_ceiling_holds_each_preparations_step_size(plain):
    kept, rows, _ = plain
    assert max(rho for k, rho in kept.starts if k > CHANGE) > 10 * RHO_MAX  # the change's adaptation carried over
    rec, capped, _ = _loop(WAKE + 3, osqp_rho_max=RHO_MAX)
    # every step's first QP starts at or below the ceiling (a change's second QP where the first left it)
    firsts = {}
    for k, rho in rec.starts:
        firsts.setdefault(k, rho)
    assert all(rho <= RHO_MAX * (1 + 1e-12) for rho in firsts.values())
    assert capped[WAKE].stats["iterations"] < rows[WAKE].stats["iterations"]


@pytest.fixture(scope="module")
def problem():
    return MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False)).problem


def test_the_trace_tools_multiplier_shift_moves_each_stage_one_earlier(problem):
    solver = RtiOsqpSolver(problem)
    y = np.arange(solver.m, dtype=float)
    shifted = wake_trace.shifted_duals(solver, y)
    rate = np.asarray(solver.r_rate)
    np.testing.assert_array_equal(shifted[rate[:-1]], y[rate[1:]])
    np.testing.assert_array_equal(shifted[rate[-1]], y[rate[-1]])
    np.testing.assert_array_equal(shifted[solver.r_x0], y[solver.r_x0])
    assert not np.any(wake_trace.rate_rows_zeroed(solver, y)[rate])


@pytest.mark.parametrize("fields, name", [({"osqp_plain_qp_cap": -1}, "osqp_plain_qp_cap"),
                                          ({"osqp_plain_qp_cap": 2000}, "osqp_plain_qp_cap"),
                                          ({"osqp_plain_qp_cap": 1.5}, "osqp_plain_qp_cap"),
                                          ({"osqp_rho_max": 0.0}, "osqp_rho_max"),
                                          ({"osqp_plain_qp_cap": 60, "osqp_plain_cap_run": -1}, "osqp_plain_cap_run"),
                                          ({"osqp_plain_cap_run": 2}, "osqp_plain_cap_run"),
                                          ({"osqp_rho_max": "high"}, "osqp_rho_max")])
def test_bad_values_are_refused_naming_the_field(fields, name):
    with pytest.raises(InvalidSettings, match=name):
        MpcSettings(**fields)


@pytest.mark.parametrize("kwargs, name", [({"plain_qp_cap": 500}, "plain_qp_cap"),
                                          ({"plain_qp_cap": True}, "plain_qp_cap"),
                                          ({"plain_qp_cap": "many"}, "plain_qp_cap"),
                                          ({"change_split_iter": 2.5}, "change_split_iter"),
                                          ({"plain_cap_run": -1}, "plain_cap_run"),
                                          ({"plain_cap_run": True}, "plain_cap_run"),
                                          ({"plain_cap_run": "many"}, "plain_cap_run"),
                                          ({"rho_max": 1e7}, "rho_max"), ({"rho_max": True}, "rho_max")])
def test_the_solver_refuses_bad_values_naming_them(problem, kwargs, name):
    with pytest.raises(ValueError, match=name):
        RtiOsqpSolver(problem, max_iter=400, **kwargs)


def test_whole_numbers_written_as_floats_build_the_controller_as_integers():
    """A settings file may write 60.0 and 2.0: both fields take them, and the solver gets integers."""
    ctrl = MpcController(settings=MpcSettings(osqp_plain_qp_cap=60.0, osqp_plain_cap_run=2.0))
    assert ctrl.solver.plain_cap_run == 2 and isinstance(ctrl.solver.plain_cap_run, int)
