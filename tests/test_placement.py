"""Where the heater outlet reading's error goes, chosen online (``MpcSettings.choose_offset_placement``,
:mod:`hvac_mpc.mpc.placement`; docs/robustness.md sec. 2.14).

Truth for the closed loop is the independent box (``hvac_mpc.mismatch``): a box outside the registry with a 4.5 s
dead time and the literal cooler fit (the core leaves winter air at about 10 C whatever the inlet: the error is the
core's, the heater air's offset carries it), and the built-in plant with its perturbed heater transfer coefficient
(the error is the heater's, the reading's own offset keeps it out of the prediction). Budget: the rule's own tests
take milliseconds; the closed loop three quick runs of the MPC (about 15 s).
"""

import dataclasses
import functools
import math

import numpy as np
import pytest

from ekf_helpers import feed_open_loop
from hvac_mpc.benchmarks import bench, mismatch_suite, plant_seam, scenarios
from hvac_mpc.benchmarks.perturbation import perturb_parameters
from hvac_mpc.benchmarks.simulate import plant_seed, simulate
from hvac_mpc.mismatch import make_plant
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.models.plant import PLANT_EFFECTS, SimulatedPlant
from hvac_mpc.contract import Command
from hvac_mpc.models import HvacModel
from hvac_mpc.mpc.estimator import MEASURED, DisturbanceEkf, EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc import placement
from hvac_mpc.mpc.placement import PLACEMENTS, PlacementChoice

LITERAL_COOLER_BOX = "B:transport_delay_s=4.5,cooler_literal_fit=true"


def choice(**kw) -> PlacementChoice:
    args = dict(window_s=10.0, ratio=0.6, evidence=1.5, dt_s=1.0, cap=50.0)
    return PlacementChoice(**{**args, **kw})


def test_the_filter_in_use_gives_way_only_to_a_clearly_better_one_and_back_alike():
    """A filter whose innovations are consistent (normalised squares about 1) is kept whatever the other does; one
    surprised 4 times as much gives way once its sum passes the evidence floor; the same rule takes it back."""
    c = choice()
    for _ in range(50):
        c.observe(0, 1.0)
        c.observe(1, 0.1)
        assert not c.decide()  # the one in use is consistent: nothing to choose
    switched_at = None
    for t in range(50):
        c.observe(0, 4.0)
        c.observe(1, 1.0)
        if c.decide():
            switched_at = t
            break
    assert switched_at is not None and c.active == 1
    for _ in range(50):  # both alike: no switch back (hysteresis)
        c.observe(0, 3.0)
        c.observe(1, 3.0)
        assert not c.decide()
    for _ in range(100):
        c.observe(0, 1.0)
        c.observe(1, 5.0)
        if c.decide():
            break
    assert c.active == 0


def test_one_outlier_counts_at_most_the_cap_and_a_missing_reading_nothing():
    c = choice(cap=5.0)
    c.observe(0, 1e6)
    c.observe(1, math.nan)
    assert c.sums == [5.0, 0.0]
    c.reset()
    assert c.sums == [0.0, 0.0] and c.active == 0


@pytest.mark.parametrize("field, bad", [("placement_window_s", 0.0), ("placement_ratio", 1.5),
                                        ("placement_ratio", 0.0), ("placement_cap", 0.0),
                                        ("placement_evidence", -1.0), ("placement_q_heater_air_c", 0.0),
                                        ("choose_offset_placement", "yes"), ("placement_margin", 0.0),
                                        ("placement_margin", -math.inf), ("placement_margin", math.nan),
                                        ("placement_from_response", 1)])
def test_placement_settings_are_checked(field, bad):
    with pytest.raises(InvalidSettings, match=field):
        MpcSettings(**{field: bad})


