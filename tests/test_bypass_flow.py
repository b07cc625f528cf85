"""The bypass split's dependence on the total flow (docs/robustness.md sec. 1): the MPC predicts with
the thesis model's none by default, and the estimator can learn its size from flow changes. The truth
is the independent box (``hvac_mpc.mismatch``) with and without a flow-dependent split of its own.

Budget: the fast tests about 1 s together; the closed loops are marked slow.
"""

import numpy as np
import pytest

from ekf_helpers import feed_open_loop
from hvac_mpc.benchmarks import bench, mismatch_suite, scenarios as S
from hvac_mpc.contract import Command
from hvac_mpc.mismatch import Variant, make_plant
from hvac_mpc.models import HvacModel, Parameters
from hvac_mpc.mpc.estimator import DisturbanceEkf, EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings

#: Blower powers held HOLD_S each (valve a 50 %, outlets open, inlet 32 C, chiller 5 C): flow steps.
BLOWER_STEPS_W = (120.0, 280.0, 80.0, 220.0, 140.0, 300.0)
HOLD_S = 30


def learn_on_box(exponent: float, prior: float, seed: int = 3, anchored: bool = False, after_s: float = 0.0,
                 exponent_max: float = 3.0, at_rest: bool = False) -> np.ndarray:
    """The estimator fed open loop by the independent box whose split has ``exponent``; per sample the
    learned exponent (``anchored``, ``after_s``, ``exponent_max``, ``at_rest``: the EkfSettings fields
    bypass_flow_anchored, bypass_flow_after_s, bypass_flow_exponent_max, bypass_flow_at_rest)."""
    plant = make_plant(Variant(bypass_flow_exponent=exponent), seed=seed)
    plant.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
    commands = [Command(b, 0.0, 50.0, 100.0, 100.0, 100.0) for b in BLOWER_STEPS_W]
    plant.settle(commands[0])
    settings = EkfSettings(learn_bypass_flow=True, bypass_flow_exponent_prior=prior, bypass_flow_anchored=anchored,
                           bypass_flow_after_s=after_s, bypass_flow_exponent_max=exponent_max,
                           bypass_flow_at_rest=at_rest)
    settings.validate()  # the settings an MpcSettings would accept
    ekf = DisturbanceEkf(HvacModel(Parameters(), ("bypass_flow",)), settings)
    learned = []
    feed_open_loop(ekf, plant, commands, HOLD_S, lambda e: learned.append(e.bypass_flow_exponent))
    return np.array(learned)


@pytest.mark.parametrize("truth", [0.0, 0.4])
def test_learned_exponent_converges_to_the_box_from_the_middle_of_the_range(truth):
    learned = learn_on_box(truth, prior=0.2)
    # at a steady flow nothing is learned (the mixed-air offset takes the level) ...
    assert np.all(learned[:HOLD_S] == 0.2)
    # ... the flow steps tell the two apart: at the end of the last three holds it is the box's exponent
    ends = learned[[HOLD_S * (i + 1) - 1 for i in range(3, len(BLOWER_STEPS_W))]]
    assert np.all(np.abs(ends - truth) < 0.05)
    assert abs(learned[-1] - truth) < 0.5 * abs(0.2 - truth)


@pytest.mark.parametrize("truth, prior", [(0.0, 0.2), (0.4, 0.0)])
def test_anchored_exponent_learns_the_box_without_overshooting_it(truth, prior):
    """Anchored (the split's reference flow follows the flow, the mixed-air offset taking the level), the
    exponent is told only by a flow that differs from the recent one: on the first flow step it does not
    swing past the box's value (unanchored it went to 0.86 for a box's 0.4, to -0.28 for its 0), and it ends
    near the box's value."""
    learned = learn_on_box(truth, prior, anchored=True)
    lo, hi = min(truth, prior), max(truth, prior)
    assert lo - 0.1 <= learned.min() and learned.max() <= hi + 0.1
    assert abs(learned[-1] - truth) < 0.1
    assert np.abs(learn_on_box(truth, prior) - truth).max() > 0.25  # the unanchored swing the anchor removes


