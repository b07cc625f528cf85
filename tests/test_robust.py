"""Robust MPC (issue 11): priorities with a flow out of reach, the transport delay in the model, the
benchmark's plant seam, the settle-time yardstick. Plants that check robustness come from the
independent simulator (``hvac_mpc.mismatch``), never from the model with a switch.

Budget: the fast tests a few seconds together; the closed loops are marked slow.
"""

import dataclasses
import functools

import numpy as np
import pytest

from hvac_mpc import cli
from hvac_mpc.benchmarks import bench, metrics, mismatch_suite, plant_seam, scenarios as S
from hvac_mpc.benchmarks.simulate import simulate
from hvac_mpc.contract import Command, Reference, StepResult
from hvac_mpc.mismatch import Variant, make_plant
from hvac_mpc.models import HvacModel, Parameters
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.priorities import ReachableFlow

M3H = 1 / 3600


class HoldController:
    """Stand-in: holds a fixed command (Controller protocol)."""

    dt_s = 1.0

    def __init__(self, command: Command | None = None):
        self.command = command or Command(150.0, 0.0, 60.0, 100.0, 100.0, 100.0)

    def reset(self) -> None:
        pass

    def step(self, measurement, reference) -> StepResult:
        return StepResult(Command(**self.command.as_dict()), {"fallback": None, "mode": "cooling"})


class ReadOnlyPlant:
    """A plant with apply/advance/read only (no truth, no settle): the independent box behind a narrow door."""

    def __init__(self, seed: int = 0, dt_s: float = 1.0):
        self._box = make_plant("delay_3s", seed=seed, dt_s=dt_s)
        self.dt_s = dt_s
        self.applied = 0

    def apply(self, command):
        self.applied += 1
        return self._box.apply(command)

    def advance(self):
        self._box.advance()

    def read(self):
        return self._box.read()


def read_only_plant(seed: int = 0, dt_s: float = 1.0) -> ReadOnlyPlant:
    return ReadOnlyPlant(seed, dt_s)


def not_a_plant(seed: int = 0):
    return object()


def short_cooling_step() -> S.Scenario:
    """Summer conditions, 20 -> 15 C at 90 m3/h: 30 s warm-up, 60 s scored."""
    sc = S.summer_cooling_steps()
    return S.Scenario(name="short_cooling_step", description="one cooling step", seed=sc.seed, kind="cooling",
                      inlet_temp_c=sc.inlet_temp_c, chiller_setpoint_c=sc.chiller_setpoint_c,
                      initial_command=sc.initial_command, warmup=S.Segment(30.0, sc.warmup.reference),
                      segments=(S.Segment(60.0, sc.segments[0].reference),))


# ---------------------------------------------------------------------------- plant seam
def test_plant_spec_errors_are_clear():
    with pytest.raises(plant_seam.InvalidPlant, match="MODULE:FACTORY"):
        plant_seam.load_factory("no_colon_here")
    with pytest.raises(plant_seam.InvalidPlant, match="cannot import module 'no_such_module_xyz'"):
        plant_seam.load_factory("no_such_module_xyz:make")
    with pytest.raises(plant_seam.InvalidPlant, match="has no attribute 'nope'"):
        plant_seam.load_factory("hvac_mpc.mismatch:nope")
    with pytest.raises(plant_seam.InvalidPlant, match=r"lacks \['apply', 'advance', 'read'\]"):
        plant_seam.build_plant(not_a_plant, seed=0, dt_s=1.0)
    with pytest.raises(plant_seam.InvalidPlant, match="sample time"):
        plant_seam.build_plant(lambda seed: make_plant("nominal", seed=seed, dt_s=2.0), seed=0, dt_s=1.0)
    assert plant_seam.load_factory("hvac_mpc.mismatch:make_plant") is make_plant