def test_settings_that_place_the_error_themselves_run_one_filter():
    """An offset of the core path's air set in ``ekf`` is the user's placement: no second filter."""
    own = MpcSettings(choose_offset_placement=True,
                      ekf=EkfSettings(q_heater_air_offset_c=0.01, q_heater_outlet_offset_c=0.0))
    ctrl = MpcController(settings=own)
    assert ctrl.placement is None and len(ctrl._filters) == 1 and ctrl.offset_placement == "heater_outlet"


def valve_steps_nis(plant, settings: EkfSettings) -> np.ndarray:
    """Open loop in winter (inlet 0 C, heater 150 W, valve a 20 -> 80 -> 20 % held 60 s each): the filter's
    normalised squared supply innovation per sample, each capped at 50 as the choice caps it."""
    plant.set_environment(inlet_temp_c=0.0, chiller_setpoint_c=5.0)
    commands = [Command(150.0, 150.0, a, 100.0, 100.0, 100.0) for a in (20.0, 80.0, 20.0)]
    plant.settle(commands[0])
    ekf = DisturbanceEkf(HvacModel(Parameters()), settings)
    nis = []
    feed_open_loop(ekf, plant, commands, 60, lambda e: nis.append(e.supply_nis))
    return np.minimum(np.array(nis), 50.0)


HEATER_AIR = EkfSettings(q_heater_air_offset_c=0.01, q_heater_outlet_offset_c=0.0, response_wait_c=0.0)
#: The reading's own offset, the response wait off (each sample's innovation counted, none left out).
OWN = EkfSettings(response_wait_c=0.0)


def test_the_valve_steps_surprise_the_filter_whose_placement_is_wrong():
    """The premise of the choice (ASSUMPTION of mpc/placement.py), open loop across two valve a steps: on the
    literal-cooler box (the core's error) the reading's own offset leaves valve a's gain the model's and the supply
    innovations after the steps sum to 991 against the heater air's 90 (measured); on the built-in plant (its heater
    transfer coefficient perturbed: the heater's error) the heater air's offset is the worse, 76 against 60."""
    literal = [float(np.sum(valve_steps_nis(make_plant("cooler_literal", seed=3), s)[60:]))
               for s in (OWN, HEATER_AIR)]
    plant_params, _ = perturb_parameters(Parameters(), 0)
    built_in = [float(np.sum(valve_steps_nis(SimulatedPlant(plant_params, effects=PLANT_EFFECTS, seed=3), s)[60:]))
                for s in (OWN, HEATER_AIR)]
    assert literal[0] > 5.0 * literal[1]
    assert built_in[0] < built_in[1] < 0.2 * literal[0]


def test_a_dropped_reading_and_a_reset_leave_the_innovation_undefined():
    plant = make_plant("nominal", seed=3)
    ekf = DisturbanceEkf(HvacModel(Parameters()), EkfSettings())
    u = Command(150.0, 0.0, 50.0, 100.0, 100.0, 100.0).vector()
    ekf.initialise(plant.read(), u, 5.0)
    ekf.predict(u, 5.0)
    ekf.update(dataclasses.replace(plant.read(), supply_temp_c=math.nan), u, 5.0)
    assert math.isnan(ekf.supply_nis) and math.isnan(ekf.supply_innovation_c)
    ekf.update(plant.read(), u, 5.0)
    assert math.isfinite(ekf.supply_nis) and ekf.supply_nis >= 0.0
    # an update without any reading and a reset leave no innovation to count again
    nothing = dataclasses.replace(plant.read(), **{n: math.nan for n in MEASURED})
    assert ekf.update(nothing, u, 5.0) == 0 and math.isnan(ekf.supply_nis) and math.isnan(ekf.supply_innovation_c)
    ekf.update(plant.read(), u, 5.0)
    ekf.reset()
    assert math.isnan(ekf.supply_nis)