@pytest.mark.parametrize("truth, prior", [(0.0, 0.2), (0.4, 0.0)])
def test_exponent_fitted_at_rest_changes_only_once_a_flow_step_has_settled(truth, prior):
    """``bypass_flow_at_rest``: the filter keeps the exponent a constant; it changes only at the samples where a
    flow step has rested ``bypass_flow_settle_s`` (20 s, so in the last 10 s of each 30 s hold after the first),
    never within a transient, and the fit of the mixed-air offset's change across the steps moves it from the
    prior most of the way to the box's value (0.01 for a box's 0 from 0.2; 0.29 for a box's 0.4 from 0)."""
    learned = learn_on_box(truth, prior, anchored=True, at_rest=True)
    moved = np.flatnonzero(np.diff(learned)) + 1
    assert len(moved) >= 3 and np.all(moved % HOLD_S >= 20)  # once per settled step, at rest
    assert np.all(learned[:HOLD_S] == prior)
    assert abs(learned[-1] - truth) < 0.35 * abs(prior - truth)
    lo, hi = min(truth, prior), max(truth, prior)
    assert lo - 0.05 <= learned.min() and learned.max() <= hi + 0.05


def test_a_flow_step_with_valve_a_moved_as_well_tells_nothing_about_the_exponent():
    """The offset's change across a step that also moved valve a (a temperature step with the flow, as in the
    proband sequence) holds the model's valve and cooler errors as well: with ``bypass_flow_rest_valve_pct`` 5
    such a step is left out of the fit and the exponent stays at the prior; with the steps' valve moves allowed
    it moves (on the box's own 0.4 split)."""
    def learned(valve_pct: float) -> float:
        plant = make_plant(Variant(bypass_flow_exponent=0.4), seed=3)
        plant.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
        commands = [Command(b, 0.0, a, 100.0, 100.0, 100.0)
                    for b, a in zip(BLOWER_STEPS_W, (50.0, 70.0, 40.0, 60.0, 30.0, 80.0))]
        plant.settle(commands[0])
        ekf = DisturbanceEkf(HvacModel(Parameters(), ("bypass_flow",)), EkfSettings(
            learn_bypass_flow=True, bypass_flow_anchored=True, bypass_flow_at_rest=True,
            bypass_flow_rest_valve_pct=valve_pct))
        feed_open_loop(ekf, plant, commands, HOLD_S, lambda e: None)
        return ekf.bypass_flow_exponent

    assert learned(5.0) == 0.0
    assert learned(100.0) > 0.1


def test_settled_flow_steps_are_reported_once_per_step_and_not_for_a_return_within_the_gate():
    """The rest before and after a flow step, once the new flow has rested ``settle_s``; the slow end of a
    flow's response does not break a rest, and a flow back within the gate of the last rest is no step."""
    from hvac_mpc.mpc.flow_term import FlowStepFit, SettledFlowSteps
    steps = SettledFlowSteps(settle_s=5.0, gate=0.05)
    flows = [0.0] * 8 + [0.3 + 0.002 * k for k in range(8)] + [0.31] * 3 + [0.33] * 8
    offsets = [1.0] * 8 + [2.0] * 19
    found = [(k, r) for k, (f, o) in enumerate(zip(flows, offsets)) if (r := steps.observe(f, o)) is not None]
    assert [k for k, _ in found] == [13]
    before, after = found[0][1]
    assert before.log_flow == 0.0 and before.offset_c == 1.0 and after.offset_c == pytest.approx(2.0)
    assert steps.observe(0.33, 2.0, eligible=False) is None
    fit = FlowStepFit(prior=0.1, prior_sd=0.1, noise_c=0.1, lo=-3.0, hi=0.9)
    assert fit.estimate() == 0.1
    fit.add(2.0, 2.0)  # y = S k with k = 1: the estimate between the prior and 1, weighted 1 : 4
    assert fit.estimate() == pytest.approx((0.1 + 4.0) / 5.0)
    fit.add(20.0, 20.0)
    assert fit.estimate() == 0.9  # held within its range