def test_cli_rejects_a_bad_plant_spec(tmp_path, capsys):
    code = cli.main(["bench", "--quick", "--scenario", "summer_cooling_steps", "--out", str(tmp_path / "b"),
                     "--plant", "hvac_mpc.mismatch:no_factory"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--plant" in err and "no_factory" in err
    assert not (tmp_path / "b").exists()


def test_simulate_on_a_plant_without_truth_falls_back_to_the_readings():
    sc = short_cooling_step()
    plant = plant_seam.build_plant(read_only_plant, seed=1, dt_s=1.0)
    tr = simulate(sc, HoldController(sc.initial_command), Parameters(), seed=1, plant=plant)
    assert plant.applied == int(sc.duration_s) + 1  # the initial command (no settle) and one per sample
    # figures come from the sensor readings: the supply reading is noisy, so not the noise-free value
    assert np.all(np.isfinite(tr.truth["supply_temp_c"])) and np.std(np.diff(tr.truth["supply_temp_c"])) > 0.01
    assert np.all(np.isnan(tr.truth["heater_temp_c"]))
    assert tr.truth["supply_air_temp_c"] == pytest.approx(tr.truth["supply_temp_c"])


def test_run_benchmark_on_mismatch_variants_through_the_seam():
    sc = short_cooling_step()
    factories = {"baseline": lambda c: HoldController(c), "mpc": lambda c: HoldController(c)}
    res, tr = bench.run_benchmark([sc], factories, seed=0, plant_factory=functools.partial(make_plant, "delay_5s"),
                                  plant_name="hvac_mpc.mismatch:make_plant")
    assert res["meta"]["plant"] == "hvac_mpc.mismatch:make_plant" and res["meta"]["perturbation"] == []
    run = tr[sc.name]["mpc"]
    # the independent box started at rest for the scenario's command in its environment
    assert run.applied[0] == pytest.approx(sc.initial_command.vector())
    assert abs(run.truth["supply_temp_c"][0] - run.truth["supply_temp_c"][5]) < 0.2
    assert res["scenarios"][sc.name]["ratios"]["temp_iae_cs"] == pytest.approx(1.0)


# ---------------------------------------------------------------------------- yardstick
def test_in_band_share_and_settle_time():
    r = np.array([20.0] * 5 + [15.0] * 10)
    y = np.array([20.0] * 5 + [19, 17, 15.3, 15.2, 15.9, 15.1, 15.0, 15.0, 15.0, 15.0])
    out = metrics.in_band_after_settling(y, r, 1.0, 0.5)
    assert out["settle_times_s"] == [2.0]  # first inside +-0.5 two samples after the step
    # before the step: 5 of 5 inside; after settling: 7 of 8 inside (15.9 is out)
    assert out["share"] == pytest.approx(12 / 13)
    never = metrics.in_band_after_settling(np.full(6, 10.0), np.array([10.0] * 3 + [12.0] * 3), 1.0, 0.5)
    assert never["settle_times_s"] == [None] and never["share"] == pytest.approx(1.0)


# ---------------------------------------------------------------------------- model delay
def test_transport_delay_becomes_a_lag_chain_in_the_model():
    plain = HvacModel(Parameters())
    delayed = HvacModel(Parameters().replace(transport_delay_s=3.0))
    assert plain.delay_states == () and len(delayed.delay_states) == 3
    u = np.array([150.0, 0.0, 50.0, 100.0, 100.0, 100.0])
    d = plain.d_vector(32.0, 5.0)
    x0p, x0d = plain.steady_state(u, d), delayed.steady_state(u, d)
    sensor = plain.states.index("supply_sensor_c")
    # same rest state of the thermocouple; after a step of valve a the delayed reading moves later
    assert x0d[delayed.states.index("supply_sensor_c")] == pytest.approx(x0p[sensor], abs=1e-6)
    u2 = u.copy()
    u2[2] = 90.0
    xp, xd = x0p.copy(), x0d.copy()
    moved_p, moved_d = [], []
    for _ in range(4):
        xp = np.asarray(plain.step(xp, u2, d, plain.p_default)).ravel()
        xd = np.asarray(delayed.step(xd, u2, d, delayed.p_default)).ravel()
        moved_p.append(abs(xp[sensor] - x0p[sensor]))
        moved_d.append(abs(xd[delayed.states.index("supply_sensor_c")] - x0p[sensor]))
    assert moved_d[0] < 0.25 * moved_p[0] and moved_d[-1] < moved_p[-1]


# ---------------------------------------------------------------------------- priorities
def test_reachable_flow_names_an_unreachable_total_flow():
    params = Parameters()
    ctrl = MpcController(params, MpcSettings())
    pb = ctrl.problem
    reach = ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, params)
    u = np.array([300.0, 0.0, 60.0, 100.0, 100.0, 100.0])
    d = pb.model.d_vector(32.0, 5.0)
    x = pb.model.steady_state(u, d)
    far = reach.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0)
    assert set(far.out_of_reach) == {"volume_flow_m3s"}
    short = far.out_of_reach["volume_flow_m3s"]
    assert 0.0 < short < 200 * M3H and far.flow_m3s < 200 * M3H
    reach.reset()
    near = reach.check(x, u, d, 18.0, 150 * M3H, 100.0, 1.0)
    assert near.out_of_reach == {} and near.flow_m3s is None
    # a low flow is not in doubt: no problem solved
    reach.reset()
    assert reach.check(x, u, d, 18.0, 60 * M3H, 100.0, 1.0).out_of_reach == {}


@functools.lru_cache(maxsize=1)
def _default_problem():
    return MpcController(Parameters(), MpcSettings()).problem


def _reach_setup(flow_offset_m3h: float = 0.0, outlets=(100.0, 24.0, 40.0)):
    """The MPC's model at rest at full blower (32 C inlet, water 5 C) with a flow offset, and a
    fresh ReachableFlow on it."""
    params = Parameters()
    pb = _default_problem()
    u = np.array([300.0, 0.0, 57.0, *outlets])
    d = np.array(pb.model.d_vector(32.0, 5.0), float).ravel()
    d[pb.model.disturbances.index("flow_offset_m3s")] = flow_offset_m3h * M3H
    x = pb.model.steady_state(u, d)
    return ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, params), x, u, d


def test_out_of_reach_flow_stays_latched_when_only_the_temperature_reference_changes():
    reach, x, u, d0 = _reach_setup()
    assert "volume_flow_m3s" in reach.check(x, u, d0, 18.0, 200 * M3H, 100.0, 1.0).out_of_reach
    # the estimator's flow offset moves the model's reachable flow above the reference (as the offsets
    # do once they absorb what the box does differently), and the temperature reference changes
    _, x1, _, d1 = _reach_setup(15.0)
    again = reach.check(x1, u, d1, 16.0, 200 * M3H, 100.0, 1.0)
    assert reach._reachable > 200 * M3H  # the model alone would call it reachable now
    assert "volume_flow_m3s" in again.out_of_reach and again.flow_m3s < 200 * M3H
    # a new flow reference is judged afresh
    lower = reach.check(x1, u, d1, 16.0, 195 * M3H, 100.0, 1.0)
    assert lower.out_of_reach == {} and lower.flow_m3s is None


def test_blower_at_full_power_short_of_the_flow_latches_it_out_of_reach():
    reach, x, u, d = _reach_setup(15.0, outlets=(100.0, 10.0, 20.0))
    ref = 200 * M3H
    assert float(reach.out(x, u, d)[0][0]) < 0.98 * ref  # the box delivers less than the reference
    answers = [reach.check(x, u, d, 18.0, ref, 100.0, 1.0) for _ in range(6)]
    assert reach._reachable > ref  # the model calls it reachable throughout
    first_latched = next(k for k, a in enumerate(answers) if a.out_of_reach)
    assert first_latched == int(reach.saturated_s) - 1  # after saturated_s seconds of evidence
    assert answers[-1].flow_m3s == pytest.approx(0.98 * ref)
    # the same state with the blower below full power is no evidence
    reach.reset()
    u_low = u.copy()
    u_low[0] = 250.0
    assert all(not reach.check(x, u_low, d, 18.0, ref, 100.0, 1.0).out_of_reach for _ in range(6))


