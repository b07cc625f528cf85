"""The MPC on the simulated plant with all effects on (issue: the MPC, 'Must show').

Budget: about a minute on a loaded two-core machine (each controller builds in ~0.5 s, a
closed-loop second costs ~2 ms of MPC and 0.1 ms of plant).
"""

import math
import re

import numpy as np
import pytest

from hvac_mpc.models import Environment, Parameters, SimulatedPlant

from hvac_mpc.contract import Command, Measurement
from hvac_mpc.contract import StepResult
from hvac_mpc.mpc.estimator import EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings, OcpSpec, TrackingProblem, Weights
from hvac_mpc.contract import Reference

PARAMS = Parameters()
REF_WARM = Reference.from_split(20.0, 0.03, (0.4, 0.3, 0.3))
REF_COOL = Reference.from_split(15.0, 0.03, (0.4, 0.3, 0.3))
START = Command(150.0, 0.0, 50.0, 100.0, 100.0, 100.0)
RATES = np.array([OcpSpec().rate_blower_w_per_s, OcpSpec().rate_heater_w_per_s] + [OcpSpec().rate_valve_pct_per_s] * 4)  # W/s, %/s
LO = np.array([30.0, 0.0, 0.0, 0.0, 0.0, 0.0])
HI = np.array([300.0, 240.0, 100.0, 100.0, 100.0, 100.0])


def closed_loop(ctrl, plant, references, record=None):
    """Run ``ctrl`` on ``plant`` for the references (one per second); returns rows of history."""
    rows = []
    for ref in references:
        res = ctrl.step(plant.read(), ref)
        assert isinstance(res, StepResult)
        applied = plant.apply(res.command)
        plant.advance()
        rows.append(dict(cmd=res.command.vector(), applied=applied, stats=res.stats, truth=plant.truth(), ref=ref))
    return rows


def assert_bounds_and_rates(rows, start):
    cmds = np.array([r["cmd"] for r in rows])
    assert np.all(cmds >= LO - 1e-9) and np.all(cmds <= HI + 1e-9), "actuator bound violated"
    steps = np.diff(np.vstack([start.vector(), cmds]), axis=0)
    assert np.all(np.abs(steps) <= RATES + 1e-9), f"rate limit violated: {np.abs(steps).max(axis=0)}"


#: the plant of the closed-loop tests: all effects on and a cooler core 5 % less effective and a
#: blower giving 5 % more flow than the controller's model (PARAMS)
PLANT_PARAMS = PARAMS.replace(cooler_slope=0.95 * PARAMS.cooler_slope,
                              flow_per_watt_m3s_per_w=1.05 * PARAMS.flow_per_watt_m3s_per_w)


@pytest.fixture(scope="module")
def cooling_run():
    plant = SimulatedPlant(PLANT_PARAMS, seed=3)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START))
    refs = [REF_WARM] * 150 + [REF_COOL] * 250
    return closed_loop(ctrl, plant, refs)


def test_cooling_step_reaches_half_a_degree_within_30_s(cooling_run):
    after = np.array([r["truth"]["supply_temp_c"] for r in cooling_run[150:]])  # noise-free thermocouple
    inside = np.abs(after - REF_COOL.supply_temp_c) <= 0.5
    settle = next(i for i in range(len(inside)) if inside[i:].all()) + 1
    assert settle <= 30, f"cooling step took {settle} s to stay within +-0.5 C"


def test_steady_state_errors_vanish_on_a_plant_that_is_not_the_model(cooling_run):
    # the plant has motor_asymmetry, chiller_hysteresis, trapped_air, noise and other cooler and blower
    # parameters, which the prediction model lacks: the disturbance states must remove the offsets
    # in temperature and flow
    for lo, hi, ref in ((90, 150, REF_WARM), (340, 400, REF_COOL)):
        window = cooling_run[lo:hi]
        temp = np.mean([r["truth"]["supply_temp_c"] for r in window])
        flow = np.mean([r["truth"]["volume_flow_m3s"] for r in window])
        assert abs(temp - ref.supply_temp_c) < 0.1
        assert abs(flow - ref.volume_flow_m3s) < 0.01 * ref.volume_flow_m3s
        # there were offsets to remove (the test is not trivially passed): the controller's model,
        # settled at the same command, misses the plant's temperature and flow
        model = SimulatedPlant(PARAMS, effects=OcpSpec().model_effects + ("ptc_power_fall",))
        model.settle(Command.from_vector(window[-1]["applied"]))
        assert abs(model.truth()["supply_temp_c"] - temp) > (0.5 if ref is REF_COOL else 0.1)
        assert abs(model.truth()["volume_flow_m3s"] - flow) > 0.02 * ref.volume_flow_m3s


