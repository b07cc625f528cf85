"""A reference change split between the step and the second thread (``MpcSettings.change_split_iter``): the
change's QPs capped in the step, their rest (the QPs to convergence and the next preparation from that plan)
finished on the controller's worker, collected by the next step whatever the thread's speed."""

import dataclasses
import threading

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import InvalidSettings, MpcController, MpcSettings
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

CAP = 10
CHANGE_STEP = 30  # solve_time.SCENARIO's first reference change
STEPS = CHANGE_STEP + 4
SPLIT = MpcSettings(codegen=False, deadline_s=3600.0, change_split_iter=CAP)


def _recorded(ctrl: MpcController) -> dict:
    """Wrap the solver's finish_change and prepare_predicted: the threads they ran on, finish_change's answers,
    and the plan each preparation shifted (the solver's ``U`` when it is called)."""
    seen = {"finish": [], "prepared_from": []}
    solver = ctrl.solver
    finish, prepare = solver.finish_change, solver.prepare_predicted

    def finish_change():
        sol = finish()
        seen["finish"].append((threading.get_ident(), sol))
        return sol

    def prepare_predicted(*args, **kwargs):
        seen["prepared_from"].append(solver.U.copy())
        return prepare(*args, **kwargs)

    solver.finish_change, solver.prepare_predicted = finish_change, prepare_predicted
    return seen


def _run(settings: MpcSettings, steps: int = STEPS, idle_s: float = 0.0):
    ctrl = MpcController(settings=settings)
    seen = _recorded(ctrl)
    loop = solve_time.Loop(ctrl, seed=1, idle_s=idle_s)
    stats, commands = [], []
    for k in range(steps):
        res = loop.step(k)
        stats.append(res.stats)
        commands.append(res.command.vector())
    ctrl.close()
    return np.array(commands), stats, seen, ctrl


def test_a_change_takes_its_capped_qps_in_the_step_and_the_next_step_collects_the_converged_rest():
    commands, stats, seen, ctrl = _run(SPLIT)
    default = _run(dataclasses.replace(SPLIT, change_split_iter=0))
    change = stats[CHANGE_STEP]
    # in the step: the change's two QPs, each at most CAP iterations; without the split the change takes more
    assert change["fallback"] is None and change["qp_solves"] == 2 and change["iterations"] <= 2 * CAP
    assert default[1][CHANGE_STEP]["iterations"] > 2 * CAP
    # identical up to the change, then the split's command differs (the capped answer)
    assert np.array_equal(commands[:CHANGE_STEP], default[0][:CHANGE_STEP])
    # the rest ran once, on the worker's thread, converged, and the next step collected it
    assert len(seen["finish"]) == 1
    ident, rest = seen["finish"][0]
    assert ident != threading.get_ident()
    assert rest.ok and not rest.extra["inexact"] and rest.iterations > 0
    collected = stats[CHANGE_STEP + 1]["change_finish"]
    assert collected["ok"] and collected["prepared"] and collected["iterations"] == rest.iterations
    assert all("change_finish" not in st for k, st in enumerate(stats) if k != CHANGE_STEP + 1)
    # one preparation per step; the change's preparation shifted the converged plan, not the capped one
    assert len(seen["prepared_from"]) == STEPS
    assert np.array_equal(seen["prepared_from"][CHANGE_STEP], rest.U)
    assert not np.allclose(rest.U[0], ctrl.problem.scale_u(commands[CHANGE_STEP]), atol=1e-6)
    # the steps after the change are ordinary ones (one QP, no fallback)
    assert all(st["fallback"] is None and st["qp_solves"] == 1 for st in stats[CHANGE_STEP + 1:])


