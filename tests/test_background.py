"""The reachable-flow solve off the control step's critical path (mpc/background.py, mpc/priorities.py):
answered one step later, the same with and without the second thread, never solved inside a step."""

import dataclasses
import gc
import sys
import threading
import time

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.contract import Reference
from hvac_mpc.models import Parameters
from hvac_mpc.models.plant import Environment, SimulatedPlant
from hvac_mpc.mpc.background import BackgroundCall, BackgroundWorker
from hvac_mpc.mpc.mpc_controller import InvalidSettings, MpcController, MpcSettings
from hvac_mpc.mpc.priorities import ReachableFlow

from test_robust import M3H, _default_problem, _reach_setup


def test_background_call_returns_what_the_call_returns_or_raises_what_it_raised():
    for thread in (True, False):
        assert BackgroundCall(lambda a, b: a * b, (6, 7), thread=thread).result() == 42
        with pytest.raises(ZeroDivisionError):
            BackgroundCall(lambda a: 1 / a, (0,), thread=thread).result()


def test_casadi_lets_python_run_while_the_reachable_flow_solve_works():
    """The assumption of mpc/background.py on the installed CasADi: IPOPT through CasADi releases the
    global interpreter lock, so the control step runs on while the second thread solves."""
    reach, x, u, d = _reach_setup()
    args = dict(x0=np.concatenate([x, u]), p=np.concatenate([d, [18.0, 100.0], reach._p]), lbx=reach.lbx,
                ubx=reach.ubx, lbg=reach.lbg, ubg=reach.ubg)
    windows: list[tuple[float, float]] = []
    inside, done = threading.Event(), threading.Event()

    def work():
        inside.set()
        # a few milliseconds each; on until 0.2 s were spent inside the solves, so that a loaded machine
        # that schedules the main thread rarely still gives it time inside them
        while len(windows) < 100 and sum(t1 - t0 for t0, t1 in windows) < 0.2:
            t0 = time.perf_counter()
            reach.solver(**args)
            windows.append((t0, time.perf_counter()))
        done.set()

    # a long switch interval: a thread holding the lock through a C call keeps it until the call's
    # thread ends (a negative control with a C loop that holds it gave no time inside a call)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(0.2)
    try:
        thread = threading.Thread(target=work)
        thread.start()
        inside.wait()
        ticks = []
        while not done.is_set():
            ticks.append(time.perf_counter())
        thread.join()
    finally:
        sys.setswitchinterval(interval)
    ticks = np.array(ticks)
    during = sum(int(np.count_nonzero((ticks > t0) & (ticks < t1))) for t0, t1 in windows)
    assert during > 100


def test_a_deferred_re_solve_answers_at_the_next_check_what_the_inline_re_solve_answers_at_once():
    inline, x, u, d = _reach_setup()
    _, x1, _, d1 = _reach_setup(15.0)  # the estimator's flow offset moves the reachable flow
    pb = _default_problem()
    deferred = ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, Parameters(), deferred=True,
                             background=True)
    # a new reference: solved inside the check, both alike
    assert deferred.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0) == inline.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0)
    before = inline._reachable
    # the periodic re-solve (every_s passed) with moved inputs: inline at once, deferred one check later
    inline.check(x1, u, d1, 18.0, 200 * M3H, 100.0, inline.every_s)
    deferred.check(x1, u, d1, 18.0, 200 * M3H, 100.0, deferred.every_s)
    assert inline._reachable > before + 1 * M3H and deferred._reachable == before
    after = [r.check(x1, u, d1, 18.0, 200 * M3H, 100.0, 1.0) for r in (inline, deferred)]
    assert after[0] == after[1] and deferred._reachable == inline._reachable
    with pytest.raises(ValueError, match="deferred"):
        ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, Parameters(), background=True)


HIGH_FLOW = ((0.0, Reference.from_split(13.0, 0.05, (0.34, 0.33, 0.33))),
             (12.0, Reference.from_split(14.0, 0.05, (0.34, 0.33, 0.33))))