def test_outlet_flows_track_the_split(cooling_run):
    for r in (cooling_run[140], cooling_run[399]):
        got = np.array([r["truth"][k] for k in ("flow_m_m3s", "flow_f_m3s", "flow_w_m3s")])
        want = np.array(r["ref"].split)
        assert np.max(np.abs(got - want)) < 0.03 * r["ref"].volume_flow_m3s


def test_no_bound_or_rate_violated_and_every_step_solved_in_one_qp(cooling_run):
    assert_bounds_and_rates(cooling_run, START)
    stats = [r["stats"] for r in cooling_run]
    assert all(s["fallback"] is None for s in stats)
    # real-time iteration: one QP per sample; only the cold start (no previous solution) and the
    # reference change at sample 150 iterate
    assert stats[0]["cold_start"] and 1 <= stats[0]["qp_solves"] <= MpcSettings().cold_start_qps
    assert not any(s["cold_start"] for s in stats[1:])
    assert all(s["qp_solves"] == 1 for k, s in enumerate(stats) if k not in (0, 150))
    assert 1 <= stats[150]["qp_solves"] <= MpcSettings().reference_change_qps
    # OSQP iterations within the cap per QP
    assert all(s["iterations"] <= s["qp_solves"] * MpcSettings().osqp_max_iter for s in stats)
    for key in ("step_time_s", "prep_time_s", "feedback_time_s", "status", "mode"):
        assert key in stats[-1]


def test_heating_keeps_valve_a_out_of_saturation_and_heater_below_its_limit():
    # winter inlet: only the heater can reach 26 C (thesis sec. 5.4.2: trapped hot air at valve a)
    env = Environment(inlet_temp_c=15.0, chiller_setpoint_c=5.0)
    plant = SimulatedPlant(PARAMS, seed=4, environment=env)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START))
    rows = closed_loop(ctrl, plant, [Reference(26.0, 0.012)] * 150 + [Reference(12.0, 0.03)] * 60)
    assert_bounds_and_rates(rows, START)
    cap = PARAMS.trap_threshold_pct - OcpSpec().trap_margin_pct
    prev_heater = START.heater_cmd_w
    heated = False
    for r in rows:
        if prev_heater > 1.0:  # heater on: valve a must stay below the saturation that traps air
            heated = True
            assert r["cmd"][2] <= cap + 1e-9
        prev_heater = r["cmd"][1]
    assert heated
    assert max(r["truth"]["heater_temp_c"] for r in rows) <= PARAMS.heater_temp_max_c
    temps = np.array([r["truth"]["supply_temp_c"] for r in rows[:150]])
    assert temps[-1] > temps[0] + 5.0  # it does heat