def closed_loop(choose: bool, plant_factory, scenario, seed: int = 0, plant_params=None, between=False):
    """The MPC on ``scenario``; its thermocouple IAE (degC s) over the scored part, commands and placements."""
    settings = MpcSettings(initial_command=scenario.initial_command, deadline_s=bench.DETERMINISTIC_DEADLINE_S,
                           choose_offset_placement=choose)
    ctrl = MpcController(Parameters(), settings)
    placements = []
    step = ctrl.step

    def watched(measurement, reference):
        out = step(measurement, reference)
        placements.append(out.stats["offset_placement"])
        if between:  # the idle part of a sample, as the timing loop gives it
            ctrl.wait_background(0.0)
        return out

    ctrl.step = watched
    plant = plant_seam.build_plant(plant_factory, plant_seed(seed, scenario.seed), 1.0) if plant_factory else None
    tr = simulate(scenario, ctrl, plant_params or Parameters(), seed, name="mpc", dt_s=1.0, plant=plant)
    scored = tr.time_s >= tr.metrics_start_s
    iae = float(np.sum(np.abs(tr.truth["supply_temp_c"] - tr.reference["supply_temp_c"])[scored]))
    return iae, tr.applied, placements


def test_on_a_box_whose_core_is_not_the_model_the_heater_air_is_chosen_and_the_loop_rings_less():
    """Quick winter heating steps on the literal-cooler box with a 4.5 s dead time (seed 0). With the reading's own
    offset alone the MPC's IAE is 1.21 of the baseline's (valve a's gain in the prediction a fraction of the box's);
    with the choice the heater air's filter takes over within the first 90 s (at 80 s, measured) and the IAE falls
    to 0.65 of the baseline's (measured 95.2 -> 50.9 degC s)."""
    _, variant = mismatch_suite.parse_box(LITERAL_COOLER_BOX)
    factory = functools.partial(make_plant, variant)
    sc = scenarios.mismatch_scenarios()["winter_heating_steps"].quick()
    plain_iae, _, plain_placements = closed_loop(False, factory, sc)
    iae, _, placements = closed_loop(True, factory, sc, between=True)
    assert set(plain_placements) == {PLACEMENTS[0]}
    assert placements[0] == PLACEMENTS[0] and PLACEMENTS[1] in placements[:90]
    assert iae < 0.7 * plain_iae


def test_on_the_built_in_plant_the_reading_keeps_its_own_offset_and_the_commands_are_the_plain_filters():
    """The quick winter warm-up on the built-in plant (seed 0), whose heater outlet error is its perturbed heater
    transfer coefficient: the heater air's filter is never chosen, so the commands are those without the choice to
    the bit (the filter not in use is run beside, never fed back)."""
    sc = next(s for s in scenarios.select(None, quick=True) if s.name == "cabin_warmup_winter")
    plant_params, _ = perturb_parameters(Parameters(), 0)
    _, plain, _ = closed_loop(False, None, sc, plant_params=plant_params)
    _, chosen, placements = closed_loop(True, None, sc, plant_params=plant_params)
    assert set(placements) == {PLACEMENTS[0]}
    np.testing.assert_array_equal(chosen, plain)


@pytest.mark.parametrize("where", ["before", "after"])
def test_a_switch_followed_by_a_failure_takes_the_new_filters_time_update_once(monkeypatch, where):
    """A step that switches filters and then fails answers with a fallback and takes the time update of the filter
    now in use exactly once: the recovery takes it where the step failed before it ("before": in the QP's
    preparation in the feedback, the QP prepared afresh after a switch), not again where the step failed after it
    ("after": the fused prediction done, then a failure). The recovery's count follows the switch; the two
    filters' counts are made to differ so that it cannot hold by coincidence."""
    from test_mpc import PARAMS, REF_WARM, START
    from test_mpc import closed_loop as run

    plant = SimulatedPlant(PARAMS, seed=6)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START, placement_warm_switch=False))  # a cold switch
    run(ctrl, plant, [REF_WARM] * 5)
    ctrl.placement.sums[:] = [1e6, 0.0]  # the rule switches at the next step

    def broken(*args, **kwargs):
        raise RuntimeError("preparation broke")

    if where == "before":
        monkeypatch.setattr(ctrl.solver, "prepare", broken)
    else:
        original = ctrl.solver.prepare_predicted

        def then_broken(*args, **kwargs):
            original(*args, **kwargs)
            raise RuntimeError("preparation broke")

        monkeypatch.setattr(ctrl.solver, "prepare_predicted", then_broken)
    air = ctrl._filters[1]
    air.time_updates += 100  # a count of its own
    before = air.time_updates  # one more comes from bringing it up to this sample, before the switch
    rows = run(ctrl, plant, [REF_WARM])
    assert "preparation broke" in rows[0]["stats"]["status"] and ctrl.ekf is air
    assert air.time_updates == before + 2


