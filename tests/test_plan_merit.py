"""The globalised real-time iteration step (mpc/plan_merit.py): the merit is the problem's cost along the model's
rollout, the step is damped only where the QP's plan costs more than the linearisation point, and on the
independent box with recirculation the damped step ends valve a's alternation."""

import numpy as np
import pytest

from hvac_mpc.models.discovered import DiscoveredTerm
from hvac_mpc.models.model_file import RefinedModel
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc.plan_merit import PlanMerit


@pytest.fixture(scope="module")
def controller():
    return MpcController(settings=MpcSettings(rti_step_fractions=(0.5, 0.25)))


def _plan(pb, heater_w: float, valve_a_pct: float) -> np.ndarray:
    """A plan holding one command (blower 150 W, valves m, f, w at 50 %), scaled, N x nu."""
    return np.tile(pb.scale_u(np.array([150.0, heater_w, valve_a_pct, 50.0, 50.0, 50.0])), (pb.N, 1))


def test_merit_is_the_problems_cost_along_the_rollout(controller):
    """With the heater body below its soft limits and the flow above the floor, the merit of a plan equals the
    problem's exact cost (TrackingProblem.cost_function, no slack) of the model's rollout with the same inputs."""
    pb, solver = controller.problem, controller.solver
    x0 = pb.scale_x(pb.placeholder_state())
    d = np.array([5.0, 5.0, 0.3, 0.0])
    ref = pb.reference_vector(_reference())
    w_y = pb.heating_weights(pb.w_y_full.copy(), heating=True)
    U = _plan(pb, 100.0, 30.0)
    U[3:] = _plan(pb, 160.0, 60.0)[3:]  # a move within the horizon, so the move terms count too
    u_prev = pb.scale_u(np.array([120.0, 80.0, 20.0, 50.0, 50.0, 50.0]))
    X = np.empty((pb.N + 1, pb.nx))
    X[0] = x0
    for k in range(pb.N):
        X[k + 1] = np.asarray(pb.F(X[k], U[k], d, k)).ravel()
    assert pb.unscale_x(X)[:, pb.i_heater].max() < 60.0  # below the PTC knee and the soft limit: no slack
    exact = float(pb.cost_function()(X.T, U.T, np.zeros(pb.N), d, ref, w_y, u_prev))
    merit = solver._merit.cost_function()(x0, U.T, d, solver._stage_weights(w_y).T, ref, u_prev, pb.model.p_default,
                                          0.0, np.zeros(pb.N))
    assert float(merit) == pytest.approx(exact, rel=1e-9)


def test_merit_carries_the_readiness_as_the_one_sided_penalty_on_the_rollout(controller):
    """With the heater readiness's floor and stage weights given (mpc/readiness.py), the merit grows by
    sum_k w_k max(x_f - x_k, 0)^2 over the rollout's scaled body at stages 1..N, and by nothing where the body is
    above the floor: the step is judged on the cost whose pull the QP carries."""
    pb, solver = controller.problem, controller.solver
    merit = solver._merit.cost_function()
    x0 = pb.scale_x(pb.placeholder_state())
    d = np.array([5.0, 5.0, 0.0, 0.0])
    ref, w_y = pb.reference_vector(_reference()), pb.heating_weights(pb.w_y_full.copy(), heating=True)
    sw, p, u_prev = solver._stage_weights(w_y).T, pb.model.p_default, pb.scale_u(np.array([150, 150, 30, 50, 50, 50.0]))
    U = _plan(pb, 150.0, 30.0)
    X = [x0]
    for k in range(pb.N):
        X.append(np.asarray(pb.F(X[k], U[k], d, k)).ravel())
    body = np.array(X)[1:, pb.i_heater]
    w = np.linspace(0.5, 2.0, pb.N)
    base = float(merit(x0, U.T, d, sw, ref, u_prev, p, 0.0, np.zeros(pb.N)))
    x_f = float(np.median(body))  # some stages below the floor, some above
    with_floor = float(merit(x0, U.T, d, sw, ref, u_prev, p, x_f, w))
    short = np.maximum(x_f - body, 0.0)
    assert 0 < np.count_nonzero(short) < pb.N
    assert with_floor - base == pytest.approx(float(np.sum(w * short ** 2)), rel=1e-9)
    assert float(merit(x0, U.T, d, sw, ref, u_prev, p, body.min() - 1.0, w)) == pytest.approx(base, rel=1e-12)


