"""``python -m hvac_mpc.benchmarks.path_trace``: variants of the MPC over seeds of one bench scenario, where paths part.

Budget: about 20 s (two short winter runs).
"""

import argparse
import json

import pytest

from hvac_mpc.benchmarks import path_trace


def test_changes_lists_each_new_value_with_its_step():
    steps = [{"d": 0.0}, {"d": 0.0}, {"d": 0.5}, {"d": 0.5}, {"d": 0.0}]
    assert path_trace.changes(steps, "d") == [(0, 0.0), (2, 0.5), (4, 0.0)]


@pytest.mark.parametrize("text", ["480", "480-420", "a-b", "10-10"])
def test_a_bad_window_is_refused_naming_the_option(text):
    with pytest.raises(argparse.ArgumentTypeError, match="--window"):
        path_trace.parse_window(text)


def test_two_variants_with_the_same_settings_run_the_same_path(capsys, tmp_path):
    """The bench's runs are deterministic (iteration caps, not the clock): the same settings under two names give the
    same IAE to the bit and the same discrete choices, so a difference the tool prints between variants is theirs."""
    assert path_trace.main(["--quick", "--seeds", "1", "--variant", "a={}", "--variant", 'b={"osqp_eps": 1e-4}',
                            "--window", "100-120", "--window", "100-100000", "--json", str(tmp_path / "r.json")]) == 0
    saved = json.loads((tmp_path / "r.json").read_text())["0"]
    assert saved["a"]["iae"] == saved["b"]["iae"] and saved["a"]["steps"] == saved["b"]["steps"]  # to the bit
    out = capsys.readouterr().out.splitlines()
    a = next(line for line in out if line.startswith("seed 0 a:"))
    b = next(line for line in out if line.startswith("seed 0 b:"))
    assert "(+0.00)" in b and a.split("(")[0].split("IAE")[1] == b.split("(")[0].split("IAE")[1]
    described = [line for line in out if line.startswith("    dead time")]
    assert len(described) == 2 and described[0] == described[1]
    assert any("100-120 s: mean command" in line for line in out)
    assert any("100-100000 s: beyond the run" in line for line in out)


@pytest.mark.parametrize("variants", [["a={not json"], ["a={}", "a={}"], ["a"]])
def test_a_bad_variant_is_refused_naming_the_option(variants, capsys):
    """Settings that are not JSON, a name given twice and a missing ``=`` end in the parser's message, before a run."""
    argv = [arg for text in variants for arg in ("--variant", text)]
    with pytest.raises(SystemExit):
        path_trace.main(["--quick", "--seeds", "1", *argv])
    assert "--variant" in capsys.readouterr().err
