"""OSQP's step size at a reference change (``mpc/change_rho.py``; ``MpcSettings.osqp_change_rho``,
``osqp_change_rho_restore``, ``osqp_change_rho_interval``, ``osqp_change_rho_tolerance``, ``osqp_change_rho_hold``;
all off by default): the remembered and restored step sizes as the rule states them, each QP's start on the
solve-time loop's changes (the generated solver), the change's adaptation set and set back, the change's later QPs
held (the adaptation off in them, the step size at the second QP's start and end, its iterations), the fields
checked.

Budget: about 55 s on a loaded two-core machine (closed loops of up to 215 steps)."""

import numpy as np
import pytest

from hvac_mpc.benchmarks import change_rho as trace_module, solve_time
from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S
from hvac_mpc.mpc import codegen
from hvac_mpc.mpc.change_rho import HOLD_INTERVAL, ChangeStepSize, change_kind
from hvac_mpc.mpc.mpc_controller import InvalidSettings, MpcController, MpcSettings
from hvac_mpc.mpc.osqp_embedded import EmbeddedOsqp
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

UP, DOWN, FLOW = (np.array([16.0, 0.03]), np.array([20.0, 0.03])), (np.array([20.0, 0.03]), np.array([15.0, 0.03])), \
    (np.array([15.0, 0.03]), np.array([15.0, 0.05]))


@pytest.fixture(scope="module")
def cache():
    """The code generation switched on while this module's loops run (the generated solver is what they check)."""
    mp = pytest.MonkeyPatch()
    mp.setenv(codegen.SWITCH_ENV, "1")
    yield
    mp.undo()


def test_a_change_kind_is_the_sign_of_the_temperature_step():
    assert [change_kind(*pair) for pair in (UP, DOWN, FLOW)] == [1, -1, 0]


def test_the_remembered_step_size_is_the_last_first_qps_of_the_same_kind():
    rule = ChangeStepSize("kind")
    assert rule.at_change(1e-3, *UP) is None  # the first change up: OSQP's own
    rule.note(0, 0.02)
    rule.note(1, 0.5)  # a later QP's end is not remembered without "_each"
    rule.close_change()
    assert rule.at_change(4e-3, *DOWN) is None  # another kind
    rule.note(0, 3e-4)
    rule.close_change()
    assert rule.at_change(5e-3, *UP) == 0.02 and rule.for_qp(1) is None
    rule.close_change()
    rule.note(0, 9.0)  # outside a change: nothing
    assert rule.remembered == {(1, 0): 0.02, (-1, 0): 3e-4}


def test_each_qp_remembers_its_own_and_last_ignores_the_kind():
    rule = ChangeStepSize("last_each")
    rule.at_change(1e-3, *UP)
    rule.note(0, 0.02)
    rule.note(1, 0.1)
    rule.close_change()
    assert rule.at_change(1e-3, *DOWN) == 0.02 and rule.for_qp(1) == 0.1 and rule.for_qp(2) is None


def test_the_restore_gives_the_value_before_the_change_once_and_only_after_its_qps():
    rule = ChangeStepSize("off", restore=True)
    assert rule.at_change(2e-3, *UP) is None
    assert rule.after_change() is None  # the change's own relinearisations keep the change's step size
    rule.close_change()
    assert rule.after_change() == 2e-3 and rule.after_change() is None
    rule.at_change(2e-3, *UP)
    rule.close_change()
    rule.at_change(0.08, *DOWN)  # a second change before a preparation took the first's value in
    rule.close_change()
    assert rule.after_change() == 2e-3


def _loop(steps: int, **fields):
    ctrl, trace = trace_module._traced_controller(
        MpcSettings(deadline_s=DETERMINISTIC_DEADLINE_S, **fields))
    assert isinstance(trace.core, EmbeddedOsqp)  # the generated solver (the trace stands in front of it)
    loop = solve_time.Loop(ctrl, seed=1)
    for k in range(steps):
        trace.step = k
        assert loop.step(k).stats["fallback"] is None
    return ctrl, trace


def _first_qps(trace, step):
    return [q for q in trace.qps if q["step"] == step]


