"""The data loop on logs of the independent simulator (hvac_mpc.mismatch, a truth that is not the
model): bad rows, the log timing check, discovered terms in the model and the model file, the
refined model in the MPC, and identification end to end (slow).

Fast part: about 15 s (short logs, no identification run). Slow part: 30 min logs, identified once
per session in quick mode.
"""

import dataclasses
import json

import numpy as np
import pytest

from hvac_mpc.identification import load_model_file, load_refined_model, write_model_file
from hvac_mpc.identification import timing
from hvac_mpc.identification.log_data import load
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS, identify
from hvac_mpc.identification.simulator import Simulator
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.mismatch.variants import Variant
from hvac_mpc.models import HvacModel, Parameters
from hvac_mpc.models.discovered import DiscoveredTerm
from hvac_mpc.models.model_file import ModelFileError, RefinedModel
from hvac_mpc.mpc.mpc_controller import MpcController

LOSS_TERM = DiscoveredTerm("duct_loss", "supply_air", ("mix_over_mass_flow", "inv_mass_flow", "one"),
                           (-0.003, 0.072, 0.0), "heat loss to surroundings at 24 C")


# ------------------------------------------------------------------ bad rows
def test_bad_rows_are_found_counted_and_masked(tmp_path):
    info = simulate_log(tmp_path / "bad.csv", "nominal", duration_s=1200, seed=2, bad_rows=True)
    inj = info["injected"]
    log = load(tmp_path / "bad.csv")
    found = log.bad_rows
    assert found["non_monotone_timestamps"] == inj["n_non_monotone"]
    assert found["duplicated_timestamps"] == inj["n_duplicated"]
    assert found["dropouts"] == 1 and found["dropout_rows"] == inj["dropout"]["n_samples"]
    assert found["dropout_time_s"] == [inj["dropout"]["start_s"]]
    assert found["stuck_sensor"]["supply_temp_c"]["rows"] == inj["stuck_supply"]["n_samples"]
    assert sum(found["empty_sensor_cells"].values()) == inj["n_missing_cells"]
    # uniform grid again, and nothing of the bad rows is left to fit
    assert np.allclose(np.diff(log.time_s), 1.0) and log.n == info["samples"]
    stuck = (log.time_s >= inj["stuck_supply"]["start_s"]) & (log.time_s < inj["stuck_supply"]["start_s"] + 60)
    assert np.all(np.isnan(log.outputs["supply_temp_c"][stuck]))
    gap = (log.time_s >= inj["dropout"]["start_s"]) & (log.time_s <= inj["dropout"]["end_s"])
    assert np.all(np.isnan(log.outputs["volume_flow_m3s"][gap]))
    assert any("stuck sensor" in n for n in log.notes) and any("dropout" in n for n in log.notes)


def test_clean_log_reports_no_bad_rows(tmp_path):
    simulate_log(tmp_path / "clean.csv", "nominal", duration_s=900, seed=4)
    log = load(tmp_path / "clean.csv")
    assert not any(n.startswith("bad rows") for n in log.notes)
    assert log.bad_rows["masked_rows"] == 0 and log.bad_rows["stuck_sensor"] == {}


# ------------------------------------------------------------------ timing
@pytest.mark.parametrize("shift", [1, -1, 0, 4, -5])
def test_log_timing_shift_is_detected_and_corrected(tmp_path, shift):
    """Shifts of 4 and 5 samples too: the check looked 3 samples either way and took a log 4 samples late for 3."""
    simulate_log(tmp_path / "s.csv", Variant(log_shift_samples=shift), duration_s=900, seed=6)
    log = load(tmp_path / "s.csv")
    y, _ = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, ("volume_flow_m3s",)).simulate(
        np.array(Parameters().vector()))
    found, errors = timing.detect_shift(log.outputs["volume_flow_m3s"], y[:, 0])
    assert found == shift
    text = timing.describe(found, 1.0, errors)
    assert ("late" in text if shift > 0 else "early" in text if shift < 0 else "in step" in text)
    n0, raw_u, raw_signals = log.n, log.u.copy(), {k: v.copy() for k, v in log.signals.items()}
    timing.correct(log, found)
    # the rows whose readings ran out are gone: every column as long as the log, the commands and the readings
    # of each kept row those of the raw log's row and its row ``shift`` later, none from before the correction
    assert log.n == n0 - abs(shift)
    keep, later = (slice(0, n0 - shift), slice(shift, n0)) if shift >= 0 else (slice(-shift, n0), slice(0, n0 + shift))
    assert np.array_equal(log.u, raw_u[keep])
    sensors = [n for n in raw_signals if n in log.outputs or n in timing.SENSOR_SIGNALS]
    assert "supply_temp_c" in sensors and "hvac_inlet_temp_c" in sensors
    for name, raw in raw_signals.items():
        assert len(log.signals[name]) == log.n
        expected = raw[later] if name in sensors else raw[keep]
        assert np.array_equal(log.signals[name], expected, equal_nan=True), name
    assert len(log.train) == len(log.holdout) == len(log.inlet_temp_c) == log.n
    assert np.isfinite(log.inlet_temp_c).all()
    y, _ = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, ("volume_flow_m3s",)).simulate(
        np.array(Parameters().vector()))
    again, _ = timing.detect_shift(log.outputs["volume_flow_m3s"], y[:, 0])
    assert again == 0


def test_a_shift_at_the_edge_of_the_scan_is_reported_as_possibly_larger():
    errors = {s: 1.0 + abs(s + 2) for s in range(-2, 3)}  # best at -2, the scan's edge
    assert "may be further off" in timing.describe(-2, 1.0, errors)
    assert "may be further off" not in timing.describe(-1, 1.0, {s: 1.0 + abs(s + 1) for s in range(-2, 3)})


# ------------------------------------------------------------------ discovered terms and the model file
def test_discovered_term_enters_the_supply_air_balance():
    plain, refined = HvacModel(Parameters()), HvacModel(Parameters(), terms=(LOSS_TERM,))
    u = np.array([100.0, 200.0, 50.0, 100.0, 100.0, 100.0])
    d = plain.d_vector(20.0, 5.0)
    x = plain.steady_state(u, d)
    y0, y1 = plain.y(x, u, d), refined.y(x, u, d)
    i = plain.outputs.index("supply_air_temp_c")
    m = y0[plain.outputs.index("mass_flow_kgs")]
    expected = -0.003 * y0[i] / m + 0.072 / m
    assert y1[i] - y0[i] == pytest.approx(expected, rel=1e-9)
    # the flows and the heater do not see a supply-air term
    assert y1[plain.outputs.index("volume_flow_m3s")] == y0[plain.outputs.index("volume_flow_m3s")]


def test_heater_body_term_is_a_heat_flow_in_the_body_balance():
    """A ``heater_body`` term (W) loses heat from the body: at rest the body is cooler by the term over the body's
    conductances, the air gets the heat that is left, and with the heater off and the body at the air's temperature
    a conductance to the inlet air moves nothing."""
    loss = DiscoveredTerm("wall", "heater_body", ("body_minus_inlet", "one"), (-0.3, 0.0))
    plain, refined = HvacModel(Parameters()), HvacModel(Parameters(), terms=(loss,))
    u = np.array([150.0, 150.0, 100.0, 100.0, 100.0, 100.0])
    d = plain.d_vector(25.0, 20.0)
    x0, x1 = plain.steady_state(u, d), refined.steady_state(u, d)
    i_body = plain.states.index("heater_temp_c")
    out = plain.outputs.index("heater_outlet_temp_c")
    y0, y1 = plain.y(x0, u, d), refined.y(x1, u, d)
    assert x1[i_body] < x0[i_body] - 1.0 and y1[out] < y0[out]
    xdot = np.asarray(refined.ode(x0, u, d, refined.p_default)).ravel()
    p = Parameters()
    assert xdot[i_body] == pytest.approx(-0.3 * (x0[i_body] - 25.0) / (p.heater_mass_kg * p.heater_c_j_per_kgk),
                                         rel=1e-9)
    with pytest.raises(ValueError, match="heater body"):
        DiscoveredTerm("bad", "heater_body", ("mix", "one"), (1.0, 0.0))


def test_cooler_outlet_term_acts_before_the_split_and_reaches_the_heater():
    """A term at the core outlet that turns the effectiveness form into the thesis's literal fit
    (0.7564 T_w + 6.312 whatever the inlet air): the air leaving the heater (heater off) follows it, the
    supply air gets it through the core share only, the flows do not see it."""
    prm = Parameters()
    literal = DiscoveredTerm("cooler_literal", "cooler_out", ("core_in", "one"),
                             (-(1.0 - prm.cooler_slope), prm.cooler_offset_c), "literal cooler fit")
    plain, refined = HvacModel(prm), HvacModel(prm, terms=(literal,))
    u = np.array([100.0, 0.0, 50.0, 100.0, 100.0, 100.0])  # heater off: heater outlet = core outlet at rest
    outs = []
    for t_in in (15.0, 30.0):
        d = plain.d_vector(t_in, 5.0)
        x0, x1 = plain.steady_state(u, d), refined.steady_state(u, d)
        y0, y1 = plain.outputs.dict(plain.y(x0, u, d)), refined.outputs.dict(refined.y(x1, u, d))
        water = x1[refined.states.index("water_temp_c")]
        assert y1["heater_outlet_temp_c"] == pytest.approx(prm.cooler_slope * water + prm.cooler_offset_c, abs=1e-6)
        assert y1["volume_flow_m3s"] == y0["volume_flow_m3s"]
        core = y1["supply_air_temp_c"] - y0["supply_air_temp_c"]
        shift = y1["heater_outlet_temp_c"] - y0["heater_outlet_temp_c"]
        assert 0.0 < core / shift < 1.0  # the bypass air does not pass the core
        outs.append(y1["heater_outlet_temp_c"])
    assert outs[0] == pytest.approx(outs[1], abs=1e-6)  # independent of the inlet air
    with pytest.raises(ValueError, match="cooler outlet"):
        DiscoveredTerm("bad", "cooler_out", ("mix", "one"), (1.0, 0.0))