def _loop(settings: MpcSettings, steps: int = 14):
    """The solve-time loop at a high flow reference (the reachable flow solved at 0 s and 12 s for new
    references, at 10 s periodically): commands, reports, and per
    reachable-flow solve whether it ran on the main thread and inside a step."""
    # no wall-clock deadline: on a loaded machine a step with the solve inside would fall back
    ctrl = MpcController(settings=dataclasses.replace(settings, deadline_s=3600.0))
    solver = ctrl.reach.solver
    solves: list[tuple[bool, bool]] = []
    in_step = [False]

    def recorded(**kw):
        solves.append((threading.current_thread() is threading.main_thread(), in_step[0]))
        return solver(**kw)

    ctrl.reach.solver = recorded
    plant = SimulatedPlant(seed=4, environment=Environment(solve_time.INLET_C, 5.0))
    plant.settle(solve_time.INITIAL)
    ctrl.reset(plant.command)
    commands, reports = [], []
    for k in range(steps):
        in_step[0] = True
        res = ctrl.step(plant.read(), solve_time.reference_at(float(k), HIGH_FLOW))
        in_step[0] = False
        assert res.stats["fallback"] is None, res.stats["status"]
        plant.apply(res.command)
        plant.advance()
        commands.append(res.command.vector())
        reports.append("volume_flow_m3s" in res.stats["out_of_reach"])
    ctrl.reach.reset()  # waits for a solve still running
    return np.array(commands), reports, solves


def test_periodic_reach_solves_run_off_the_step_and_the_commands_do_not_depend_on_the_thread():
    inline_changes = dict(codegen=False, reach_deferred=True, reach_changes_deferred=False)
    on_thread = _loop(MpcSettings(**inline_changes, reach_background=True))
    at_once = _loop(MpcSettings(**inline_changes, reach_background=False))
    assert np.array_equal(on_thread[0], at_once[0]) and on_thread[1] == at_once[1]
    assert len(on_thread[2]) == len(at_once[2]) == 3
    assert all(main and in_step for main, in_step in at_once[2])
    # new references (0 s, 12 s) solved inside the step, the periodic re-solve (10 s) on the second thread
    assert [main for main, _ in on_thread[2]] == [True, False, True]
    assert on_thread[2][0][1] and on_thread[2][2][1]
    # when the deferred answer is used (one check later) is held by the test above, on the check itself
    with pytest.raises(InvalidSettings, match="reach_background"):
        MpcSettings(reach_deferred=False, reach_background=True)


def test_with_changes_deferred_a_new_reference_answers_from_the_last_solve_and_then_from_its_own():
    inline, x, u, d = _reach_setup()
    _, x1, _, d1 = _reach_setup(15.0)
    pb = _default_problem()
    deferred = ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, Parameters(), deferred=True,
                             changes_deferred=True)
    # no solve before: the first check tracks the reference as it is, the next one answers as the inline check
    assert deferred.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0).flow_m3s is None
    first = inline.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0)
    assert first.flow_m3s is not None and deferred.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0) == first
    before = inline._reachable
    # a new temperature reference with moved inputs: the deferred check answers from the last solve first
    moved = inline.check(x1, u, d1, 17.0, 200 * M3H, 100.0, 1.0)
    assert inline._reachable > before + 1 * M3H
    assert deferred.check(x1, u, d1, 17.0, 200 * M3H, 100.0, 1.0) != moved and deferred._reachable == before
    assert deferred.check(x1, u, d1, 17.0, 200 * M3H, 100.0, 1.0) == moved
    with pytest.raises(ValueError, match="deferred"):
        ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, Parameters(), changes_deferred=True)


def test_by_default_no_reach_solve_runs_on_the_step_and_the_commands_do_not_depend_on_the_thread():
    on_thread = _loop(MpcSettings(codegen=False))
    at_once = _loop(MpcSettings(codegen=False, reach_background=False))
    assert np.array_equal(on_thread[0], at_once[0]) and on_thread[1] == at_once[1]
    assert len(on_thread[2]) == 3 and not any(main for main, _ in on_thread[2])
    # without deferred solves the setting has nothing to defer: a change is solved in its step
    assert not MpcController(settings=MpcSettings(codegen=False, reach_deferred=False,
                                                  reach_background=False)).reach.changes_deferred