def test_anchored_exponent_moves_the_prediction_only_away_from_the_recent_flow():
    """At the flow in force the anchored exponent does not move the model's supply air (so learning it
    cannot step the prediction), at another flow it does; the anchor follows the flow and the mixed-air
    offset takes the change, so the supply air the filter explains stays put."""
    ekf = DisturbanceEkf(HvacModel(Parameters(), ("bypass_flow",)),
                         EkfSettings(learn_bypass_flow=True, bypass_flow_anchored=True))
    box = make_plant("nominal", seed=0)
    box.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
    u = Command(150.0, 0.0, 50.0, 100.0, 100.0, 100.0).vector()
    box.settle(Command(150.0, 0.0, 50.0, 100.0, 100.0, 100.0))
    ekf.initialise(box.read(), u, 5.0)

    def air(z, command):
        return float(ekf.mix_fn(z, command, 5.0, ekf.p)[0])

    z = ekf.z.copy()
    z[ekf.i_exponent] = 0.8
    assert air(z, u) == pytest.approx(air(ekf.z, u), abs=1e-9)
    more_flow = u.copy()
    more_flow[0] = 300.0
    assert abs(air(z, more_flow) - air(ekf.z, more_flow)) > 0.1
    # the anchor moved towards a new flow: the offset takes the model's change, the supply air stays
    ekf.z[ekf.i_exponent] = 0.8
    anchor, before = ekf.z[ekf.i_anchor], air(ekf.z, more_flow)
    ekf._move_anchor(more_flow, 5.0)
    assert ekf.z[ekf.i_anchor] > anchor + 0.01
    assert air(ekf.z, more_flow) == pytest.approx(before, abs=1e-9)


def test_the_exponent_is_learned_only_after_the_start_up_and_within_its_range():
    """``bypass_flow_after_s``: no learning before that long since the start (the filter's own start-up);
    ``bypass_flow_exponent_min``/``_max``: the estimate held in its range (the box's 0.4 above a cap of 0.3)."""
    late = learn_on_box(0.4, 0.0, anchored=True, after_s=HOLD_S * len(BLOWER_STEPS_W))
    assert np.all(late == 0.0)
    capped = learn_on_box(0.4, 0.0, anchored=True, exponent_max=0.3)
    assert capped.max() == pytest.approx(0.3) and 0.25 < capped[-1] <= 0.3
    with pytest.raises(InvalidSettings, match="ekf.bypass_flow_exponent_prior must lie within"):
        EkfSettings(bypass_flow_exponent_min=0.5).validate()


@pytest.mark.parametrize("fields, message", [
    ({"bypass_flow_exponent_min": 1.0, "bypass_flow_exponent_max": 0.5},
     r"ekf.bypass_flow_exponent_min must be less than .*ekf.bypass_flow_exponent_max; got 1.0 and 0.5"),
    ({"bypass_flow_exponent_min": 0.5, "bypass_flow_exponent_max": 0.5}, r"must be less than"),
    ({"learn_bypass_flow": True, "bypass_flow_after_s": 3601.0},
     r"ekf.bypass_flow_after_s = 3601.0 is outside the allowed range \[0.0, 3600.0\]"),
    ({"learn_bypass_flow": True, "bypass_flow_after_s": -1.0}, r"ekf.bypass_flow_after_s = -1.0 is outside"),
    ({"motor_sd_after_response_c": 11.0}, r"ekf.motor_sd_after_response_c = 11.0 is outside the allowed range "
                                          r"\[0.0, 10.0\]"),
    ({"bypass_flow_anchored": True}, r"ekf.bypass_flow_anchored = True shapes the learning .* needs "
                                     r".*ekf.learn_bypass_flow = True"),
    ({"bypass_flow_after_response": True}, r"ekf.bypass_flow_after_response = True .*ekf.learn_bypass_flow"),
    ({"bypass_flow_after_s": 30.0}, r"ekf.bypass_flow_after_s = 30.0 .*ekf.learn_bypass_flow"),
    ({"bypass_flow_commit_at_rest": True}, r"ekf.bypass_flow_commit_at_rest = True .*ekf.learn_bypass_flow"),
    ({"bypass_flow_at_rest": True}, r"ekf.bypass_flow_at_rest = True shapes the learning .*ekf.learn_bypass_flow"),
    ({"learn_bypass_flow": True, "bypass_flow_at_rest": True},
     r"ekf.bypass_flow_at_rest = True needs .*ekf.bypass_flow_anchored = True"),
    ({"learn_bypass_flow": True, "bypass_flow_anchored": True, "bypass_flow_settle_s": 0.5},
     r"ekf.bypass_flow_settle_s = 0.5 is outside the allowed range \[1.0, 3600.0\]"),
    ({"q_mix_offset_unseen_c": -0.01}, r"ekf.q_mix_offset_unseen_c = -0.01 is outside"),
    ({"bypass_flow_rest_valve_pct": 0.0}, r"ekf.bypass_flow_rest_valve_pct = 0.0 is outside"),
])
def test_bad_bypass_flow_settings_are_refused_naming_the_fields(fields, message):
    """Each bound its own range (the start-up gate up to an hour, the motor deviation up to the largest motor rise),
    the exponent's range before the prior within it, and the learning's gates only with the learning; an
    MpcSettings with them is refused and the defaults stand."""
    with pytest.raises(InvalidSettings, match=message):
        EkfSettings(**fields).validate()
    with pytest.raises(InvalidSettings, match=message):
        MpcSettings(ekf=EkfSettings(**fields))
    EkfSettings(motor_sd_after_response_c=10.0).validate()  # the motor deviation acts without the learning
    EkfSettings(learn_bypass_flow=True, bypass_flow_anchored=True, bypass_flow_after_s=3600.0).validate()


