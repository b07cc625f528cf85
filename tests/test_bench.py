"""Benchmark command: scenario definitions, plant perturbation, the closed loop and the output files.

Budget: under a minute on two loaded cores (one end-to-end quick scenario with the real MPC and
baseline, the rest on short runs of a stand-in controller).
"""

import io
import json
import math

import numpy as np
import pytest

from hvac_mpc import cli
from hvac_mpc.benchmarks import bench, metrics, report, scenarios as S
from hvac_mpc.benchmarks.perturbation import MAGNITUDE_RANGE, PERTURBED, perturb_parameters
from hvac_mpc.benchmarks.simulate import simulate
from hvac_mpc.models import measurement_log
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.models.plant import Environment, SimulatedPlant
from hvac_mpc.contract import Command
from hvac_mpc.contract import StepResult
from hvac_mpc.contract import Reference

M3H = 1 / 3600


class HoldController:
    """Stand-in for the tests: holds a fixed command (Controller protocol)."""

    def __init__(self, command: Command | None = None, dt_s: float = 1.0):
        self.command = command or Command(150.0, 0.0, 60.0, 100.0, 100.0, 100.0)
        self.dt_s = dt_s
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1

    def step(self, measurement, reference) -> StepResult:
        return StepResult(Command(**self.command.as_dict()), {"step_time_s": 0.0, "fallback": None,
                                                                "mode": "cooling", "status": "ok"})


# ---------------------------------------------------------------------------- scenarios
def test_scenarios_are_named_seeded_and_valid():
    all_ = S.all_scenarios()
    assert list(all_) == ["summer_cooling_steps", "winter_heating_steps", "flow_split_changes", "proband_sequence",
                          "chiller_hysteresis_step", "trapped_air_release", "cabin_cooldown_summer",
                          "cabin_warmup_winter"]
    seeds = [s.seed for s in all_.values()]
    assert len(set(seeds)) == len(seeds)
    for sc in all_.values():
        assert sc.description
        refs = [sc.warmup.reference] + [seg.reference for seg in sc.segments]
        assert all(isinstance(r, Reference) and r.split is not None for r in refs)
        # every scored segment after the first starts with a change of some reference field (the
        # first continues the warm-up reference in the proband sequence, its 'optimal start')
        for a, b in zip(refs[1:], refs[2:]):
            assert a != b
        assert refs[0] != refs[1] or sc.name == "proband_sequence"
        q = sc.quick()
        assert q.duration_s < sc.duration_s or sc.duration_s <= 300
        assert q.name == sc.name and q.seed == sc.seed
        # piecewise constant: the reference in force just before and at each step
        for t, seg, before in zip(sc.step_times_s(), sc.segments, refs):
            assert sc.reference_at(t) == seg.reference
            assert sc.reference_at(t - 0.5) == before
    # the whole quick run stays short (the tests and the 2-minute budget)
    assert sum(s.quick().duration_s for s in all_.values()) <= 1500


def test_summer_and_winter_conditions():
    all_ = S.all_scenarios()
    for name in ("summer_cooling_steps", "flow_split_changes", "proband_sequence", "chiller_hysteresis_step"):
        sc = all_[name]
        assert (sc.inlet_temp_c, sc.chiller_setpoint_c, sc.kind) == (32.0, 5.0, "cooling")
    for name in ("winter_heating_steps", "trapped_air_release"):
        sc = all_[name]
        assert sc.kind == "heating" and sc.chiller_setpoint_c == sc.inlet_temp_c <= 10.0
        temps = [seg.reference.supply_temp_c for seg in sc.segments]
        assert min(temps) > sc.inlet_temp_c  # heating is needed
    flows = [(seg.reference.volume_flow_m3s, seg.reference.split) for seg in all_["flow_split_changes"].segments]
    assert len({f for f, _ in flows}) == len(flows)
    assert len({s for _, s in flows}) > 1