def test_on_the_loop_each_change_starts_where_the_last_change_of_its_kind_ended(cache):
    """The loop's changes: 16 -> 13 C at 30 s (down), 20 C at 60 (up), 18 C at 90 (down), 24 C at 120 (up), 15 C at
    150 (down), 22 C at 180 (up), 17 C at 210 (down)."""
    _, trace = _loop(212, osqp_change_rho="kind")
    changes = [30, 60, 90, 120, 150, 180, 210]
    for later, earlier in zip(changes[2:], changes):
        assert _first_qps(trace, later)[0]["rho_start"] == _first_qps(trace, earlier)[0]["rho_end"]
    _, kept = _loop(212)
    assert any(_first_qps(kept, c)[0]["rho_start"] != _first_qps(kept, p)[0]["rho_end"]
               for c, p in zip(changes[2:], changes))


def test_the_restore_starts_the_step_after_a_change_at_the_step_size_before_it(cache):
    _, trace = _loop(64, osqp_change_rho_restore=True)
    change = _first_qps(trace, 60)
    assert change[-1]["rho_end"] > 10 * change[0]["rho_start"]  # the change's QPs raised it (0.0006 -> 0.1)
    assert _first_qps(trace, 61)[0]["rho_start"] == pytest.approx(change[0]["rho_start"], rel=1e-12)
    _, kept = _loop(64)
    assert _first_qps(kept, 61)[0]["rho_start"] == _first_qps(kept, 60)[-1]["rho_end"]


def test_the_changes_adaptation_is_set_for_its_qps_and_set_back_after(cache):
    ctrl, trace = trace_module._traced_controller(MpcSettings(deadline_s=DETERMINISTIC_DEADLINE_S,
                                                              osqp_change_rho_interval=10,
                                                              osqp_change_rho_tolerance=2.0))
    loop = solve_time.Loop(ctrl, seed=1)
    for k in range(59):
        loop.step(k)
    core, seen = trace.core, []
    assert core.rho_adaptation == (50, 5.0)  # OSQP's set-up: every 50 iterations, a factor of 5
    solve = core.solve
    core.solve = lambda: (seen.append(core.rho_adaptation), solve())[1]
    for k in range(59, 62):  # the change at 60 s: two QPs
        loop.step(k)
    assert seen == [(50, 5.0), (10, 2.0), (10, 2.0), (50, 5.0)]  # 59 s, the change's two QPs, 61 s


def _iterations(trace, steps):
    return sum(q["iterations"] for q in trace.qps if q["step"] in steps)


def test_the_last_changes_step_size_takes_the_change_at_90_s_in_fewer_iterations(cache):
    """The loop (seed 1) to the change at 90 s (20 -> 18 C, a flow change): with the defaults its first QP starts at
    the step size the change at 60 s's second QP raised (0.016, after the wake) and its QPs take 245 + 25 OSQP
    iterations; with "last" at the step size the change at 60 s's first QP ended with (1e-4): 75 + 25 (measured).
    The loops are the same to 89 s (the first change has nothing remembered)."""
    _, last = _loop(91, osqp_change_rho="last")
    _, kept = _loop(91)
    assert _iterations(last, range(90)) == _iterations(kept, range(90))
    assert _iterations(last, [90]) < 0.5 * _iterations(kept, [90])


def test_the_restore_shortens_the_slowest_qp_after_the_change_at_60_s(cache):
    """The change at 60 s's second QP raises OSQP's step size to 0.10; the QP at 62 s then takes 210 OSQP iterations
    from it (the defaults); restored to the value before the change (6.5e-4) the steps 61-65 take at most 105
    (measured)."""
    _, restored = _loop(66, osqp_change_rho_restore=True)
    _, kept = _loop(66)
    wake = range(61, 66)
    assert max(q["iterations"] for q in restored.qps if q["step"] in wake) < 0.7 * max(
        q["iterations"] for q in kept.qps if q["step"] in wake)


