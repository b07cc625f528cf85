"""The start of a reference change (mpc/steady_target.py): the steady-state target holds the reference at rest on
the model, the plan toward it keeps the QP's bounds and rate rows, its states are the model's rollout; in the
controller a change's QPs start there, with fewer OSQP iterations than from the shifted plan and the same
commands with OSQP's generated C and with its Python interface.

Budget: about 15 s on a loaded two-core machine (CasADi's interpreter, three short closed loops).
"""

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import STAGE_OUTPUTS
from hvac_mpc.mpc.steady_target import SteadyStart

#: Inlet and water (degC), mixed-air and flow offsets: the solve-time loop's conditions.
D = np.array([32.0, 5.0, 0.0, 0.0])
#: The command in force (W, W, %, %, %, %): the solve-time loop's start.
U_PREV = np.array([150.0, 0.0, 70.0, 100.0, 100.0, 100.0])


@pytest.fixture(scope="module")
def controller():
    return MpcController(settings=MpcSettings(codegen=False, steady_start=True))


def _start(ctrl, reference, x_phys=None, u_prev=U_PREV):
    pb = ctrl.problem
    x = pb.placeholder_state() if x_phys is None else x_phys
    lo, hi = pb.input_bounds(u_prev)
    ref = pb.reference_vector(reference)
    w_y = pb.output_weights(reference)
    return pb.scale_x(x), lo, hi, ref, ctrl.solver._steady.start(pb.scale_x(x), pb.scale_u(u_prev), D, pb.model.p_default,
                                                                  ref, w_y, lo, hi)


def test_the_target_holds_the_reference_at_rest_on_the_model(controller):
    pb = controller.problem
    reference = solve_time.SCENARIO[1][1]  # 13 degC, 35 L/s split 0.40 / 0.35 / 0.25
    _, _, _, ref, (u_t, _, _) = _start(controller, reference)
    x = pb.scale_x(pb.placeholder_state())
    for _ in range(60):  # 16 minutes at the target, the last stage's 16 s at a time
        x = np.asarray(pb.F(x, u_t, D, pb.N - 1)).ravel()
    y = np.asarray(pb.Y(x, u_t, D)).ravel()
    i_t, i_q = STAGE_OUTPUTS.index("supply_air_temp_c"), STAGE_OUTPUTS.index("volume_flow_m3s")
    assert abs(y[i_t] - ref[i_t]) < 0.05
    np.testing.assert_allclose(y[i_q:i_q + 4], ref[i_q:i_q + 4], atol=5e-4)  # flow and split within 0.5 L/s
    # from the command in force the outlets are far off: the target is not where it started
    assert np.abs(pb.unscale_u(u_t) - U_PREV).max() > 20.0


def test_the_plan_keeps_the_bounds_and_rates_and_its_states_are_the_rollout(controller):
    pb = controller.problem
    low = np.array([30.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # the blower at its least: the flow's ramp takes seconds
    x0, lo, hi, _, (u_t, U, X) = _start(controller, solve_time.SCENARIO[3][1], u_prev=low)
    tol = 1e-9
    assert np.all(U >= lo - tol) and np.all(U <= hi + tol)  # stage 0's bounds hold the first move's rate limits
    assert np.all(np.abs(np.diff(U, axis=0)) <= pb.rate_bounds() + tol)
    np.testing.assert_allclose(U[-1], np.clip(u_t, lo[-1], hi[-1]), atol=1e-12)  # the ramp arrives
    assert not np.allclose(U[0], U[-1])  # and takes time: the first move is rate-limited
    assert np.array_equal(X[0], x0)
    for k in range(pb.N):
        np.testing.assert_allclose(X[k + 1], np.asarray(pb.F(X[k], U[k], D, k)).ravel(), rtol=1e-9, atol=1e-9)


def test_a_state_that_is_not_finite_gives_no_start(controller):
    x = controller.problem.placeholder_state()
    x[0] = np.nan
    assert _start(controller, solve_time.SCENARIO[1][1], x)[-1] is None


def _change(steady: bool, osqp_codegen: bool = True):
    """The solve-time loop's references of 60 s and 90 s, the second from step 10 on; per step OSQP iterations and
    QPs, and the commands."""
    scenario = ((0.0, solve_time.SCENARIO[2][1]), (10.0, solve_time.SCENARIO[3][1]))
    ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=osqp_codegen, deadline_s=3600.0,
                                              steady_start=steady))
    loop = solve_time.Loop(ctrl, seed=7, scenario=scenario)
    rows = [loop.step(k) for k in range(12)]
    assert all(r.stats["fallback"] is None for r in rows)
    return ([r.stats["iterations"] for r in rows], [r.stats["qp_solves"] for r in rows],
            np.array([r.command.vector() for r in rows]), ctrl)


def test_a_change_starts_at_the_target_with_fewer_iterations_and_the_same_commands_either_osqp():
    its, qps, commands, ctrl = _change(True)
    assert ctrl.solver.settings["steady_start"]
    shifted_its, shifted_qps, shifted, _ = _change(False)
    assert qps[10] == shifted_qps[10] == 2 and all(n == 1 for n in qps[1:10] + qps[11:])
    assert its[:10] == shifted_its[:10] and np.array_equal(commands[:10], shifted[:10])  # the same until the change
    assert its[10] <= shifted_its[10] / 2, (its[10], shifted_its[10])
    assert ctrl.solver.last_target is not None
    python_its, _, python, _ = _change(True, osqp_codegen=False)
    assert python_its == its and np.array_equal(python, commands)


def test_the_benchmark_finds_the_changes_and_counts_their_iterations():
    from hvac_mpc.benchmarks import change_start
    starts = [t for t, _ in solve_time.SCENARIO[1:]]  # every reference of the scenario differs from the one before
    assert change_start.change_steps(240) == [int(t) for t in starts]
    assert change_start.change_steps(31) == [30]
    iterations = np.array([100, 10, 10, 80, 30, 20, 10, 10, 10, 10])
    cpu = np.array([9.0, 1.0, 1.0, 4.0, 2.0, 1.5, 1.0, 1.0, 1.0, 1.0])
    s = change_start.summary(iterations, cpu, [3])
    assert s["iterations"] == 190 and s["change_iterations"] == [80]  # the cold step 0 left out
    assert s["wake_iterations"] == 30 + 20 + 10 + 10 + 10
    assert s["change_cpu_max_ms"] == 4.0 and s["cpu_max_ms"] == 4.0 and s["largest_steps"][0] == [3, 80]
