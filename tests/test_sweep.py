"""hvac-mpc sweep: spec validation and expansion, exact replay, failures recorded, resume, Dask runs."""

from __future__ import annotations

import json
import os
import signal
from collections import Counter

import pytest

pytest.importorskip("pyarrow", reason="the sweep writes Parquet (extra 'sweep')")

from hvac_mpc.benchmarks import sweep  # noqa: E402
from hvac_mpc.benchmarks.scenarios import all_scenarios  # noqa: E402
from hvac_mpc.benchmarks.sweep_run import KPIS, TIMING_KPIS, ControllerCache, differing_kpis, execute  # noqa: E402
from hvac_mpc.benchmarks.sweep_spec import (InvalidSweep, RunSpec, expand, make_spec, scenario_of,  # noqa: E402
                                            shorten)
from hvac_mpc.cli import main  # noqa: E402

SHORT = 30.0  # s of simulated time per test run


def _raw_ids(folder) -> list[str]:
    """Run ids of every stored row, repeats included (read_results drops repeats)."""
    import pyarrow.parquet as pq

    return [i for f in sorted(folder.glob("part-*.parquet")) for i in pq.read_table(f).column("run_id").to_pylist()]


def _runs(n_seeds=1, plants=("simulated",), controllers=("mpc", "baseline"), scenarios=("summer_cooling_steps",)):
    return expand(make_spec({"scenarios": list(scenarios), "seeds": list(range(n_seeds)), "plants": list(plants),
                             "controllers": list(controllers), "max_duration_s": SHORT}))


# ---------------------------------------------------------------------------- spec
def test_bad_spec_names_the_field_and_the_allowed_values():
    with pytest.raises(InvalidSweep, match=r"scenarios.*unknown scenario 'nope'.*summer_cooling_steps"):
        make_spec({"scenarios": ["nope"]})
    with pytest.raises(InvalidSweep, match=r"weights.*unknown weight.*'tempo'.*supply_temp"):
        make_spec({"weights": [{"tempo": 1.0}]})
    with pytest.raises(InvalidSweep, match=r"horizons.*sum to at least 60 s"):
        make_spec({"horizons": [[1.0, 2.0]]})
    with pytest.raises(InvalidSweep, match=r"samples"):
        make_spec({"sampling": "lhs"})
    with pytest.raises(InvalidSweep, match=r"plants.*unknown plant 'box'.*delay_3s"):
        make_spec({"plants": ["box"]})
    with pytest.raises(InvalidSweep, match=r"max_duration_s"):
        make_spec({"max_duration_s": -5})


def test_grid_crosses_the_axes_and_baselines_do_not_multiply_with_mpc_settings():
    spec = make_spec({"scenarios": ["summer_cooling_steps", "winter_heating_steps"], "seeds": [0, 1, 2],
                      "plants": ["simulated", "delay_3s"], "weights": [{}, {"supply_temp": 3.0}],
                      "horizons": ["default", [1.0] * 8 + [4.0] * 13]})
    runs = expand(spec)
    count = Counter(r.controller for r in runs)
    assert count["mpc"] == 2 * 3 * 2 * 2 * 2
    assert count["baseline"] == 2 * 3 * 2
    assert len({r.run_id for r in runs}) == len(runs)
    # each MPC run has exactly one baseline run with the same pair key
    base = Counter(r.pair_key() for r in runs if r.controller == "baseline")
    assert all(base[r.pair_key()] == 1 for r in runs if r.controller == "mpc")


def test_latin_hypercube_stratifies_each_axis():
    spec = make_spec({"sampling": "lhs", "samples": 12, "sample_seed": 3, "controllers": ["mpc"],
                      "scenarios": ["summer_cooling_steps", "winter_heating_steps", "flow_split_changes"],
                      "seeds": [0, 1, 2, 3], "inlet_temp_range_c": [20.0, 35.0],
                      "weight_ranges": {"supply_temp": [0.5, 2.0]}})
    runs = expand(spec)
    assert len(runs) == 12
    assert set(Counter(r.scenario for r in runs).values()) == {4}
    assert set(Counter(r.seed for r in runs).values()) == {3}
    bins = Counter(int((r.inlet_temp_c - 20.0) / 15.0 * 12) for r in runs)
    assert sorted(bins) == list(range(12))
    assert all(0.5 <= r.weights["supply_temp"] <= 2.0 for r in runs)
    assert [r.run_id for r in expand(spec)] == [r.run_id for r in runs]  # the same seed draws the same runs


