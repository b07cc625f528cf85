"""Heater readiness (mpc/readiness.py): the floor is the model's heater outlet balance solved for the body, it is out
of the cost outside the heating duty, the QP carries it only where the plan is below it, and on the independent box
with recirculation it keeps the body warm through the warm-up the refined MPC otherwise spends it in."""

import numpy as np
import pytest

from heater_body_helpers import body_at_step_and_iae
from hvac_mpc.models.discovered import DiscoveredTerm
from hvac_mpc.models.model_file import RefinedModel
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings, OcpSpec, Weights
from hvac_mpc.mpc.readiness import HeaterReadiness


def _settings(weight: float, lead_c: float | None = 3.0, **kwargs) -> MpcSettings:
    return MpcSettings(ocp=OcpSpec(weights=Weights(heater_ready_per_c2=weight), ready_lead_c=lead_c), **kwargs)


@pytest.fixture(scope="module")
def controller():
    """Without the bound on the floor above the body's estimate (the floor's own formula)."""
    return MpcController(settings=_settings(0.5, lead_c=None))


def test_floor_is_the_heater_outlet_balance_solved_for_the_body(controller):
    """At 40 m3/h, the air through the heater leaves a body at the floor at the reference plus ready_step_c:
    (kA T_floor + g T_core) / (kA + g) = r + 3 K, g the core's mass flow times c_p (valve a at its cap)."""
    pb = controller.problem
    ready = HeaterReadiness(pb)
    x = np.array([1.0, 5.0, 30.0, 9.0])
    u = np.array([60.0, 0.0, 0.0, 100.0, 100.0, 100.0])
    d = np.array([5.0, 5.0, 0.0, 0.0])
    flow = 40.0 / 3600.0
    floor = ready.floor_c(x, u, d, pb.model.p_default, 9.0, flow, 90.0)
    u_cap = u.copy()
    u_cap[2] = 90.0
    al = pb.model.algebraic(x, u_cap, d, pb.params)
    g = float((1.0 - al["bypass"]) * al["mass_flow"] / al["flow"]) * flow * pb.params.cp_air_j_per_kgk
    ka = pb.params.heater_ka_w_per_k
    outlet = (ka * floor + g * float(al["t_cooler"])) / (ka + g)
    assert outlet == pytest.approx(9.0 + 3.0, abs=1e-6)
    assert 30.0 < floor < pb.params.ptc_knee_c  # well above the body a warm-up at 9 C leaves (26 C, the module)


def test_floor_is_held_below_the_ptc_knee_and_off_outside_the_heating_duty_and_in_a_step_up(controller):
    pb = controller.problem
    ready = HeaterReadiness(pb)
    x = np.array([1.0, 5.0, 30.0, 9.0])
    u = np.array([60.0, 0.0, 0.0, 100.0, 100.0, 100.0])
    d = np.array([5.0, 5.0, 0.0, 0.0])
    assert ready.floor_c(x, u, d, pb.model.p_default, 20.0, 40.0 / 3600.0, 90.0) == pb.params.ptc_knee_c
    assert ready.floor_c(x, u, d, pb.model.p_default, 5.0, 40.0 / 3600.0, 90.0) is None  # not above the inlet
    assert ready.floor_c(x, u, d, pb.model.p_default, None, 40.0 / 3600.0, 90.0) is None
    # a step up is being served: the reading 1 K below the reference, out; 0.3 K below or above it, in; 1 K above
    # it (more heat than asked), out
    assert ready.floor_c(x, u, d, pb.model.p_default, 12.0, 40.0 / 3600.0, 90.0, supply_now_c=11.0) is None
    assert ready.floor_c(x, u, d, pb.model.p_default, 12.0, 40.0 / 3600.0, 90.0, supply_now_c=11.7) is not None
    assert ready.floor_c(x, u, d, pb.model.p_default, 12.0, 40.0 / 3600.0, 90.0, supply_now_c=12.3) is not None
    assert ready.floor_c(x, u, d, pb.model.p_default, 12.0, 40.0 / 3600.0, 90.0, supply_now_c=13.0) is None
    assert ready.scaled(None) is None