def test_heater_off_bound_relaxes_towards_the_air_with_the_heater_time_constant():
    from hvac_mpc.models import heater
    from hvac_mpc.mpc.ocp import HeaterOffBound

    params = Parameters()
    bound = HeaterOffBound(params, 1.0)
    mass_flow = 0.04
    tau = float(heater.time_constant_s(mass_flow, params))
    # heater on: the estimate stands
    assert bound.update(60.0, 12.0, 200.0, mass_flow) == 60.0
    # heater off from here; an estimate that stays 20 C above the air is bounded by the relaxation
    used = [bound.update(32.0, 12.0, 0.0, mass_flow) for _ in range(int(3 * tau))]
    assert used[0] == 32.0  # min(estimate, 12 + 48 exp(-1/tau))
    assert used[-1] - 12.0 == pytest.approx(48.0 * np.exp(-int(3 * tau) / tau), rel=1e-9)
    assert used[-1] - 12.0 < 5.0  # below the guard's warm threshold: valve a is free again
    # a falling air temperature is followed with the lag, not instantly
    assert bound.update(32.0, 8.0, 0.0, mass_flow) > 8.0 + (used[-1] - 12.0)
    # switching the heater on again trusts the estimate at once
    assert bound.update(45.0, 8.0, 100.0, mass_flow) == 45.0


@pytest.mark.slow
def test_unreachable_flow_keeps_the_supply_temperature_and_reports_the_shortfall():
    sc = S.flow_out_of_reach().quick()
    ctrl = bench.mpc_factory()(sc.initial_command)
    plant = make_plant("nominal", seed=2)
    tr = simulate(sc, ctrl, Parameters(), seed=2, plant=plant)
    steady = mismatch_suite.out_of_reach_steady(tr, sc)
    assert steady["steady_temp_error_max_c"] <= 0.3
    assert steady["steady_samples_reported"] >= 25
    last = tr.out_of_reach[-1]
    ref = sc.segments[0].reference.volume_flow_m3s
    # the reported shortfall is what the plant really misses, within a few m3/h
    missing = ref - tr.truth["volume_flow_m3s"][-10:].mean()
    assert last["volume_flow_m3s"] == pytest.approx(missing, abs=6 * M3H)
    assert all(f is None for f in tr.fallback)


@pytest.mark.slow
def test_mpc_told_of_a_3_s_delay_holds_a_cooling_step_on_the_delayed_box():
    sc = short_cooling_step()
    told = Parameters().replace(transport_delay_s=3.0)
    factories = {"baseline": bench.baseline_factory(), "mpc": lambda c: MpcController(told, MpcSettings(initial_command=c))}
    plant = functools.partial(make_plant, "delay_3s")
    res, _ = bench.run_benchmark([sc], factories, seed=0, plant_factory=plant)
    r = res["scenarios"][sc.name]
    unaware, _ = bench.run_benchmark([sc], {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()}, seed=0,
                                     plant_factory=plant)
    iae_told = r["mpc"]["figures"]["temp_iae_cs"]
    iae_unaware = unaware["scenarios"][sc.name]["mpc"]["figures"]["temp_iae_cs"]
    # told of the delay, the MPC does as well as when its estimator finds the dead time itself (the
    # estimate then is the dead time beyond the model's, none here, so the two are not added up) ...
    assert abs(iae_told - iae_unaware) <= 0.15 * iae_unaware
    # ... and comes within 15 % of the baseline's IAE (1.13 measured with the valves' former 20 %/s, 1.07
    # before the prediction dropped the bypass split's flow dependence and the heater outlet reading got its
    # own offset, docs/robustness.md sec. 1 and 2.3; README, Robustness)
    assert r["ratios"]["temp_iae_cs"] <= 1.15
    assert r["mpc"]["figures"]["fallbacks"] == 0 and r["mpc"]["figures"]["violations_total"] == 0


def test_cooling_step_on_the_independent_box_beats_the_baseline_by_more_than_a_third():
    """docs/robustness.md sec. 2.3: the valves' rate limit (50 %/s) and the reading-heavy tracked temperature
    (sensor share 0.75) let the MPC hurry the thermocouple at a step. Measured on this step (20 -> 15 C): 0.57
    of the baseline's IAE; with the former 20 %/s 0.70, with the former share 0.5 0.645."""
    sc = short_cooling_step()
    res, _ = bench.run_benchmark([sc], {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()}, seed=0,
                                 plant_factory=functools.partial(make_plant, "nominal"))
    r = res["scenarios"][sc.name]
    assert r["ratios"]["temp_iae_cs"] <= 0.62
    assert r["mpc"]["figures"]["fallbacks"] == 0 and r["mpc"]["figures"]["violations_total"] == 0


@pytest.mark.slow
def test_cli_bench_runs_on_a_plant_from_module_and_factory(tmp_path, capsys):
    out = tmp_path / "bench"
    code = cli.main(["bench", "--quick", "--scenario", "summer_cooling_steps", "--no-plots", "--out", str(out),
                     "--plant", "test_robust:read_only_plant"])
    assert code == 0
    text = (out / "report.md").read_text()
    assert "test_robust:read_only_plant" in text
    assert "summer_cooling_steps" in capsys.readouterr().out


