"""Identification's whole-log runs as generated C built beside the caller (mpc/codegen_background.py): the same
values to the bit as CasADi's interpreter, built once per structure, found in the cache by the next process."""

import os
import shutil
import time

import numpy as np
import pytest

from hvac_mpc.identification.log_data import load
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS
from hvac_mpc.identification.simulator import Simulator
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.models import Parameters
from hvac_mpc.mpc import codegen_background as cb

pytestmark = pytest.mark.skipif(cb.compiler() is None or shutil.which("sh") is None, reason="no C compiler or no POSIX shell: the runs stay in CasADi's interpreter")


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """20 min of the independent box with three effects the model lacks (recirculation, a delay, shifted valves)."""
    path = tmp_path_factory.mktemp("log") / "combo.csv"
    simulate_log(path, "combo_recirc_delay_valve", duration_s=1200.0, seed=31)
    return load(path)


def _runs(log, builds):
    """A free run and the sensitivities of four parameters on ``log``, with ``builds`` (None: interpreted)."""
    sim = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, tuple(log.outputs), builds=builds)
    p = np.asarray(Parameters().vector())
    e = np.zeros((len(p), 4))
    for j, i in enumerate((0, 3, 7, 11)):
        e[i, j] = 1.0
    y, states = sim.simulate(p)
    y_s, dy = sim.simulate_with_sensitivity(p, e)
    return y, states, y_s, dy


def test_the_generated_runs_give_the_interpreters_values_to_the_bit_and_the_next_process_finds_them(
        log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    reference = _runs(log, None)
    builds = cb.BackgroundBuilds(after=0, wait=True, on=True)
    compiled = _runs(log, builds)
    assert builds.summary() == {"built": 2}, builds.outcomes  # the free run's step and the sensitivities' step
    for a, b in zip(reference, compiled):
        assert np.array_equal(a, b, equal_nan=True)
    assert len(list(tmp_path.glob("*.so"))) == 2 and not list(tmp_path.glob(".build_*"))
    again = cb.BackgroundBuilds(after=0, wait=True, on=True)
    for a, b in zip(reference, _runs(log, again)):
        assert np.array_equal(a, b, equal_nan=True)
    assert again.summary() == {"cached": 2}, again.outcomes


def test_a_function_is_built_only_after_the_calls_asked_for(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    sim = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, tuple(log.outputs))
    builds = cb.BackgroundBuilds(after=2, wait=True, on=True)
    assert builds.function(sim.f_step_y) is sim.f_step_y
    assert builds.function(sim.f_step_y) is sim.f_step_y
    assert builds.summary() == {"counted": 1} and not list(tmp_path.glob("*.so"))
    third = builds.function(sim.f_step_y)
    assert third is not sim.f_step_y and builds.summary() == {"built": 1}
    assert builds.function(sim.f_step_y) is third  # loaded once


def test_a_build_under_way_elsewhere_is_not_started_again_and_a_stale_one_is_taken_over(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    sim = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, tuple(log.outputs))
    probe = cb.BackgroundBuilds(after=10, on=True)  # counts, starts nothing
    probe.function(sim.f_y)
    (stem,) = probe.outcomes
    claim = tmp_path / f".build_{stem}"
    claim.mkdir()
    held = cb.BackgroundBuilds(after=0, wait=True, on=True)
    assert held.function(sim.f_y) is sim.f_y and held.summary() == {"counted": 1}
    old = time.time() - cb.STALE_S - 10
    os.utime(claim, (old, old))
    taken = cb.BackgroundBuilds(after=0, wait=True, on=True)
    assert taken.function(sim.f_y) is not sim.f_y and taken.summary() == {"built": 1}
    assert not claim.exists()


def test_switched_off_the_runs_stay_interpreted_and_nothing_is_written(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv(cb.RUN_BUILDS_ENV, "0")
    builds = cb.BackgroundBuilds(after=0, wait=True)
    assert not builds.on
    sim = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, tuple(log.outputs), builds=builds)
    sim.simulate(np.asarray(Parameters().vector()))
    assert builds.outcomes == {} and not any(tmp_path.iterdir())
    monkeypatch.setenv(cb.RUN_BUILDS_ENV, "1")
    monkeypatch.setenv("HVAC_MPC_CODEGEN", "0")
    assert cb.BackgroundBuilds().on  # the MPC's switch off, these builds asked for
    monkeypatch.delenv(cb.RUN_BUILDS_ENV)
    assert not cb.BackgroundBuilds().on  # the MPC's switch alone turns them off too


def test_no_build_starts_while_the_cap_of_builds_is_under_way(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    sim = Simulator(log, Parameters(), DOCUMENTED_EFFECTS, tuple(log.outputs))
    others = [tmp_path / f".build_other_{k}" for k in range(cb.MAX_BUILDS)]
    for folder in others:
        folder.mkdir()
    builds = cb.BackgroundBuilds(after=0, wait=True, on=True)
    assert builds.function(sim.f_y) is sim.f_y and builds.summary() == {"counted": 1}
    assert sorted(tmp_path.iterdir()) == sorted(others)  # nothing of its own started
    others[0].rmdir()
    assert builds.function(sim.f_y) is not sim.f_y and builds.summary() == {"built": 1}  # a place found