def test_proband_sequence_like_the_thesis():
    sc = S.proband_sequence()
    assert len(sc.segments) == 7
    assert [seg.duration_s for seg in sc.segments] == [300.0] * 7
    assert np.diff(sc.step_times_s()).tolist() == [300.0] * 6
    temps = [seg.reference.supply_temp_c for seg in sc.segments]
    assert all(min(abs(t - c) for c in (15.0, 18.0, 20.0)) <= 0.7 for t in temps)
    assert all(a != b for a, b in zip(temps, temps[1:]))
    for seg in sc.segments:
        r = seg.reference
        assert r.volume_flow_m3s <= 130 * M3H + 1e-12
        assert r.flow_m_m3s == max(r.split)  # mostly middle outlet
    assert S.proband_references(14) == S.proband_references(14)
    assert S.proband_references(14) != S.proband_references(15)


def test_chiller_step_arrives_when_the_chiller_switches():
    sc = S.chiller_hysteresis_step()
    t_off, t_on = S.chiller_switch_times_s()
    plant = SimulatedPlant(perturb_parameters(seed=0)[0], seed=1,
                           environment=Environment(sc.inlet_temp_c, sc.chiller_setpoint_c),
                           initial_command=sc.initial_command)
    water = []
    for _ in range(int(sc.step_times_s()[0]) + 1):
        water.append(plant.truth()["water_temp_c"])
        plant.advance()
    turn = int(np.argmin(water))  # the water stops cooling when the chiller switches off
    assert abs(turn - t_off) <= 2.0
    assert 0.0 < sc.step_times_s()[0] - turn <= 10.0
    assert sc.step_times_s()[1] - t_on == pytest.approx(5.0, abs=1.0)
    assert sc.quick().step_times_s()[0] == sc.step_times_s()[0]


def test_trapped_air_demand_exceeds_what_the_heater_delivers():
    sc = S.trapped_air_release()
    high = sc.segments[0].reference
    for params in (Parameters(), perturb_parameters(seed=0)[0]):
        for valve_a in (80.0, 100.0):
            blower = high.volume_flow_m3s / params.flow_per_watt_m3s_per_w
            for _ in range(3):  # blower power for the reference flow (fixed point on the flow)
                plant = SimulatedPlant(params, seed=0, environment=Environment(sc.inlet_temp_c, sc.chiller_setpoint_c))
                plant.settle(Command(blower, 240.0, valve_a, 100.0, 100.0, 100.0))
                plant.advance(300)
                blower *= high.volume_flow_m3s / plant.truth()["volume_flow_m3s"]
            assert plant.truth()["supply_temp_c"] < high.supply_temp_c - 0.5
    assert sc.segments[1].reference.supply_temp_c < high.supply_temp_c


def test_select_names_and_unknown_name():
    assert [s.name for s in S.select(["proband_sequence"])] == ["proband_sequence"]
    with pytest.raises(ValueError, match="unknown name.*summer_cooling_steps"):
        S.select(["no_such"])


def test_bad_scenario_fields_are_named():
    ref = Reference(18.0, 0.02)
    with pytest.raises(ValueError, match="duration_s"):
        S.Segment(0.0, ref)
    with pytest.raises(ValueError, match="kind"):
        S.Scenario("x", "d", 1, "drying", 20.0, 5.0, Command(), S.Segment(10, ref), (S.Segment(10, ref),))
    with pytest.raises(ValueError, match="inlet_temp_c"):
        S.Scenario("x", "d", 1, "cooling", 99.0, 5.0, Command(), S.Segment(10, ref), (S.Segment(10, ref),))


# ---------------------------------------------------------------------------- perturbation
def test_perturbation_is_seeded_bounded_and_leaves_nominal_alone():
    p0, rec0 = perturb_parameters(seed=3)
    p1, rec1 = perturb_parameters(seed=3)
    p2, _ = perturb_parameters(seed=4)
    assert p0 == p1 and p0 != p2
    nominal = Parameters()
    assert [r.name for r in rec0] == list(PERTURBED)
    for r in rec0:
        assert MAGNITUDE_RANGE[0] <= abs(r.relative) <= MAGNITUDE_RANGE[1]
        assert getattr(p0, r.name) == pytest.approx(getattr(nominal, r.name) * (1 + r.relative))
        assert r.nominal == getattr(nominal, r.name)
    others = [n for n in Parameters.scalar_names() if n not in PERTURBED]
    assert all(getattr(p0, n) == getattr(nominal, n) for n in others)
    with pytest.raises(ValueError, match="seed"):
        perturb_parameters(seed=-1)