def test_cooler_outlet_term_keeps_the_core_outlet_between_the_air_and_the_water():
    """A term at the core outlet fitted where the log's inlet air lies (20-32 C) and extrapolated: with the literal
    fit's slope it makes the core *warm* 5 C air to about 10 C with 5 C water, which no passive exchanger does. The
    model holds the core outlet between the air entering the core and the water (second law); inside that range
    the term is unchanged (the test above: 15 and 30 C)."""
    prm = Parameters()
    literal = DiscoveredTerm("cooler_literal", "cooler_out", ("core_in", "one"),
                             (-(1.0 - prm.cooler_slope), prm.cooler_offset_c), "literal cooler fit")
    model = HvacModel(prm, terms=(literal,))
    u = np.array([100.0, 0.0, 50.0, 100.0, 100.0, 100.0])  # heater off: heater outlet = core outlet at rest
    d = model.d_vector(5.0, 5.0)
    x = model.steady_state(u, d)
    y = model.outputs.dict(model.y(x, u, d))
    core_in = 5.0 + x[model.states.index("motor_rise_c")]
    water = x[model.states.index("water_temp_c")]
    assert prm.cooler_slope * water + prm.cooler_offset_c > core_in + 3.0  # the extrapolated term alone
    assert min(water, core_in) - 1e-6 <= y["heater_outlet_temp_c"] <= max(water, core_in) + 1e-6


def test_literal_cooler_effect_follows_the_thesis_fit_whatever_the_inlet_air():
    """Effect ``cooler_literal_fit``: the thesis's cooler fit as written (sec. 4.2, T_a = 0.7564 T_w + 6.312, the
    numbers here the thesis's, not the model's parameters) whatever the air entering the core, at 5 C too, where it
    warms the air past both streams (the equation the box of that name follows; unlike a discovered term it is not
    held between the air and the water). Off by default: the effectiveness form, which follows the inlet air."""
    u = np.array([100.0, 0.0, 50.0, 100.0, 100.0, 100.0])  # heater off: heater outlet = core outlet at rest
    literal, plain = HvacModel(Parameters(), ("cooler_literal_fit",)), HvacModel(Parameters())
    outs, plain_outs = [], []
    for t_in in (5.0, 15.0, 30.0):
        d = literal.d_vector(t_in, 5.0)
        x = literal.steady_state(u, d)
        water = x[literal.states.index("water_temp_c")]
        y = literal.outputs.dict(literal.y(x, u, d))
        assert y["heater_outlet_temp_c"] == pytest.approx(0.7564 * water + 6.312, abs=1e-3)
        outs.append(y["heater_outlet_temp_c"])
        xp = plain.steady_state(u, d)
        plain_outs.append(plain.outputs.dict(plain.y(xp, u, d))["heater_outlet_temp_c"])
    assert outs[0] > 5.0 + 3.0  # 5 C air and water leave the core near 10 C
    assert plain_outs[2] - plain_outs[0] > 5.0  # the effectiveness form follows the inlet air