def test_a_recovery_restarts_the_filter_not_in_use_and_the_choice_waits_for_it(monkeypatch):
    """After a failed step the filter not in use (which misses that sample) starts afresh and both sums are
    forgotten, whichever filter is in use; the rule does not switch to a filter that has not run yet."""
    from test_mpc import PARAMS, REF_WARM, START
    from test_mpc import closed_loop as run

    plant = SimulatedPlant(PARAMS, seed=6)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START))
    run(ctrl, plant, [REF_WARM] * 5)
    ctrl.placement.sums[:] = [1e6, 0.0]
    run(ctrl, plant, [REF_WARM])
    default, air = ctrl._filters
    assert ctrl.ekf is air and default.healthy()

    def broken(*args, **kwargs):
        raise RuntimeError("preparation broke")

    monkeypatch.setattr(ctrl.solver, "prepare_predicted", broken)
    rows = run(ctrl, plant, [REF_WARM])
    assert "preparation broke" in rows[0]["stats"]["status"]
    assert not default.healthy() and ctrl.placement.sums == [0.0, 0.0]
    monkeypatch.undo()
    ctrl.placement.sums[:] = [0.0, 1e6]  # the rule would switch back, but the default filter has not run yet
    rows = run(ctrl, plant, [REF_WARM])
    assert ctrl.ekf is air and rows[0]["stats"]["fallback"] is None
    run(ctrl, plant, [REF_WARM])
    assert default.healthy()  # started from the readings of the sample it missed the step after


def test_a_switch_binds_the_fused_prediction_built_with_the_controller_and_commands_the_same(monkeypatch):
    """Each filter's time update fused with the QP data is built with the controller, so a switch (there and back)
    builds nothing inside its step; the commands are those of switches that build it afresh (as before it was
    built ahead), to the bit."""
    from test_mpc import PARAMS, REF_WARM, START
    from test_mpc import closed_loop as run

    def no_build(*args, **kwargs):
        raise AssertionError("a fused prediction was built inside a step")

    commands = {}
    for ahead in (True, False):
        plant = SimulatedPlant(PARAMS, seed=6)
        plant.settle(START)
        ctrl = MpcController(PARAMS, MpcSettings(initial_command=START))
        default, air = ctrl._filters
        assert set(ctrl.solver._fused) == {id(default), id(air)}
        rows = run(ctrl, plant, [REF_WARM] * 5)
        with monkeypatch.context() as m:
            if ahead:
                m.setattr(ctrl.solver, "_fuse", no_build)
            for sums, now_in_use in (([1e6, 0.0], air), ([0.0, 1e6], default)):
                if not ahead:
                    ctrl.solver._fused.clear()  # built again at the switch
                ctrl.placement.sums[:] = sums  # the rule switches at the next step
                rows += run(ctrl, plant, [REF_WARM] * 4)
                assert ctrl.ekf is now_in_use
        assert all(r["stats"]["fallback"] is None for r in rows)
        commands[ahead] = np.array([r["cmd"] for r in rows])
    np.testing.assert_array_equal(commands[True], commands[False])