# ---------------------------------------------------------------------------- closed loop
def _short(name="summer_cooling_steps"):
    sc = S.all_scenarios()[name].quick()
    return sc


def test_simulate_records_and_noise_is_shared_between_controllers():
    sc = _short()
    params = perturb_parameters(seed=0)[0]
    a = HoldController(Command(150.0, 0.0, 60.0, 100.0, 100.0, 100.0))
    b = HoldController(Command(200.0, 0.0, 80.0, 100.0, 50.0, 100.0))
    ta = simulate(sc, a, params, seed=0, name="a")
    tb = simulate(sc, b, params, seed=0, name="b")
    n = int(sc.duration_s)
    assert ta.time_s.shape == (n,) and ta.applied.shape == (n, 6)
    assert a.resets == 1
    noise_a = ta.measured["supply_temp_c"] - ta.truth["supply_temp_c"]
    noise_b = tb.measured["supply_temp_c"] - tb.truth["supply_temp_c"]
    assert np.allclose(noise_a, noise_b) and np.std(noise_a) > 0
    assert not np.allclose(ta.truth["supply_temp_c"], tb.truth["supply_temp_c"])
    tc = simulate(sc, a, params, seed=1, name="a")
    assert not np.allclose(tc.measured["supply_temp_c"], ta.measured["supply_temp_c"])
    # the recorded reference is the scenario's
    assert ta.reference["supply_temp_c"][int(sc.step_times_s()[0])] == sc.segments[0].reference.supply_temp_c


def test_simulate_rejects_a_controller_with_another_sample_time():
    with pytest.raises(ValueError, match="sample time"):
        simulate(_short(), HoldController(dt_s=2.0), Parameters(), seed=0)


def test_run_benchmark_with_stand_ins_ratios_and_outputs(tmp_path, monkeypatch):
    sc = _short()
    factories = {"baseline": lambda c: HoldController(Command(150.0, 0.0, 60.0, 100.0, 100.0, 100.0)),
                 "mpc": lambda c: HoldController(Command(120.0, 0.0, 75.0, 100.0, 100.0, 100.0))}
    stream = io.StringIO()
    bar = bench.ProgressBar(int(sc.duration_s) * 2, stream=stream)
    results, traces = bench.run_benchmark([sc], factories, seed=0, progress=bar)
    assert bar.done == bar.total and "100%" in stream.getvalue()
    r = results["scenarios"][sc.name]
    b, m = r["baseline"]["figures"], r["mpc"]["figures"]
    assert b["blower_wh"] == pytest.approx(150.0 * r["scored_s"] / 3600)
    assert m["blower_wh"] == pytest.approx(120.0 * r["scored_s"] / 3600)
    assert r["ratios"]["blower_wh"] == pytest.approx(0.8)
    assert r["ratios"]["temp_iae_cs"] == pytest.approx(m["temp_iae_cs"] / b["temp_iae_cs"])
    energy = next(c for c in r["criteria"] if c["criterion"].startswith("electric energy"))
    assert energy["status"] == "met" and energy["ratio"] == pytest.approx(0.8)
    with pytest.raises(ValueError, match="missing controller"):
        bench.run_benchmark([sc], {"mpc": factories["mpc"]}, seed=0)
    # without matplotlib the report is still written, with a note
    results["meta"].update(command="hvac-mpc bench", quick=True, elapsed_s=1.0, platform="test", python="3")
    monkeypatch.setattr(report, "import_pyplot", lambda: None)
    notes = bench.write_outputs(results, traces, tmp_path, plots=True)
    text = (tmp_path / "report.md").read_text()
    assert "matplotlib is not installed" in text and notes and not list(tmp_path.glob("*.png"))
    assert "| supply temp IAE, thermocouple [C s] |" in text