def test_cli_rejects_a_missing_mpc_parameter_file(tmp_path, capsys):
    code = cli.main(["bench", "--quick", "--scenario", "summer_cooling_steps", "--out", str(tmp_path / "b"),
                     "--mpc-params", str(tmp_path / "missing.toml")])
    assert code == 2
    assert "--mpc-params" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_suite_summary_names_the_worst_cell_and_judges_the_checks():
    def cell(t, fallbacks=0, steady=None):
        c = {"temp_iae_cs": t, "flow_iae_m3": 0.5, "energy_wh": 0.9, "fallback_storm": fallbacks > 10,
             "mpc_violations": 0}
        if steady is not None:
            c["mpc_steady"] = {"steady_temp_error_max_c": steady, "steady_samples_reported": 30}
        return c
    matrix = {"nominal": {"a": cell(0.6), "b": cell(0.5), "flow_out_of_reach": cell(0.7, steady=0.1)},
              "delay_3s": {"a": cell(1.3), "b": cell(0.6), "flow_out_of_reach": cell(0.8, steady=0.4)}}
    s = mismatch_suite.summarise(matrix)
    assert s["temp_iae_cs"]["worst"] == 1.3 and s["temp_iae_cs"]["worst_cell"] == "delay_3s / a"
    assert s["temp_iae_cs"]["median"] == pytest.approx(0.65)
    checks = s["checks"]
    assert not checks["temperature ratio <= 1.0 in every cell"] and checks["temperature ratio median <= 0.7"]
    assert checks["no fallback storm"] and checks["no constraint violation (MPC)"]
    assert not checks["flow out of reach: steady supply temperature within 0.3 C"]
    assert checks["flow out of reach: reported in steady state (where not reached)"]


@pytest.mark.slow
def test_daemon_status_names_an_unreachable_flow_reference(tmp_path):
    from hvac_mpc.daemon.config import config_from_mapping
    from hvac_mpc.daemon.loop import Daemon

    cfg = config_from_mapping({
        "loop": {"speedup": "max", "max_ticks": 40, "deadline_s": 30.0},
        "log": {"path": str(tmp_path / "log.csv"), "fsync": False}, "api": {"enabled": False},
        "controller": {"name": "mpc"}, "backend": {"simulated": {"inlet_temp_c": 32.0}},
        "safety": {"cooldown_max_s": 5.0, "cooldown_min_s": 1.0},
        "reference": {"supply_temp_c": 18.0, "volume_flow_m3s": 200 * M3H}})
    seen = []
    daemon = Daemon(cfg, tick_hook=lambda d, sample: seen.append(d.status()["out_of_reach"]))
    daemon.run()
    reported = [s for s in seen if s]
    assert reported and set(reported[-1]) == {"volume_flow_m3s"}
    assert 0.0 < reported[-1]["volume_flow_m3s"] < 200 * M3H


@pytest.mark.slow
def test_flow_out_of_reach_on_a_weak_blower_keeps_the_temperature_as_well_as_the_baseline():
    """The whole out-of-reach scenario (200 m3/h at 18 C, at 16 C, then 90 m3/h) on the independent box
    with a blower 20 % weaker than the controllers' model: steady supply temperature within 0.3 C and a
    thermocouple IAE no worse than the thesis baseline's."""
    sc = S.flow_out_of_reach()
    factory = mismatch_suite.variant_factory("blower_weak")
    res, tr = bench.run_benchmark([sc], {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()}, 0,
                                  plant_factory=factory)
    cell = res["scenarios"][sc.name]
    steady = mismatch_suite.out_of_reach_steady(tr[sc.name]["mpc"], sc)
    assert steady["steady_temp_error_max_c"] <= 0.3
    assert steady["steady_samples_reported"] > 0 and not steady["flow_reached"]
    assert cell["ratios"]["temp_iae_cs"] <= 1.0
    assert cell["mpc"]["figures"]["fallbacks"] == 0


def test_flow_weight_factor_caps_what_a_flow_error_buys_in_supply_temperature():
    from hvac_mpc.mpc.priorities import TEMP_PER_FLOW_VIA_VALVE_A_C_PER_LPS as r, flow_weight_factor
    w_q, w_t, trade_c = 2.0, 1.0, 0.05
    for error_lps in (1.0, 30.0, -30.0):
        f = flow_weight_factor(error_lps * 1e-3, w_q, w_t, trade_c)
        # the gradient balance w_T e_T = f w_Q |e_Q| / r then gives e_T = trade_c
        assert f * w_q * abs(error_lps) / (w_t * r) == pytest.approx(trade_c)
    assert flow_weight_factor(0.1e-3, w_q, w_t, trade_c) == 1.0  # a small error keeps the full weight
    assert flow_weight_factor(1e-3, w_q, 2 * w_t, trade_c) == pytest.approx(2 * flow_weight_factor(1e-3, w_q, w_t, trade_c))
    with pytest.raises(ValueError, match="flow_trade_c"):
        MpcSettings(flow_trade_c=0.0)


def test_flow_step_within_reach_does_not_buy_flow_with_supply_temperature():
    """A flow step the blower can make (90 -> 200 m3/h on the independent box with a blower 20 % stronger than
    the model: within reach, so the priorities' reachable flow does not engage): while the blower ramps at its
    rate limit the MPC must not buy flow with valve a. The plain weighted sum did (valve a 20 % in one step,
    the supply air 1.8 C warm); with the flow weights capped by ``flow_trade_c`` the thermocouple stays
    within 0.3 C of its reference and the blower still brings the flow up at once."""
    quick = S.flow_out_of_reach().quick()
    sc = dataclasses.replace(quick, segments=(dataclasses.replace(quick.segments[0], duration_s=15.0),))
    ctrl = bench.mpc_factory()(sc.initial_command)
    tr = simulate(sc, ctrl, Parameters(), seed=0, plant=make_plant("blower_strong", seed=0))
    step = tr.time_s >= sc.step_times_s()[0]
    error = np.abs(tr.truth["supply_temp_c"][step] - sc.segments[0].reference.supply_temp_c)
    assert error.max() <= 0.3
    assert tr.truth["volume_flow_m3s"][step][5] >= 190 * M3H  # the flow is there after 5 s
    assert not any(tr.out_of_reach[k] for k in np.flatnonzero(step))  # within reach: nothing reported
    assert all(f is None for f in tr.fallback)