def test_a_margin_switches_on_a_clear_lead_that_a_shared_start_up_hides_from_the_ratio():
    """Both filters surprised alike at the cap for a while (a dead time not yet found), then one surprised 40 times
    as much as the other: the ratio of the sums stays above 0.6 for long (the shared start-up sits in both), the
    difference passes the margin within a few samples; with the other one no better than the one in use (equal
    surprise) the margin never switches, and a consistent filter in use is kept whatever the lead."""
    def first_switch(c, later_own, later_other, n=60):
        for _ in range(30):
            c.observe(0, 50.0)
            c.observe(1, 50.0)
            assert not c.decide()
        for t in range(n):
            c.observe(0, later_own)
            c.observe(1, later_other)
            if c.decide():
                return t
        return None

    assert first_switch(choice(window_s=60.0), 40.0, 1.0) > 15  # the ratio alone: 17 samples
    assert first_switch(choice(window_s=60.0, margin=100.0), 40.0, 1.0) <= 3
    assert first_switch(choice(window_s=60.0, margin=100.0), 40.0, 40.0) is None
    c = choice(window_s=60.0, margin=10.0)
    for _ in range(200):
        c.observe(0, 1.2)  # consistent: below the evidence floor, whatever the other's sum
        c.observe(1, 0.0)
        assert not c.decide()


@pytest.mark.parametrize("warm", [False, True])
def test_a_warm_switch_prepares_the_qp_at_the_new_filter_instead_of_a_cold_start(warm):
    """With ``placement_warm_switch`` the switch step keeps the shifted plan and OSQP's warm start, the QP linearised
    again at the new filter's prediction: no cold start and no more QPs than a step without a switch; without it
    the switch step starts cold (the default)."""
    from test_mpc import PARAMS, REF_WARM, START
    from test_mpc import closed_loop as run

    plant = SimulatedPlant(PARAMS, seed=6)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START, placement_warm_switch=warm))
    rows = run(ctrl, plant, [REF_WARM] * 5)
    assert not rows[-1]["stats"]["cold_start"]
    ctrl.placement.sums[:] = [1e6, 0.0]  # the rule switches at the next step
    switch = run(ctrl, plant, [REF_WARM])[0]["stats"]
    assert ctrl.ekf is ctrl._filters[1] and switch["fallback"] is None
    assert switch["cold_start"] is (not warm)
    if warm:
        assert switch["qp_solves"] <= rows[-1]["stats"]["qp_solves"]


def test_a_warm_switch_whose_rebase_fails_leaves_the_old_filter_bound_and_in_use(monkeypatch):
    """Where the warm switch's preparation raises, the switch is undone as a whole: the filter in use, the one the
    solver predicts with and the choice's own record stay the old filter's, and the step falls back."""
    from test_mpc import PARAMS, REF_WARM, START
    from test_mpc import closed_loop as run

    plant = SimulatedPlant(PARAMS, seed=6)
    plant.settle(START)
    ctrl = MpcController(PARAMS, MpcSettings(initial_command=START, placement_warm_switch=True))
    run(ctrl, plant, [REF_WARM] * 5)
    old = ctrl.ekf
    bound = []
    original = ctrl.solver.use_prediction
    monkeypatch.setattr(ctrl.solver, "use_prediction", lambda ekf: (bound.append(ekf), original(ekf))[1])

    def fail(*_args, **_kwargs):
        raise RuntimeError("rebase failed")

    monkeypatch.setattr(ctrl.solver, "rebase", fail)
    ctrl.placement.sums[:] = [1e6, 0.0]  # the rule switches at the next step
    step = run(ctrl, plant, [REF_WARM])[0]["stats"]
    assert step["fallback"] is not None
    assert ctrl.ekf is old and ctrl._filters[ctrl.placement.active] is old
    assert bound[:2] == [ctrl._filters[1], old]  # bound to the new filter, then back to the old one


