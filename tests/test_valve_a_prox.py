"""Valve a's curvature at the heater's bound (docs/robustness.md sec. 2.43): the measuring tool's parts
(:mod:`hvac_mpc.benchmarks.valve_a_curvature`), the proximal term on valve a at the heater's bound
(``MpcSettings.rti_valve_a_prox``, a setting, off), its checks, and on the independent mismatch simulator (box S1-13 of
the seeded box sweep, seed 1) valve a's two-cycle at the heater's bound in the quick winter heating steps."""

from __future__ import annotations

import numpy as np
import pytest

from hvac_mpc.benchmarks import box_trace, valve_a_curvature as vac
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings, OcpSpec, TrackingProblem
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver, check_prox

#: Box S1-13 as ``python -m hvac_mpc.benchmarks.box_sweep --seed 1 --count 14 --list`` prints it.
S1_13 = ("S1-13:transport_delay_s=4.24,duct_loss_ua_w_per_k=2.73,thermocouple_tau_scale=0.78,blower_gain_scale=1.15,"
         "valve_shift_pct=-5.14,heater_power_scale=0.89,chiller_rate_scale=0.54")


@pytest.fixture(scope="module")
def problem():
    return TrackingProblem(None, OcpSpec())


def _prepared(pb, prox: float, heater_w: float):
    """A solver prepared (the cold start's plan: the command held over the horizon) at a heater command of
    ``heater_w`` W, valve a at 40 %; its P data, gradient and linearisation point."""
    solver = RtiOsqpSolver(pb, valve_a_prox=prox)
    u = pb.scale_u(np.array([100.0, heater_w, 40.0, 100.0, 100.0, 100.0]))
    x0 = pb.scale_x(pb.placeholder_state())
    d = np.array([5.0, 5.0, 0.0, 0.0])
    ref = np.array([15.0, 0.011, 0.0, 0.0, 0.0, 0.0, 0.0])
    solver.prepare(x0, u, d, ref, pb.w_y_full)
    q = np.array(solver._q(ref, d, u), float)
    return solver, np.array(solver._written[0], float), q, solver._z_lin.copy(), (x0, u, d, ref)


def test_the_setting_is_checked_and_off_by_default():
    assert MpcSettings().rti_valve_a_prox == 0.0
    assert check_prox("x", 3) == 3.0
    for bad in (-1.0, True, float("nan"), 2e4, "3"):
        with pytest.raises(ValueError, match=r"x.*\[0\.0, 10000\.0\]"):
            check_prox("x", bad)
    with pytest.raises(InvalidSettings, match=r"rti_valve_a_prox = -0.5"):
        MpcSettings(rti_valve_a_prox=-0.5)
    with pytest.raises(InvalidSettings, match=r"rti_valve_a_prox = 3.0 with .*solver = 'ipopt'.*allowed: solver 'rti'"):
        MpcSettings(solver="ipopt", rti_valve_a_prox=3.0)
    assert MpcSettings(solver="sqp", rti_valve_a_prox=3.0).rti_valve_a_prox == 3.0


def test_the_proximal_term_is_on_valve_a_only_at_the_heater_bound(problem):
    """At 240 W (the bound) the QP's Hessian has ``2 w`` more on valve a's diagonal at every stage and its gradient
    ``-2 w a_lin`` more, nothing else changed; at 120 W the QP is the same as without the term."""
    pb, w = problem, 5.0
    off, P_off, q_off, z_off, _ = _prepared(pb, 0.0, 240.0)
    on, P_on, q_on, z_on, _ = _prepared(pb, w, 240.0)
    assert on.valve_a_prox_on and not off.valve_a_prox_on
    assert np.array_equal(z_on, z_off)
    dP = P_on - P_off
    assert np.allclose(dP[on._P_valve_a_slots], 2.0 * w)
    assert np.count_nonzero(dP) == pb.N
    ia = on.iu0 + np.arange(pb.N) * pb.nu + pb.i_valve_a
    assert np.allclose((q_on - q_off)[ia], -2.0 * w * z_on[ia])
    assert np.count_nonzero(q_on - q_off) == pb.N
    below, P_below, q_below, _, _ = _prepared(pb, w, 120.0)
    off_below, P_off_below, q_off_below, _, _ = _prepared(pb, 0.0, 120.0)
    assert not below.valve_a_prox_on
    assert np.array_equal(P_below, P_off_below) and np.array_equal(q_below, q_off_below)