def test_reachable_flow_is_solved_again_only_when_its_inputs_have_moved_materially():
    from hvac_mpc.mpc.priorities import MATERIAL_CHANGE

    reach, x, u, d = _reach_setup()
    reach.skip_unmoved = True
    solves = []
    solver = reach.solver

    def counted(**kwargs):
        solves.append(kwargs["p"])
        return solver(**kwargs)

    reach.solver = counted
    ref = 200 * M3H
    first = reach.check(x, u, d, 18.0, ref, 100.0, 1.0)
    assert len(solves) == 1 and "volume_flow_m3s" in first.out_of_reach
    # 25 s with inputs moving less than MATERIAL_CHANGE: the answer stands, nothing solved
    small = d + 0.5 * MATERIAL_CHANGE[:-1]
    answers = [reach.check(x, u, small, 18.0, ref, 100.0, 1.0) for _ in range(25)]
    assert len(solves) == 1 and all(a.flow_m3s == first.flow_m3s for a in answers)
    # the flow offset moves by more than its threshold: solved again at the next periodic check
    moved = d.copy()
    moved[3] += 2.0 * MATERIAL_CHANGE[3]
    for _ in range(int(reach.every_s)):
        reach.check(x, u, moved, 18.0, ref, 100.0, 1.0)
    assert len(solves) == 2 and solves[-1][3] == moved[3]
    # a new temperature reference is solved at once, whatever the inputs
    reach.check(x, u, moved, 17.0, ref, 100.0, 1.0)
    assert len(solves) == 3


class CappedSolver:
    """Stand-in for the reachable-flow IPOPT solver: the real solve, the blower of its answer at its lowest
    and ``success`` False (a solve stopped at its iteration cap, as seen on the independent box)."""

    def __init__(self, solver, reach):
        self.solver, self.reach = solver, reach

    def __call__(self, **kwargs):
        sol = self.solver(**kwargs)
        w = np.asarray(sol["x"], float).ravel().copy()
        w[self.reach.nx + self.reach.i_blower] = 30.0  # the blower's lowest power (W)
        return {**sol, "x": w}

    def stats(self):
        return {**self.solver.stats(), "success": False, "return_status": "Maximum_Iterations_Exceeded"}


def test_a_capped_reachable_flow_solve_keeps_the_last_converged_answer():
    reach, x, u, d = _reach_setup()
    ref = 200 * M3H
    first = reach.check(x, u, d, 18.0, ref, 100.0, 1.0)
    assert "volume_flow_m3s" in first.out_of_reach and first.flow_m3s > 100 * M3H
    converged = reach.solver
    reach.solver = CappedSolver(converged, reach)
    capped = reach.check(x, u, d, 17.0, ref, 100.0, 1.0)  # a new reference: solved at once, stops at the cap
    assert capped.flow_m3s == first.flow_m3s
    reach.solver = converged
    assert reach.check(x, u, d, 16.0, ref, 100.0, 1.0).flow_m3s != first.flow_m3s  # converged again: taken


def assert_out_of_reach_cell(variant, ekf, limit: float = 0.95) -> None:
    """The quick flow-out-of-reach scenario on the independent box ``variant`` (seed 0), the MPC with the estimator
    settings ``ekf``: at most ``limit`` of the baseline's thermocouple IAE, the steady supply temperature within
    0.3 C, no fallback, no violation. The deadline is lifted: the check is about the loop, not the machine's load."""
    sc = S.flow_out_of_reach().quick()
    settings = MpcSettings(deadline_s=10.0, ekf=ekf)
    mpc = lambda c: MpcController(Parameters(), dataclasses.replace(settings, initial_command=c))  # noqa: E731
    res, tr = bench.run_benchmark([sc], {"baseline": bench.baseline_factory(), "mpc": mpc}, 0,
                                  plant_factory=functools.partial(make_plant, variant))
    cell = res["scenarios"][sc.name]
    assert cell["ratios"]["temp_iae_cs"] <= limit
    assert mismatch_suite.out_of_reach_steady(tr[sc.name]["mpc"], sc)["steady_temp_error_max_c"] <= 0.3
    assert cell["mpc"]["figures"]["fallbacks"] == 0 and cell["mpc"]["figures"]["violations_total"] == 0


#: A box with a dead time, a duct loss and the literal cooler fit, as ``combo_delay_loss_cooler`` but with other
#: values and not in the suite's registry (ASSUMPTION: picked to differ, not to be hard).
UNLISTED_DELAY_LOSS_COOLER = Variant(transport_delay_s=2.0, duct_loss_ua_w_per_k=4.0, cooler_literal_fit=True)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["combo_delay_loss_cooler", UNLISTED_DELAY_LOSS_COOLER],
                         ids=["combo_delay_loss_cooler", "unlisted_2s_4wk_cooler"])
def test_flow_out_of_reach_with_a_dead_time_no_response_has_shown(variant):
    """200 m3/h at 18 C, out of reach, on a box with a dead time the MPC is not told: no temperature step
    excites the dead-time estimate, and unhonoured the dead time turns the sensor noise into ringing (1.10 of
    the baseline's IAE on combo_delay_loss_cooler with the defaults, 0.99 on the unlisted box before the re-anchor
    of docs/robustness.md sec. 2.9, 0.75 with it). A prior of
    1.5 s (``EkfSettings.dead_time_prior_s``, not a default: it costs the built-in plant's flow_split_changes,
    docs/robustness.md sec. 2.4) holds both well below the baseline (0.80 and 0.88 measured). The deadline is
    lifted: the test is about the loop, not the machine's load (a missed deadline hands a step to the
    fallback chain)."""
    from hvac_mpc.mpc.estimator import EkfSettings

    assert_out_of_reach_cell(variant, EkfSettings(dead_time_prior_s=1.5))