def test_mpc_with_the_literal_cooler_term_heats_as_well_as_the_nominal_mpc():
    """The box whose core outlet does not depend on the inlet air (``cooler_literal``) in winter_heating_steps
    (inlet and water 5 C, quick): the MPC with the core-outlet term identification adds for it (the literal fit's
    slope and offset, docs/identification.md) against the nominal MPC, same noise. With the term extrapolated
    linearly the refined MPC believed the core warms the air to 10 C, held the heater body cool and waited for it
    on the step up (43.7 against 25.9 C s measured); with the core outlet held between air and water it tracks
    like the nominal MPC (25.8 against 25.9 C s). Both without the online choice of the heater outlet error's
    placement (``MpcSettings.choose_offset_placement``, docs/robustness.md sec. 2.14): with it the nominal MPC learns
    online what the term says (26.95 against the refined 28.73 C s, measured), and the term would be compared with
    itself."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import closed_loop_iae
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    prm = Parameters()
    term = DiscoveredTerm("cooler_outlet_term", "cooler_out", ("core_in", "one"),
                          (-(1.0 - prm.cooler_slope), prm.cooler_offset_c), "literal cooler fit")
    refined = RefinedModel(prm, ("ptc_power_fall", "fan_curve", "valve_leakage"), (term,), absent=("bypass_flow",))
    sc = scenarios.select(["winter_heating_steps"], quick=True)[0]
    settings = MpcSettings(initial_command=sc.initial_command, choose_offset_placement=False)
    nominal = closed_loop_iae(sc, MpcController(settings=settings), "cooler_literal", seed=0)
    known = closed_loop_iae(sc, MpcController(settings=settings, model=refined), "cooler_literal", seed=0)
    assert known["temp_iae_cs"] < 1.05 * nominal["temp_iae_cs"], (known, nominal)


def test_mpc_with_the_literal_cooler_term_tracks_the_literal_cooler_box_better_in_cooling():
    """The box whose core outlet does not depend on the inlet air (``cooler_literal``), the quick proband sequence
    (cooling, seven references), the default settings (the online placement of the heater outlet error included):
    the MPC with the core-outlet term identification adds for it (the literal fit's slope and offset, thesis
    parameters otherwise) against the nominal MPC, same noise. In cooling the term acts unbounded (the literal
    fit's 10 C lies between the water and the air entering the core) and the refined model has the box's core and
    valve a gain, where the nominal MPC's mixed-air offset is right only at the valve position it was learned at:
    measured 32.79 against 34.09 C s (0.962; noise seeds 1-3: 0.967, 0.950, 0.957). In heating the core outlet is
    held between air and water (the box's core warms 5 C air to 10 C with 5 C water) and both MPCs learn the rest
    online, level within the spread of the nominal MPC itself (docs/identification.md, "The literal cooler and the
    duct exchange at low flow")."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import closed_loop_iae
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    prm = Parameters()
    term = DiscoveredTerm("cooler_outlet_term", "cooler_out", ("core_in", "one"),
                          (-(1.0 - prm.cooler_slope), prm.cooler_offset_c), "literal cooler fit")
    refined = RefinedModel(prm, ("ptc_power_fall", "fan_curve", "valve_leakage"), (term,), absent=("bypass_flow",))
    sc = scenarios.select(["proband_sequence"], quick=True)[0]
    settings = MpcSettings(initial_command=sc.initial_command)
    nominal = closed_loop_iae(sc, MpcController(settings=settings), "cooler_literal", seed=0)
    known = closed_loop_iae(sc, MpcController(settings=settings, model=refined), "cooler_literal", seed=0)
    assert known["temp_iae_cs"] < 0.99 * nominal["temp_iae_cs"], (known, nominal)


def test_trapped_air_guard_reads_the_heater_inlet_with_the_core_outlet_term():
    """The guard counts the heater as warm when its body is ``trap_warm_c`` (5 C) above the air entering it. On the
    box whose core outlet does not depend on the inlet air (``cooler_literal``; inlet 10 C, water 5 C) that air is
    the literal fit's 10.1 C (hvac_mpc.mismatch, the truth), so a heater body at 14 C is not warm and valve a keeps
    its whole travel. The guard read the cooler equation without the discovered term (6.3 C there) and capped
    valve a at 90 % with the MPC that has the term in its model."""
    from hvac_mpc.contract import Command, Measurement
    from hvac_mpc.mismatch import physics
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    prm = Parameters()
    term = DiscoveredTerm("cooler_outlet_term", "cooler_out", ("core_in", "one"),
                          (-(1.0 - prm.cooler_slope), prm.cooler_offset_c), "literal cooler fit")
    refined = RefinedModel(prm, ("ptc_power_fall", "fan_curve", "valve_leakage"), (term,), absent=("bypass_flow",))
    ctrl = MpcController(settings=MpcSettings(initial_command=Command(60.0, 0.0, 50.0, 100.0, 100.0, 100.0)),
                         model=refined)
    ctrl.ekf.initialise(Measurement(0.0, 12.0, 0.011, 10.0, water_temp_c=5.0), ctrl.u_prev, 5.0)
    x = ctrl.ekf.x
    heater_in_box = physics.cooler_outlet_c(10.0 + x[ctrl.problem.model.states.index("motor_rise_c")], 5.0,
                                            literal_fit=True)
    ctrl.ekf.z[ctrl.problem.i_heater] = heater_in_box + 4.0
    assert ctrl._trap_cap() == 100.0
    ctrl.heater_bound.reset()
    ctrl.ekf.z[ctrl.problem.i_heater] = heater_in_box + 6.0  # warm: capped at the threshold less the margin
    assert ctrl._trap_cap() == pytest.approx(prm.trap_threshold_pct - ctrl.settings.ocp.trap_margin_pct)


def test_trapped_air_guard_bound_follows_the_body_balance_with_a_heater_body_term():
    """With the heater off the guard bounds the body by its relaxation towards the air (HeaterOffBound). A discovered
    heat flow into the body (a ``heater_body`` term) changes that relaxation: the bound follows the prediction model's
    body balance, so it stays above a body that a term heats (a bound from the air alone fell below it and freed
    valve a with a hot body) and falls faster with a loss (here against a term of zero, the model's balance alone).
    Without such a term the bound is the air relaxation."""
    from hvac_mpc.contract import Command, Measurement
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    def bound_after(terms, seconds=60):
        ctrl = MpcController(settings=MpcSettings(initial_command=Command(60.0, 0.0, 50.0, 100.0, 100.0, 100.0)),
                             model=RefinedModel(Parameters(), terms=terms))
        ctrl.ekf.initialise(Measurement(0.0, 12.0, 0.011, 10.0, water_temp_c=5.0), ctrl.u_prev, 5.0)
        i_heater = ctrl.problem.i_heater
        for _ in range(seconds):
            ctrl.ekf.z[i_heater] = 60.0  # an estimate that does not cool: the bound alone brings the body down
            ctrl._trap_cap()
        model = ctrl.problem.model
        rest = model.steady_state(ctrl.u_prev, ctrl._disturbance(5.0))[model.states.index("heater_temp_c")]
        return ctrl.heater_bound.bound_c, rest, ctrl

    assert bound_after(())[2]._heater_body_rate is None  # no term at the body: the air relaxation (test_robust.py)
    plain, rest_plain, ctrl = bound_after((DiscoveredTerm("none", "heater_body", ("one",), (0.0,)),))
    assert ctrl._heater_body_rate is not None
    gain, rest_gain, _ = bound_after((DiscoveredTerm("gain", "heater_body", ("one",), (20.0,)),))
    loss, rest_loss, _ = bound_after((DiscoveredTerm("loss", "heater_body", ("one",), (-20.0,)),))
    assert rest_loss < rest_plain < rest_gain  # the model's rest temperature of the body with each term
    assert loss < plain < gain
    for bound, rest in ((plain, rest_plain), (gain, rest_gain), (loss, rest_loss)):
        assert rest < bound < 60.0  # still above where the body comes to rest, below the estimate


CABIN_TERM = DiscoveredTerm("duct_cabin", "supply_air", ("cabin_minus_mix_over_mass_flow",), (0.003,),
                            "duct-to-cabin exchange")


def test_cabin_term_uses_the_logged_cabin_temperature_and_the_parameter_in_the_model(tmp_path):
    simulate_log(tmp_path / "c.csv", "duct_loss", duration_s=700, seed=3)
    log = load(tmp_path / "c.csv")
    assert log.cabin_temp_c is not None and abs(np.median(log.cabin_temp_c) - 24.0) < 0.05
    p = np.array(Parameters().vector())
    j = ("supply_temp_c",)
    y0 = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, j, (CABIN_TERM,)).simulate(p)[0][:, 0]
    log.cabin_temp_c = log.cabin_temp_c + 5.0  # a warmer cabin warms the supply air, more at low flow
    y1, states = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, j, (CABIN_TERM,)).simulate(p)
    rise = (y1[:, 0] - y0)[200:]
    assert np.all(rise > 0) and np.ptp(rise) > 0.1
    # the model (the controller's) takes the cabin temperature from Parameters.cabin_temp_c
    model = HvacModel(Parameters().replace(cabin_temp_c=30.0), terms=(CABIN_TERM,))
    u, d = np.array([100.0, 0.0, 50.0, 100.0, 100.0, 100.0]), model.d_vector(20.0, 5.0)
    x = model.steady_state(u, d)
    y = model.outputs.dict(model.y(x, u, d))
    plain = HvacModel(Parameters()).outputs.dict(HvacModel(Parameters()).y(x, u, d))
    # ... as the exchanger it is: (T_cabin - T_mix) (1 - exp(-c / m_dot)), c = UA / c_p (models/discovered.py)
    assert y["supply_air_temp_c"] - plain["supply_air_temp_c"] == pytest.approx(
        (30.0 - plain["supply_air_temp_c"]) * -np.expm1(-0.003 / y["mass_flow_kgs"]), rel=1e-6)


def test_duct_exchange_term_is_its_fitted_linear_form_at_a_logs_flows_and_stays_short_of_the_cabin_at_low_flow():
    """The cabin term is fitted linear in one over the mass flow (UA / (m_dot c_p) (T_cabin - T_mix)); the model
    evaluates it as the duct's exchange, (T_cabin - T_mix) (1 - exp(-UA / (m_dot c_p))): within half the number of
    transfer units of the linear form at a log's flows, and never past the cabin's temperature where the flow falls
    (the linear form at 10 m3/h, UA 3 W/K: 0.74 of the difference; the exchange 0.52, the box's own equation's)."""
    import casadi as ca
    from hvac_mpc.mismatch import physics
    from hvac_mpc.models.discovered import exchange_c

    ua_w_per_k, cp = 3.0, 1007.0
    c = ua_w_per_k / cp
    for m in (0.02, 0.03, 0.06):  # 60-180 m3/h: the logs' flows
        ntu = c / m
        linear = c * 10.0 / m
        assert exchange_c(c, 10.0, m) == pytest.approx(linear, rel=ntu / 2.0)
        assert exchange_c(c, 10.0, m) < linear
    m_low = 10.0 / 3600.0 * 1.2  # 10 m3/h
    assert c * 10.0 / m_low > 7.0  # the linear form: 7.4 C of a 10 C difference
    exchanged = exchange_c(c, 10.0, m_low)
    assert 0.0 < exchanged < 10.0
    assert exchanged == pytest.approx(physics.duct_outlet_c(14.0, 24.0, ua_w_per_k, m_low) - 14.0, rel=1e-3)
    assert float(exchange_c(c, ca.DM(10.0), ca.DM(m_low))) == pytest.approx(exchanged, rel=1e-12)  # numpy = CasADi
    # in the model: no flow takes the supply air past the cabin
    model = HvacModel(Parameters().replace(cabin_temp_c=24.0), terms=(CABIN_TERM,))
    d = model.d_vector(10.0, 10.0)
    for blower_w in (30.0, 60.0, 120.0):
        u = np.array([blower_w, 0.0, 50.0, 100.0, 100.0, 100.0])
        y = model.outputs.dict(model.y(model.steady_state(u, d), u, d))
        assert y["supply_air_temp_c"] < 24.0


def test_chiller_band_is_read_where_the_water_cycles_not_on_set_point_ramps(tmp_path):
    from hvac_mpc.identification.diagnostics import chiller_cycling
    from hvac_mpc.identification.fitting import Fitter

    simulate_log(tmp_path / "w.csv", "nominal", duration_s=3600, seed=5)  # set point 5 C and 20 C phases
    log = load(tmp_path / "w.csv")
    assert np.ptp(log.chiller_setpoint_c) == 15.0
    band = chiller_cycling(Fitter(log, Parameters()))
    assert band["cycling"] and band["half_band_c"] == pytest.approx(1.0, abs=0.15)  # the box's +-1 C


def test_model_file_round_trip_with_terms_and_delay(tmp_path):
    params = Parameters().replace(transport_delay_s=3.0, fan_k_kg_m7=9.0e4)
    path = write_model_file(tmp_path / "m.toml", params, ("fan_curve", "ptc_power_fall"), {"note_s": 1.0},
                            terms=(LOSS_TERM,))
    refined = load_refined_model(path)
    assert refined.transport_delay_s == 3.0 and refined.parameters.fan_k_kg_m7 == 9.0e4
    assert refined.effects == ("ptc_power_fall", "fan_curve") and refined.terms == (LOSS_TERM,)
    assert "format_version = 3" in path.read_text() and "absent" not in path.read_text()
    p, e = load_model_file(path)  # the public API of version 1 keeps working
    assert p == refined.parameters and e == refined.effects
    js = write_model_file(tmp_path / "m.json", params, ("fan_curve",), terms=(LOSS_TERM,))
    assert load_refined_model(js).terms == (LOSS_TERM,)


@pytest.mark.parametrize("edit, field", [
    ('features = ["mix_over_mass_flow", "inv_mass_flow", "one"]', "model.terms.0.features.1"),
    ('location = "supply_air"', "model.terms.0.location"),
    ("format_version = 3", "format_version"),
    ('effects = ["fan_curve"]', "model.effects.0"),
    ('absent = ["bypass_flow"]', "model.absent.0"),
])
def test_bad_model_file_names_the_field(tmp_path, edit, field):
    path = write_model_file(tmp_path / "m.toml", Parameters(), ("fan_curve",), terms=(LOSS_TERM,), absent=("bypass_flow",))
    text = path.read_text()
    broken = {"features": edit.replace("inv_mass_flow", "cabin_magic"), "location": edit.replace("supply_air", "roof"),
              "format_version = 3": "format_version = 7", "effects": edit.replace("fan_curve", "warp_drive"),
              "absent": edit.replace("bypass_flow", "gremlins")}
    key = next(k for k in broken if edit.startswith(k))
    assert edit in text
    path.write_text(text.replace(edit, broken[key]))
    with pytest.raises(ModelFileError, match=field.replace(".", r"\.")):
        load_refined_model(path)


def test_absent_effects_round_trip_and_an_effect_cannot_be_both(tmp_path):
    path = write_model_file(tmp_path / "m.toml", Parameters(), ("fan_curve",), absent=("bypass_flow", "fan_curve"))
    assert load_refined_model(path).absent == ("bypass_flow",)  # an effect in the model is not absent
    path.write_text(path.read_text().replace('absent = ["bypass_flow"]', 'absent = ["fan_curve"]'))
    with pytest.raises(ModelFileError, match=r"model\.absent.*fan_curve"):
        load_refined_model(path)
    js = write_model_file(tmp_path / "m.json", Parameters(), (), absent=("bypass_flow",))
    assert load_refined_model(js).absent == ("bypass_flow",)


def test_mpc_with_a_model_file_keeps_its_own_bypass_treatment_and_its_delay_in_the_estimator():
    """bypass_flow is the controller's device (OcpSpec.model_effects); a model file saying the box lacks it
    changes nothing there, a controller configured without it does not get it from the file either. The file's
    delay starts the estimator's dead time (one estimate, moved by the readings) instead of a lag chain."""
    from hvac_mpc.mpc.mpc_controller import MpcSettings
    from hvac_mpc.mpc.ocp import OcpSpec

    refined = RefinedModel(Parameters().replace(transport_delay_s=3.0), ("fan_curve", "valve_leakage"),
                           absent=("bypass_flow",))
    mpc = MpcController(model=refined)
    assert "bypass_flow" in mpc.problem.model.effects
    assert mpc.problem.model.delay_states == () and mpc.ekf.dead_time_s == 3.0
    mpc.reset(MpcSettings().initial_command)
    assert mpc.ekf.dead_time_s == 3.0
    without = MpcSettings(ocp=OcpSpec(model_effects=("fan_curve",)))
    effects = MpcController(settings=without, model=refined).problem.model.effects
    assert "bypass_flow" not in effects and "valve_leakage" in effects


def test_mpc_with_the_duct_loss_term_tracks_the_box_with_the_loss_better():
    """Fast: the independent box with a 3 W/K duct loss to a 24 C cabin (hvac_mpc.mismatch ``duct_loss``), the
    MPC with the term identification adds for it (coefficients of the seed-5 2 h log, docs/identification.md)
    against the nominal MPC, same noise, one quick scenario. The slow tests identify the term themselves."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import closed_loop_iae
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    term = DiscoveredTerm("supply_residual_term", "supply_air", ("cabin_minus_mix_over_mass_flow", "one"),
                          (0.002874, 0.01491), "heat exchange between the duct and the cabin, UA about 2.89 W/K")
    refined = RefinedModel(Parameters().replace(motor_gain_max_c=2.19), ("ptc_power_fall", "fan_curve", "valve_leakage"),
                           (term,), absent=("bypass_flow",))
    sc = scenarios.select(["flow_split_changes"], quick=True)[0]
    settings = MpcSettings(initial_command=sc.initial_command)
    nominal = closed_loop_iae(sc, MpcController(settings=settings), "duct_loss", seed=0)
    better = closed_loop_iae(sc, MpcController(settings=settings, model=refined), "duct_loss", seed=0)
    assert better["temp_iae_cs"] < 0.85 * nominal["temp_iae_cs"], (better, nominal)
    # temperature first (Weights.supply_temp 5 against the flow's 2): the better model gives up a little more
    # flow for a temperature error half the nominal's (1.20 times the flow IAE measured, 1.1 with weight 1)
    assert better["flow_iae_m3"] < 1.3 * nominal["flow_iae_m3"], (better, nominal)


@pytest.mark.slow
def test_mpc_with_a_heater_body_term_tracks_the_box_with_the_wall_loss_better():
    """A term at a place the library has no parameter for: the independent box's heater body loses 0.3 W/K to the box
    walls (hvac_mpc.mismatch ``heater_wall_loss``), and the MPC with the ``heater_body`` term identification adds for
    it (-0.28 W/K (T_body - T_inlet) + 0.14 W, the seed-23 2 h log, docs/identification.md; thesis parameters
    otherwise) against the nominal MPC, same noise, the quick trapped-air scenario (heating at the heater's limit,
    then a step down): measured 346.4 against 404.5 C s. The nominal MPC, believing the body keeps that heat,
    plans on a hotter body than the box has. Both with the filter that weighs the thermocouple alike at rest and in
    transients (``EkfSettings.r_supply_rest_c`` 0), as measured: with the default, which weighs it less at rest
    (docs/robustness.md sec. 2.10), the nominal MPC is at 363.6 C s and the refined one at 345.4 (0.95), the rest
    gate taking most of the nominal's loss on this box; the check is about the term.

    Without the start-up's caution (``start_rate_share`` 1), as measured. The caution's bound never binds here (the
    start closes valve a, 50 -> 18 -> 0 %, and the filter has seen a response at 8 s), but it moves the first QPs'
    answers by about 1e-6, and the run's outcome hangs on the QP of the step to 22 C at 30 s, which ends at OSQP's
    iteration limit: without the caution it is accepted ("solved inaccurate"), with it (0.4) the step falls back to
    the shifted plan for 5 s and the run scores 393.7 C s (docs/robustness.md sec. 2.27). The same edge without the
    caution: the term's coefficient -0.2817 -> -0.28 W/K, one fallback, 356.8; with the caution at -0.2816 or
    -0.2818 W/K no fallback, 345.9 / 346.0. The nominal MPC falls back there for 4 s with either setting. With the
    caution (0.4) the refined run stays below the nominal's.

    These runs with OSQP's retry at its cap off (``osqp_cap_retry_rho`` 0): the contrast above is measured on the
    solver that leaves the QP of 30 s at the cap. With the retry (3e-3, not on a cold start; the default since
    docs/robustness.md sec. 2.44) the nominal MPC's QPs of 30 s are answered (the first "maximum iterations reached",
    which fell back for 4 s, retried: 1000, solved inaccurate, taken; the second retried: 35, solved) and it scores
    363.1 C s (404.5 without), the term's MPC 345.6 (346.4 without): both lower, the term's gain 10 % -> 5 %, its
    nominal's solver failure no longer counted. Asserted with the retry: the term's MPC below 0.96 x the nominal's
    (measured 0.952) and neither run above its own without the retry."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import closed_loop_iae
    from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S
    from hvac_mpc.mpc.estimator import EkfSettings
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    term = DiscoveredTerm("heater_body_term", "heater_body", ("body_minus_inlet", "one"), (-0.2817, 0.1384),
                          "a heat loss of the body at the inlet air's temperature, about 0.28 W/K")
    refined = RefinedModel(Parameters(), ("ptc_power_fall", "fan_curve", "valve_leakage"), (term,),
                           absent=("bypass_flow",))
    sc = scenarios.select(["trapped_air_release"], quick=True)[0]
    settings = MpcSettings(initial_command=sc.initial_command, deadline_s=DETERMINISTIC_DEADLINE_S,
                           ekf=EkfSettings(r_supply_rest_c=0.0), osqp_cap_retry_rho=0.0)
    nominal = closed_loop_iae(sc, MpcController(settings=settings), "heater_wall_loss", seed=0)
    uncautious = dataclasses.replace(settings, start_rate_share=1.0)
    better = closed_loop_iae(sc, MpcController(settings=uncautious, model=refined), "heater_wall_loss", seed=0)
    assert better["temp_iae_cs"] < 0.9 * nominal["temp_iae_cs"], (better, nominal)
    assert better["flow_iae_m3"] < 1.05 * nominal["flow_iae_m3"], (better, nominal)  # not bought with flow
    cautious = closed_loop_iae(sc, MpcController(settings=dataclasses.replace(settings, start_rate_share=0.4), model=refined), "heater_wall_loss", seed=0)
    assert cautious["temp_iae_cs"] < nominal["temp_iae_cs"], (cautious, nominal)
    retry = {"osqp_cap_retry_rho": 3e-3, "osqp_cap_retry_on_cold_start": False}
    nominal_r = closed_loop_iae(sc, MpcController(settings=dataclasses.replace(settings, **retry)), "heater_wall_loss",
                                seed=0)
    better_r = closed_loop_iae(sc, MpcController(settings=dataclasses.replace(uncautious, **retry), model=refined),
                               "heater_wall_loss", seed=0)
    assert better_r["temp_iae_cs"] < 0.96 * nominal_r["temp_iae_cs"], (better_r, nominal_r)
    assert nominal_r["temp_iae_cs"] <= nominal["temp_iae_cs"] and better_r["temp_iae_cs"] <= better["temp_iae_cs"]