def test_run_id_hashes_every_input():
    a = RunSpec(scenario="summer_cooling_steps", seed=1)
    assert a.run_id == RunSpec(scenario="summer_cooling_steps", seed=1).run_id
    others = [RunSpec(scenario="summer_cooling_steps", seed=2), RunSpec(scenario="summer_cooling_steps", seed=1,
              plant="delay_3s"), RunSpec(scenario="summer_cooling_steps", seed=1, weights={"supply_temp": 2.0}),
              RunSpec(scenario="summer_cooling_steps", seed=1, inlet_temp_c=30.0)]
    assert len({a.run_id, *(o.run_id for o in others)}) == 5
    with pytest.raises(ValueError, match="MPC only"):
        RunSpec(scenario="summer_cooling_steps", controller="baseline", weights={"supply_temp": 2.0})


def test_shortened_scenario_keeps_the_warmup_and_cuts_segments():
    sc = all_scenarios()["summer_cooling_steps"].quick()
    cut = shorten(sc, 100.0)
    assert cut.duration_s == 100.0
    assert cut.warmup == sc.warmup
    assert cut.segments[0].reference == sc.segments[0].reference
    run = RunSpec(scenario="summer_cooling_steps", max_duration_s=100.0, inlet_temp_c=28.0)
    assert scenario_of(run).duration_s == 100.0 and scenario_of(run).inlet_temp_c == 28.0


# ---------------------------------------------------------------------------- runs
def test_a_reused_controller_repeats_a_fresh_one_exactly():
    """Replays and cached controllers: the figures of a run do not depend on what ran before."""
    target = RunSpec(scenario="winter_heating_steps", seed=3, max_duration_s=60.0, plant="delay_3s").inputs()
    other = RunSpec(scenario="winter_heating_steps", seed=1, max_duration_s=60.0).inputs()
    fresh = execute(target, ControllerCache())
    cache = ControllerCache()
    execute(other, cache)
    again = execute(target, cache)
    assert cache.builds == 1
    assert fresh["error"] is None and again["error"] is None
    assert differing_kpis(fresh, again) == []
    assert fresh["temp_iae_cs"] > 0 and fresh["energy_wh"] > 0


def test_failed_run_is_recorded_and_resumed_sweep_skips_finished_runs(tmp_path):
    model = tmp_path / "model.toml"
    model.write_text("[parameters]\n")
    runs = expand(make_spec({"scenarios": ["summer_cooling_steps"], "seeds": [0, 1], "controllers": ["baseline"],
                             "model_files": [str(model), None], "max_duration_s": SHORT}))
    model.write_text("[parameters]\nfan_k_kg_m7 = 90000.0\n")  # changed after planning: those runs must fail
    out = tmp_path / "res"
    first = sweep.run_sweep(runs, out, None, progress=False, batch_size=1)
    rows = sweep.read_results(out)
    assert first["ran"] == 4 and first["failed"] == 2
    failed = [r for r in rows if r["error"]]
    assert {r["model_file"] for r in failed} == {str(model)}
    assert all("changed since the sweep was planned" in r["error"] for r in failed)
    assert all(r["temp_iae_cs"] is not None for r in rows if not r["error"])
    parts = sorted(out.glob("part-*.parquet"))
    again = sweep.run_sweep(runs, out, None, progress=False)
    assert again["skipped"] == 4 and again["ran"] == 0
    assert sorted(out.glob("part-*.parquet")) == parts


def test_interrupted_sweep_keeps_finished_runs_and_resumes(tmp_path):
    runs = _runs(n_seeds=3, controllers=("baseline",), scenarios=("summer_cooling_steps", "winter_heating_steps"))
    seen = []

    def stop_after_two(row):
        seen.append(row["run_id"])
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep.run_sweep(runs, tmp_path, None, progress=False, on_result=stop_after_two)
    assert {r["run_id"] for r in sweep.read_results(tmp_path)} == set(seen)
    rest = sweep.run_sweep(runs, tmp_path, None, progress=False)
    assert rest["skipped"] == 2 and rest["ran"] == len(runs) - 2
    assert sorted(_raw_ids(tmp_path)) == sorted(r.run_id for r in runs)