@pytest.mark.slow
def test_cooling_steps_on_a_2_s_dead_time_the_suite_does_not_have():
    """A dead time between the suite's 1 s (below ``dead_time_min_s``, not honoured) and its 3 s: 2 s, not a
    registered variant. The estimator finds it in the warm-up and honours it; the quick cooling steps then
    cost 0.857 of the baseline's IAE (0.874 on seed 1; docs/robustness.md sec. 2.5), 1.48 with the dead-time
    handling off (``EkfSettings(dead_time_max_s=0)``). The deadline is lifted: the test is about the loop,
    not the machine's load."""
    sc = S.summer_cooling_steps().quick()
    mpc = lambda c: MpcController(Parameters(), MpcSettings(initial_command=c, deadline_s=10.0))  # noqa: E731
    res, _ = bench.run_benchmark([sc], {"baseline": bench.baseline_factory(), "mpc": mpc}, 0,
                                 plant_factory=functools.partial(make_plant, Variant(transport_delay_s=2.0)))
    cell = res["scenarios"][sc.name]
    assert cell["ratios"]["temp_iae_cs"] <= 0.95
    assert cell["mpc"]["figures"]["fallbacks"] == 0 and cell["mpc"]["figures"]["violations_total"] == 0


def test_heater_never_runs_below_the_minimum_flow_when_the_temperature_is_out_of_reach():
    """trapped_air_release asks for more heat than the heater gives at 40 m3/h: the supply
    temperature is out of reach. On the independent box the MPC gives up flow for it (temperature
    first, ``Weights.supply_temp`` 5), but only down to the flow floor the OCP holds while the heater is
    on, never so far that the heater runs below the minimum flow, and without fallbacks. Without the
    floor a supply temperature weight of 2 took the flow down to 0.24 of the reference, 10 samples with
    the heater on below the minimum flow, 6 fallbacks (docs/robustness.md sec. 2.2)."""
    from hvac_mpc.mpc.ocp import OcpSpec

    sc = S.trapped_air_release().quick()
    res, tr = bench.run_benchmark([sc], {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()}, 0,
                                  plant_factory=mismatch_suite.variant_factory("nominal"))
    f = res["scenarios"][sc.name]["mpc"]["figures"]
    assert f["violations_heater_low_flow"] == 0 and f["violations_total"] == 0
    assert f["fallbacks"] == 0
    mpc = tr[sc.name]["mpc"]
    scored = mpc.time_s >= mpc.metrics_start_s
    flow = mpc.truth["volume_flow_m3s"][scored]
    assert flow.min() >= 0.9 * OcpSpec().heater_min_flow_m3s  # 4.9 L/s measured (the floor 5 L/s)
    assert flow.min() <= 0.6 * mpc.reference["volume_flow_m3s"][scored].min()  # the flow was the lever
    assert res["scenarios"][sc.name]["ratios"]["temp_iae_cs"] <= 1.0
    # and says so: the supply temperature out of reach while the heater and valve a sit at their limits,
    # with the gap the box really has (61 of the step's 61 samples from the 89th second on, 0.97-1.50 C)
    reports = [(k, r["supply_temp_c"]) for k, r in enumerate(mpc.out_of_reach) if r and "supply_temp_c" in r]
    assert len(reports) >= 30
    gaps = np.array([g for _, g in reports])
    true_gaps = np.array([mpc.reference["supply_temp_c"][k] - mpc.truth["supply_temp_c"][k] for k, _ in reports])
    assert np.all(gaps > 0.3) and np.max(np.abs(gaps - true_gaps)) < 0.3
    assert res["scenarios"][sc.name]["mpc"]["details"]["out_of_reach"]["supply_temp_c"]["samples"] == len(reports)


@pytest.mark.parametrize("floor_m3s", [0.005, None])
def test_the_ocp_keeps_the_flow_floor_while_the_heater_is_on(floor_m3s):
    """A heating step the heater cannot follow (12 -> 22 C at 40 m3/h from a 10 C inlet, the heater at
    its limit, valve a at the trapped-air cap) with a heavy temperature weight, ten steps on the model:
    the QP keeps the model's total flow at the floor or above at every stage of every answer (stage 0,
    the command applied, included) with the heater on. Without the floor
    (``heater_min_flow_m3s=None``) the same QP trades the flow down to 2.6 L/s, so the row is what holds
    it (docs/robustness.md sec. 2.2)."""
    from hvac_mpc.mpc.ocp import OcpSpec, TrackingProblem, Weights
    from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

    pb = TrackingProblem(Parameters(), OcpSpec(weights=Weights(supply_temp=5.0), heater_min_flow_m3s=floor_m3s))
    ref = Reference.from_split(22.0, 40 * M3H, (0.2, 0.3, 0.5))
    command = Command(40 * M3H / Parameters().flow_per_watt_m3s_per_w, 60.0, 50.0, 100.0, 100.0, 100.0)
    d = np.array([10.0, 10.0, 0.0, 0.0])
    x0 = pb.scale_x(pb.model.steady_state(command.vector(), d))
    u_prev = pb.scale_u(command.vector())
    rti = RtiOsqpSolver(pb, lm_inputs=0.1, cold_start_qps=10, sqp_tol=2e-2)
    y_ref, w_y = pb.reference_vector(ref), pb.output_weights(ref)
    lowest, heater_w = np.inf, []
    for _ in range(10):
        lo, hi = pb.input_bounds(pb.unscale_u(u_prev), 85.0)
        res = rti.feedback(x0, u_prev, d, y_ref, w_y, lo, hi)
        assert res.ok
        lowest = min(lowest, min(float(pb.Y(res.X[k], res.U[k], d)[1]) for k in range(pb.N)))
        heater_w.append(pb.unscale_u(res.U[0])[pb.i_heater_cmd])
        x0, u_prev = res.X[1], res.U[0]
        rti.prepare(x0, u_prev, d, y_ref, w_y)
    assert min(heater_w[3:]) > 200.0  # the heater at its limit once it has ramped up
    if floor_m3s is None:
        assert lowest < 0.003  # 2.6 L/s measured; 40 m3/h is 11.1 L/s
    else:
        assert lowest >= floor_m3s - 1e-4  # 4.96 L/s measured: the linearisation's error


