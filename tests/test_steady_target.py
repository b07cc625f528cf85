"""The start of a reference change (mpc/steady_target.py): the steady-state target holds the reference at rest on
the model, the plan toward it keeps the QP's bounds and rate rows, its states are the model's rollout; in the
controller a change's QPs start there, with fewer OSQP iterations than from the shifted plan and the same
commands with OSQP's generated C and with its Python interface; with ``steady_start_on="temperature"`` only a
change of the supply-temperature reference starts there (a flow change alone as without the start).

Budget: about 20 s on a loaded two-core machine (CasADi's interpreter, six short closed loops).
"""

import functools

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.contract import Reference
from hvac_mpc.mpc.ocp import STAGE_OUTPUTS, InvalidSettings
from hvac_mpc.mpc.steady_target import SteadyStart, starts_at_target

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


#: The solve-time loop's references of 60 s and 90 s (the temperature changes 20 -> 18 degC)
TEMPERATURE_CHANGE = ((0.0, solve_time.SCENARIO[2][1]), (10.0, solve_time.SCENARIO[3][1]))
#: The reference of 60 s, then its flow and split changed alone (20 degC both)
FLOW_CHANGE = ((0.0, solve_time.SCENARIO[2][1]), (10.0, Reference.from_split(20.0, 0.04, (0.4, 0.35, 0.25))))


@functools.lru_cache(maxsize=None)
def _change(steady: bool, osqp_codegen: bool = True, on: str = "any", scenario=TEMPERATURE_CHANGE):
    """Twelve steps of the solve-time loop through ``scenario`` (its second reference from step 10 on); per step
    OSQP iterations and QPs, the commands, and the solver's steady-state targets after steps 9 and 10."""
    ctrl = MpcController(settings=MpcSettings(codegen=False, osqp_codegen=osqp_codegen, deadline_s=3600.0,
                                              steady_start=steady, steady_start_on=on))
    loop = solve_time.Loop(ctrl, seed=7, scenario=scenario)
    rows, targets = [], []
    for k in range(12):
        rows.append(loop.step(k))
        targets.append(ctrl.solver.last_target)
    assert all(r.stats["fallback"] is None for r in rows)
    return ([r.stats["iterations"] for r in rows], [r.stats["qp_solves"] for r in rows],
            np.array([r.command.vector() for r in rows]), ctrl.solver.settings, targets[9:11])


def test_a_change_starts_at_the_target_with_fewer_iterations_and_the_same_commands_either_osqp():
    its, qps, commands, settings, targets = _change(True)
    assert settings["steady_start"] and settings["steady_start_on"] == "any"
    shifted_its, shifted_qps, shifted, _, _ = _change(False)
    assert qps[10] == shifted_qps[10] == 2 and all(n == 1 for n in qps[1:10] + qps[11:])
    assert its[:10] == shifted_its[:10] and np.array_equal(commands[:10], shifted[:10])  # the same until the change
    assert its[10] <= shifted_its[10] / 2, (its[10], shifted_its[10])
    assert targets[0] is None and targets[1] is not None  # the first target is the change's
    python_its, _, python, _, _ = _change(True, osqp_codegen=False)
    assert python_its == its and np.array_equal(python, commands)


def test_a_temperature_only_start_starts_a_temperature_change_alike():
    its, _, commands, settings, targets = _change(True, on="temperature")
    assert settings["steady_start_on"] == "temperature"
    any_its, _, any_commands, _, any_targets = _change(True)
    assert its == any_its and np.array_equal(commands, any_commands)
    np.testing.assert_array_equal(targets[1], any_targets[1])


def test_a_temperature_only_start_leaves_a_flow_change_to_the_shifted_plan():
    its, qps, commands, _, targets = _change(True, on="temperature", scenario=FLOW_CHANGE)
    shifted_its, shifted_qps, shifted, _, _ = _change(False, scenario=FLOW_CHANGE)
    any_its, _, _, _, any_targets = _change(True, scenario=FLOW_CHANGE)
    assert qps[10] == 2  # a change all the same: its two QPs
    assert targets[1] is None and its == shifted_its and np.array_equal(commands, shifted)
    assert any_targets[1] is not None and any_its[10] != shifted_its[10]  # where "any" starts it at the target


def test_which_changes_start_at_the_target():
    old = np.array([20.0, 0.025, 0.005, 0.0125, 0.0075, 0.0, 0.0])
    flow = old.copy()
    flow[1:5] *= 1.2
    warmer = old.copy()
    warmer[STAGE_OUTPUTS.index("supply_air_temp_c")] = 21.0
    assert starts_at_target("any", old, flow) and starts_at_target("any", old, warmer)
    assert not starts_at_target("temperature", old, flow) and starts_at_target("temperature", old, warmer)


@pytest.mark.parametrize("value", ["flow", "", None, True])
def test_an_unknown_choice_of_changes_is_refused_naming_the_field(value):
    with pytest.raises(InvalidSettings, match=r"MpcSettings\.steady_start_on .*'any', 'temperature'"):
        MpcSettings(steady_start=True, steady_start_on=value)


def test_the_benchmark_finds_the_changes_and_counts_their_iterations():
    from hvac_mpc.benchmarks import change_start
    from hvac_mpc.mpc.settings_file import settings_with
    starts = [t for t, _ in solve_time.SCENARIO[1:]]  # every reference of the scenario differs from the one before
    assert change_start.change_steps(240) == [int(t) for t in starts]
    assert change_start.change_steps(31) == [30]
    iterations = np.array([100, 10, 10, 80, 30, 20, 10, 10, 10, 10])
    cpu = np.array([9.0, 1.0, 1.0, 4.0, 2.0, 1.5, 1.0, 1.0, 1.0, 1.0])
    s = change_start.summary(iterations, cpu, [3])
    assert s["iterations"] == 190 and s["change_iterations"] == [80]  # the cold step 0 left out
    assert s["wake_iterations"] == 30 + 20 + 10 + 10 + 10
    assert s["change_cpu_max_ms"] == 4.0 and s["cpu_max_ms"] == 4.0 and s["largest_steps"][0] == [3, 80]
    qps = np.array([10, 1, 1, 2, 1, 1, 1, 1, 1, 1])
    slow = change_start.summary(iterations, cpu, [3], qps)["slowest_steps"]
    assert slow[:2] == [[3, 4.0, 80, 2, True], [4, 2.0, 30, 1, False]]  # by CPU time, the cold step left out
    # its variants whatever the defaults: the shifted start, every change, the temperature's only
    starts = {v: (s.steady_start, s.steady_start_on)
              for v, s in ((v, settings_with(MpcSettings(), f)) for v, f in change_start.VARIANTS.items())}
    assert starts["shifted"][0] is False and starts["steady"] == (True, "any")
    assert starts["temperature"] == starts["one_qp"] == (True, "temperature")
    assert MpcSettings(**change_start.VARIANTS["one_qp"]).reference_change_qps == 1


def test_a_run_too_short_for_a_change_is_refused_with_a_clear_message(capsys):
    from hvac_mpc.benchmarks import change_start
    first = change_start.first_change_step()
    assert first == int(solve_time.SCENARIO[1][0])  # the scenario's second reference starts the first change
    with pytest.raises(SystemExit) as exit_:  # refused before any loop runs
        change_start.main(["--steps", str(first), "--seeds", "1"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"--steps {first} holds no reference change" in err and f"at least {first + 1}" in err
    with pytest.raises(ValueError, match="no reference change within the 5 steps"):
        change_start.summary(np.full(5, 10), np.ones(5), [])