def test_the_sums_are_forgotten_once_when_the_first_response_is_seen():
    """With ``placement_from_response`` both sums start afresh at the step in which the filter in use first sees a
    response (its dead-time estimate informed), and not again after it; without it they are never forgotten."""
    from test_mpc import PARAMS, REF_COOL, REF_WARM, START

    for on in (False, True):
        plant = SimulatedPlant(PARAMS, seed=6)
        plant.settle(START)
        ctrl = MpcController(PARAMS, MpcSettings(initial_command=START, placement_from_response=on,
                                                 placement_dead_time_hold_s=0.0))  # each sample counted as it comes
        restarts = []
        original = ctrl.placement.restart

        def counted(original=original, restarts=restarts):
            restarts.append(ctrl.ekf.time_updates)
            original()

        ctrl.placement.restart = counted
        seen_at = None
        for k in range(120):
            ref = REF_WARM if k < 20 else REF_COOL  # a step the supply air answers
            res = ctrl.step(plant.read(), ref)
            plant.apply(res.command)
            plant.advance()
            if seen_at is None and ctrl.ekf.response_seen:
                seen_at = ctrl.ekf.time_updates
                if on:  # forgotten in this step, before the filter in use added its sample
                    assert ctrl.placement.sums[1] == 0.0
                    assert ctrl.placement.sums[0] == pytest.approx(min(ctrl.ekf.supply_nis, ctrl.placement.cap))
        assert seen_at is not None
        assert restarts == ([seen_at - 1] if on else [])


@pytest.mark.parametrize("field, bad, off", [("placement_margin", -1.0, "inf"), ("osqp_rho_reset", 0.0, "None")])
def test_a_setting_with_an_off_value_names_it_in_its_error(field, bad, off):
    with pytest.raises(InvalidSettings, match=rf"{field}.*allowed range.*or {off} \(off\)"):
        MpcSettings(**{field: bad})


def test_a_forced_switch_is_a_trial_that_the_sums_take_back_soon_where_the_filter_left_is_better():
    """After :meth:`PlacementChoice.force` (the sign check's switch) the sums start afresh and the floor counts from
    there: a filter in use surprised 4 times as much as the one left gives way within a fifth of the window, where
    after a plain restart (the full floor) it takes most of a window."""
    def steps_to_switch_back(start) -> int:
        c = choice(window_s=60.0)
        start(c)
        for k in range(1, 200):
            c.observe(c.active, 4.0)
            c.observe(1 - c.active, 1.0)
            if c.decide():
                return k
        return 200
    on_trial = steps_to_switch_back(lambda c: c.force())
    after_restart = steps_to_switch_back(lambda c: (c.observe(0, 1.0), c.restart()))
    assert on_trial <= 12 and after_restart >= 25
    c = choice(window_s=60.0)
    c.force()
    assert c.active == 1 and c.sums == [0.0, 0.0] and c.trial_steps == 0


@pytest.mark.parametrize("seed", range(10))
def test_on_trial_two_consistent_filters_do_not_switch_back_on_noise(seed):
    """Both filters' normalised squares chi-square with one degree (consistent): the trial's floor asks a few
    samples for the confidence the window's floor asks of the window, so noise alone does not undo the switch."""
    rng = np.random.default_rng(seed)
    c = choice(window_s=60.0)
    c.force()
    for _ in range(3 * 60):
        c.observe(c.active, rng.chisquare(1))
        c.observe(1 - c.active, rng.chisquare(1))
        c.decide()
    assert c.active == 1 and c.trial_steps is None  # the trial ended (three windows) with the forced filter in use


def test_the_trial_floor_grows_to_the_window_floor():
    forget = math.exp(-1.0 / 60.0)
    floors = [placement.trial_floor(90.0, forget, n) for n in (1, 5, 20, 60, 600)]
    assert floors == sorted(floors) and floors[0] > 5.0  # one sample must be far beyond a consistent one
    assert floors[-1] == pytest.approx(90.0, rel=1e-3)