class _DeadTimeRecorder:
    """A controller that records its estimator's dead time (s) after every step, for a closed loop that only steps it."""

    def __init__(self, mpc: MpcController):
        self.mpc, self.dead_times_s = mpc, []

    def reset(self, command):
        self.mpc.reset(command)

    def step(self, measurement, reference):
        result = self.mpc.step(measurement, reference)
        self.dead_times_s.append(self.mpc.ekf.dead_time_s)
        return result


@pytest.mark.slow
def test_a_delay_in_the_model_file_spares_the_mpc_the_online_search():
    """The independent box with a 3 s transport delay (``delay_3s``), the MPC with a model file that names the
    delay (the thesis parameters otherwise) against the nominal MPC, which finds the dead time online: over the
    whole run, the unscored warm-up included, the file's delay removes the search's transient (measured 65.5
    against 83.8 C s with the identified file, docs/identification.md); on the scored part the two are level.
    Why level: the file's 3 s is honoured from the first sample and never moved, and the nominal MPC's search
    reaches the same 3 s before the scored part and stays there, so from then on both compare the reading at the
    same dead time (docs/identification.md, "delay_3s: where the file's delay counts")."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import closed_loop_iae
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    refined = RefinedModel(Parameters().replace(transport_delay_s=3.0), ("ptc_power_fall", "fan_curve", "valve_leakage"),
                           absent=("bypass_flow",))
    sc = scenarios.select(["summer_cooling_steps"], quick=True)[0]
    settings = MpcSettings(initial_command=sc.initial_command)
    searching = _DeadTimeRecorder(MpcController(settings=settings))
    told = _DeadTimeRecorder(MpcController(settings=settings, model=refined))
    nominal = closed_loop_iae(sc, searching, "delay_3s", seed=0)
    known = closed_loop_iae(sc, told, "delay_3s", seed=0)
    for r in (nominal, known):
        assert r["run_temp_iae_cs"] > r["temp_iae_cs"] > 0.0, r  # the warm-up adds its error to the scored part
    assert known["run_temp_iae_cs"] < 0.9 * nominal["run_temp_iae_cs"], (known, nominal)
    assert known["temp_iae_cs"] < 1.06 * nominal["temp_iae_cs"], (known, nominal)
    scored = int(sc.metrics_start_s)  # steps of 1 s
    assert set(told.dead_times_s) == {3.0}  # honoured from the first sample, never moved
    assert searching.dead_times_s[0] == 0.0 and set(searching.dead_times_s[scored:]) == {3.0}, searching.dead_times_s


def test_mpc_takes_the_refined_model_without_breaking_its_signature():
    refined = RefinedModel(Parameters().replace(tau_tc_s=7.0), ("ptc_power_fall", "fan_curve", "motor_asymmetry"),
                           (LOSS_TERM,))
    mpc = MpcController(model=refined)
    assert mpc.problem.model.terms == (LOSS_TERM,) and mpc.ekf.model.terms == (LOSS_TERM,)
    assert "motor_asymmetry" in mpc.problem.model.effects and mpc.params.tau_tc_s == 7.0
    assert MpcController().problem.model.terms == ()  # default unchanged


#: The box-inlet term identification adds on the recirculating box's 2 h log of seed 5 (15 % of 24 C cabin air drawn
#: in behind the inlet sensor, hvac_mpc.mismatch ``recirculation``): -0.1499 T_in + 3.600 C = 0.1499 (24.02 C - T_in).
RECIRCULATION_TERM = DiscoveredTerm("box_inlet_term", "box_in", ("inlet", "one"), (-0.1499, 3.600),
                                    "cabin air drawn into the box behind the inlet sensor")


def test_mpc_with_the_recirculation_term_tracks_the_recirculating_box_better_in_the_cabin_warm_up():
    """The box that draws 15 % of 24 C cabin air in behind its inlet sensor (``recirculation``, hvac_mpc.mismatch),
    the MPC with the box-inlet term of the seed-5 log (thesis parameters otherwise) against the nominal MPC, same
    noise, quick cabin_warmup_winter (inlet 1.4 C, the heater alone): the term says the air entering the box is
    3.4 C warmer than the inlet reading (the box's 15 % of (24 - 1.4) C), outside the log's inlet range (20-32 C)
    and right there, and the refined MPC heats without the nominal's offset lag: 30.7 against 39.1 C s measured
    (flow 0.023 against 0.032 m3). Where it does not hold (the
    heater-limited steps of trapped_air_release, whose warm-up asks for air below the entering air: the refined MPC
    cools it through the core and draws the heater body down before the step) docs/identification.md, "The
    recirculation traced again"."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import closed_loop_iae
    from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    sc = scenarios.select(["cabin_warmup_winter"], quick=True)[0]
    settings = MpcSettings(initial_command=sc.initial_command, deadline_s=DETERMINISTIC_DEADLINE_S)
    nominal = closed_loop_iae(sc, MpcController(settings=settings), "recirculation", seed=0)
    refined = RefinedModel(Parameters(), ("ptc_power_fall", "fan_curve", "valve_leakage"), (RECIRCULATION_TERM,),
                           absent=("bypass_flow",))
    known = closed_loop_iae(sc, MpcController(settings=settings, model=refined), "recirculation", seed=0)
    assert known["temp_iae_cs"] < 0.95 * nominal["temp_iae_cs"], (known, nominal)
    assert known["flow_iae_m3"] < 1.1 * nominal["flow_iae_m3"], (known, nominal)


# ------------------------------------------------------------------ end to end (slow)
_RESULTS: dict = {}


def identified(tmp_path_factory, variant, seed=11, duration_s=2400.0):
    """Identification of a 40 min log of ``variant`` (cached per session)."""
    if variant not in _RESULTS:
        path = tmp_path_factory.mktemp("logs") / f"{variant}.csv"
        simulate_log(path, variant, duration_s=duration_s, seed=seed)
        _RESULTS[variant] = identify(load(path), base_effects=DOCUMENTED_EFFECTS, quick=True)
    return _RESULTS[variant]


@pytest.mark.slow
def test_clean_log_gets_nothing_added(tmp_path_factory):
    res = identified(tmp_path_factory, "nominal")
    assert res.accepted == [] and res.terms == ()


@pytest.mark.slow
def test_clean_log_without_the_water_column_gets_nothing_and_the_supply_error_of_the_noise(tmp_path):
    """The nominal box logged without its water temperature: the model's water follows the chiller's two-point
    control, so the +-1 C cycling is explained by the nominal model and nothing is added (measured on the seed-23
    2 h log: 0.247 C held-out supply RMS before, 0.052 C, the noise, now; this 40 min log 0.855 and 0.083 C)."""
    path = tmp_path / "nowater.csv"
    simulate_log(path, "nominal", duration_s=2400.0, seed=11, omit=("water_temp_c",))
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS, quick=True)
    assert res.accepted == [] and res.terms == ()
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] < 0.15, e  # measured 0.083 C (the noise 0.05 C); 0.855 C with the water ramped to the set point