@pytest.mark.parametrize("fields, match", [
    ({"osqp_change_rho": "first"}, r"osqp_change_rho = 'first', allowed: one of"),
    ({"osqp_change_rho_restore": 1}, r"osqp_change_rho_restore = 1, allowed: True or False"),
    ({"osqp_change_rho_interval": -1}, r"osqp_change_rho_interval = -1, allowed: an integer in \[0, 1000\]"),
    ({"osqp_change_rho_interval": 2.5}, r"osqp_change_rho_interval = 2.5"),
    ({"osqp_change_rho_tolerance": 1.0}, r"osqp_change_rho_tolerance = 1.0, allowed: 0 \(OSQP's\) or a factor"),
    ({"osqp_change_rho": "last", "osqp_rho_reset": 1e-3, "osqp_rho_reset_on": "change"}, r"one of them"),
    ({"osqp_change_rho_tolerance": 2.0}, r"osqp_change_rho_tolerance = 2.0 needs .*osqp_change_rho_interval"),
    ({"osqp_change_rho": "last", "change_split_iter": 50}, r"change_split_iter = 50: not supported"),
    ({"osqp_change_rho_restore": True, "change_split_iter": 50}, r"change_split_iter = 50: not supported"),
    ({"osqp_change_rho_hold": "both"}, r"osqp_change_rho_hold = 'both', allowed: one of \['off', 'end', 'start'\]"),
    ({"osqp_change_rho_hold": True}, r"osqp_change_rho_hold = True, allowed: one of"),
    ({"osqp_change_rho_hold": "start", "change_split_iter": 50}, r"change_split_iter = 50: not supported"),
    ({"osqp_change_rho_hold": "start", "osqp_rho_reset": 1e-3},
     r"osqp_change_rho_hold = 'start' with osqp_rho_reset = 0.001 on 'preparation'.*allowed: osqp_rho_reset None or "
     r"osqp_rho_reset_on 'change'"),
    ({"osqp_change_rho_hold": "end", "osqp_change_rho": "kind_each"},
     r"osqp_change_rho_hold = 'end' with osqp_change_rho = 'kind_each'.*allowed: osqp_change_rho 'off', 'last' or "
     r"'kind'"),
    ({"osqp_change_rho_hold": "start", "osqp_change_rho": "last_each"}, r"osqp_change_rho = 'last_each'"),
    ({"osqp_change_rho_hold": "end", "osqp_codegen": False},
     r"osqp_change_rho_hold = 'end' with osqp_codegen = False.*allowed: osqp_codegen True, or 'start' / 'off'"),
])
def test_the_fields_are_checked_naming_the_field(fields, match):
    with pytest.raises(InvalidSettings, match=match):
        MpcSettings(**fields)


def test_the_solver_refuses_both_change_step_sizes():
    pb = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False)).problem
    with pytest.raises(ValueError, match=r"change_rho and rho_reset with rho_reset_on='change'"):
        RtiOsqpSolver(pb, change_rho="kind", rho_reset=1e-3, rho_reset_on="change")
    with pytest.raises(ValueError, match=r"with change_split_iter: not supported"):
        RtiOsqpSolver(pb, change_rho_restore=True, change_split_iter=50)
    with pytest.raises(ValueError, match=r"change_rho_hold = 'late', allowed"):
        RtiOsqpSolver(pb, change_rho_hold="late")
    with pytest.raises(ValueError, match=r"change_rho_hold with change_split_iter: not supported"):
        RtiOsqpSolver(pb, change_rho_hold="end", change_split_iter=50)
    with pytest.raises(ValueError, match=r"change_rho_hold = 'start' with rho_reset = 0.001 on 'preparation'"):
        RtiOsqpSolver(pb, change_rho_hold="start", rho_reset=1e-3)
    with pytest.raises(ValueError, match=r"change_rho_hold = 'start' with change_rho = 'last_each'"):
        RtiOsqpSolver(pb, change_rho_hold="start", change_rho="last_each")
    with pytest.raises(ValueError, match=r"change_rho_hold = 'end' with osqp_codegen = False"):
        RtiOsqpSolver(pb, change_rho_hold="end")


def test_the_hold_is_taken_with_what_does_not_override_it_and_reported():
    """The combinations left: "start" with ``rho_reset`` on "change", with ``change_rho`` "kind", and with the
    Python interface; the mode in the solver's settings (reports tell the runs apart)."""
    for fields in (dict(osqp_rho_reset=1e-3, osqp_rho_reset_on="change"), dict(osqp_change_rho="kind"),
                   dict(osqp_codegen=False)):
        assert MpcSettings(osqp_change_rho_hold="start", **fields).osqp_change_rho_hold == "start"
    ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False, osqp_change_rho_hold="start"))
    assert ctrl.solver.settings["change_rho_hold"] == "start"
    ctrl.close()


