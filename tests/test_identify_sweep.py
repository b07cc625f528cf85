"""The identification sweep's check (``benchmarks/identify_sweep.py``): what passes and fails a log, and the logs of
``--set edges`` (their own length and columns) reaching the identification as declared. The identification itself is
tested on logs of the independent box in tests/test_data_loop.py; here the runs are replaced by recorded rows."""

import json

from hvac_mpc.benchmarks import identify_sweep as sweep
from hvac_mpc.mismatch.variants import Variant


def _row(added, before=0.4, after=0.05, shift=0):
    return {"added": list(added), "supply_rms_before": before, "supply_rms_after": after,
            "timing_shift_samples": shift, "cpu_s": 1.0}


def test_a_clean_log_passes_with_nothing_added_and_fails_with_anything():
    clean = sweep.SweepLog("clean", Variant())
    assert sweep.verdict(clean, _row([], after=0.4))["passed"]
    assert not sweep.verdict(clean, _row(["transport_delay:supply_temp_c"]))["passed"]


def test_a_shift_other_than_the_logs_fails_even_with_the_effect_found():
    log = sweep.SweepLog("delay_shift4", Variant(transport_delay_s=3.0, log_shift_samples=4), (sweep.DELAY,))
    assert sweep.verdict(log, _row(["transport_delay:supply_temp_c"], shift=4))["passed"]
    wrong = sweep.verdict(log, _row(["transport_delay:supply_temp_c"], shift=3))
    assert not wrong["passed"] and not wrong["shift_ok"]


def test_every_effect_must_be_found_and_the_error_halved():
    log = sweep.SweepLog("three", Variant(transport_delay_s=2.0, thermocouple_tau_scale=1.4, recirculation_share=0.12),
                         (sweep.DELAY, sweep.LAG, sweep.TERM))
    found = ["transport_delay:supply_temp_c", "sensor_lag", "term dT_box_in = -0.12 [C / (C)] * inlet +2.9 [C] * one"]
    assert sweep.verdict(log, _row(found))["passed"]
    assert not sweep.verdict(log, _row(found[:2]))["passed"]  # the term missing
    assert not sweep.verdict(log, _row(found, after=0.21))["passed"]  # 0.21 / 0.4 > 0.5
    extra = sweep.verdict(log, _row(found + ["output_gain:heater_power_w"]))
    assert extra["passed"] and extra["extra"] == ["output_gain:heater_power_w"]  # reported, not failed


def test_edge_logs_reach_the_identification_with_their_own_length_and_columns(monkeypatch, tmp_path, capsys):
    seen = {}

    def fake_time_case(name, case, duration_s, seed, folder, best_place=False):
        seen[name] = (duration_s, case.omit, case.variant.log_shift_samples)
        return dict(_row([], after=0.4, shift=case.variant.log_shift_samples), log=name)

    monkeypatch.setattr(sweep, "time_case", fake_time_case)
    out = tmp_path / "rows.json"
    assert sweep.main(["--set", "edges", "--seed", "5", "--duration", "5000", "--json", str(out)]) == 0
    assert set(seen) == {log.name for log in sweep.EDGES}
    assert seen["clean_1h_noise2_bad"][0] == 3600.0 and seen["delay_2s_40min"][0] == 2400.0
    assert seen["delay_3s_shift3"][0] == 5000.0  # no length of its own: the run's
    assert seen["delay_3s_nowater"][1] == ("water_temp_c",) and seen["delay_3s_shift3"][1] == ()
    assert {s for _, _, s in seen.values()} >= {3, -4, 5}
    rows = json.loads(out.read_text())["runs"]
    assert {r["log"]: r["duration_s"] for r in rows}["duct_ua3_1h"] == 3600.0
    # the clean edge logs pass with nothing added; the others fail (nothing found)
    verdicts = {r["log"]: r["check"]["passed"] for r in rows}
    assert verdicts["clean_shift5"] and verdicts["clean_nowater"] and not verdicts["delay_3s_nowater"]
    assert "passed 3 of 10" in capsys.readouterr().out