@pytest.mark.slow
def test_slower_chiller_without_the_water_column_is_named_and_halves_the_supply_error(tmp_path):
    """The box's chiller ramps at half the thesis's slopes (``chiller_slow``) and the log holds no water temperature:
    under the two-point control the nominal refit absorbs part of the slower water (k_p -38 % on the seed-23 2 h log)
    and the fit of the slopes from there is local, so ``chiller_asymmetry`` is screened from each of its grid points
    at the refit and at the starting parameters (measured on that log: nothing named, 1.649 C held-out RMS, before;
    named, 1.649 -> 0.051 C, now)."""
    path = tmp_path / "slow_nowater.csv"
    simulate_log(path, "chiller_slow", duration_s=2400.0, seed=11, omit=("water_temp_c",))
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS, quick=True, discover=False)
    assert "chiller_asymmetry" in [a.name for a in res.accepted]
    assert res.params.water_rise_rate_c_per_s == pytest.approx(0.5 * 0.00702, rel=0.2)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"], e


@pytest.mark.slow
def test_delay_is_named_and_halves_the_supply_error(tmp_path_factory):
    res = identified(tmp_path_factory, "delay_3s")
    assert [a.name for a in res.accepted] == ["transport_delay:supply_temp_c"]
    assert res.params.transport_delay_s == pytest.approx(3.0, abs=1.0)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"]


@pytest.mark.slow
def test_a_log_four_samples_late_is_moved_back_by_four_and_its_delay_is_the_box_s(tmp_path):
    """Outputs 4 samples late on a box with a 3 s delay: the timing check looked 3 samples either way, moved the log
    back by 3 and left one sample of the shift for the temperature's transport delay to take (4 s for the box's 3 s)."""
    path = tmp_path / "delay_shift4.csv"
    simulate_log(path, Variant(transport_delay_s=3.0, log_shift_samples=4), duration_s=2400.0, seed=11)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS, quick=True, discover=False)
    assert res.timing_shift_samples == 4
    assert any("4 sample(s) (4 s) late" in n for n in res.notes)
    assert [a.name for a in res.accepted] == ["transport_delay:supply_temp_c"]
    assert res.params.transport_delay_s == pytest.approx(3.0, abs=0.5)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"], e


@pytest.mark.slow
def test_a_large_duct_loss_keeps_its_term_and_no_heater_power_gain_the_box_does_not_have(tmp_path):
    """A 10 W/K duct loss (the sweep's ``duct_ua10``, seed 211, 2 h): the forward pass keeps a heater-power gain (the
    heater's share k_p bent to cover the loss in heating), then discovery adds the duct's term on that residual. The
    backward pass, the term's coefficients fixed, kept the gain (23 % of the heater power's held-out structure); with
    them refit beside it the gain costs 6 % and goes (measured: supply 1.512 -> 0.367 C with the gain, 0.301
    without)."""
    path = tmp_path / "duct_ua10.csv"
    simulate_log(path, Variant(duct_loss_ua_w_per_k=10.0), duration_s=7200.0, seed=211)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    assert [a.name for a in res.accepted] == []
    assert any(n.startswith("backward pass: output_gain:heater_power_w removed") for n in res.notes)
    assert [t.location for t in res.terms] == ["supply_air"]
    assert res.discovery["formula"] == res.terms[0].formula()  # the record carries the refit coefficients
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.25 * e["rms_before"], e


@pytest.mark.slow
def test_duct_loss_outside_the_library_is_added_as_a_term(tmp_path_factory, tmp_path):
    res = identified(tmp_path_factory, "duct_loss")
    assert len(res.terms) == 1 and res.discovery["accepted"]
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"]
    from hvac_mpc.identification.report import write_report
    files = write_report(res, tmp_path, plots=False)
    md = files["report"].read_text()
    assert "Discovered term" in md and "Formula" in md and "Residual tests on the held-out rows" in md
    summary = json.loads(files["summary"].read_text())
    assert summary["discovered_terms"][0]["formula"].startswith("dT_supply_air")
    assert load_refined_model(files["model"]).terms == res.terms


@pytest.mark.slow
def test_literal_cooler_fit_is_added_as_a_term_at_the_core_outlet(tmp_path_factory):
    """The box's core outlet does not depend on the inlet air (0.7564 T_w + 6.312): discovery puts the term
    before the split between heater path and bypass and finds the missing slope on the core inlet air."""
    res = identified(tmp_path_factory, "cooler_literal")
    cooler = [t for t in res.terms if t.location == "cooler_out"]
    assert len(cooler) == 1 and res.discovery["accepted"]
    c = dict(zip(cooler[0].features, cooler[0].coefficients))
    assert c.get("core_in") == pytest.approx(-(1.0 - Parameters().cooler_slope), abs=0.05)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"]