def test_floor_asks_at_most_the_lead_above_the_body_estimate():
    """ready_lead_c 3 K: a body estimated at 30 C gets the floor 33 C instead of the outlet balance's 44 C (9 C at
    40 m3/h); a body estimated at 50 C, above the balance's floor, the balance's floor."""
    pb = MpcController(settings=_settings(0.5)).problem
    bounded, free = HeaterReadiness(pb), HeaterReadiness(MpcController(settings=_settings(0.5, lead_c=None)).problem)
    u = np.array([60.0, 0.0, 0.0, 100.0, 100.0, 100.0])
    d = np.array([5.0, 5.0, 0.0, 0.0])
    args = (u, d, pb.model.p_default, 9.0, 40.0 / 3600.0, 90.0)
    cold, warm = np.array([1.0, 5.0, 30.0, 9.0]), np.array([1.0, 5.0, 50.0, 9.0])
    assert free.floor_c(cold, *args) > 40.0
    assert bounded.floor_c(cold, *args) == pytest.approx(33.0)
    assert bounded.floor_c(warm, *args) == pytest.approx(free.floor_c(warm, *args))
    assert free.floor_c(warm, *args) < 50.0


def test_the_qp_carries_the_penalty_only_where_the_plan_is_below_the_floor(controller):
    """_with_readiness: Hessian 2 w and gradient -2 w x_f on the body of the stages whose linearised body is below
    the floor, nothing elsewhere; the target off leaves P as it was."""
    pb, solver = controller.problem, controller.solver
    ready = HeaterReadiness(pb)
    target = ready.scaled(40.0)
    X = np.tile(pb.scale_x(np.array([1.0, 5.0, 45.0, 9.0])), (pb.N + 1, 1))
    X[1:6, pb.i_heater] = pb.scale_x(np.array([1.0, 5.0, 30.0, 9.0]))[pb.i_heater]  # stages 1..5 below 40 C
    Px = np.zeros(solver.P.nnz)
    solver.readiness_target = target
    try:
        out = solver._with_readiness(X, Px)
        w = target[1]
        assert np.allclose(out[solver._P_body_slots[:5]], 2.0 * w[:5])
        assert np.all(out[solver._P_body_slots[5:]] == 0.0) and out.sum() == pytest.approx(2.0 * w[:5].sum())
        assert np.allclose(solver._ready_q[:5], -2.0 * w[:5] * target[0]) and np.all(solver._ready_q[5:] == 0.0)
        solver.readiness_target = None
        assert solver._with_readiness(X, Px) is Px and solver._ready_q is None
    finally:
        solver.readiness_target = None


@pytest.mark.slow
def test_the_readiness_keeps_the_body_warm_through_the_warm_up_on_the_recirculating_box():
    """The independent box drawing 15 % of cabin air behind the inlet sensor, the MPC with the ``box_in`` term
    identification finds (-0.15 T_in + 3.6 C, thesis parameters otherwise), the quick winter_heating_steps: the
    warm-up holds 9 C with the air entering at about 9.05 C, and without the readiness the MPC cools through the
    core with the heater off, the body 33.1 -> 26.3 C at the step (measured), 146.5 C s. With the readiness (0.5
    per K^2 s) the body is warmer at the step and the IAE about half (measured 30.7 C, 78.9 C s). The warm-up's
    reading at 9 C is where the readiness pays: counted while the reading was up to any height above the
    reference, it held the reading above the band and the body at 43.2 C (37.3 C s); within the band on both
    sides, it may cost the warm-up's reference at most the band (docs/identification.md 'Heater readiness').
    Both runs without the search along the reversing input (``rti_reversal_search`` 0; on by default), the readiness
    alone measured: with the search the body at the step is 26.3 C without the readiness and 28.6 C with it (30.7
    without the search), 131.5 and 76.4 C s (138.5 and 75.2 without; docs/identification.md, "The guarded search as
    the default")."""
    term = DiscoveredTerm("recirculation", "box_in", ("inlet", "one"), (-0.15, 3.6))
    refined = RefinedModel(Parameters(), ("ptc_power_fall", "fan_curve", "valve_leakage"), (term,),
                           absent=("bypass_flow",))

    def run(weight):
        return body_at_step_and_iae("winter_heating_steps", "recirculation",
                                    _settings(weight, rti_reversal_search=0.0), refined)

    body_off, iae_off = run(0.0)
    body_on, iae_on = run(0.5)
    assert body_off < 28.0, body_off  # the warm-up spends the body's heat
    assert body_on > body_off + 3.0, (body_on, body_off)
    assert iae_on < 0.6 * iae_off, (iae_on, iae_off)