def test_heating_steps_up_and_down_at_low_flow_respect_the_ptc_line():
    # winter_heating_steps conditions: 5 C inlet, water at the inlet temperature, 40 m3/h; the plant
    # has the flow-dependent bypass and the PTC power fall. With the PTC fall inside the prediction
    # model (min(command, available)) the heater command ran up to 14 W above the available power
    # here, where its gradient is zero; in the benchmark it stuck at full command with the supply air
    # 3 C too warm after a step down.
    env = Environment(inlet_temp_c=5.0, chiller_setpoint_c=5.0)
    start = Command(75.0, 80.0, 60.0, 100.0, 100.0, 100.0)
    plant = SimulatedPlant(PARAMS, seed=9, environment=env, initial_command=start)
    plant.settle(start)
    # no wall-clock deadline: the closed loop is the same on a loaded machine
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=start, deadline_s=3600.0))
    flow = 40.0 / 3600.0
    ref_up, ref_down = Reference(14.0, flow), Reference(10.0, flow)
    rows = closed_loop(ctrl, plant, [ref_up] * 200 + [ref_down] * 120)
    assert_bounds_and_rates(rows, start)
    for ref, part in ((ref_up, rows[:200]), (ref_down, rows[200:])):
        temp = np.array([r["truth"]["supply_temp_c"] for r in part])
        inside = np.abs(temp - ref.supply_temp_c) <= 0.5
        settle = next((i for i in range(len(inside)) if inside[i:].all()), None)
        # up: the heater body warms with 240 W (80 s measured); down: 60 s measured. Traced: from the step
        # on the heater is off and valve a closed (both at their bounds), and the supply air falls as fast as
        # the plant's heater body cools (69 -> 44 C in 60 s), whose heat still reaches the air through the
        # core path valve a never closes (bypass fraction at most 0.9, thesis sec. 4.5.1); the estimator puts
        # the body at 38 C there, the difference carried by its offset. The controller has no faster move
        # left: the settling is the body's
        limit = 110 if ref is ref_up else 90
        assert settle is not None and settle <= limit, f"step to {ref.supply_temp_c} C: settle {settle} s"
    # the applied heater command never asks for more than the PTC line gives at the plant's heater
    # temperature, up to the estimate's error: the line falls 2.29 W/K, and 10 W is 4.4 K of the unmeasured
    # heater body (7.5 W measured with the supply-temperature weight 5 and valves at 50 %/s, 2 W before; the
    # bug this catches ran 14 W above)
    pb = ctrl.problem
    for before, r in zip(rows, rows[1:]):
        assert r["cmd"][1] <= pb.ptc_available_w(before["truth"]["heater_temp_c"]) + 10.0


def test_fallback_uses_shifted_plan_first_then_the_baseline_and_recovers():
    plant = SimulatedPlant(PARAMS, seed=5)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START, plan_fallback_s=4.0))
    rows = closed_loop(ctrl, plant, [REF_WARM] * 40)
    plan = ctrl.problem.unscale_u(ctrl._last_solution.U)
    t_nodes = ctrl.problem.t_nodes
    ctrl.force_solver_failure(8)
    rows += closed_loop(ctrl, plant, [REF_WARM] * 8)
    used = [r["stats"]["fallback"] for r in rows[40:]]
    assert used[:3] == ["shifted_plan"] * 3  # ages 1, 2, 3 s < plan_fallback_s
    assert used[3:] == ["baseline"] * 5
    # the shifted plan is the last plan read at the elapsed time, projected onto bounds and rates
    previous = rows[39]["cmd"]
    for age, r in zip((1.0, 2.0, 3.0), rows[40:43]):
        j = int(np.searchsorted(t_nodes, age, side="right") - 1)
        expected = np.clip(plan[j], *ctrl.problem.command_bounds(previous, r["stats"]["valve_a_cap_pct"]))
        assert np.allclose(r["cmd"], expected)
        previous = r["cmd"]
    rows += closed_loop(ctrl, plant, [REF_WARM] * 30)
    assert all(r["stats"]["fallback"] is None for r in rows[48:])  # solver back, warm start rebuilt
    assert_bounds_and_rates(rows, START)
    assert abs(rows[-1]["truth"]["supply_temp_c"] - REF_WARM.supply_temp_c) < 0.5


def test_without_baseline_the_last_command_is_held(monkeypatch):
    plant = SimulatedPlant(PARAMS, seed=6)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START, plan_fallback_s=0.0))

    def missing():
        raise ImportError("no baseline")

    monkeypatch.setattr(ctrl, "_get_baseline", missing)
    closed_loop(ctrl, plant, [REF_WARM] * 5)
    ctrl.force_solver_failure(2)
    rows = closed_loop(ctrl, plant, [REF_WARM] * 2)
    assert [r["stats"]["fallback"] for r in rows] == ["hold_last_command"] * 2
    assert np.array_equal(rows[0]["cmd"], rows[1]["cmd"])