def test_progress_bar_in_a_terminal_redraws_one_line():
    class Tty(io.StringIO):
        def isatty(self):
            return True
    s = Tty()
    bar = bench.ProgressBar(4, stream=s, width=4)
    for _ in range(4):
        bar.advance(1, "x")
    bar.close()
    out = s.getvalue()
    assert out.startswith("\r[") and "[####] 100% x" in out and out.endswith("\n")


# ---------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_cli_quick_scenario_end_to_end(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="the plots need the 'plot' extra; the rest is tested without it")
    out = tmp_path / "bench"
    code = cli.main(["bench", "--quick", "--scenario", "summer_cooling_steps", "--out", str(out), "--seed", "2"])
    assert code == 0
    printed = capsys.readouterr()
    assert "summer_cooling_steps" in printed.out and "MPC/base" in printed.out
    assert "criteria met:" in printed.out and str(out / "report.md") in printed.out
    assert "%" in printed.err  # the progress bar
    data = json.loads((out / "results.json").read_text())
    assert set(data) >= {"scenarios", "summary", "meta", "criteria_names"}
    assert data["meta"]["command"] == f"hvac-mpc bench --quick --scenario summer_cooling_steps --out {out} --seed 2"
    assert data["meta"]["quick"] is True and data["meta"]["seed"] == 2
    assert "MpcController" in data["meta"]["controller_settings"]["mpc"]
    assert "deadline_s=3600.0" in data["meta"]["controller_settings"]["mpc"]  # no wall-clock fallback by default
    assert data["meta"]["controller_settings"]["baseline"] == "BaselineController"
    sc = data["scenarios"]["summer_cooling_steps"]
    keys = {"temp_iae_cs", "air_temp_iae_cs", "temp_time_to_band_max_s", "temp_overshoot_max_c", "flow_iae_m3",
            "flow_time_to_band_max_s", "outlet_rms_m3s", "blower_wh", "heater_wh", "energy_wh", "travel_mean",
            "violations_bounds", "violations_heater_temp", "violations_heater_low_flow", "step_median_ms",
            "step_p99_ms", "time_ratio", "fallbacks", "ideal_temp_iae_cs"}
    for c in ("baseline", "mpc"):
        assert keys <= set(sc[c]["figures"])
        assert sc[c]["figures"]["temp_steps"] == 2
        assert sc[c]["figures"]["step_median_ms"] > 0
    # ratios come from the same run's figures
    for k in metrics.RATIO_FIGURES:
        mv, bv = sc["mpc"]["figures"][k], sc["baseline"]["figures"][k]
        expected = metrics.ratio(mv, bv)
        if expected is None or math.isinf(expected):
            assert sc["ratios"][k] in (None, expected)
        else:
            assert sc["ratios"][k] == pytest.approx(expected)
    assert [c["criterion"] for c in sc["criteria"]] == data["criteria_names"]
    assert all(c["status"] in ("met", "not met", "n/a") for c in sc["criteria"])
    assert all(c["why"] for c in sc["criteria"] if c["status"] == "not met")
    s = data["summary"]
    assert s["met"] + s["not_met"] + s["n_a"] == len(sc["criteria"])
    text = (out / "report.md").read_text()
    assert "summer_cooling_steps" in text and "![summer_cooling_steps](summer_cooling_steps.png)" in text
    assert f"{sc['mpc']['figures']['temp_iae_cs']:.1f}" in text
    assert (out / "summer_cooling_steps.png").stat().st_size > 10_000
    log = measurement_log.read_log(out / "logs" / "summer_cooling_steps__mpc.csv")
    assert len(log["time_s"]) == int(sc["duration_s"])


def test_cli_unknown_scenario_fails_cleanly(tmp_path, capsys):
    code = cli.main(["bench", "--quick", "--scenario", "nope", "--out", str(tmp_path / "x")])
    assert code == 2
    assert "unknown name" in capsys.readouterr().err
    assert cli.main(["bench", "--quick", "--seed", "-1", "--out", str(tmp_path / "x")]) == 2
    assert "--seed" in capsys.readouterr().err
    for bad in ("0", "-0.5", "7200", "nan"):
        assert cli.main(["bench", "--quick", "--deadline-s", bad, "--out", str(tmp_path / "x")]) == 2
        assert "--deadline-s must be within (0, 3600] s" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow  # above 7 s on a loaded machine; the whole suite runs it