def test_a_wait_between_steps_takes_no_result_and_result_reports_its_own_wait():
    release = threading.Event()
    call = BackgroundCall(lambda: (release.wait(5.0), 7)[1], ())
    waited = call.wait(0.02)  # the call is held: the wait runs out
    assert not call.done and 0.015 < waited < 1.0
    release.set()
    call.wait(5.0)
    assert call.done and call.wait(1.0) == 0.0
    assert call.result() == 7 and call.waited_s == 0.0  # finished before: result() did not wait
    slow = BackgroundCall(time.sleep, (0.05,))
    slow.result()
    assert slow.waited_s > 0.02
    at_once = BackgroundCall(lambda: 1, (), thread=False)
    assert at_once.done and at_once.wait(1.0) == 0.0 and at_once.result() == 1 and at_once.waited_s == 0.0
    with pytest.raises(ValueError, match="timeout_s"):
        at_once.wait(-1.0)


def test_time_given_between_steps_keeps_the_steps_from_waiting_and_the_commands_as_they_are():
    """The solve-time loop's idle time (benchmarks/solve_time.py ``Loop(idle_s=...)``): the reachable-flow
    solves of HIGH_FLOW (0 s, 10 s, 12 s) finish between the steps, no step waits for one, and the commands
    are those of the loop stepped back to back (where steps may wait)."""
    runs = {}
    for idle_s in (0.0, 1.0):
        ctrl = MpcController(settings=MpcSettings(codegen=False, deadline_s=3600.0))
        solver, on_thread = ctrl.reach.solver, []

        def counted(**kw):
            on_thread.append(threading.current_thread() is not threading.main_thread())
            return solver(**kw)

        ctrl.reach.solver = counted
        loop = solve_time.Loop(ctrl, seed=4, scenario=HIGH_FLOW, idle_s=idle_s)
        commands = [loop.step(k).command.vector() for k in range(14)]
        ctrl.reach.reset()
        runs[idle_s] = (np.array(commands), loop, on_thread)
    assert np.array_equal(runs[0.0][0], runs[1.0][0])
    paced = runs[1.0][1]
    assert runs[1.0][2] == [True, True, True]  # three solves, all on the second thread
    assert max(paced.step_wait_s) == 0.0 and solve_time.background_waits(paced, 1.0)["steps_waiting"] == 0
    assert all(w == 0.0 for w in runs[0.0][1].idle_wait_s)
    with pytest.raises(ValueError, match="idle_s"):
        solve_time.Loop(ctrl, seed=4, idle_s=-1.0)


def test_a_worker_runs_every_call_handed_to_it_on_one_thread_and_ends_it_when_closed_or_dropped():
    worker = BackgroundWorker()
    calls = [BackgroundCall(lambda i: (i, threading.get_ident()), (i,), worker=worker) for i in range(20)]
    answers = [call.result() for call in calls]
    assert [i for i, _ in answers] == list(range(20))
    assert len({ident for _, ident in answers}) == 1 and answers[0][1] != threading.get_ident()
    assert worker.threads_started == 1 and worker.running
    with pytest.raises(ZeroDivisionError):  # an exception is the call's, the thread goes on
        BackgroundCall(lambda: 1 / 0, (), worker=worker).result()
    assert BackgroundCall(lambda: 5, (), worker=worker).result() == 5 and worker.threads_started == 1
    thread = worker._thread
    worker.close()
    assert not thread.is_alive() and not worker.running
    assert BackgroundCall(lambda: 6, (), worker=worker).result() == 6 and worker.threads_started == 2  # again
    dropped = worker._thread
    del worker, calls
    gc.collect()
    dropped.join(5.0)
    assert not dropped.is_alive()


def _threads_of_solves(ctrl: MpcController) -> list[int]:
    """Record the thread of every reachable-flow solve of ``ctrl`` from now on."""
    solver, idents = ctrl.reach.solver, []

    def recorded(**kw):
        idents.append(threading.get_ident())
        return solver(**kw)

    ctrl.reach.solver = recorded
    return idents