@pytest.mark.slow
def test_the_commands_do_not_depend_on_the_thread_and_two_runs_and_two_controllers_agree():
    on_thread, stats, seen, _ = _run(SPLIT)
    at_once, _, seen_at_once, _ = _run(dataclasses.replace(SPLIT, change_split_thread=False))
    again, _, _, _ = _run(SPLIT)
    assert np.array_equal(on_thread, at_once) and np.array_equal(on_thread, again)
    assert seen_at_once["finish"][0][0] == threading.get_ident()  # at once: inside the step, on its thread
    # two controllers in one process, stepped in turn: each its own worker, the same commands as alone
    ctrls = [MpcController(settings=SPLIT) for _ in range(2)]
    seens = [_recorded(c) for c in ctrls]
    loops = [solve_time.Loop(c, seed=1) for c in ctrls]
    commands = [[], []]
    for k in range(STEPS):
        for i in (k % 2, 1 - k % 2):
            commands[i].append(loops[i].step(k).command.vector())
    assert all(np.array_equal(np.array(c), on_thread) for c in commands)
    idents = [s["finish"][0][0] for s in seens]
    assert idents[0] != idents[1] and threading.get_ident() not in idents
    assert ctrls[0].reach.worker is not ctrls[1].reach.worker
    for c in ctrls:
        c.close()
    assert not any(c.reach.worker.running for c in ctrls)


@pytest.mark.slow
def test_without_the_reach_worker_the_controller_uses_a_worker_of_its_own():
    settings = dataclasses.replace(SPLIT, reach_background=False)
    commands, stats, seen, ctrl = _run(settings)
    assert ctrl.reach.worker is None and ctrl._own_worker is not None
    assert seen["finish"][0][0] != threading.get_ident()
    reference, _, _, _ = _run(SPLIT)
    assert np.array_equal(commands, reference)
    assert not ctrl._own_worker.running  # closed by close()


def test_every_step_split_caps_each_qp_and_finishes_only_the_capped_ones():
    """``split_every_step``: any step's QPs capped, the rest finished on the thread where a QP reached the cap (and
    at every change); a step whose QP met the tolerance within the cap hands nothing over."""
    commands, stats, seen, _ = _run(dataclasses.replace(SPLIT, split_every_step=True))
    warm = stats[1:]  # the first step starts cold: its QPs are not capped
    assert all(st["fallback"] is None and st["iterations"] <= st["qp_solves"] * CAP for st in warm)
    finished = [k for k, st in enumerate(stats) if "change_finish" in st]
    capped = [k for k, st in enumerate(stats) if k > 0 and "maximum iterations" in str(st["status"])]
    assert CHANGE_STEP + 1 in finished and len(seen["finish"]) == len(finished)
    assert capped and set(finished) >= {k + 1 for k in capped if k + 1 < STEPS}
    assert len(finished) < STEPS - 1  # not every step


def test_time_between_steps_keeps_the_next_step_from_waiting():
    """A generous bound beside the deterministic checks above: given up to 5 s after the change (the rest takes a
    few milliseconds), the next step finds it done; the change step itself stays well inside a sample."""
    _, stats, _, _ = _run(SPLIT, idle_s=5.0)
    change, after = stats[CHANGE_STEP], stats[CHANGE_STEP + 1]
    assert change["qp_solves"] == 2 and change["iterations"] <= 2 * CAP  # deterministic: the change's QPs capped
    assert after["change_finish"]["ok"] and after["change_finish"]["prepared"]  # the rest converged and prepared
    assert after["change_wait_s"] < 0.05
    assert change["step_time_s"] < 0.25


def test_the_capped_solve_keeps_its_cap_and_leaves_the_solver_settings_as_they_were():
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    loop = solve_time.Loop(ctrl, seed=1)
    for k in range(CHANGE_STEP):
        loop.step(k)
    core = ctrl.solver._core
    status_val, _, iterations, x = core.solve_capped(3)
    assert iterations <= 3 and np.isfinite(x).all()
    assert core._mode == "full"
    core.warm_start(np.zeros_like(x))
    status_val, _, iterations, _ = core.solve()
    assert status_val == 1 and iterations > 3  # the full settings again: from zeros solved past the cap of 3
    with pytest.raises(ValueError, match="max_iter"):
        core.solve_capped(0)