def test_a_preparation_failure_takes_the_estimators_time_update_once(monkeypatch):
    """A step that fails after the estimator's time update (in the preparation of the next step) answers
    with a fallback and does not predict the estimate a second time."""
    plant = SimulatedPlant(PARAMS, seed=6)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START))
    closed_loop(ctrl, plant, [REF_WARM] * 5)

    def broken(*args, **kwargs):
        raise RuntimeError("preparation broke")

    monkeypatch.setattr(ctrl.solver, "_write", broken)  # the fused path: after the time update
    monkeypatch.setattr(ctrl.solver, "prepare", broken)  # the other path: after ekf.predict
    before = ctrl.ekf.time_updates
    rows = closed_loop(ctrl, plant, [REF_WARM])
    assert rows[0]["stats"]["status"].startswith("error") and "preparation broke" in rows[0]["stats"]["status"]
    assert ctrl.ekf.time_updates == before + 1


def test_missed_deadline_falls_back_and_never_raises():
    plant = SimulatedPlant(PARAMS, seed=7)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START, deadline_s=1e-7))
    rows = closed_loop(ctrl, plant, [REF_WARM] * 5)
    assert all(r["stats"]["fallback"] is not None for r in rows)
    assert_bounds_and_rates(rows, START)


def test_bad_inputs_do_not_raise_out_of_step():
    plant = SimulatedPlant(PARAMS, seed=8)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START))
    closed_loop(ctrl, plant, [REF_WARM] * 5)
    m = plant.read()
    nan = Measurement(m.time_s, math.nan, math.nan, math.nan)
    res = ctrl.step(nan, REF_WARM)
    assert np.all(np.isfinite(res.command.vector()))
    assert "open loop" in res.stats["status"]
    res = ctrl.step(plant.read(), None)  # not a reference: the last valid one is kept
    assert np.all(np.isfinite(res.command.vector())) and "invalid reference" in res.stats["status"]
    res = ctrl.step(plant.read(), {"supply_temp_c": 500.0, "volume_flow_m3s": 0.03})
    assert "invalid reference" in res.stats["status"]
    fresh = MpcController(PARAMS, MpcSettings(initial_command=START))
    res = fresh.step(plant.read(), "nonsense")
    assert res.stats["fallback"] == "hold_last_command" and res.command == START


def test_two_controllers_side_by_side_give_identical_results():
    a, b = (MpcController(PARAMS, MpcSettings(initial_command=START)) for _ in range(2))
    other = MpcController(PARAMS, MpcSettings(initial_command=START, ocp=OcpSpec(weights=Weights(supply_temp=5.0))))
    plant = SimulatedPlant(PARAMS, seed=9)
    plant.settle(START)
    other_plant = SimulatedPlant(PARAMS, seed=10, environment=Environment(30.0, 5.0))
    other_plant.settle(START)
    for k in range(40):
        ref = REF_WARM if k < 20 else REF_COOL
        m = plant.read()
        ra, rb = a.step(m, ref), b.step(m, ref)
        ro = other.step(other_plant.read(), REF_COOL)  # interleaved, different data and settings
        other_plant.apply(ro.command)
        other_plant.advance()
        assert ra.command == rb.command
        assert ra.stats["iterations"] == rb.stats["iterations"]
        plant.apply(ra.command)
        plant.advance()


def test_converged_sqp_matches_ipopt_on_the_same_problem():
    """The QP built from the problem is right: Gauss-Newton SQP converges to IPOPT's optimum."""
    from hvac_mpc.mpc.ipopt_reference import IpoptReferenceSolver
    from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

    pb = TrackingProblem(PARAMS, OcpSpec())
    u_prev = pb.scale_u(Command(160.0, 0.0, 40.0, 90.0, 60.0, 50.0).vector())
    d = np.array([28.0, 5.0, -0.3, 0.0])
    x0 = pb.scale_x(pb.model.steady_state(pb.unscale_u(u_prev), np.array([28.0, 5.0, 0.0, 0.0])))
    ref = pb.reference_vector(REF_COOL)
    w_y = pb.output_weights(REF_COOL)
    lo, hi = pb.input_bounds(pb.unscale_u(u_prev))
    sqp = RtiOsqpSolver(pb, eps=1e-7, max_iter=20000, sqp_max_iter=40, sqp_tol=1e-6)
    ip = IpoptReferenceSolver(pb, tol=1e-9)
    rs = sqp.feedback(x0, u_prev, d, ref, w_y, lo, hi)
    ri = ip.feedback(x0, u_prev, d, ref, w_y, lo, hi)
    assert rs.ok and ri.ok
    assert rs.qp_solves > 1
    cost = pb.cost_function()
    c_sqp = float(cost(rs.X.T, rs.U.T, rs.S, d, ref, w_y, u_prev))
    c_ip = float(cost(ri.X.T, ri.U.T, ri.S, d, ref, w_y, u_prev))
    assert c_sqp == pytest.approx(c_ip, rel=1e-3)
    assert np.max(np.abs(pb.unscale_u(rs.U[0]) - pb.unscale_u(ri.U[0]))) < 0.5  # W and %