@pytest.mark.slow
def test_literal_cooler_fit_asked_for_is_named_as_the_thesis_fit(tmp_path):
    """The same box with the optional candidate ``cooler_literal_fit`` scored (the thesis fit as written): it is
    named with the box's slope and offset, and no term at the core outlet is needed; on the clean box it is not
    named (docs/identification.md, "The literal cooler as a library effect")."""
    for variant in ("cooler_literal", "nominal"):
        path = tmp_path / f"{variant}.csv"
        simulate_log(path, variant, duration_s=2400.0, seed=11)
        res = identify(load(path), base_effects=DOCUMENTED_EFFECTS, quick=True,
                       optional_candidates=("cooler_literal_fit",))
        if variant == "nominal":
            assert res.accepted == [] and res.terms == () and "cooler_literal_fit" in res.absent
            continue
        assert [a.name for a in res.accepted] == ["cooler_literal_fit"] and "cooler_literal_fit" in res.effects
        assert res.params.cooler_offset_c == pytest.approx(6.312, abs=0.3)
        assert res.params.cooler_slope == pytest.approx(0.7564, abs=0.02)
        assert not [t for t in res.terms if t.location == "cooler_out"]
        e = res.holdout_errors()["supply_temp_c"]
        assert e["rms_after"] <= 0.5 * e["rms_before"]


def test_optional_candidates_are_named_or_refused():
    """Only the named optional candidates join the library; an unknown name is refused with the allowed ones; the
    command line offers the same names."""
    from hvac_mpc.identification.candidates import OPTIONAL_CANDIDATES, library
    from hvac_mpc.identification.cli import OPTIONAL_CANDIDATE_NAMES

    outputs = ("supply_temp_c", "heater_outlet_temp_c")
    assert "cooler_literal_fit" not in [c.name for c in library(outputs)]
    assert "cooler_literal_fit" in [c.name for c in library(outputs, ("cooler_literal_fit",))]
    with pytest.raises(ValueError, match="allowed: \\['cooler_literal_fit'\\]"):
        library(outputs, ("cooler_literal",))
    assert OPTIONAL_CANDIDATE_NAMES == tuple(c.name for c in OPTIONAL_CANDIDATES)


def literal_cooler_model(tmp_path_factory):
    """The model file of issue 12's literal-cooler check (built once per test run): a 2 h log of the ``cooler_literal``
    box (the core outlet 0.7564 T_w + 6.312 whatever the inlet air, seed 5) identified with the default library."""
    if "cooler_literal_file" not in _RESULTS:
        folder = tmp_path_factory.mktemp("cooler_literal")
        path = folder / "cooler_literal.csv"
        simulate_log(path, "cooler_literal", duration_s=7200.0, seed=5)
        res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
        assert [t.location for t in res.terms] == ["cooler_out"]
        _RESULTS["cooler_literal_file"] = write_model_file(folder / "refined.toml", res.params, res.effects,
                                                           res.extras, res.terms, res.absent)
    return _RESULTS["cooler_literal_file"]


#: The noise seeds of the bench the literal-cooler check sums over.
LITERAL_COOLER_SEEDS = (0, 1, 2, 3)


@pytest.mark.slow
def test_refined_mpc_beats_the_nominal_mpc_on_the_literal_cooler_box_over_four_noise_sequences(tmp_path_factory):
    """Issue 12's check on the literal-cooler box (``cooler_literal``), what ``hvac-mpc bench --model FILE
    --model-plant cooler_literal`` runs: the identified model file (:func:`literal_cooler_model`) and the MPC with it
    against the nominal MPC through the eight full bench scenarios with the controller's defaults, same noise, the
    IAEs summed over the bench's noise seeds 0-3. With the optional ``cooler_literal_fit`` candidate the file has the
    exact core and the refined MPC loses (509.9 C s, 1.032 on seed 0; docs/identification.md, "The literal cooler as a
    library effect").

    Summed over seeds, not one seed (docs/robustness.md sec. 2.30, 2.44): one sequence's ratio scatters more than the
    bound's margin, with the start-up's caution or without (refined / nominal with ``start_rate_share`` 1: 0.990,
    0.982, 0.995, 0.999 for seeds 0-3; with the default 0.4: 1.011, 0.974, 0.991, 0.984, sums 1967.2 / 1987.6 C s,
    0.990, 29 November 2026); the sums do not. The refined MPC lower in at least 6 of the 8 scenarios' sums (not in
    winter and the cabin warm-up). The same check without the caution (``start_rate_share`` 1, sums 0.989-0.991 as
    measured) was a second test until 29 November 2026, which also asked the refined MPC to be lower on every one of
    the four seeds (0.990, 0.982, 0.995, 0.999); it ran the same 64 closed loops again (six minutes of the suite on a
    2-core machine) for a setting that is not the default, and no test asks for one seed's ratio now."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import compare

    model = literal_cooler_model(tmp_path_factory)
    chosen = scenarios.select(None, quick=False)
    runs = [compare(model, "cooler_literal", chosen, seed=seed) for seed in LITERAL_COOLER_SEEDS]
    _assert_pooled_below(runs)


def _assert_pooled_below(runs: list[dict]) -> None:
    """The literal-cooler check over noise seeds (``runs``: one :func:`~hvac_mpc.benchmarks.refined_model.compare`
    each): the refined MPC's IAE summed below 0.995 x the nominal's, and lower in at least 6 of the 8 scenarios'
    sums."""
    total = {k: sum(c["total"][k]["temp_iae_cs"] for c in runs) for k in ("nominal", "refined")}
    assert total["refined"] < 0.995 * total["nominal"], total
    per_scenario = {sc: {k: sum(c["scenarios"][sc][k]["temp_iae_cs"] for c in runs) for k in ("nominal", "refined")}
                    for sc in runs[0]["scenarios"]}
    lower = [sc for sc, r in per_scenario.items() if r["refined"] < r["nominal"]]
    assert len(lower) >= 6, per_scenario


@pytest.mark.slow
def test_thermocouple_seeing_the_heater_body_is_added_as_a_term(tmp_path_factory):
    """An effect outside the library the discovery was not shaped on (``tc_radiation``: the thermocouple reads
    3 % of the heater body's excess over the air): found as a supply-air term on the heater body's excess over
    the mixed air (docs/identification.md, "Effects the discovery was not shaped on")."""
    res = identified(tmp_path_factory, "tc_radiation")
    body = [t for t in res.terms if "body_minus_mix" in t.features]
    assert len(body) == 1 and res.discovery["accepted"]
    assert dict(zip(body[0].features, body[0].coefficients))["body_minus_mix"] == pytest.approx(0.03, abs=0.01)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"], e


@pytest.mark.slow
def test_mpc_with_the_refined_model_tracks_better_on_the_plant_with_the_effect(tmp_path_factory, tmp_path):
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import compare

    res = identified(tmp_path_factory, "duct_loss")
    path = write_model_file(tmp_path / "refined.toml", res.params, res.effects, res.extras, res.terms)
    chosen = scenarios.select(["flow_split_changes"], quick=True)
    cmp = compare(path, "duct_loss", chosen, seed=0)
    r = cmp["scenarios"]["flow_split_changes"]
    assert r["refined"]["temp_iae_cs"] < r["nominal"]["temp_iae_cs"], r


@pytest.mark.slow
def test_several_effects_together_are_found_and_the_refined_mpc_tracks_better(tmp_path_factory, tmp_path):
    """Delay, duct loss (with the cabin temperature logged) and the literal cooler fit in one 2 h log: the delay
    is named, the loss is added as a term on the cabin temperature, the supply error at least halves, and
    the MPC with the model file tracks the box better than the nominal MPC."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import compare

    # two hours: on a 40 min log the duct loss's residual hides the delay (it removes 3 % of the held-out
    # structure in the first round there)
    path = tmp_path / "combo.csv"
    simulate_log(path, "combo_delay_loss_cooler", duration_s=7200, seed=5)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    assert "transport_delay:supply_temp_c" in [a.name for a in res.accepted]
    assert res.params.transport_delay_s == pytest.approx(3.0, abs=1.0)
    assert len(res.terms) == 1 and "cabin_minus_mix_over_mass_flow" in res.terms[0].features
    # the duct's conductance as the box has it (3 W/K): the model's exchange form refit, not its linear first order
    # (2.42 W/K on this log when the model evaluated the term linearly: it stands for a smaller exchange at low flow)
    ua = dict(zip(res.terms[0].features, res.terms[0].coefficients))["cabin_minus_mix_over_mass_flow"] * 1007.0
    assert ua == pytest.approx(3.0, rel=0.1)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"]
    path = write_model_file(tmp_path / "refined.toml", res.params, res.effects, res.extras, res.terms)
    # the proband sequence (cooling, seven references): the nominal MPC finds the 3 s dead time itself
    # (mpc/dead_time.py), so what the model file adds here is the duct loss and the delay in the prediction
    # (measured 0.93 of the nominal MPC's IAE, 0.77 before the nominal MPC dropped the bypass split's flow
    # dependence the box does not have and gave the heater outlet reading its own offset, docs/robustness.md
    # sec. 1; on the cooling steps alone the two are level, 1.01)
    cmp = compare(path, "combo_delay_loss_cooler", scenarios.select(["proband_sequence"], quick=True), seed=0)
    r = cmp["scenarios"]["proband_sequence"]
    assert r["refined"]["temp_iae_cs"] < 0.97 * r["nominal"]["temp_iae_cs"], r


@pytest.mark.slow
def test_flow_dependent_bypass_is_named_and_its_model_makes_the_mpc_track_better(tmp_path_factory, tmp_path):
    """A box whose bypass split depends on the total flow (exponent 0.3, the independent simulator's own
    equation), an effect the thesis model and the nominal MPC leave out: identification names
    ``bypass_flow`` with its exponent, the supply error at least halves, and the MPC with the model file
    (the identified exponent as its prediction's) tracks the flow-split steps better than the nominal MPC."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import compare

    res = identified(tmp_path_factory, "bypass_flow")
    assert [a.name for a in res.accepted] == ["bypass_flow"]
    assert res.params.bypass_flow_exponent == pytest.approx(0.3, abs=0.05)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"]
    path = write_model_file(tmp_path / "refined.toml", res.params, res.effects, res.extras, res.terms,
                            absent=res.absent)
    chosen = scenarios.select(["flow_split_changes"], quick=True)
    r = compare(path, "bypass_flow", chosen, seed=0)["scenarios"]["flow_split_changes"]
    assert r["refined"]["temp_iae_cs"] < 0.6 * r["nominal"]["temp_iae_cs"], r  # 0.33 on the 2 h log


@pytest.mark.slow
@pytest.mark.parametrize("variant, also", [("valve_shift", ()), ("combo_tc_blower_valve", ("sensor_lag",))])
def test_shifted_valve_curves_are_named_and_halve_the_supply_and_flow_errors(tmp_path_factory, variant, also):
    """The box's valve curves moved 10 % of travel (``valve_shift``; with a slower thermocouple and a weaker blower
    in ``combo_tc_blower_valve``): before the model had a shift, nothing was named and the bypass exponent and the
    motor gain bent (seed 23: 0.270 C held-out supply RMS). Valve a's shift is named near 10 %, the outlet valves'
    on the flow, and the held-out supply and flow errors at least halve."""
    res = identified(tmp_path_factory, variant)
    names = [a.name for a in res.accepted]
    assert {"valve_shift:a", "valve_shift:outlets", *also} == set(names), names
    assert res.params.valve_a_shift_pct == pytest.approx(10.0, abs=2.0)
    assert min(res.params.valve_m_shift_pct, res.params.valve_f_shift_pct, res.params.valve_w_shift_pct) > 5.0
    for output in ("supply_temp_c", "volume_flow_m3s"):
        e = res.holdout_errors()[output]
        assert e["rms_after"] <= 0.5 * e["rms_before"], (output, e)


@pytest.mark.slow
def test_mpc_with_the_identified_valve_shifts_tracks_the_shifted_box_better(tmp_path_factory, tmp_path):
    """The model file of the ``valve_shift`` log in the MPC, on the box with the shifted valves: lower thermocouple
    IAE in the summer cooling steps and lower flow IAE in the flow-split changes than the nominal MPC (2 h log,
    every quick scenario: 531.7 against 543.8 C s, flow 0.85 against 1.10 m3; docs/identification.md)."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.refined_model import compare

    res = identified(tmp_path_factory, "valve_shift")
    path = write_model_file(tmp_path / "refined.toml", res.params, res.effects, res.extras, res.terms,
                            absent=res.absent)
    chosen = scenarios.select(["summer_cooling_steps", "flow_split_changes"], quick=True)
    r = compare(path, "valve_shift", chosen, seed=0)["scenarios"]
    cooling, split = r["summer_cooling_steps"], r["flow_split_changes"]
    assert cooling["refined"]["temp_iae_cs"] < cooling["nominal"]["temp_iae_cs"], cooling
    assert split["refined"]["flow_iae_m3"] < 0.5 * split["nominal"]["flow_iae_m3"], split