def test_summary_pairs_mpc_with_baseline_and_names_the_worst_run():
    def row(rid, ctrl, key, iae, plant="simulated"):
        r = {"run_id": rid, "controller": ctrl, "pair_key": key, "plant": plant, "error": None}
        r.update({k: 1.0 for k in KPIS})
        r["temp_iae_cs"] = iae
        return r

    rows = [row("b1", "baseline", "k1", 10.0), row("m1", "mpc", "k1", 5.0),
            row("b2", "baseline", "k2", 10.0), row("m2", "mpc", "k2", 20.0),
            row("m3", "mpc", "k3", 1.0)]  # no baseline partner: not in the ratios
    s = sweep.summarise(rows)
    r = s["mpc_over_baseline"]["temp_iae_cs"]
    assert r["n"] == 2 and r["median"] == pytest.approx(1.25) and r["worst"] == 2.0 and r["worst_run_id"] == "m2"
    g = s["groups"]["simulated / mpc"]["temp_iae_cs"]
    assert g["n"] == 3 and g["worst_run_id"] == "m2" and g["median"] == 5.0
    assert s["groups"]["all / baseline"]["temp_iae_cs"]["n"] == 2


def test_cli_rejects_bad_options_and_changes_nothing(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["sweep", "--scenario", "nope", "--out", str(out)]) == 2
    assert "unknown scenario 'nope'" in capsys.readouterr().err
    assert main(["sweep", "--replay", str(out)]) == 2
    assert "--row" in capsys.readouterr().err
    assert main(["sweep", "--quick", "--seeds", "0", "--out", str(out)]) == 2
    assert "--seeds: expected an integer >= 1" in capsys.readouterr().err
    assert not out.exists()


# ---------------------------------------------------------------------------- Dask
@pytest.mark.slow  # above 7 s on a loaded machine; the whole suite runs it
def test_tiny_sweep_on_a_local_cluster_and_replay_of_a_row(tmp_path, capsys):
    """Two worker processes; every run once in the Parquet; a row replays exactly from the CLI."""
    out = tmp_path / "res"
    rc = main(["sweep", "--scenario", "summer_cooling_steps", "--seeds", "2", "--plant", "simulated", "--plant",
               "delay_3s", "--controller", "mpc", "--max-duration-s", str(SHORT), "--workers", "2", "--out", str(out),
               "--no-plots", "--no-progress", "--batch-size", "2"])
    assert rc == 0
    rows = sweep.read_results(out)
    assert len(rows) == 4 and len({r["run_id"] for r in rows}) == 4
    assert all(r["error"] is None and r["temp_iae_cs"] > 0 for r in rows)
    assert len({r["host"] for r in rows}) == 2  # both worker processes ran runs
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 4 and summary["failed"] == 0
    capsys.readouterr()
    assert main(["sweep", "--replay", str(out), "--row", "2"]) == 0
    assert "replay: identical figures" in capsys.readouterr().out


@pytest.mark.slow
def test_a_killed_worker_loses_no_run(tmp_path):
    """A worker process is killed mid-sweep (SIGKILL): Dask reschedules, every run is stored exactly once."""
    runs = _runs(n_seeds=2, plants=("simulated", "nominal"), controllers=("baseline", "mpc"))
    client = sweep.local_client(2)
    killed = {}

    def kill_one(row):
        if killed:
            return
        pids = client.run(os.getpid)
        victim = sorted(pids)[0]
        killed["pid"] = pids[victim]
        os.kill(pids[victim], signal.SIGKILL)

    try:
        counts = sweep.run_sweep(runs, tmp_path, client, progress=False, on_result=kill_one, batch_size=4)
        pids_after = set(client.run(os.getpid).values())
    finally:
        client.close()
        client.cluster.close()
    assert killed and killed["pid"] not in pids_after  # the worker really died (the nanny started a new one)
    rows = sweep.read_results(tmp_path)
    assert counts["ran"] == len(runs) == 8
    assert sorted(_raw_ids(tmp_path)) == sorted(r.run_id for r in runs)
    assert all(r["error"] is None for r in rows)
    assert all(k in rows[0] for k in KPIS if k not in TIMING_KPIS)