def test_flow_jump_is_not_met_with_phantom_heat_from_an_unpowered_heater_estimate():
    """The flow jump to an unreachable 200 m3/h on the independent box with a 3 s dead time, seed 1, heater off
    throughout. In the warm-up, before the dead time was found, the filter parked the late response in the
    heater body (23 C estimated for a true 11.7 C) and in the motor rise (-1.1 C for +0.7 C); at the jump the
    prediction released that phantom heat as the core flow rose, and the MPC opened the bypass for it (the
    noise-free thermocouple 0.17 C warm three seconds later, 1.32 of the baseline's IAE over the quick cell).
    With the unpowered body held between the air and its relaxation, the motor rise's start-up uncertainty cut
    to its lag's (both opt-in: they cost the built-in plant, docs/robustness.md sec. 2.6), and no flow trade
    while the reach of the new reference is being solved (the default), the estimate follows the box's body
    and the reading stays within 0.1 C. The deadline is lifted: the test is about the loop, not the machine's
    load."""
    from hvac_mpc.mpc.estimator import EkfSettings

    quick = S.flow_out_of_reach().quick()
    sc = dataclasses.replace(quick, segments=(dataclasses.replace(quick.segments[0], duration_s=20.0),))
    ctrl = MpcController(Parameters(), MpcSettings(initial_command=sc.initial_command, deadline_s=10.0,
                                                   bound_heater_estimate=True,
                                                   ekf=EkfSettings(initial_sd_motor_c=0.1)))
    plant = make_plant("delay_3s", seed=1)
    heater_error = []
    advance = plant.advance

    def advance_and_compare(n_steps: int = 1) -> None:
        advance(n_steps)
        heater_error.append(abs(float(ctrl.ekf.x[ctrl.ekf.model.states.index("heater_temp_c")])
                                - plant.truth()["heater_temp_c"]))

    plant.advance = advance_and_compare
    tr = simulate(sc, ctrl, Parameters(), seed=1, plant=plant)
    assert max(heater_error[1:]) <= 1.0  # the estimate after a step against the box's body before the next
    step = tr.time_s >= sc.step_times_s()[0]
    error = np.abs(tr.truth["supply_temp_c"][step] - sc.segments[0].reference.supply_temp_c)
    assert error.max() <= 0.1
    assert all(f is None for f in tr.fallback)


def test_a_flow_reference_whose_reach_is_being_solved_is_undecided_until_the_answer():
    """With the solve of a changed reference deferred (the default), the step of the change answers from an
    earlier solve, or none: the MPC then gives the flow no more weight than one out of reach (temperature
    first) until the answer is in, one step later."""
    _, x, u, d = _reach_setup()
    pb = _default_problem()
    reach = ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, Parameters(), deferred=True,
                          changes_deferred=True)
    first = reach.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0)
    assert reach.undecided and first.flow_m3s is None and first.out_of_reach == {}
    answered = reach.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0)
    assert not reach.undecided and "volume_flow_m3s" in answered.out_of_reach
    for _ in range(int(reach.every_s)):  # a periodic re-solve is deferred as well, but decided: the last answer stands
        reach.check(x, u, d, 18.0, 200 * M3H, 100.0, 1.0)
        assert not reach.undecided
    reach.check(x, u, d, 17.0, 200 * M3H, 100.0, 1.0)  # a change of the temperature reference: solved afresh
    assert reach.undecided
    reach.check(x, u, d, 17.0, 20 * M3H, 100.0, 1.0)  # a flow reference not in doubt needs no solve
    assert not reach.undecided


@pytest.mark.slow
def test_flow_jump_on_a_box_whose_split_depends_on_the_flow_is_met_by_the_learned_exponent():
    """The quick out-of-reach scenario (90 -> 200 m3/h) on the independent box given a bypass split that
    depends on the flow (``Variant(bypass_flow_exponent=0.4)``, the built-in plant's ASSUMPTION): the
    thesis model the MPC predicts with leaves that out, and at the jump the box's air warms. With the
    exponent learned, anchored at the recent flow and only after the filter's start-up
    (docs/robustness.md sec. 2.7), the MPC predicts the warming of the next flow change: 0.447 of the
    baseline's thermocouple IAE, against 0.953 with the defaults (seed 0)."""
    from hvac_mpc.mpc.estimator import EkfSettings

    ekf = EkfSettings(learn_bypass_flow=True, bypass_flow_anchored=True, bypass_flow_after_s=30.0)
    assert_out_of_reach_cell(Variant(bypass_flow_exponent=0.4), ekf, limit=0.6)