def test_the_converged_reference_takes_the_model_parameters_at_run_time():
    """The IPOPT reference's NLP takes the model parameters as parameters (``set_parameters``), as the RTI's QP does: with
    a heat of 20 W into the mixed air both converge to one optimum, another than with the parameters the problem was
    built with; and the MPC with ``solver="ipopt"`` runs with the filter's heat flow (``q_supply_heat_w``, which hands
    the filter's parameters to the solver at every step: without ``set_parameters`` each step fell back)."""
    from hvac_mpc.mpc.ipopt_reference import IpoptReferenceSolver
    from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

    pb = TrackingProblem(PARAMS, OcpSpec())
    u_prev = pb.scale_u(Command(160.0, 0.0, 40.0, 90.0, 60.0, 50.0).vector())
    d = np.array([28.0, 5.0, -0.3, 0.0])
    x0 = pb.scale_x(pb.model.steady_state(pb.unscale_u(u_prev), np.array([28.0, 5.0, 0.0, 0.0])))
    ref, w_y = pb.reference_vector(REF_COOL), pb.output_weights(REF_COOL)
    lo, hi = pb.input_bounds(pb.unscale_u(u_prev))
    p = np.array(pb.model.p_default, float)
    p[pb.model.param_names.index("supply_heat_w")] = 20.0
    built = IpoptReferenceSolver(pb, tol=1e-9).feedback(x0, u_prev, d, ref, w_y, lo, hi)
    sqp, ip = RtiOsqpSolver(pb, eps=1e-7, max_iter=20000, sqp_max_iter=40, sqp_tol=1e-6), IpoptReferenceSolver(pb, tol=1e-9)
    sqp.set_parameters(p)
    ip.set_parameters(p)
    rs, ri = sqp.feedback(x0, u_prev, d, ref, w_y, lo, hi), ip.feedback(x0, u_prev, d, ref, w_y, lo, hi)
    assert rs.ok and ri.ok and built.ok
    assert np.max(np.abs(pb.unscale_u(rs.U[0]) - pb.unscale_u(ri.U[0]))) < 0.5  # W and %
    assert np.max(np.abs(pb.unscale_u(built.U) - pb.unscale_u(ri.U))) > 2.0  # W and %, over the plan
    from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S
    heat = EkfSettings(q_supply_heat_w=0.5, supply_heat_release_at_rest=True)  # docs/robustness.md sec. 2.33
    ctrl = MpcController(PARAMS, MpcSettings(solver="ipopt", deadline_s=DETERMINISTIC_DEADLINE_S, ekf=heat))
    plant = SimulatedPlant(PARAMS, seed=0)
    for _ in range(3):
        r = ctrl.step(plant.read(), REF_COOL)
        assert r.stats["fallback"] is None, r.stats
        plant.apply(r.command)
        plant.advance()