@pytest.mark.parametrize("name", ["summer_cooling_steps", "winter_heating_steps"])
def test_mpc_settles_every_temperature_step_faster_than_the_baseline(name):
    # issue: temperature steps reach +-0.5 C faster than the baseline, on the perturbed plant with
    # every effect on; the full scenarios, seed 0, as `hvac-mpc bench` runs them
    results, _ = bench.run_benchmark([S.all_scenarios()[name]],
                                     {"baseline": bench.baseline_factory(), "mpc": bench.mpc_factory()}, seed=0)
    sc = results["scenarios"][name]
    b, m = sc["baseline"]["figures"], sc["mpc"]["figures"]
    assert m["temp_steps"] >= 3 and m["temp_unsettled"] == 0
    assert m["temp_time_to_band_max_s"] < b["temp_time_to_band_max_s"]
    assert m["temp_iae_cs"] < b["temp_iae_cs"]
    assert m["violations_total"] == 0


# --- boxes the registry does not have (--box) and the suite's rows (--variant) ---------------------

def test_parse_box_builds_the_variant_and_names_bad_fields():
    from hvac_mpc.benchmarks import mismatch_suite
    from hvac_mpc.mismatch import Variant
    label, box = mismatch_suite.parse_box("U4:transport_delay_s=2.5,duct_loss_ua_w_per_k=5,cooler_literal_fit=1")
    assert label == "U4"
    assert box == Variant(transport_delay_s=2.5, duct_loss_ua_w_per_k=5.0, cooler_literal_fit=True)
    for spec, names in (("U1", "LABEL:FIELD=VALUE"), ("U1:foo=2", "unknown field 'foo'"),
                        ("U1:transport_delay_s=x", "transport_delay_s takes a number"),
                        ("U1:transport_delay_s=-1", "transport_delay_s"),
                        ("U1:cooler_literal_fit=maybe", "cooler_literal_fit takes true or false"),
                        ("a/b:transport_delay_s=1", "LABEL")):
        with pytest.raises(ValueError, match=names):
            mismatch_suite.parse_box(spec)


def test_suite_rows_from_variant_and_box_options():
    import argparse
    ns = lambda **kw: argparse.Namespace(**{"variant": None, "box": None, **kw})
    everything, none = bench.suite_plants(ns())
    assert everything == bench.mismatch_suite.variant_names() and none == {}
    variants, boxes = bench.suite_plants(ns(variant=["delay_3s", "delay_3s"], box=["U1:transport_delay_s=2"]))
    assert variants == ["delay_3s"] and list(boxes) == ["U1"] and boxes["U1"].transport_delay_s == 2.0
    assert bench.suite_plants(ns(box=["U1:transport_delay_s=2"]))[0] == []
    with pytest.raises(ValueError, match="--variant: unknown"):
        bench.suite_plants(ns(variant=["nope"]))
    with pytest.raises(ValueError, match="registered variant names"):
        bench.suite_plants(ns(box=["delay_3s:transport_delay_s=2"]))


def test_run_suite_puts_boxes_after_variants_on_their_own_plants():
    from hvac_mpc.benchmarks import mismatch_suite
    from hvac_mpc.mismatch import Variant
    seen = []

    def fake_benchmark(chosen, factories, seed, progress=None, plant_factory=None, plant_name=""):
        seen.append((plant_factory.args[0], plant_name))
        return {"scenarios": {}}, {}

    box = Variant(transport_delay_s=2.0)
    results, _ = mismatch_suite.run_suite(["delay_3s"], [], {}, 0, fake_benchmark, boxes={"U1": box})
    assert list(results["variants"]) == ["delay_3s", "U1"]
    assert seen[0] == ("delay_3s", "hvac_mpc.mismatch:make_plant('delay_3s')")
    assert seen[1][0] is box and "transport_delay_s=2.0" in seen[1][1]
