"""A second Gauss-Newton QP on a step whose plan reverses (``MpcSettings.rti_reversal_second_qp``, a setting, off):
the rule's pure parts, the setting's checks, the reversal count of ``box_trace``, and, on the independent mismatch
simulator (box S1-13 of the seeded box sweep, seed 1: a 4.24 s dead time, the heater x0.89), valve a's two-cycle
at the heater's bound in the quick winter heating steps, broken by the second QP where the first reverses with the
heater at its bound (docs/robustness.md sec. 2.41)."""

from __future__ import annotations

import numpy as np
import pytest

from hvac_mpc.benchmarks import box_trace
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc.reversal_search import at_upper_bound, check_second_qp
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

#: Box S1-13 as ``python -m hvac_mpc.benchmarks.box_sweep --seed 1 --count 14 --list`` prints it.
S1_13 = ("S1-13:transport_delay_s=4.24,duct_loss_ua_w_per_k=2.73,thermocouple_tau_scale=0.78,blower_gain_scale=1.15,"
         "valve_shift_pct=-5.14,heater_power_scale=0.89,chiller_rate_scale=0.54")


def test_reversals_count_turns_beyond_the_move_and_across_a_held_sample():
    a = [0, 50, 50, 10, 12, 60, 62, 61]  # up, held, down (a turn), small, up (a turn), small moves
    assert box_trace.reversals(a).tolist() == [3, 5]
    assert box_trace.reversals(a, min_move=45.0).size == 0  # no two moves beyond 45
    applied = np.zeros((len(a), 6))
    applied[:, 2] = a
    applied[:, 1] = [240, 240, 240, 240, 100, 240, 240, 240]  # the heater off its bound before the turn at 5
    assert box_trace.reversals_at_heater_bound(applied, 240.0) == (2, 1)


def test_a_plan_at_its_upper_bound():
    U = np.array([[0.2, 0.99], [0.1, 0.5]])
    hi = np.array([1.0, 1.0])
    assert at_upper_bound(U, hi, 1, 2.0)  # 0.99 within 2 % of a span of 2 from 1.0
    assert not at_upper_bound(U, hi, 0, 2.0)


def test_the_setting_is_checked_and_off_by_default():
    assert MpcSettings().rti_reversal_second_qp == "off"
    assert check_second_qp("x", "heater_bound") == "heater_bound"
    with pytest.raises(ValueError, match="x = 'both'"):
        check_second_qp("x", "both")
    with pytest.raises(InvalidSettings, match="rti_reversal_second_qp"):
        MpcSettings(rti_reversal_second_qp="always")
    with pytest.raises(InvalidSettings, match="rti_reversal_second_qp = 'reversal' needs rti_reversal_search"):
        MpcSettings(rti_reversal_second_qp="reversal", rti_reversal_search=0.0)


def test_the_second_qp_is_refused_where_it_never_fires():
    """Only a plain one-QP step takes it: refused with ``solver="sqp"`` and with ``split_every_step`` (every step
    split), in the settings and in the solver; taken and reported with ``solver="rti"``."""
    on = dict(rti_reversal_second_qp="reversal", rti_reversal_search=0.3)
    with pytest.raises(InvalidSettings, match=r"rti_reversal_second_qp = 'reversal' with .*solver = 'sqp'.*allowed: "
                                              r"solver 'rti' and split_every_step False"):
        MpcSettings(solver="sqp", **on)
    with pytest.raises(InvalidSettings, match=r"split_every_step = True: it never fires"):
        MpcSettings(split_every_step=True, change_split_iter=50, **on)
    ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False, **on))
    assert ctrl.solver.settings["reversal_second_qp"] == "reversal"
    pb = ctrl.problem
    ctrl.close()
    kept = dict(reversal_second_qp="reversal", reversal_search=0.3)
    with pytest.raises(ValueError, match=r"reversal_second_qp = 'reversal' with sqp_max_iter = 2"):
        RtiOsqpSolver(pb, sqp_max_iter=2, **kept)
    with pytest.raises(ValueError, match=r"split_every_step = True \(change_split_iter = 50\): it never fires"):
        RtiOsqpSolver(pb, split_every_step=True, change_split_iter=50, **kept)


@pytest.mark.slow
def test_the_second_qp_breaks_valve_a_two_cycle_at_the_heater_bound_on_s1_13():
    """Today's defaults: valve a turns every step or two with the heater at 240 W after the step to 15 C (29
    reversals beyond 5 % at the bound, 121.8 C s); the second QP where the first reverses with the heater at its
    bound: 5 reversals there, 106.0 C s (sec. 2.41, 28 November 2026)."""
    runs = {rule: box_trace.run_trace(S1_13, "winter_heating_steps", quick=True,
                                      settings={"rti_reversal_second_qp": rule}) for rule in ("off", "heater_bound")}
    counts = {rule: box_trace.reversals_at_heater_bound(run["mpc"].applied, 240.0)[1] for rule, run in runs.items()}
    iae = {rule: run["iae"]["mpc"] for rule, run in runs.items()}
    assert counts["off"] >= 20  # the two-cycle
    assert counts["heater_bound"] <= counts["off"] / 3
    assert iae["heater_bound"] < 0.92 * iae["off"]