def _assert_cabin_share_at_the_box_inlet(res) -> None:
    """The one term is the cabin air drawn in at the box inlet, with the box's share (0.15)."""
    (term,) = res.terms
    share = dict(zip(term.features, term.coefficients))["cabin_minus_inlet"]
    assert term.location == "box_in" and share == pytest.approx(0.15, abs=0.03)


@pytest.mark.slow
def test_two_effects_that_mask_each_other_are_found_together(tmp_path):
    """The box draws 15 % cabin air behind the inlet sensor (outside the library), its valve curves act 10 % less
    open and the supply reading is 3 s late (``combo_recirc_delay_valve``, the 2 h log of seed 31). With the
    recirculation missing, valve a's shift makes the held-out supply error worse (the nominal refit has bent the
    bypass exponent from 1.3 to 1.02); with the shift missing, the cabin term at the box inlet does; forward
    selection named neither (0.652 -> 0.311 C). Screened as a pair they are kept together, each said to be
    identified only jointly, with the box's share (0.15) and shift (10 %), and the error falls to near the noise."""
    path = tmp_path / "combo_recirc_delay_valve.csv"
    simulate_log(path, "combo_recirc_delay_valve", duration_s=7200.0, seed=31)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    names = [a.name for a in res.accepted]
    assert {"valve_shift:a", "valve_shift:outlets", "transport_delay:supply_temp_c"} == set(names), names
    joint = next(a for a in res.accepted if a.name == "valve_shift:a")
    assert joint.jointly_with == "term box_inlet_term" and "only jointly" in joint.reason
    assert res.params.valve_a_shift_pct == pytest.approx(10.0, abs=2.0)
    _assert_cabin_share_at_the_box_inlet(res)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] < 0.2 * e["rms_before"], e
    from hvac_mpc.identification.report import write_report

    files = write_report(res, tmp_path / "out", plots=False)
    assert "Kept only jointly with valve_shift:a" in files["report"].read_text()
    (kept,) = [p for p in json.loads(files["summary"].read_text())["pairs"] if p["status"] == "accepted"]
    assert kept["members"] == ["valve_shift:a", "term box_inlet_term"]


@pytest.mark.slow
def test_three_effects_that_mask_each_other_are_found_by_the_joint_refit(tmp_path):
    """The same box on the 2 h log of seed 17: the delay removes just under 10 % of the supply's held-out structure,
    valve a's shift 8 %, ``bypass_flow`` (which the box does not have) is kept as a stand-in and the recirculation is
    missing; no pair passes, and forward selection named only the outlet shifts (0.397 -> 0.312 C). The joint refit
    of the kept effects and the last round's best candidates, eliminated backward, keeps the delay and valve a's
    shift and drops the stand-in; discovery then finds the cabin air at the box inlet."""
    path = tmp_path / "combo_recirc_delay_valve.csv"
    simulate_log(path, "combo_recirc_delay_valve", duration_s=7200.0, seed=17)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    names = {a.name for a in res.accepted}
    assert names == {"valve_shift:a", "valve_shift:outlets", "transport_delay:supply_temp_c"}, names
    assert "bypass_flow" not in res.effects
    assert res.joint["accepted"] and "bypass_flow" not in res.joint["kept"], res.joint
    assert res.params.valve_a_shift_pct == pytest.approx(10.0, abs=2.0)
    assert res.extras["supply_temp_c_delay_s"] == pytest.approx(3.0, abs=1.0)
    _assert_cabin_share_at_the_box_inlet(res)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"], e
    # the effects the joint refit added are one step, the term found after them its own
    steps = {st["added"]: st["holdout"]["supply_temp_c"] for st in res.steps}
    together = steps["transport_delay:supply_temp_c + valve_shift:a (refit together)"]
    term_step = steps["term box_inlet_term"]
    assert term_step["rms_before"] == pytest.approx(together["rms_after"])
    assert term_step["rms_after"] <= 0.5 * term_step["rms_before"], steps


@pytest.mark.slow
def test_the_joint_refit_takes_the_fourth_candidate_by_training_cost(tmp_path):
    """Seed 73 of the same box: valve a's shift is the fourth candidate of the last round by the training cost its
    screening step removed. With three in the joint set ``motor_asymmetry`` (the box has none) stayed as a stand-in
    for it and the recirculation (0.355 -> 0.192 C); with four the stand-in is eliminated, valve a's shift kept and
    the cabin air found at the box inlet."""
    path = tmp_path / "combo_recirc_delay_valve.csv"
    simulate_log(path, "combo_recirc_delay_valve", duration_s=7200.0, seed=73)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    assert {a.name for a in res.accepted} == {"valve_shift:a", "valve_shift:outlets",
                                              "transport_delay:supply_temp_c"}, res.joint
    assert res.joint["accepted"] and res.joint["members"][-1] == "valve_shift:a", res.joint
    assert "motor_asymmetry" in res.joint["members"] and "motor_asymmetry" not in res.effects
    assert res.params.valve_a_shift_pct == pytest.approx(10.0, abs=2.0)
    (term,) = res.terms
    assert term.location == "box_in"
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"], e

@pytest.mark.slow
def test_a_pairs_stand_in_term_is_replaced_by_the_recirculation_in_the_joint_refit(tmp_path):
    """Seed 79 of the same box: the pair step keeps valve a's shift only jointly with a four-feature term on the mixed
    supply air, a stand-in for the recirculation found on the residual of a model without the shift (0.420 -> 0.194 C).
    The term was chosen with its partner missing, so the joint refit runs after the pair: the effects refit together
    without it, discovery then finds the cabin air at the box inlet, the box's 15 %, and the report says which term it
    replaced and that valve a's shift is no longer kept only jointly."""
    path = tmp_path / "combo_recirc_delay_valve.csv"
    simulate_log(path, "combo_recirc_delay_valve", duration_s=7200.0, seed=79)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    assert {a.name for a in res.accepted} == {"valve_shift:a", "valve_shift:outlets",
                                              "transport_delay:supply_temp_c"}, res.notes
    assert [p["status"] for p in res.pairs] == ["accepted"] and "term supply_residual_term" in res.pairs[0]["members"]
    assert res.joint["accepted"], res.joint
    (replaced,) = res.joint["replaced_terms"]
    assert replaced["location"] == "supply_air"
    valve_a = next(a for a in res.accepted if a.name == "valve_shift:a")
    assert valve_a.jointly_with == "" and "kept in the joint refit without the term" in valve_a.reason
    assert res.params.valve_a_shift_pct == pytest.approx(10.0, abs=2.0)
    _assert_cabin_share_at_the_box_inlet(res)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.25 * e["rms_before"], e


