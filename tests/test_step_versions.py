"""The side-by-side benchmark of two code versions (benchmarks/step_versions.py)."""

from __future__ import annotations

import pytest

from hvac_mpc.benchmarks import step_versions


def test_a_version_is_an_import_root_or_a_revision(tmp_path):
    root = step_versions.installed_layout(step_versions.REPOSITORY, tmp_path / "root")
    assert (root / "hvac_mpc" / "mpc" / "rti_osqp.py").is_file()
    assert (root / "hvac_mpc" / "benchmarks" / "step_versions.py").is_file()
    assert step_versions.import_root(str(root), tmp_path / "unused") == root.resolve()
    with pytest.raises(ValueError, match="'no-such-revision' is n"):
        step_versions.import_root("no-such-revision", tmp_path / "bad")


def test_a_bad_version_is_refused_with_its_name(capsys):
    assert step_versions.main(["--before", "no-such-revision", "--steps", "3"]) == 2
    assert "no-such-revision" in capsys.readouterr().out
    assert step_versions.main(["--before", "HEAD", "--steps", "2"]) == 2


@pytest.mark.slow
def test_the_same_code_side_by_side_gives_the_same_commands(tmp_path):
    """The installed version against a copy of itself: two processes in lockstep, the same commands and cost."""
    root = step_versions.installed_layout(step_versions.REPOSITORY, tmp_path / "root")
    out = step_versions.side_by_side({"before": root, "after": None}, steps=4, seed=1)
    assert out["command_difference"] == 0.0
    assert out["before"]["cost"] == out["after"]["cost"] > 0.0
    assert out["before"]["total_iterations"] == out["after"]["total_iterations"] > 0
    assert out["before"]["thread_median_ms"] > 0.0 and out["median_ratio"] > 0.0


def test_after_settings_that_are_no_json_object_are_refused(capsys):
    for bad in ("[0.5]", "rti_step_fractions=0.5"):
        assert step_versions.main(["--before", "HEAD", "--after-settings", bad]) == 2
        assert "--after-settings must be a JSON object" in capsys.readouterr().out


def test_which_version_steps_first_alternates_with_the_step_and_the_round(monkeypatch):
    """A reference change falls on the same steps every round: the version that takes it first alternates between
    rounds, so neither takes every change's step first (which biased the 99th percentile's ratio on identical code)."""
    calls = []

    class Fake:
        def __init__(self, root, seed, settings=None, idle_s=0.0, python=None):
            self.name, self.idle_s = root, idle_s

        def ask(self, line):
            calls.append((self.name, line))
            return 1.0 if line == "cost" else [1e-3, 10, [0.0] * 6]

        def close(self):
            pass
    monkeypatch.setattr(step_versions, "Version", Fake)
    firsts = {}
    for swap in (False, True):
        calls.clear()
        out = step_versions.side_by_side({"before": "before", "after": "after"}, steps=4, seed=1, idle_s=1.0,
                                         swap=swap)
        steps = [name for name, line in calls if line.startswith("step")]
        firsts[swap] = steps[0::2]
        assert out["command_difference"] == 0.0 and out["quiet_median_ratio"] == 1.0
    assert firsts[False] == ["before", "after", "before", "after"]
    assert firsts[True] == ["after", "before", "after", "before"]


@pytest.mark.slow
def test_the_same_code_side_by_side_with_the_idle_time_gives_the_same_commands(tmp_path):
    """``--idle``: each loop gives the second thread the sample's idle time between its steps; the commands are the
    same, and the quiet steps' median is reported."""
    root = step_versions.installed_layout(step_versions.REPOSITORY, tmp_path / "root")
    out = step_versions.side_by_side({"before": root, "after": None}, steps=4, seed=1, idle_s=0.2, swap=True)
    assert out["command_difference"] == 0.0
    assert out["before"]["cost"] == out["after"]["cost"] > 0.0
    assert out["after"]["quiet_median_ms"] > 0.0 and out["quiet_median_ratio"] > 0.0
