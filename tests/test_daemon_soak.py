"""Soak run, short version (1.5 plant hours of the MPC at full speed, references every 5 min
through the API): no missed sample, consecutive times, no memory growth between the first and
the last memory sample (every 15 plant minutes). The full 24 h run is
``hvac-mpc daemon --soak 24 --soak-controller mpc`` (minutes of wall time; see the report).
About 20 s."""

from __future__ import annotations

import pytest

import logging

from hvac_mpc.daemon.soak import RSS_GROWTH_LIMIT_MB, print_report, run_soak

pytestmark = pytest.mark.slow


def test_short_soak_no_missed_sample_no_memory_growth(tmp_path, capsys):
    logging.getLogger("hvac_mpc.daemon").setLevel(logging.ERROR)
    r = run_soak(1.5, tmp_path / "soak.csv", controller="mpc", reference_every_s=300.0, memory_every_s=900.0)
    with capsys.disabled():
        print()
        print_report(r)
    assert r["exit_code"] == 0
    assert r["run_rows"] == r["expected_rows"] == 5400 and r["missed_samples"] == 0 and r["consecutive"]
    assert r["references_sent"] == 17 and r["references_accepted"] == 17
    assert len(r["memory"]) == 6 and r["rss_growth_mb"] <= RSS_GROWTH_LIMIT_MB
    assert r["median_abs_temp_error_c"] < 0.3 and r["median_abs_flow_error_m3s"] < 0.003
    assert r["ok"]