@pytest.mark.slow
def test_the_bounded_floor_tracks_the_wall_loss_box_better_than_the_unbounded_one():
    """The independent box whose heater body loses heat to the box walls (hvac_mpc.mismatch ``heater_wall_loss``,
    0.3 W/K), the MPC with the ``heater_body`` term identification finds (-0.28 W/K (T_body - T_in), the thesis
    parameters otherwise), the quick cabin warm-up: after the step up the heater runs at its limit and the
    unbounded floor is the PTC knee, 10 K above the body the MPC estimates right; it pulls valve a towards less air
    through the heater, the reading leaves the band and the term drops out, from second to second (measured 47.5
    C s, the readiness off 50.2 C s). Bounded at 3 K above the estimate the pull is the same whatever the distance
    (measured 38.3 C s; the MPC with the nominal model 40.4 unbounded, 37.3 bounded)."""
    term = DiscoveredTerm("heater_body_term", "heater_body", ("body_minus_inlet", "one"), (-0.28, 0.0))
    refined = RefinedModel(Parameters(), ("ptc_power_fall", "fan_curve", "valve_leakage"), (term,),
                           absent=("bypass_flow",))

    def iae(lead_c):
        return body_at_step_and_iae("cabin_warmup_winter", "heater_wall_loss", _settings(0.5, lead_c=lead_c),
                                    refined)[1]

    bounded, unbounded = iae(3.0), iae(None)
    assert bounded < 0.9 * unbounded, (bounded, unbounded)


@pytest.mark.parametrize("field, value", [("heater_ready_per_c2", -0.1), ("ready_step_c", 31.0),
                                          ("ready_step_c", float("nan")), ("ready_lead_c", 0.0),
                                          ("ready_lead_c", float("inf"))])
def test_readiness_settings_out_of_range_name_the_field(field, value):
    with pytest.raises(InvalidSettings, match=field):
        if field.startswith("ready_"):
            MpcSettings(ocp=OcpSpec(**{field: value}))
        else:
            MpcSettings(ocp=OcpSpec(weights=Weights(heater_ready_per_c2=value)))


def test_refined_comparison_changes_both_mpcs_settings_alike_and_names_unknown_fields():
    """refined_model.with_overrides (refined_variants --settings / --weights): the fields given are replaced, a
    list becomes a tuple, and a name that is not a field raises naming it."""
    from hvac_mpc.benchmarks.refined_model import with_overrides

    s = with_overrides(MpcSettings(), {"rti_step_fractions": [0.5, 0.25]}, {"heater_ready_per_c2": 0.5})
    assert s.rti_step_fractions == (0.5, 0.25) and s.ocp.weights.heater_ready_per_c2 == 0.5
    assert s.ocp.weights.supply_temp == Weights().supply_temp
    with pytest.raises(ValueError, match="heater_ready"):
        with_overrides(MpcSettings(), None, {"heater_ready": 0.5})
    with pytest.raises(ValueError, match="step_fraction"):
        with_overrides(MpcSettings(), {"step_fraction": 0.5})
