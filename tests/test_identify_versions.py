"""The side-by-side benchmark of two versions of ``identify`` (benchmarks/identify_versions.py)."""

from __future__ import annotations

import json

import pytest

from hvac_mpc.benchmarks import identify_versions, step_versions


def test_a_bad_version_is_refused_with_its_name(capsys):
    assert identify_versions.main(["--before", "no-such-revision", "--variant", "nominal", "--duration", "600"]) == 2
    assert "no-such-revision" in capsys.readouterr().out


def test_a_run_without_a_log_is_refused():
    with pytest.raises(SystemExit):
        identify_versions.main(["--before", "HEAD"])


@pytest.mark.slow
def test_the_same_code_side_by_side_finds_the_same_to_the_bit(tmp_path, capsys):
    """The installed version against a copy of itself on a short log of the independent box with an effect."""
    root = step_versions.installed_layout(step_versions.REPOSITORY, tmp_path / "root")
    out = tmp_path / "rows.json"
    assert identify_versions.main(["--before", str(root), "--variant", "delay_3s", "--duration", "1500", "--seed", "4",
                                   "--json", str(out)]) == 0
    row = json.loads(out.read_text())["rows"][0]
    assert row["same"] and row["before"]["added"] == row["after"]["added"] == ["transport_delay:supply_temp_c"]
    assert row["before"]["cpu_s"] > 0.0 and row["ratio"] > 0.0
    assert "the same to the bit" in capsys.readouterr().out