def test_a_restored_step_keeps_its_proximal_term_with_its_p(problem):
    """A step saved at the heater's bound (the term on) and restored after a relinearisation below it (the term off),
    as a replayed change does: the restored P carries the term, so the gradient built after it does too."""
    pb = problem
    solver, P_bound, q_bound, _, (x0, u, d, ref) = _prepared(pb, 5.0, 240.0)
    saved = solver._save_step()
    u_below = pb.scale_u(np.array([100.0, 120.0, 40.0, 100.0, 100.0, 100.0]))
    solver.prepare(x0, u_below, d, ref, pb.w_y_full)
    assert not solver.valve_a_prox_on
    solver._restore_step(saved)
    assert solver.valve_a_prox_on
    assert np.array_equal(np.array(solver._written[0], float), P_bound)
    assert np.array_equal(np.array(solver._q(ref, d, u), float), q_bound)


def test_the_settings_report_names_the_weight():
    ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=False, rti_valve_a_prox=3.0))
    assert ctrl.solver.settings["valve_a_prox"] == 3.0


def test_valve_a_curvature_by_term_adds_up_to_the_reduced_hessian(problem):
    """The tool's split of valve a's reduced Hessian (the states through the dynamics rows, the other inputs held)
    into each residual's Gauss-Newton part and the constant part is the whole of it; the other inputs minimised out
    (their Schur complement) lower it, never raise it."""
    pb = problem
    solver, Px, q, z_lin, (x0, u, d, ref) = _prepared(pb, 0.0, 240.0)
    rec = {"Px": Px, "Ax": np.array(solver._written[1], float), "gw2": np.array(solver._prepared["data"]["gw2"]),
           "sw": solver._weights(pb.w_y_full).copy(), "z": z_lin, "z_lin": z_lin, "q": q,
           "l": solver.l.copy(), "u": solver.u.copy()}
    P = vac.full_p(solver, Px)
    T = vac.input_map(solver, rec["Ax"])
    fixed = vac.reduced_hessian(solver, P, T)
    terms = vac.term_curvatures(solver, rec, T)
    assert np.allclose(sum(terms.values()), fixed, rtol=1e-9, atol=1e-9)
    assert terms["supply_air_temp_c"].max() > 0.0  # valve a moves the air at 40 %
    free = np.ones((pb.N, pb.nu), bool)
    h_free = vac.reduced_hessian(solver, P, T, free)
    assert np.all(np.linalg.eigvalsh(fixed - h_free) > -1e-9)
    assert np.diag(h_free).sum() < np.diag(fixed).sum()


@pytest.mark.slow
def test_the_proximal_term_breaks_valve_a_two_cycle_at_the_heater_bound_on_s1_13():
    """Today's defaults: valve a turns every step or two with the heater at 240 W after the step to 15 C (29
    reversals beyond 5 % at the bound, 121.8 C s); with the proximal term at 30 per scaled unit squared: 2 reversals
    there, 105.3 C s (sec. 2.43, 28 November 2026)."""
    runs = {w: box_trace.run_trace(S1_13, "winter_heating_steps", quick=True, settings={"rti_valve_a_prox": w})
            for w in (0.0, 30.0)}
    counts = {w: box_trace.reversals_at_heater_bound(run["mpc"].applied, 240.0)[1] for w, run in runs.items()}
    iae = {w: run["iae"]["mpc"] for w, run in runs.items()}
    assert counts[0.0] >= 20  # the two-cycle
    assert counts[30.0] <= counts[0.0] / 5
    assert iae[30.0] < 0.92 * iae[0.0]


def test_the_second_order_diagonal_leaves_a_relinearised_qp_alone(problem):
    """The measurement's gradient part goes with the P it was added to: once a relinearisation writes a new P (a
    change's second QP, the cold start's QPs), the gradient is the plain one again."""
    pb = problem
    solver, _, q_plain, _, (x0, u, d, ref) = _prepared(pb, 0.0, 240.0)
    with vac.SecondOrderDiagonal():
        solver._so_extra = (np.full(8, 2.0), solver._written)
        assert not np.array_equal(np.array(solver._q(ref, d, u), float), q_plain)
        solver.prepare(x0, u, d, ref, pb.w_y_full)
        q_stale = np.array(solver._q(ref, d, u), float)  # the extra still held, its P gone
        solver._so_extra = None
        assert np.array_equal(q_stale, np.array(solver._q(ref, d, u), float))