def test_the_settings_refuse_a_cap_out_of_range_naming_the_field():
    with pytest.raises(InvalidSettings, match="change_split_iter"):
        MpcSettings(change_split_iter=-1)
    with pytest.raises(InvalidSettings, match="change_split_iter"):
        MpcSettings(osqp_max_iter=100, change_split_iter=101)
    with pytest.raises(InvalidSettings, match="change_split_thread"):
        MpcSettings(change_split_thread="yes")
    with pytest.raises(ValueError, match="change_split_iter"):
        RtiOsqpSolver(MpcController(settings=MpcSettings(codegen=False)).problem, max_iter=50, change_split_iter=60)
    with pytest.raises(InvalidSettings, match="change_split_iter .* needs solver"):
        MpcSettings(solver="ipopt", change_split_iter=10)
    with pytest.raises(InvalidSettings, match="split_every_step needs change_split_iter"):
        MpcSettings(split_every_step=True)
    assert MpcSettings().change_split_iter == 0  # off by default


def _step_sizes(settings: MpcSettings, steps: int) -> tuple[list[float], list[float], list]:
    """OSQP's step size as each feedback finds it, and as each rest's QPs leave it (before ``split_keeps_rho``
    sets it back); the stats of the loop's steps."""
    ctrl = MpcController(settings=settings)
    solver = ctrl.solver
    feedback, finish = solver.feedback, solver._finish
    at_feedback, after_rest = [], []

    def recorded_feedback(*args, **kwargs):
        at_feedback.append(solver._core.rho)
        return feedback(*args, **kwargs)

    def recorded_finish(*args, **kwargs):
        sol = finish(*args, **kwargs)
        after_rest.append(solver._core.rho)
        return sol

    solver.feedback, solver._finish = recorded_feedback, recorded_finish
    loop = solve_time.Loop(ctrl, seed=1)
    stats = [loop.step(k).stats for k in range(steps)]
    ctrl.close()
    return at_feedback, after_rest, stats


RHO_CHANGE_STEP = 60  # the loop's second change: there the rest's QPs move OSQP's step size (seed 1)


@pytest.mark.parametrize("generated", [True, False], ids=["generated OSQP", "OSQP's Python interface"])
def test_the_rest_leaves_osqp_step_size_as_the_change_step_found_it_with_split_keeps_rho(generated):
    """``split_keeps_rho``: the rest's QPs may adapt OSQP's step size (the first continues from an iterate at the
    cap); with the setting the step after the change finds the value the change step found, without it the rest's.
    The change's QPs in its step are capped alike either way. The same through OSQP's Python interface
    (``_OsqpCore.rho``, ``rho_next_update``)."""
    k = RHO_CHANGE_STEP
    split = dataclasses.replace(SPLIT, osqp_codegen=generated)
    adapted, rest_adapted, stats_adapted = _step_sizes(split, k + 2)
    kept, rest_kept, stats_kept = _step_sizes(dataclasses.replace(split, split_keeps_rho=True), k + 2)
    for stats in (stats_adapted, stats_kept):
        assert stats[k]["qp_solves"] == 2 and stats[k]["iterations"] <= 2 * CAP
        assert stats[k + 1]["change_finish"]["ok"]
    assert len(rest_adapted) == len(rest_kept) == 2  # the changes at CHANGE_STEP and k
    # the same run up to the second rest (the first leaves the step size where it was); there the rest moves it by
    # more than OSQP's factor of 5
    assert rest_adapted[0] == adapted[CHANGE_STEP]
    assert adapted[:k + 1] == kept[:k + 1] and rest_adapted == rest_kept
    before = kept[k]
    assert max(rest_kept[1] / before, before / rest_kept[1]) > 5.0
    assert adapted[k + 1] == rest_adapted[1]
    assert kept[k + 1] == before


def test_split_keeps_rho_is_refused_without_the_split_naming_the_field():
    with pytest.raises(InvalidSettings, match="split_keeps_rho needs change_split_iter"):
        MpcSettings(split_keeps_rho=True)
    with pytest.raises(InvalidSettings, match="split_keeps_rho"):
        MpcSettings(change_split_iter=30, split_keeps_rho="yes")
    assert MpcSettings().split_keeps_rho is False
