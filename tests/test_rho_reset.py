"""OSQP's step size reset at every preparation (``MpcSettings.osqp_rho_reset``, ``RtiOsqpSolver(rho_reset=...)``):
the value in force at the start of each QP, taken in by the matrix update's refactorisation of the generated solver
(the same commands and iterations as OSQP's Python interface with its own ``update_rho``), the reset for a reference
change's QPs only (``osqp_rho_reset_on="change"``), fewer OSQP iterations at the solve-time loop's heating change, and
the fields checked.

Budget: about 20 s on a loaded two-core machine (closed loops of 33 to 62 steps; a build of the generated solver,
about 3 s, where the code cache does not hold it yet)."""

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S
from hvac_mpc.mpc import codegen
from hvac_mpc.mpc.mpc_controller import InvalidSettings, MpcController, MpcSettings
from hvac_mpc.mpc.ocp import shift_nodes
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver
from recording_helpers import StartingRho

RHO = 1e-3
#: The solve-time loop's change to 20 C at 60 s (the heater comes on): the change whose QPs took the most OSQP
#: iterations with the step size left by the QPs before (docs/architecture.md, 'Slow steps').
HEATING_CHANGE = 60


@pytest.fixture(scope="module")
def cache():
    """The code generation switched on while this module's tests run (the generated solver is what they check; built
    into the code cache in use where it is not there yet)."""
    mp = pytest.MonkeyPatch()
    mp.setenv(codegen.SWITCH_ENV, "1")
    yield
    mp.undo()


def _loop(steps: int, **fields):
    # the deadline lifted: a missed wall-clock deadline on a loaded machine is the load's, not the solver's
    ctrl = MpcController(settings=MpcSettings(deadline_s=DETERMINISTIC_DEADLINE_S, **fields))
    loop = solve_time.Loop(ctrl, seed=1)
    rec = None
    if ctrl.solver.settings["osqp_generated"]:
        ctrl.solver._core = rec = StartingRho(ctrl.solver._core)
    rows = []
    for k in range(steps):
        if rec is not None:
            rec.step = k
        rows.append(loop.step(k))
    assert all(r.stats["fallback"] is None for r in rows)
    return rec, np.array([r.command.vector() for r in rows]), [r.stats["iterations"] for r in rows]


def test_each_qp_starts_at_the_reset_step_size_and_both_osqp_routes_answer_alike(cache):
    rec, generated, its_g = _loop(35, osqp_rho_reset=RHO)
    assert len(rec.starts) > 35 and all(rho == pytest.approx(RHO) for _, rho in rec.starts)
    kept, _, _ = _loop(35)
    assert sum(rho != pytest.approx(RHO, rel=0.05) for _, rho in kept.starts) > 10  # without: the adaptation stays
    _, interface, its_i = _loop(35, osqp_rho_reset=RHO, osqp_codegen=False)
    np.testing.assert_array_equal(generated, interface)  # the fused reset is OSQP's update_rho, then the update
    assert its_g == its_i


def test_reset_on_changes_only_sets_it_for_the_change_steps_qps(cache):
    change = int(solve_time.SCENARIO[1][0])
    rec, _, _ = _loop(change + 3, osqp_rho_reset=RHO, osqp_rho_reset_on="change")
    at_change = [rho for k, rho in rec.starts if k == change]
    assert at_change[0] == pytest.approx(RHO)  # the change's first QP (its second starts where the first left it)
    assert sum(rho != pytest.approx(RHO, rel=0.05) for k, rho in rec.starts if k != change) > 10


def test_the_heating_change_takes_fewer_osqp_iterations_with_the_reset(cache):
    _, _, reset = _loop(HEATING_CHANGE + 2, osqp_rho_reset=RHO)
    _, _, kept = _loop(HEATING_CHANGE + 2)
    assert reset[HEATING_CHANGE] < 0.9 * kept[HEATING_CHANGE]


@pytest.mark.parametrize("value", [0.0, -1e-3, 1e7, float("nan"), True, "1e-3"])
def test_a_step_size_outside_the_range_is_refused_naming_the_field(value):
    with pytest.raises(InvalidSettings, match=r"MpcSettings\.osqp_rho_reset"):
        MpcSettings(osqp_rho_reset=value)


def test_the_solver_refuses_a_bad_step_size_naming_the_argument():
    pb = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False)).problem
    with pytest.raises(ValueError, match=r"rho_reset = 0\.0, allowed: None or a number in \[1e-6, 1e6\]"):
        RtiOsqpSolver(pb, rho_reset=0.0)
    with pytest.raises(ValueError, match=r"rho_reset_on = 'always', allowed: one of \['preparation', 'change'\]"):
        RtiOsqpSolver(pb, rho_reset=RHO, rho_reset_on="always")
    with pytest.raises(InvalidSettings, match=r"MpcSettings\.osqp_rho_reset_on = 'always' must be one of"):
        MpcSettings(osqp_rho_reset_on="always")


@pytest.mark.parametrize("in_place", [False, True])
def test_weights_changed_after_the_preparation_relinearise_the_prepared_plan_or_one_shifted_again(in_place):
    """``reweigh_in_place``: where the output weights change between the preparation and the feedback (the flow's
    weight factor, steps after the loop's reference changes) without a reference change, the QP is linearised
    again at the plan the preparation shifted (on), or at that plan shifted once more (off, the default)."""
    ctrl = MpcController(settings=MpcSettings(deadline_s=DETERMINISTIC_DEADLINE_S, reweigh_in_place=in_place))
    sv = ctrl.solver
    loaded, pure_reweighs = [], []
    load, feedback = sv._load, sv.feedback

    def spy_load(X, *args):
        loaded.append(X.copy())
        return load(X, *args)

    def spy_feedback(x0, u_prev, d, ref, w_y, *args, **kw):
        p, plan = sv._prepared, None if sv.X is None else sv.X.copy()
        before = len(loaded)
        out = feedback(x0, u_prev, d, ref, w_y, *args, **kw)
        if p is not None and np.array_equal(p["ref"], ref) and not np.array_equal(p["w_y"], w_y):
            pure_reweighs.append((plan, loaded[before]))  # (the plan prepared, the one linearised again)
        return out

    sv._load, sv.feedback = spy_load, spy_feedback
    loop = solve_time.Loop(ctrl, seed=1)
    for k in range(160):
        loop.step(k)
    assert pure_reweighs, "the loop changes the weights without a reference change (step 151)"
    for prepared, again in pure_reweighs:
        shifted = shift_nodes(prepared, sv._i0, sv._w1)
        if in_place:
            np.testing.assert_array_equal(again[1:], prepared[1:])
        else:
            assert not np.array_equal(again[1:], prepared[1:])
            np.testing.assert_array_equal(again[1:], shifted[1:])


def test_reweigh_in_place_is_checked():
    with pytest.raises(InvalidSettings, match="reweigh_in_place"):
        MpcSettings(reweigh_in_place=1)