def test_two_controllers_each_run_all_their_reach_solves_on_one_thread_of_their_own():
    """HIGH_FLOW over 34 s: the reachable flow solved for new references (0 s, 12 s) and periodically (10 s,
    22 s, 32 s), all five on the controller's one worker thread (not one thread per solve), two controllers
    stepped in turn in one process each on its own; the commands those of the solves inside the step; after
    ``close`` the thread is gone, and a reset controller's next solve starts it again."""
    steps = 34
    settings = MpcSettings(codegen=False, deadline_s=3600.0)
    ctrls = [MpcController(settings=settings) for _ in range(2)]
    idents = [_threads_of_solves(c) for c in ctrls]
    loops = [solve_time.Loop(c, seed=4, scenario=HIGH_FLOW) for c in ctrls]
    commands = [[], []]
    for k in range(steps):
        for i in (k % 2, 1 - k % 2):
            commands[i].append(loops[i].step(k).command.vector())
    inline = MpcController(settings=dataclasses.replace(settings, reach_background=False))
    inline_idents = _threads_of_solves(inline)
    inline_loop = solve_time.Loop(inline, seed=4, scenario=HIGH_FLOW)
    reference = np.array([inline_loop.step(k).command.vector() for k in range(steps)])
    for c in ctrls:
        c.reach.reset()  # waits for a solve still running
    assert all(np.array_equal(np.array(cmds), reference) for cmds in commands)
    assert len(inline_idents) == 5 and set(inline_idents) == {threading.get_ident()}
    workers = [c.reach.worker for c in ctrls]
    assert [len(i) for i in idents] == [5, 5] and [w.threads_started for w in workers] == [1, 1]
    assert [set(i) for i in idents] == [{w._thread.ident} for w in workers]
    assert idents[0][0] != idents[1][0]
    threads = [w._thread for w in workers]
    ctrls[0].close()
    assert not threads[0].is_alive() and threads[1].is_alive()
    loops[0] = solve_time.Loop(ctrls[0], seed=4, scenario=HIGH_FLOW)  # resets the controller
    assert np.array_equal(loops[0].step(0).command.vector(), reference[0])
    ctrls[0].reach.reset()
    assert workers[0].threads_started == 2 and len(idents[0]) == 6
    for c in ctrls:
        c.close()
    assert not any(w.running for w in workers)


def test_a_held_worker_queues_nothing_until_released_and_waiting_for_a_held_call_releases_it():
    worker = BackgroundWorker()
    worker.hold()
    ran = []
    first = BackgroundCall(ran.append, (1,), worker=worker)
    second = BackgroundCall(ran.append, (2,), worker=worker)
    assert worker._jobs.empty() and worker.threads_started == 0 and not first.done
    worker.release()
    first.result(), second.result()
    assert ran == [1, 2] and worker.threads_started == 1
    worker.hold()
    held = BackgroundCall(lambda: 3, (), worker=worker)
    assert held.result() == 3  # released by the wait, not left to wait for ever
    worker.hold()
    late = BackgroundCall(lambda: 4, (), worker=worker)
    worker.close()  # runs what is held before the thread ends
    assert late.done and late.result() == 4 and not worker.running


def test_the_controller_hands_its_reach_solves_over_at_the_end_of_its_step():
    """The step holds its worker: every solve of HIGH_FLOW (0, 10, 12 s) is handed over while held, and the step
    returns with nothing held."""
    ctrl = MpcController(settings=MpcSettings(codegen=False, deadline_s=3600.0))
    worker, held_at_hand_over, left_held = ctrl.reach.worker, [], []
    hand_over = worker.hand_over

    def recorded(job):
        held_at_hand_over.append(worker._held is not None)
        hand_over(job)

    worker.hand_over = recorded
    loop = solve_time.Loop(ctrl, seed=4, scenario=HIGH_FLOW)
    for k in range(14):
        loop.step(k)
        left_held.append(worker._held)
    ctrl.close()
    # each held hand-over is handed over again by release(): pairs of (held, not held)
    assert held_at_hand_over == [True, False] * 3
    assert left_held == [None] * 14