def test_the_offset_gets_variance_at_a_flow_step_and_the_motor_rise_stays_physical():
    """``q_mix_offset_per_log_flow_c``: the time update where the model's flow changed adds (c * change of ln flow)^2
    to the mixed-air offset's variance (less ``q_mix_offset_flow_deadband`` of the change), nothing at a steady flow
    nor before a response has shown the dead time; ``q_mix_offset_unseen_c``: the offset's walk before
    the dead-time estimate has seen a response; ``bound_motor_rise``: the motor rise held within
    [0, motor_gain_max_c] however hard a reading pushes it (docs/robustness.md sec. 2.8)."""
    from hvac_mpc.contract import Measurement
    from hvac_mpc.mpc.estimator import DisturbanceEkf, EkfSettings

    def filter_after(settings, blower_w):
        ekf = DisturbanceEkf(HvacModel(Parameters()), settings)
        u = Command(150.0, 0.0, 50.0, 100.0, 100.0, 100.0).vector()
        ekf.initialise(Measurement(0.0, 18.0, 0.025, 32.0, water_temp_c=5.0), u, 5.0)
        ekf.predict(u, 5.0)
        p0 = ekf.P[ekf.i_mix_offset, ekf.i_mix_offset]
        u2 = u.copy()
        u2[0] = blower_w
        ekf.predict(u2, 5.0)
        return ekf, p0, u2

    c = 0.5
    # without the dead-time handling (with it, the variance is added only once a response has been seen)
    none = {"q_mix_offset_per_log_flow_c": 0.0, "dead_time_max_s": 0.0}
    plain, p0, _ = filter_after(EkfSettings(**none), 300.0)
    stepped, q0, u2 = filter_after(EkfSettings(q_mix_offset_per_log_flow_c=c, dead_time_max_s=0.0), 300.0)
    steady, _, _ = filter_after(EkfSettings(q_mix_offset_per_log_flow_c=c, dead_time_max_s=0.0), 150.0)
    banded, _, _ = filter_after(EkfSettings(q_mix_offset_per_log_flow_c=c, q_mix_offset_flow_deadband=0.1,
                                            dead_time_max_s=0.0), 300.0)
    unseen_step, _, _ = filter_after(EkfSettings(q_mix_offset_per_log_flow_c=c), 300.0)
    plain_delay, _, _ = filter_after(EkfSettings(), 300.0)
    assert not unseen_step.dead_time.informed and unseen_step.P[unseen_step.i_mix_offset, unseen_step.i_mix_offset] == \
        pytest.approx(plain_delay.P[plain_delay.i_mix_offset, plain_delay.i_mix_offset], abs=1e-15)
    assert q0 == pytest.approx(p0, abs=1e-15)  # the first time update has no flow before it
    u = Command(150.0, 0.0, 50.0, 100.0, 100.0, 100.0).vector()
    flows = [float(stepped.f_p(stepped.z, v, 5.0, stepped.p)[3]) for v in (u, u2)]
    added = stepped.P[stepped.i_mix_offset, stepped.i_mix_offset] - plain.P[plain.i_mix_offset, plain.i_mix_offset]
    assert added == pytest.approx((c * np.log(flows[1] / flows[0])) ** 2, rel=0.05) and added > 1e-3
    with_band = banded.P[banded.i_mix_offset, banded.i_mix_offset] - plain.P[plain.i_mix_offset, plain.i_mix_offset]
    assert with_band == pytest.approx((c * (np.log(flows[1] / flows[0]) - 0.1)) ** 2, rel=0.05)
    plain_steady, _, _ = filter_after(EkfSettings(**none), 150.0)
    assert steady.P[steady.i_mix_offset, steady.i_mix_offset] == pytest.approx(
        plain_steady.P[plain_steady.i_mix_offset, plain_steady.i_mix_offset], abs=1e-15)
    unseen, _, _ = filter_after(EkfSettings(q_mix_offset_unseen_c=0.03), 150.0)
    plain_unseen, _, _ = filter_after(EkfSettings(), 150.0)
    assert not unseen.dead_time.informed
    assert unseen.P[unseen.i_mix_offset, unseen.i_mix_offset] == pytest.approx(
        plain_unseen.P[plain_unseen.i_mix_offset, plain_unseen.i_mix_offset] + 2 * (0.03 ** 2 - 0.015 ** 2), rel=1e-6)
    # a reading far below what the model explains pushes the motor rise down; bounded, it stops at 0
    for bound in (False, True):
        ekf, _, u2 = filter_after(EkfSettings(bound_motor_rise=bound), 150.0)
        i = ekf.model.states.index("motor_rise_c")
        for _ in range(15):
            ekf.update(Measurement(0.0, 12.0, 0.025, 32.0, water_temp_c=5.0), u2, 5.0)
            ekf.predict(u2, 5.0)
        assert (ekf.x[i] >= 0.0) == bound


#: The unlisted box of sec. 2.8: a 4 s dead time, a duct loss twice the suite's, the literal cooler fit.
UNLISTED_LONG_DELAY_LOSS_COOLER = Variant(transport_delay_s=4.0, duct_loss_ua_w_per_k=6.0, cooler_literal_fit=True)


@pytest.mark.slow
def test_flow_out_of_reach_on_a_long_dead_time_with_a_duct_loss_meets_the_baseline_with_the_physical_states():
    """200 m3/h at 18 C, out of reach, on a box not in the suite (4 s dead time, duct loss 6 W/K, literal cooler
    fit): without the re-anchor of docs/robustness.md sec. 2.9 (0.82 with it, the default) 1.21 of the baseline's
    IAE (seed 0; the motor rise estimate at -2.5 C for the box's
    +0.9 after the warm-up, and the offset slow to follow the flow jump's change of the duct loss). The motor rise
    bounded and the offset given variance at the flow step (``bound_motor_rise``, ``q_mix_offset_per_log_flow_c``
    0.5; settings, not defaults: they cost the built-in plant's winter_heating_steps and trapped_air_release,
    docs/robustness.md sec. 2.8): 0.854 measured."""
    from hvac_mpc.mpc.estimator import EkfSettings

    assert_out_of_reach_cell(UNLISTED_LONG_DELAY_LOSS_COOLER,
                             EkfSettings(bound_motor_rise=True, q_mix_offset_per_log_flow_c=0.5))


@pytest.mark.slow
def test_flow_out_of_reach_with_a_dead_time_never_shown_and_a_slower_offset_walk_until_it_is():
    """The suite's combo_delay_loss_cooler with the flow out of reach (1.10 of the baseline's IAE with the defaults,
    seed 0: the 3 s dead time never shows, sec. 2.4): with the mixed-air offset walking at 0.0075 degC per sample
    until the dead-time estimate has seen a response (``q_mix_offset_unseen_c``; a setting: it costs the built-in
    plant's winter_heating_steps and cabin_cooldown_summer, docs/robustness.md sec. 2.8) 0.87 measured."""
    from hvac_mpc.mpc.estimator import EkfSettings

    assert_out_of_reach_cell("combo_delay_loss_cooler", EkfSettings(q_mix_offset_unseen_c=0.0075))