# a change's second QP held at the first's step size (osqp_change_rho_hold; docs/architecture.md, 'The change's
# second QP held')
HOLD_CHANGE = 60  # the loop's change at 60 s (13 -> 20 C): its first QP lowers OSQP's rho 6.5e-4 -> 9.8e-5 (seed 1)


def _traced(steps: int = HOLD_CHANGE + 2, **fields):
    """The solve-time loop (seed 1) to ``steps``, each QP's OSQP adaptation (interval, tolerance) noted in its row."""
    ctrl, trace = trace_module._traced_controller(MpcSettings(deadline_s=DETERMINISTIC_DEADLINE_S, **fields))
    core = trace.core
    assert isinstance(core, EmbeddedOsqp)  # the generated solver (the trace stands in front of it)
    adaptations = []
    solve = core.solve
    core.solve = lambda: (adaptations.append(core.rho_adaptation), solve())[1]
    loop = solve_time.Loop(ctrl, seed=1)
    for k in range(steps):
        trace.step = k
        loop.step(k)
    for q, a in zip(trace.qps, adaptations):
        q["adaptation"] = a
    return trace


@pytest.fixture(scope="module")
def kept(cache):
    return _traced()


@pytest.fixture(scope="module")
def start(cache):
    return _traced(osqp_change_rho_hold="start")


def test_the_adaptation_is_off_in_the_changes_later_qps_and_back_on_after(start):
    steps = (HOLD_CHANGE - 1, HOLD_CHANGE, HOLD_CHANGE + 1)
    seen = [q["adaptation"] for step in steps for q in _first_qps(start, step)]
    assert seen == [(50, 5.0), (50, 5.0), (HOLD_INTERVAL, 5.0), (50, 5.0)]  # OSQP's set-up: every 50, a factor 5


def test_start_holds_the_second_qp_at_the_step_size_the_first_started_with(start, kept):
    """Held: the second QP starts and ends at the first QP's start (6.5e-4), and so does the step after the change.
    Kept (the defaults): it starts where the first ended (9.8e-5) and OSQP raises it to 0.10 (measured)."""
    first, second = _first_qps(start, HOLD_CHANGE)
    assert first["rho_end"] < 0.5 * first["rho_start"]  # the first QP adapts as set up
    assert second["rho_start"] == pytest.approx(first["rho_start"], rel=1e-12) and second["rho_end"] == second[
        "rho_start"]
    assert _first_qps(start, HOLD_CHANGE + 1)[0]["rho_start"] == second["rho_end"]
    first, second = _first_qps(kept, HOLD_CHANGE)
    assert second["rho_start"] == first["rho_end"] and second["rho_end"] > 100 * second["rho_start"]


def test_the_second_qp_held_takes_several_times_the_iterations_it_takes_adapted(start, kept):
    """The finding that leaves the setting off: the change at 60 s's second QP wants the large step size OSQP raises
    it to (its estimate 0.08); held at 6.5e-4 it takes 995 OSQP iterations against 135 (measured; the first QP's 175
    alike)."""
    assert _first_qps(start, HOLD_CHANGE)[0]["iterations"] == _first_qps(kept, HOLD_CHANGE)[0]["iterations"]
    assert _first_qps(start, HOLD_CHANGE)[1]["iterations"] > 4 * _first_qps(kept, HOLD_CHANGE)[1]["iterations"]


def test_end_holds_the_second_qp_at_the_first_qps_end_where_it_reaches_the_cap(cache):
    """Held at the value the first QP ended with (9.8e-5) the second QP reaches OSQP's 1000 iterations unsolved and
    the step falls back (measured: one fallback on each of seeds 1-3, at this change). The retry at OSQP's cap
    (``osqp_cap_retry_rho``) off: it would solve that QP once more (a third QP in the trace), and this test measures
    the held step size's own QP at the cap."""
    trace = _traced(HOLD_CHANGE + 1, osqp_change_rho_hold="end", osqp_cap_retry_rho=0.0)
    first, second = _first_qps(trace, HOLD_CHANGE)
    assert second["rho_start"] == first["rho_end"] == second["rho_end"]
    assert second["adaptation"] == (HOLD_INTERVAL, 5.0)
    assert second["iterations"] == MpcSettings().osqp_max_iter and second["status"] != "solved"
