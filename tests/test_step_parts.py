"""benchmarks/step_parts.py: the timers time the parts of a step and leave the classes as they were."""

import time

from hvac_mpc.benchmarks import solve_time, step_parts
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings


def test_the_timers_time_the_parts_and_are_taken_off_after():
    before = {(cls, name): cls.__dict__[name] for cls, name, _ in step_parts.PARTS}
    totals: dict[str, float] = {}
    with step_parts.timed(totals):
        loop = solve_time.Loop(MpcController(settings=MpcSettings(codegen=False)), seed=7)
        loop.step(0)
        totals.clear()
        loop.step(1)
    assert all(cls.__dict__[name] is f for (cls, name), f in before.items())
    whole = totals["whole step"]
    parts = [totals[label] for _, _, label in step_parts.PARTS if not label.startswith(" ") and label != "whole step"]
    assert whole > 0 and sum(parts) < whole  # the top-level parts are inside the step, one after the other
    assert totals["  OSQP solve"] < totals["feedback (gradient, bounds, OSQP solve)"]


def test_the_steps_measured_are_the_median_kind_or_the_changes():
    one, change = {"qp_solves": 1, "iterations": 15}, {"qp_solves": 2, "iterations": 80}
    assert step_parts.selected(one, 20, changes=False) and not step_parts.selected(change, 20, changes=False)
    assert not step_parts.selected({"qp_solves": 1, "iterations": 21}, 20, changes=False)
    assert step_parts.selected(change, 20, changes=True) and not step_parts.selected(one, 20, changes=True)


def test_a_part_counts_inside_the_step_only():
    """The filter not in use is brought up to the sample between the steps where the loop idles (its updates are
    not the step's, so not counted), and inside the next step back to back (counted under its own label)."""
    for idle_s, inside in ((0.2, False), (0.0, True)):
        totals: dict[str, float] = {}
        with step_parts.timed(totals, clock=time.thread_time):  # CPU time: a preempted call is not counted long
            loop = solve_time.Loop(MpcController(settings=MpcSettings(codegen=False)), seed=7, idle_s=idle_s)
            loop.step(0)
            loop.step(1)
            totals.clear()
            loop.step(2)
        other = totals.get("the other filter (measurement and time update)", 0.0)
        # idling, the step finds the other filter already brought up (a call that returns at once)
        assert (other > 0.01 * totals["whole step"]) == inside and other < totals["whole step"]
        assert 0.0 < totals["estimator update"] < totals["whole step"]