@pytest.mark.slow
def test_an_effect_a_later_term_explains_is_dropped(tmp_path):
    """The heater body loses 0.3 W/K to the box walls (``heater_wall_loss``, outside the library; the 2 h log of
    seed 5). Before the term discovery runs, the flow-dependent bypass split (``bypass_flow``, which this box does
    not have) is kept as a stand-in; the heater-body term then explains the loss and the exponent goes to about 0.
    The backward pass re-tests the lone effect with the term in and drops it: the model file names only the term
    (before: ``bypass_flow`` with exponent -0.002 beside the term)."""
    path = tmp_path / "wall_loss.csv"
    simulate_log(path, "heater_wall_loss", duration_s=7200.0, seed=5)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    assert res.accepted == [], [a.name for a in res.accepted]
    assert "bypass_flow" not in res.effects
    assert any(n.startswith("backward pass: bypass_flow removed") for n in res.notes), res.notes
    (term,) = res.terms
    assert term.location == "heater_body"
    assert dict(zip(term.features, term.coefficients))["body_minus_inlet"] == pytest.approx(-0.3, abs=0.05)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"], e


#: The documented physics without the PTC power fall: identification must find the fall itself.
WITHOUT_PTC = tuple(e for e in DOCUMENTED_EFFECTS if e != "ptc_power_fall")


@pytest.mark.slow
def test_weaker_heater_is_named_as_a_gain_on_its_power_and_a_lower_kp(tmp_path):
    """The box's heater draws 85 % of the model's power (``heater_weak``). The logged heater power has no
    parameter to move, and its misfit (15 W against a noise of about 1 W) held the nominal refit's k_p near the
    thesis value (seed 23: held-out supply RMS 0.234 C, nothing added). With a gain on the heater power among
    the candidates (scored jointly with the nominal parameters), the gain is named, k_p moves by -15 % and the
    supply error falls to the noise."""
    path = tmp_path / "weak.csv"
    simulate_log(path, "heater_weak", duration_s=7200, seed=23)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    assert [a.name for a in res.accepted] == ["output_gain:heater_power_w"]
    assert res.extras["heater_power_w_gain"] == pytest.approx(0.85, abs=0.02)
    kp = next(c for c in res.parameter_confidence if c["name"] == "heater_kp")
    assert kp["moved"] and kp["change"] == pytest.approx(-0.15, abs=0.03)
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.5 * e["rms_before"]
    from hvac_mpc.identification import load_identification_extras
    from hvac_mpc.identification.report import write_report
    files = write_report(res, tmp_path / "out", plots=False)
    assert "output_gain:heater_power_w" in files["report"].read_text()
    assert load_identification_extras(files["model"])["heater_power_w_gain"] == pytest.approx(0.85, abs=0.02)


@pytest.mark.slow
@pytest.mark.parametrize("variant, seed", [("nominal", 31), ("heater_weak", 31), ("heater_weak", 41)])
def test_ptc_power_fall_is_named_on_a_log_that_runs_the_heater_hot(tmp_path, variant, seed):
    """The box's PTC heater draws less once its body passes ~60 C. On a log whose heating phases run the heater
    near full power at low flow (the ``hot_heater`` excitation), identification started without the fall names
    ``ptc_power_fall`` with a knee near the box's 60 C and at least halves the held-out supply error (or brings
    it to the noise), alone and with a weaker heater (then with the gain on the heater power too). Seed 41: the
    gain kept in the first round had taken up part of the fall; refit with the later candidates it leaves the
    fall to ``ptc_power_fall`` (before: the fall not named, supply 0.094 -> 0.093 C)."""
    path = tmp_path / "hot.csv"
    simulate_log(path, variant, duration_s=7200, seed=seed, excitation="hot_heater")
    res = identify(load(path), base_effects=WITHOUT_PTC)
    names = [a.name for a in res.accepted]
    assert "ptc_power_fall" in names and "ptc_power_fall" in res.effects
    assert res.params.ptc_knee_c == pytest.approx(60.0, abs=10.0)
    if variant == "heater_weak":
        assert "output_gain:heater_power_w" in names
    else:
        assert names == ["ptc_power_fall"]
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= max(0.5 * e["rms_before"], 1.1 * res.sigma["supply_temp_c"]), e


def test_mpc_runs_with_a_discovered_term_at_every_place():
    """Terms at the four places discovery uses (supply air, heater body, the air entering the box, the core outlet)
    build into the MPC's prediction and estimator, and it controls the independent box with them: 40 steps of the
    winter heating scenario's start (10 s warm-up, 30 s of the first step), no fallback, finite commands; the trapped-air guard reads the heater inlet
    through the model when a term sits before the heater (a box-inlet term)."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.simulate import simulate
    from hvac_mpc.mismatch import make_plant
    from hvac_mpc.mpc.mpc_controller import MpcSettings

    terms = (DiscoveredTerm("radiation", "supply_air", ("body_minus_mix",), (0.03,)),
             DiscoveredTerm("wall_loss", "heater_body", ("body_minus_inlet",), (-0.28,)),
             DiscoveredTerm("recirculation", "box_in", ("inlet", "one"), (-0.15, 3.6)),
             DiscoveredTerm("literal_cooler", "cooler_out", ("core_in", "one"), (-0.24, 6.3)))
    sc = dataclasses.replace(scenarios.winter_heating_steps(), quick_warmup_s=10.0, quick_segment_s=30.0,
                             quick_segments=1).quick()
    ctrl = MpcController(settings=MpcSettings(initial_command=sc.initial_command, deadline_s=3600.0),
                         model=RefinedModel(terms=terms))
    trace = simulate(sc, ctrl, Parameters(), seed=3, plant=make_plant("nominal", seed=3))
    assert len(trace.fallback) == 40 and np.all(np.isfinite(trace.applied)) and trace.fallback == [None] * len(trace.fallback)
    assert {t.location for t in ctrl.problem.model.terms} == {"supply_air", "heater_body", "box_in", "cooler_out"}
    # the estimator and the reachable-flow problem predict with the same terms
    assert ctrl.ekf.model.terms == ctrl.reach.model.terms == ctrl.problem.model.terms == terms
    inlet_only = MpcController(model=RefinedModel(terms=terms[2:3]))
    assert inlet_only._heater_inlet is not None and inlet_only._heater_body_rate is None
    body_only = MpcController(model=RefinedModel(terms=terms[1:2]))
    assert body_only._heater_inlet is None and body_only._heater_body_rate is not None


def test_trapped_air_guard_reads_the_literal_cooler_fit_of_a_model_file():
    """With the effect ``cooler_literal_fit`` the trapped-air guard's heater inlet is the thesis fit as written,
    0.7564 T_w + 6.312 C (the thesis's cooler fit), whatever the air entering the core; without it, the
    effectiveness form, which follows the inlet air."""
    def inlet_c(ctrl, inlet_temp_c, water_temp_c=5.0):
        m = ctrl.problem.model
        x = m.states.vector({"motor_rise_c": 1.0, "water_temp_c": water_temp_c, "heater_temp_c": 30.0,
                             "supply_sensor_c": 15.0})
        u = m.inputs.vector({"blower_power_w": 60.0, "heater_cmd_w": 0.0, "valve_a_pct": 50.0, "valve_m_pct": 100.0,
                             "valve_f_pct": 100.0, "valve_w_pct": 100.0})
        d = m.disturbances.vector({"inlet_temp_c": inlet_temp_c, "chiller_setpoint_c": 5.0, "mix_offset_c": 0.0,
                                   "flow_offset_m3s": 0.0})
        if ctrl._heater_inlet is None:
            return None
        return float(ctrl._heater_inlet(x, u, d))
    literal = MpcController(model=RefinedModel(effects=("cooler_literal_fit",)))
    p = literal.problem.model.params
    for t_in in (5.0, 20.0, 32.0):
        assert inlet_c(literal, t_in) == pytest.approx(p.cooler_slope * 5.0 + p.cooler_offset_c, abs=1e-9)
    assert inlet_c(MpcController(), 20.0) is None  # the nominal model: the cooler equation the guard reads itself


@pytest.mark.slow
def test_two_effects_outside_the_library_at_two_places_get_a_term_each(tmp_path):
    """The box draws 20 % cabin air behind the inlet sensor and its duct loses heat to the cabin (UA 3 W/K), both
    outside the library and at two places (the air entering the box, the supply air after mixing; the 2 h log of seed
    211, magnitudes of no fixed variant). One term per log took the duct loss and left the recirculation: 0.775 ->
    0.348 C held-out supply RMS (0.45). Discovery runs again at the places without a term: the box-inlet term takes
    the cabin air with about the box's share, and the error falls to a quarter."""
    path = tmp_path / "recirc_duct.csv"
    simulate_log(path, Variant(recirculation_share=0.2, duct_loss_ua_w_per_k=3.0), duration_s=7200.0, seed=211)
    res = identify(load(path), base_effects=DOCUMENTED_EFFECTS)
    places = {t.location: dict(zip(t.features, t.coefficients)) for t in res.terms}
    assert set(places) == {"supply_air", "box_in"}, res.terms
    assert places["supply_air"].get("cabin_minus_mix_over_mass_flow", 0.0) > 0.0  # heat from the cabin into the duct
    box_in = places["box_in"]
    share = box_in.get("cabin_minus_inlet", -box_in.get("inlet", 0.0))  # 0.2 (T_cabin - T_in), or -0.2 T_in + const
    assert share == pytest.approx(0.2, abs=0.05), box_in
    assert len(res.discovery["further"]) == 1 and res.discovery["further"][0]["location"] == "box_in"
    e = res.holdout_errors()["supply_temp_c"]
    assert e["rms_after"] <= 0.3 * e["rms_before"], e  # measured 0.775 -> 0.181 C; one term: 0.348 C