def _reference():
    from hvac_mpc.contract import Reference
    return Reference(supply_temp_c=30.0, volume_flow_m3s=0.012)


def test_the_step_is_damped_only_where_the_qp_plan_costs_more(controller):
    """choose: the QP's plan is taken whole where its merit is no higher than the linearisation point's; the
    other way round (heater off against heating to 30 C, far beyond the tolerance), one of the damped fractions
    is taken, the one of least merit."""
    pb, solver = controller.problem, controller.solver
    merit = solver._merit
    x0 = pb.scale_x(pb.placeholder_state())
    d = np.array([5.0, 5.0, 0.0, 0.0])
    ref = pb.reference_vector(_reference())
    w_y = pb.heating_weights(pb.w_y_full.copy(), heating=True)
    sw, p = solver._stage_weights(w_y), pb.model.p_default
    u_prev = pb.scale_u(np.array([150.0, 150.0, 30.0, 50.0, 50.0, 50.0]))
    good, bad = _plan(pb, 150.0, 30.0), _plan(pb, 0.0, 90.0)  # heating towards 30 C against the heater off
    cost, off = merit.cost_function(), (0.0, np.zeros(pb.N))  # the readiness out
    c_good = float(cost(x0, good.T, d, sw.T, ref, u_prev, p, *off))
    c_bad = float(cost(x0, bad.T, d, sw.T, ref, u_prev, p, *off))
    assert c_bad > c_good
    assert merit.choose(bad, good, x0, d, sw, ref, u_prev, p) == 1.0
    fraction = merit.choose(good, bad, x0, d, sw, ref, u_prev, p)
    assert fraction in merit.fractions
    damped = {a: float(cost(x0, (good + a * (bad - good)).T, d, sw.T, ref, u_prev, p, *off)) for a in merit.fractions}
    assert damped[fraction] == min(damped.values()) < c_bad


@pytest.mark.parametrize("value", [(1.0,), (0.0,), (0.5, -0.1), [0.5], (0.5,) * 9, ("half",)])
def test_step_fractions_out_of_range_name_the_field(value):
    with pytest.raises(InvalidSettings, match="rti_step_fractions"):
        MpcSettings(rti_step_fractions=value)