def test_reset_forgets_the_last_runs_learned_exponent():
    """After :meth:`DisturbanceEkf.reset` the parameters handed to the prediction are those of a filter never run
    (the prior exponent), not the value the last run committed, and its start-up gate counts from 0 again."""
    plant = make_plant(Variant(bypass_flow_exponent=0.4), seed=3)
    plant.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
    commands = [Command(b, 0.0, 50.0, 100.0, 100.0, 100.0) for b in BLOWER_STEPS_W]
    plant.settle(commands[0])
    settings = EkfSettings(learn_bypass_flow=True, bypass_flow_anchored=True, bypass_flow_commit_at_rest=True,
                           motor_sd_after_response_c=0.5)
    ekf = DisturbanceEkf(HvacModel(Parameters(), ("bypass_flow",)), settings)
    fresh = ekf.model_parameters()
    feed_open_loop(ekf, plant, commands, HOLD_S, lambda e: None)
    i = ekf.i_exponent_p
    assert abs(ekf.model_parameters()[i] - 0.4) < 0.1 and ekf._age_s > 0.0 and ekf._motor_released
    ekf.reset()
    assert np.array_equal(ekf.model_parameters(), fresh) and fresh[i] == 0.0
    assert ekf._age_s == 0.0 and not ekf._motor_released and not ekf.learning


def test_the_trapped_air_guard_takes_the_heater_body_rate_with_the_learned_parameters():
    """With a ``heater_body`` term the guard's bound follows the body balance of the model the QP predicts with:
    the learned exponent and anchor (DisturbanceEkf.model_parameters), not the parameters the problem was built
    with."""
    from hvac_mpc.contract import Measurement
    from hvac_mpc.models.discovered import DiscoveredTerm
    from hvac_mpc.models.model_file import RefinedModel

    term = DiscoveredTerm("wall", "heater_body", ("body_minus_inlet", "one"), (-0.28, 0.14))
    ekf = EkfSettings(learn_bypass_flow=True, bypass_flow_anchored=True, bypass_flow_exponent_prior=0.2)
    ctrl = MpcController(settings=MpcSettings(codegen=False, ekf=ekf,
                                              initial_command=Command(200.0, 0.0, 50.0, 100.0, 100.0, 100.0)),
                         model=RefinedModel(Parameters(), ("bypass_flow",), terms=(term,)))
    e, m = ctrl.ekf, ctrl.problem.model
    e.initialise(Measurement(0.0, 12.0, 0.03, 10.0, water_temp_c=5.0), ctrl.u_prev, 5.0)
    e.z[e.i_exponent], e.z[e.i_anchor] = 1.5, np.log(0.01)  # far from what the problem was built with
    x = np.array(e.x, float)
    x[m.states.index("heater_temp_c")] = 40.0

    def body_rate(p):
        return float(m.ode(x, ctrl.u_prev, ctrl._disturbance(5.0), p)[m.states.index("heater_temp_c")])

    guard = ctrl._body_rate_at(e.x)(40.0)
    assert guard == pytest.approx(body_rate(e.model_parameters()), abs=1e-12)
    assert abs(guard - body_rate(m.p_default)) > 0.05