@pytest.mark.slow
def test_jit_and_virtual_machine_linearise_identically():
    pb = TrackingProblem(PARAMS, OcpSpec())
    rng = np.random.default_rng(0)
    X = rng.uniform(-0.5, 0.5, (pb.N + 1, pb.nx))
    U = rng.uniform(-0.9, 0.9, (pb.N + 1, pb.nu))
    d = np.array([25.0, 5.0, 0.0, 0.0])
    vm = pb.linearise(X, U, d)
    from hvac_mpc.mpc.mpc_controller import _try_jit
    if not _try_jit(pb):
        pytest.skip("no working C compiler for CasADi's JIT; the virtual machine is used instead")
    jit = pb.linearise(X, U, d)
    for key in vm:
        assert np.allclose(vm[key], jit[key], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("kwargs, field", [
    (dict(deadline_s=-1.0), "MpcSettings.deadline_s"),
    (dict(solver="cplex"), "MpcSettings.solver"),
    (dict(osqp_max_iter=2.5), "MpcSettings.osqp_max_iter"),
    (dict(osqp_alpha=2.0), r"MpcSettings.osqp_alpha .* open range \(0, 2\)"),
    (dict(osqp_scaling=-1), "MpcSettings.osqp_scaling"),
    (dict(osqp_first_pass_iter=1.5), "MpcSettings.osqp_first_pass_iter"),
    (dict(ocp=OcpSpec(stage_durations_s=(2.0,) * 40)), r"MpcSettings.ocp.stage_durations_s\[0\]"),
    (dict(ocp=OcpSpec(stage_durations_s=(1.0,) * 30)), "MpcSettings.ocp.stage_durations_s"),
    (dict(ocp=OcpSpec(rate_valve_pct_per_s=0.0)), "MpcSettings.ocp.rate_valve_pct_per_s"),
    (dict(ocp=OcpSpec(weights=Weights(energy_per_100w2=-1.0))), "MpcSettings.ocp.weights.energy_per_100w2"),
    (dict(ocp=OcpSpec(model_effects=("warp_drive",))), "MpcSettings.ocp.model_effects"),
    (dict(ekf=EkfSettings(r_supply_c=0.0)), "MpcSettings.ekf.r_supply_c"),
    (dict(water_prediction="guess"), "MpcSettings.water_prediction"),
    (dict(jit=1), "MpcSettings.jit: expected True or False"),
    (dict(reach_deferred="yes"), "MpcSettings.reach_deferred: expected True or False"),
    (dict(ocp=OcpSpec(ptc_limit=0)), "MpcSettings.ocp.ptc_limit: expected True or False"),
    (dict(ekf=EkfSettings(learn_bypass_flow=1)), "MpcSettings.ekf.learn_bypass_flow: expected True or False"),
])
def test_settings_errors_name_the_field_and_range(kwargs, field):
    with pytest.raises(InvalidSettings, match=field) as info:
        MpcSettings(**kwargs)
    # the message names the allowed range or the allowed choices
    assert re.search(r"[\[(][^\]]*\]|one of|allowed|'air'|'hold'|True or False", str(info.value))


@pytest.mark.slow
def test_valve_a_weight_while_heating_keeps_the_heater_ready_for_a_step_up():
    """The independent box (hvac_mpc.mismatch, nominal variant), winter_heating_steps (quick: 9 -> 12 -> 15 C at
    40 m3/h): with valve a's weight while heating (Weights.valve_a_heating_per_pct2) the MPC holds valve a lower
    and the heater body hotter at the same heat, and follows the steps better than without it (measured 151.7
    against 191.7 C s); with the heater off the weight is off."""
    import dataclasses

    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import closed_loop_iae

    sc = scenarios.select(["winter_heating_steps"], quick=True)[0]
    settings = MpcSettings(initial_command=sc.initial_command, deadline_s=3600.0)
    without = dataclasses.replace(settings, ocp=dataclasses.replace(
        settings.ocp, weights=dataclasses.replace(settings.ocp.weights, valve_a_heating_per_pct2=0.0)))
    ready = closed_loop_iae(sc, MpcController(settings=settings), "nominal", seed=0)
    plain = closed_loop_iae(sc, MpcController(settings=without), "nominal", seed=0)
    assert ready["temp_iae_cs"] < 0.9 * plain["temp_iae_cs"], (ready, plain)
    pb = MpcController(settings=settings).problem
    w = pb.output_weights(Reference.from_split(12.0, 0.011, (0.3, 0.5, 0.2)))
    assert pb.heating_weights(w.copy(), heating=True)[-1] == settings.ocp.weights.valve_a_heating_per_pct2 > 0.0
    assert pb.heating_weights(w.copy(), heating=False)[-1] == 0.0