@pytest.mark.slow  # above 7 s on a loaded machine; the whole suite runs it
def test_the_globalised_step_ends_valve_a_alternating_on_the_recirculating_box():
    """The independent box drawing 15 % of cabin air behind the inlet sensor (hvac_mpc.mismatch
    ``recirculation``), the MPC with the ``box_in`` term identification finds for it (-0.15 T_in + 3.6 C, the
    thesis parameters otherwise), the quick trapped-air scenario: at the step up the air through the heater is
    hardly warmer than the bypass air, and the plain real-time iteration moves valve a 0 -> 50 -> 0 % from sample
    to sample (measured: 104 reversals of more than 20 % over the run, 484.0 C s). With the damped step three, in
    the first 5 s after the step, and the thermocouple tracks better (382.4 C s). Both runs without the search along
    the reversing input (``rti_reversal_search`` 0; on by default): it ends most of the same alternation itself
    (measured on this run: 107 -> 19 reversals, 506.7 -> 415.9 C s), so the plain run with it would not show the
    damped step's effect; with both 4 reversals, 382.5 C s."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S, plant_seed
    from hvac_mpc.mismatch import make_plant

    term = DiscoveredTerm("recirculation", "box_in", ("inlet", "one"), (-0.15, 3.6))
    refined = RefinedModel(Parameters(), ("ptc_power_fall", "fan_curve", "valve_leakage"), (term,),
                           absent=("bypass_flow",))
    sc = scenarios.select(["trapped_air_release"], quick=True)[0]

    def run(fractions):
        # valve a's reversing moves applied whole (valve_a_reversal_share=1): the iteration's steps alone compared
        settings = MpcSettings(initial_command=sc.initial_command, deadline_s=DETERMINISTIC_DEADLINE_S,
                               rti_step_fractions=fractions, valve_a_reversal_share=1.0, rti_reversal_search=0.0)
        ctrl = MpcController(settings=settings, model=refined)
        plant = make_plant("recirculation", seed=plant_seed(0, sc.seed), inlet_temp_c=sc.inlet_temp_c,
                           chiller_setpoint_c=sc.chiller_setpoint_c, initial_command=sc.initial_command)
        ctrl.reset(sc.initial_command)
        valve_a, iae, damped = [], 0.0, 0
        for k in range(int(sc.duration_s)):
            r = sc.reference_at(float(k))
            m = plant.read()
            if k >= sc.metrics_start_s:
                iae += abs(plant.truth()["supply_temp_c"] - r.supply_temp_c)
            u = np.asarray(ctrl.step(m, r).command.vector(), float)
            damped += ctrl._last_solution.extra.get("step_fraction", 1.0) < 1.0
            valve_a.append(u[2])
            plant.apply(u)
            plant.advance()
        move = np.diff(valve_a)
        reversals = int(np.sum((move[1:] * move[:-1] < 0) & (np.abs(move[1:]) > 20) & (np.abs(move[:-1]) > 20)))
        return reversals, iae, damped

    plain, plain_iae, plain_damped = run(())
    globalised, globalised_iae, damped = run((0.5, 0.25))
    assert plain > 50 and plain_damped == 0  # the case alternates without the damped step
    assert globalised <= 5 and damped > 0, (globalised, damped)
    assert globalised_iae < 0.9 * plain_iae, (globalised_iae, plain_iae)


def test_the_merit_takes_the_parameters_rows_from_its_parameter_input():
    """The soft rows' and the body heat's constants that follow from the model parameters (the heater's limit, the PTC
    line, the body's capacity: ``TrackingProblem.parameter_rows``) come from the merit's parameter input, so the
    generated merit of one parameter set is the function of another (the same structure key, built once into the code
    cache) and prices a plan as the other's own merit does; with the first set's parameters it prices it otherwise."""
    from hvac_mpc.mpc import codegen
    from hvac_mpc.mpc.ocp import OcpSpec, TrackingProblem, Weights

    spec = OcpSpec(weights=Weights(body_heat_power_w=50.0))  # the body's heat priced: its coefficient counts
    other = Parameters(heater_power_max_w=200.0, ptc_knee_c=55.0, heater_mass_kg=0.3, heater_temp_max_c=150.0)
    pb_a, pb_b = TrackingProblem(Parameters(), spec), TrackingProblem(other, spec)
    f_a, f_b = (PlanMerit(pb, (0.5,)).cost_function() for pb in (pb_a, pb_b))
    assert codegen.structure_key(f_a) == codegen.structure_key(f_b)
    x0 = pb_a.placeholder_state()
    x0[pb_a.i_heater] = 140.0  # beyond both PTC knees, near the lower heater limit: the rows' slack counts
    x0 = pb_a.scale_x(x0)
    d = np.array([5.0, 5.0, 0.0, 0.0])
    ref, w_y = pb_a.reference_vector(_reference()), pb_a.heating_weights(pb_a.w_y_full.copy(), heating=True)
    sw = MpcController(settings=MpcSettings(codegen=False, ocp=spec)).solver._stage_weights(w_y).T
    U, u_prev = _plan(pb_a, 190.0, 60.0), pb_a.scale_u(np.array([150.0, 190.0, 60.0, 50.0, 50.0, 50.0]))
    off = (0.0, np.zeros(pb_a.N))
    p_a, p_b = pb_a.model.p_default, pb_b.model.p_default
    priced_b = float(f_b(x0, U.T, d, sw, ref, u_prev, p_b, *off))
    assert float(f_a(x0, U.T, d, sw, ref, u_prev, p_b, *off)) == pytest.approx(priced_b, rel=1e-12)
    assert float(f_a(x0, U.T, d, sw, ref, u_prev, p_a, *off)) != pytest.approx(priced_b, rel=1e-3)
    assert pb_b.parameter_rows(p_b) == (pb_b.heater_row_bound, pb_b.ptc_row_coef_u, pb_b.ptc_row_bound,
                                        pb_b.body_heat_coef)
    # the closed forms the problem held before the rows came from the parameters, to the bit
    ih, xh = pb_b.i_heater_cmd, pb_b.x_off[pb_b.i_heater]
    slope_w_per_k = other.heater_power_max_w / (other.ptc_zero_c - other.ptc_knee_c)
    price_per_j = 2.0 * pb_b.energy_weight * spec.weights.body_heat_power_w / pb_b.energy_scale_w ** 2
    assert pb_b.heater_row_bound == float(other.heater_temp_max_c - xh)
    assert pb_b.ptc_row_coef_u == float(pb_b.u_sc[ih] / slope_w_per_k)
    assert pb_b.ptc_row_bound == float(other.ptc_zero_c - pb_b.u_off[ih] / slope_w_per_k - xh)
    assert pb_b.body_heat_coef == pytest.approx(
        -price_per_j * other.heater_mass_kg * other.heater_c_j_per_kgk * pb_b.x_sc[pb_b.i_heater], rel=1e-12)


def test_a_second_merit_of_the_same_structure_shares_the_first_ones_functions_and_prices_alike(controller):
    """The mapped merits are kept by structure (plan_merit._mapped, codegen.kept): a second PlanMerit of the same problem takes
    the first one's functions (the same objects, not built again), a merit of another horizon builds its own, and
    the kept function prices plans to the bit as one built afresh without the memo."""
    from hvac_mpc.mpc import plan_merit
    from hvac_mpc.mpc.casadi_eval import BufferedFunction

    pb, first = controller.problem, controller.solver._merit
    second = PlanMerit(pb, first.fractions)
    assert second._pair.fn is first._pair.fn and second._damped.fn is first._damped.fn
    from hvac_mpc.mpc.ocp import OcpSpec, TrackingProblem

    longer = OcpSpec(stage_durations_s=(*OcpSpec().stage_durations_s, 5.0))  # one stage more
    other = PlanMerit(TrackingProblem(Parameters(), longer), first.fractions)
    assert other._pair.fn is not first._pair.fn and other._pair.fn.size_in(1) != first._pair.fn.size_in(1)
    afresh = BufferedFunction(plan_merit._mapped_afresh(first.cost_function(), 2, "fresh"))
    x0, d = pb.scale_x(pb.placeholder_state()), np.array([5.0, 5.0, 0.3, 0.0])
    sw = controller.solver._stage_weights(pb.heating_weights(pb.w_y_full.copy(), heating=True))
    args = (x0, np.concatenate([_plan(pb, 100.0, 30.0), _plan(pb, 160.0, 60.0)]), d, sw,
            pb.reference_vector(_reference()), pb.scale_u(np.array([120.0, 80.0, 20.0, 50.0, 50.0, 50.0])),
            pb.model.p_default, 0.0, np.zeros(pb.N))
    kept = np.asarray(second._pair(*args)[0]).ravel()
    assert np.array_equal(kept, np.asarray(afresh(*args)[0]).ravel()) and kept[0] != kept[1]


def test_other_move_weights_share_the_merits_functions_and_price_with_their_own(controller):
    """The move weights are an input of the mapped merits, filled once (``TrackingProblem.w_du``): a problem with
    three times the valve move weight (tests/test_small_code.py's second controller) takes the default structure's
    functions (one build, one code cache key), and prices plans to the bit as its own merit with the weights as
    constants does (the form before), not as the default's."""
    import dataclasses

    from hvac_mpc.mpc import codegen, plan_merit
    from hvac_mpc.mpc.casadi_eval import BufferedFunction
    from hvac_mpc.mpc.ocp import TrackingProblem

    pb, first = controller.problem, controller.solver._merit
    weights = dataclasses.replace(pb.spec.weights, move_valve_per_pct2=3 * pb.spec.weights.move_valve_per_pct2)
    moved = TrackingProblem(Parameters(), dataclasses.replace(pb.spec, weights=weights))
    other = PlanMerit(moved, first.fractions)
    assert other._pair.fn is first._pair.fn and other._damped.fn is first._damped.fn
    assert codegen.structure_key(other._pair.fn) == codegen.structure_key(first._pair.fn)
    U = _plan(pb, 100.0, 30.0)
    U[3:] = _plan(pb, 160.0, 60.0)[3:]  # valve a moves within the horizon: the move weights count
    sw = controller.solver._stage_weights(pb.heating_weights(pb.w_y_full.copy(), heating=True))
    args = (pb.scale_x(pb.placeholder_state()), np.concatenate([U, _plan(pb, 160.0, 60.0)]),
            np.array([5.0, 5.0, 0.3, 0.0]), sw, pb.reference_vector(_reference()),
            pb.scale_u(np.array([120.0, 80.0, 20.0, 50.0, 50.0, 50.0])), pb.model.p_default, 0.0, np.zeros(pb.N))
    for merit, problem in ((other, moved), (first, pb)):
        constants = BufferedFunction(plan_merit._mapped_afresh(PlanMerit.cost_function(merit), 2, "constants"))
        assert np.array_equal(merit._pair(*args)[0], constants(*args)[0]), problem.w_du
    priced = [np.asarray(merit._pair(*args)[0]).ravel() for merit in (other, first)]
    assert priced[0][0] > priced[1][0]  # the plan that moves valve a costs more with its move weight tripled