def test_the_prediction_takes_a_learned_exponent_only_once_its_flow_change_is_over():
    """``bypass_flow_commit_at_rest``: while the flow moves the filter learns the exponent, but the parameters
    it hands the prediction keep the value from before the change; once the flow has settled (the gate shut)
    they take the learned value, so no transient is met with a half-learned exponent."""
    plant = make_plant(Variant(bypass_flow_exponent=0.4), seed=3)
    plant.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
    commands = [Command(b, 0.0, 50.0, 100.0, 100.0, 100.0) for b in BLOWER_STEPS_W]
    plant.settle(commands[0])
    ekf = DisturbanceEkf(HvacModel(Parameters(), ("bypass_flow",)),
                         EkfSettings(learn_bypass_flow=True, bypass_flow_anchored=True, bypass_flow_commit_at_rest=True))
    i = ekf.i_exponent_p
    rows = []
    feed_open_loop(ekf, plant, commands, HOLD_S,
                   lambda e: rows.append((e.bypass_flow_exponent, e.model_parameters()[i], e.learning)))
    learned, used, moving = (np.array(c) for c in zip(*rows))
    assert moving.any() and not moving.all() and not moving[0]
    during = np.flatnonzero(moving)
    assert np.all(used[during] == used[during - 1])  # held while the flow moves ...
    assert np.abs(learned[during] - used[during]).max() > 0.1  # ... while the filter learns
    at_rest = ~moving
    assert np.allclose(used[at_rest], learned[at_rest])
    assert abs(used[-1] - 0.4) < 0.1  # the box's value, once the steps are over


def test_the_box_split_depends_on_the_flow_only_with_the_exponent():
    low, high = Command(80.0, 0.0, 50.0, 100.0, 100.0, 100.0), Command(300.0, 0.0, 50.0, 100.0, 100.0, 100.0)
    share = {}
    for exponent in (0.0, 0.4):
        box = make_plant(Variant(bypass_flow_exponent=exponent), seed=0)
        share[exponent] = []
        for command in (low, high):
            box.settle(command)
            share[exponent].append(box.truth()["bypass_fraction"])
    assert share[0.0][0] == pytest.approx(share[0.0][1])
    assert share[0.4][0] < share[0.0][0] < share[0.4][1]  # below the reference flow less, above more


def test_the_prediction_uses_the_thesis_model_exponent_unless_told():
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    assert not ctrl.ekf.learns_bypass_flow and ctrl.ekf.bypass_flow_exponent == 0.0
    i = ctrl.problem.model.param_names.index("bypass_flow_exponent")
    # the problem every solver is built from carries the same exponent (the reference solvers take no
    # runtime parameters), not the simulated plant's assumed 0.4
    assert ctrl.problem.model.p_default[i] == 0.0 != Parameters().bypass_flow_exponent
    told = MpcController(settings=MpcSettings(codegen=False, ekf=EkfSettings(bypass_flow_exponent_prior=0.4)))
    assert told.ekf.bypass_flow_exponent == 0.4
    ref = {"supply_temp_c": 18.0, "volume_flow_m3s": 0.025}
    box = make_plant("nominal", seed=0)
    for c in (ctrl, told):
        res = c.step(box.read(), ref)
        assert res.stats["bypass_flow_exponent"] == c.ekf.bypass_flow_exponent
        assert c.solver._p[i] == c.ekf.bypass_flow_exponent and c.reach._p[i] == c.ekf.bypass_flow_exponent
    with pytest.raises(InvalidSettings, match="ekf.bypass_flow_exponent_prior"):
        MpcSettings(ekf=EkfSettings(bypass_flow_exponent_prior=5.0))


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["nominal", "cooler_literal"])
def test_flow_jump_out_of_reach_keeps_the_temperature_as_well_as_the_baseline(variant):
    """The quick out-of-reach scenario (90 -> 200 m3/h at 18 C, 32 C inlet) on the independent box: the
    MPC no longer opens valve a for a warming the box does not have (2.99 and 4.69 times the baseline's
    thermocouple IAE before)."""
    sc = S.flow_out_of_reach().quick()
    res, tr = bench.run_benchmark([sc], {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()}, 0,
                                  plant_factory=mismatch_suite.variant_factory(variant))
    cell = res["scenarios"][sc.name]
    assert cell["ratios"]["temp_iae_cs"] <= 1.0
    assert mismatch_suite.out_of_reach_steady(tr[sc.name]["mpc"], sc)["steady_temp_error_max_c"] <= 0.3
    assert cell["mpc"]["figures"]["fallbacks"] == 0 and cell["mpc"]["figures"]["violations_total"] == 0
